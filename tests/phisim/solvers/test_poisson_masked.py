"""The weighted cut-cell Poisson operator: its fast fixed-weight stencil and preconditioner against the generic
gradient/weights/divergence form, and the closed-box null-space projection."""

import pytest
import torch

from phisim.solvers.box import apply_multiplier
from phisim.solvers.masked import MaskedPoisson

KINDS = [
    (("neumann", "neumann"), ("neumann", "neumann")),
    (("dirichlet", "neumann"), ("neumann", "dirichlet")),
    (("periodic", "periodic"), ("dirichlet", "neumann")),
    (("dirichlet", "dirichlet"), ("periodic", "periodic")),
]


def _weights(batch, res, kinds, seed):
    gen = torch.Generator().manual_seed(seed)
    out = []
    for a in range(len(res)):
        shape = [batch, *res]
        shape[1 + a] += 1
        w = torch.rand(shape, dtype=torch.float64, generator=gen)
        w[w < 0.25] = 0.0
        w[w > 0.8] = 1.0
        if kinds[a][0] == "periodic":  # face n is face 0
            w.narrow(1 + a, res[a], 1).copy_(w.narrow(1 + a, 0, 1))
        out.append(w)
    return out


KINDS_3D = (("neumann", "dirichlet"), ("periodic", "periodic"), ("neumann", "neumann"))


@pytest.mark.parametrize("kinds", KINDS + [KINDS_3D])
@pytest.mark.parametrize("batch", [1, 3])
def test_fixed_weight_stencil_equals_generic_operator(kinds, batch):
    res = (9, 7) if len(kinds) == 2 else (5, 4, 6)
    op = MaskedPoisson(_weights(batch, res, kinds, 1), (0.7, 1.3, 1.1)[: len(res)], kinds)
    p = torch.randn(batch, *res, dtype=torch.float64, generator=torch.Generator().manual_seed(2))
    generic = op._apply(p, *op.weights)
    torch.testing.assert_close(op._apply_fixed(p), generic, rtol=1e-13, atol=1e-13)
    torch.testing.assert_close(op.apply(p), generic, rtol=1e-13, atol=1e-13)
    # symmetric: <q, A p> = <A q, p>
    q = torch.randn(batch, *res, dtype=torch.float64, generator=torch.Generator().manual_seed(3))
    torch.testing.assert_close((q * op.apply(p)).sum(), (op.apply(q) * p).sum())
    # the float32 stencil holds the same coefficients
    torch.testing.assert_close(op.apply(p.float()), generic.float(), rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("kinds", KINDS)
def test_preconditioner_fast_path_equals_composed_form_and_is_symmetric(kinds):
    res = (10, 8)
    op = MaskedPoisson(_weights(2, res, kinds, 4), 1.0, kinds)
    gen = torch.Generator().manual_seed(5)
    r = op.project(torch.randn(2, *res, dtype=torch.float64, generator=gen))
    act = op.active.double()
    ref = -apply_multiplier(r * act, op.kinds, op._inv, op.engine)
    ref = op.project(torch.where(op.active, ref, r) + op._cut_inv * r)
    torch.testing.assert_close(op._precondition(r), ref, rtol=1e-12, atol=1e-12)
    s = op.project(torch.randn(2, *res, dtype=torch.float64, generator=gen))
    torch.testing.assert_close((s * op._precondition(r)).sum(), (op._precondition(s) * r).sum())


def test_closed_box_projection_removes_the_region_mean_only():
    kinds = (("neumann", "neumann"), ("neumann", "neumann"))
    res = (8, 6)
    w = [torch.ones(1, 9, 6, dtype=torch.float64), torch.ones(1, 8, 7, dtype=torch.float64)]
    w[0][:, 3:6, 2:4] = 0.0  # a body: its interior cells are inactive
    w[1][:, 3:5, 2:5] = 0.0
    op = MaskedPoisson(w, 1.0, kinds)
    assert op.null.shape[:2] == (1, 1)
    t = torch.randn(3, *res, dtype=torch.float64, generator=torch.Generator().manual_seed(6))
    out = op.project(t)
    act = op.active.expand_as(t)
    means = (out * act).flatten(1).sum(1) / act.flatten(1).sum(1)
    torch.testing.assert_close(means, torch.zeros(3, dtype=torch.float64), rtol=0, atol=1e-13)
    torch.testing.assert_close(out[~act], t[~act])  # inactive cells are not touched
    torch.testing.assert_close(op.project(out), out)  # a projector


def _disc_and_box_operator(n=24):
    from phisim.boundary import Boundary
    from phisim.fluid import Body, Box, Sphere, solid_layout
    from phisim.grid import Grid
    from phisim.solvers.poisson import field_kinds_and_values

    grid = Grid((n, n), bounds=[(0, 1), (0, 1)])
    boundary = Boundary.create({"x": ("wall", "open"), "y": "wall"}, 2)
    bodies = [Body(Sphere((0.3, 0.45), 0.17)), Body(Box((0.55, 0.25), (0.8, 0.7)))]
    layout = solid_layout(bodies, grid, boundary, 0.0, torch.float64)
    return MaskedPoisson(layout.theta, grid.dx, field_kinds_and_values(boundary.for_pressure())[0])


def test_leaves_are_weak_cells_that_touch_no_other_leaf():
    op = _disc_and_box_operator()
    leaves = op._leaves()
    assert leaves is not None
    leaf_idx, inv_d, src, dst, frac, mask, weak = leaves
    w = tuple(wi.detach() for wi in op.weights)
    diag = op._diagonal(w)[0].flatten()
    d0 = op._diagonal(tuple(torch.ones_like(wi) for wi in w))[0].flatten()
    assert len(leaf_idx) > 0
    assert bool((diag[leaf_idx] <= 0.2 * d0[leaf_idx]).all()) and bool(op.active[0].flatten()[leaf_idx].all())
    assert not bool(mask.flatten()[dst].any())  # a leaf's neighbours are never leaves
    torch.testing.assert_close(inv_d, 1.0 / diag[leaf_idx])
    # the couplings of each leaf sum to its diagonal (no Dirichlet face here): fractions sum to 1 per leaf
    sums = torch.zeros_like(diag).index_add_(0, src, frac)
    torch.testing.assert_close(sums[leaf_idx], torch.ones_like(inv_d))
    # maximal and weakest first: every weak cell left out has a leaf neighbour with a smaller diagonal
    cand = op.active[0].flatten() & (diag > 0) & (diag <= 0.2 * d0)
    out = cand & ~mask.flatten()
    assert bool(out.any()) and torch.equal(weak.flatten(), out)  # the weak cells kept take the Jacobi term
    rows, cols = _couplings(op)
    beaten = torch.zeros_like(out)
    beaten[rows[mask.flatten()[cols] & (diag[cols] <= diag[rows])]] = True
    assert bool(beaten[out].all())


def _couplings(op):
    """The pairs ``(row, col)`` of flat cell indices coupled by a face of positive weight (both ways)."""
    res = op.resolution
    idx = torch.arange(res[0] * res[1]).view(res)
    rows, cols = [], []
    for a, w in enumerate(op.weights):
        inner = w[0].detach().narrow(a, 1, res[a] - 1) > 0
        lo, hi = idx.narrow(a, 0, res[a] - 1)[inner], idx.narrow(a, 1, res[a] - 1)[inner]
        rows += [lo, hi]
        cols += [hi, lo]
    return torch.cat(rows), torch.cat(cols)


def test_leaves_read_only_the_couplings_of_candidates():
    """``_leaves`` keeps the couplings that touch a candidate and runs the weakest-first rounds on those between
    candidates: the same leaves, couplings and fractions as the rounds over every coupling of the grid."""
    from phisim.solvers.masked import _weakest_first

    for op in (_disc_and_box_operator(), _disc_and_box_operator(37)):
        leaf_idx, inv_d, src, dst, frac, mask, weak = op._leaves()
        w = tuple(wi.detach() for wi in op.weights)
        diag = op._diagonal(w)[0].flatten()
        d0 = op._diagonal(tuple(torch.ones_like(wi) for wi in w))[0].flatten()
        cand = op.active[0].flatten() & (diag > 0) & (diag <= 0.2 * d0)
        rows, cols = _couplings(op)
        full = _weakest_first(cand, diag, rows, cols)
        assert torch.equal(mask.flatten(), full) and torch.equal(weak.flatten(), cand & ~full)
        sel = full[rows]
        assert torch.equal(src, rows[sel]) and torch.equal(dst, cols[sel])
        c = torch.cat([wa[0].narrow(a, 1, op.resolution[a] - 1).flatten() / op.dx[a] ** 2
                       for a, wa in enumerate(w) for _ in range(2)])
        c = c[torch.cat([(wa[0].narrow(a, 1, op.resolution[a] - 1).flatten() > 0)
                         for a, wa in enumerate(w) for _ in range(2)])]
        torch.testing.assert_close(frac, c[sel] / diag[rows[sel]], rtol=0, atol=0)
    # random graphs: the rounds read the couplings between candidates only
    gen = torch.Generator().manual_seed(5)
    for _ in range(20):
        n = 60
        i, j = torch.randint(0, n, (2, 150), generator=gen)
        keep = i != j
        src, dst = torch.cat([i[keep], j[keep]]), torch.cat([j[keep], i[keep]])
        cand = torch.rand(n, generator=gen) < 0.5
        diag = torch.rand(n, dtype=torch.float64, generator=gen)
        among = cand[src] & cand[dst]
        assert torch.equal(_weakest_first(cand, diag, src, dst), _weakest_first(cand, diag, src[among], dst[among]))


def test_a_cell_tied_to_the_fluid_by_a_sliver_next_to_a_weak_cell_is_eliminated():
    """A face fraction of 1e-7 (a surface grazing a face, as a moving curved body makes) gives the cell behind it a
    diagonal of 1e-7 of the open one. Next to another weak cell, the rule that left out every weak cell touching
    another one handed it to the box preconditioner: the preconditioned operator had an eigenvalue of 3e-8 there
    (measured; CG of a moving free-slip sphere's layout stalled). Weakest first it is eliminated: the spectrum of
    ``M A`` stays within [0.2, 1.4] (measured 0.215 and 1.35, with the additive Jacobi term on the weak cells
    that are not eliminated)."""
    op = _disc_and_box_operator()
    w = [x.detach().clone() for x in op.weights]
    act, res = op.active[0], op.resolution
    diag = op._diagonal(tuple(w))[0]
    d0 = op._diagonal(tuple(torch.ones_like(x) for x in w))[0]
    slivers = [(i + 1, j) for i in range(res[0] - 1) for j in range(res[1])
               if act[i, j] and diag[i, j] <= 0.2 * d0[i, j] and not act[i + 1, j]]
    assert slivers
    for i, j in slivers:
        w[0][0, i, j] = 1e-7  # face i along x: between the weak cell (i - 1, j) and the inactive cell (i, j)
    sliver = MaskedPoisson(w, op.dx, op.kinds, direct=False)
    leaf = sliver._leaves()[5][0]
    assert all(bool(sliver.active[0][c]) and bool(leaf[c]) for c in slivers)
    n = res[0] * res[1]
    basis = torch.eye(n, dtype=torch.float64).view(n, *res)
    a = sliver.active[0].flatten()
    ma = sliver._precondition(basis).reshape(n, n)[a][:, a] @ sliver.apply(basis).reshape(n, n)[a][:, a]
    ev = torch.linalg.eigvals(ma).real
    assert float(ev.min()) > 0.2 and float(ev.max()) < 1.4, (float(ev.min()), float(ev.max()))


def test_preconditioner_with_leaf_elimination_is_symmetric_positive_definite_on_the_range():
    op = _disc_and_box_operator()
    assert op._leaves() is not None
    gen = torch.Generator().manual_seed(8)
    n = op.resolution[0] * op.resolution[1]
    basis = op.project(torch.eye(n, dtype=torch.float64).view(n, *op.resolution))  # rows span the range
    M = op._precondition(basis).reshape(n, n)  # M[k] = M e_k (projected), so M @ basis^T is M on the range
    act = op.active[0].flatten()
    Mr = M[act][:, act]
    torch.testing.assert_close(Mr, Mr.T, rtol=1e-10, atol=1e-12)
    r = op.project(torch.randn(5, *op.resolution, dtype=torch.float64, generator=gen) * op.active)
    quad = (r * op._precondition(r)).flatten(1).sum(1)
    assert bool((quad > 0).all())
    # and it is a good preconditioner: the preconditioned operator's spectrum on the range is clustered
    b = op.project(torch.randn(1, *op.resolution, dtype=torch.float64, generator=gen) * op.active)
    from phisim.solvers.linalg import Solve

    _, info = op.solve(b, solve=Solve(rtol=1e-8))
    _, info_plain = op.solve(b, solve=Solve(rtol=1e-8), preconditioned=False)
    assert int(info.iterations[0]) * 2 < int(info_plain.iterations[0])


def test_scatter_add_in_rounds_equals_index_add():
    from phisim.solvers.masked import _scatter_add, scatter_rounds

    gen = torch.Generator().manual_seed(9)
    index = torch.randint(0, 7, (40,), generator=gen)
    values = torch.randn(3, 40, dtype=torch.float64, generator=gen)
    out = torch.randn(3, 7, dtype=torch.float64, generator=gen)
    ref = out.clone().index_add_(1, index, values)
    rounds = _scatter_add(out.clone(), index, values, in_rounds=True)
    torch.testing.assert_close(rounds, ref, rtol=1e-14, atol=1e-14)
    # each round adds one value per index, in the order the values come: bit for bit on a second call
    assert torch.equal(rounds, _scatter_add(out.clone(), index, values, in_rounds=True))
    # rounds built once: no index repeats within a round, every position is used once, the same sums
    plan = scatter_rounds(index)
    assert len(plan) == int(torch.bincount(index).max())
    assert all(len(torch.unique(ik)) == len(ik) and torch.equal(index[sk], ik) for ik, sk in plan)
    assert torch.equal(torch.sort(torch.cat([sk for _, sk in plan])).values, torch.arange(len(index)))
    assert torch.equal(rounds, _scatter_add(out.clone(), index, values, in_rounds=True, rounds=plan))
    assert scatter_rounds(index[:0]) == ()


def test_preconditioner_in_rounds_equals_the_cpu_scatter():
    """The deterministic scatter of other devices (rounds built once per layout), forced on the CPU: the same
    preconditioner and the same solve as ``index_add_``."""
    from phisim.solvers.linalg import Solve

    plain, rounds = _disc_and_box_operator(), _disc_and_box_operator()
    rounds.deterministic_rounds = True
    assert plain._rounds(torch.device("cpu")) is None and len(rounds._rounds(torch.device("cpu"))[0]) >= 2
    gen = torch.Generator().manual_seed(4)
    r = plain.project(torch.randn(3, *plain.resolution, dtype=torch.float64, generator=gen) * plain.active)
    torch.testing.assert_close(rounds._precondition(r), plain._precondition(r), rtol=1e-14, atol=1e-14)
    # after the first call (which builds the rounds) the preconditioner reads nothing back from the device: no
    # numbers, no nonzero (each would stall a GPU's queue once per CG iteration)
    from torch.utils._python_dispatch import TorchDispatchMode

    class Reads(TorchDispatchMode):
        names: list = []

        def __torch_dispatch__(self, func, types, args=(), kwargs=None):
            if func.__name__.split(".")[0] in ("_local_scalar_dense", "nonzero", "masked_select"):
                self.names.append(func.__name__)
            return func(*args, **(kwargs or {}))

    with Reads() as reads:
        rounds._precondition(r)
    assert reads.names == []
    x1, i1 = plain.solve(r[:1], solve=Solve(rtol=1e-10))
    x2, i2 = rounds.solve(r[:1], solve=Solve(rtol=1e-10))
    assert int(i1.iterations[0]) == int(i2.iterations[0])
    torch.testing.assert_close(x1, x2, rtol=1e-12, atol=1e-12)


# ---- the direct (capacitance) solve of a layout that keeps coming back ----------------------------------------


def _disc_weights(res, centres, radius, batch=1):
    """Fractional face weights of discs/spheres: 0 inside, 1 outside, a linear ramp over one cell."""
    out = []
    for a in range(len(res)):
        shape = list(res)
        shape[a] += 1
        axes = []
        for b, n in enumerate(shape):
            x = torch.arange(n, dtype=torch.float64) + (0.0 if b == a else 0.5)
            axes.append(x / res[0])
        grid = torch.stack(torch.meshgrid(*axes, indexing="ij"), -1)
        w = torch.ones(shape, dtype=torch.float64)
        for c in centres:
            dist = (grid - torch.tensor(c, dtype=torch.float64)).norm(dim=-1)
            w = torch.minimum(w, ((dist - radius) * res[0] + 0.5).clamp(0, 1))
        out.append(w[None].expand(batch, *shape).contiguous())
    return out


DIRECT_CASES = [
    ("channel disc", (24, 12), [(0.3, 0.25)], 0.12, (("neumann", "dirichlet"), ("neumann", "neumann"))),
    ("two discs, periodic", (20, 16), [(0.25, 0.4), (0.7, 0.35)], 0.1, (("dirichlet", "dirichlet"),
                                                                        ("periodic", "periodic"))),
    ("disc on a Dirichlet side", (16, 16), [(0.0, 0.5)], 0.3, (("dirichlet", "neumann"), ("neumann", "neumann"))),
    ("sphere", (10, 9, 8), [(0.5, 0.45, 0.4)], 0.25, (("neumann", "dirichlet"), ("periodic", "periodic"),
                                                     ("neumann", "neumann"))),
    ("closed box", (20, 16), [(0.3, 0.4), (0.7, 0.5)], 0.12, (("neumann", "neumann"), ("neumann", "neumann"))),
]


@pytest.mark.parametrize("name, res, centres, radius, kinds", DIRECT_CASES, ids=[c[0] for c in DIRECT_CASES])
def test_direct_solve_is_exact_and_equals_converged_pcg(name, res, centres, radius, kinds):
    from phisim.solvers.linalg import Solve

    weights = _disc_weights(res, centres, radius)
    dx = tuple(1.0 / res[0] for _ in res)
    rhs = torch.randn(2, *res, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    ref, info = MaskedPoisson(weights, dx, kinds, direct=False).solve(rhs, solve=Solve(rtol=1e-13))
    assert bool(info.converged.all())
    op = MaskedPoisson(weights, dx, kinds, direct=True)  # tiny grids: the rank is large against the cells
    p, info = op.solve(rhs, solve=Solve(rtol=1e-10))
    assert op._direct and op._direct.lu is not None
    # the direct answer alone meets the tolerance: CG, which checks it, takes no iteration
    assert info.iterations.tolist() == [0, 0]
    torch.testing.assert_close(p, ref, rtol=0, atol=1e-9 * float(ref.abs().max()))
    # residual of the Woodbury solve itself, on the active cells (a closed box: the compatible right-hand side)
    act = op.active.double()
    b = op.project(rhs * act)
    x = op.project(op._direct.solve(b) * act)
    resid = (op.apply(x) - b) * act
    assert float(resid.norm()) <= 1e-11 * float(b.norm())
    assert float(p[:, ~op.active[0]].abs().max()) == 0
    if op.singular:  # zero mean over the fluid, as the PCG answer
        assert float((p * act).sum(dim=(1, 2)).abs().max()) <= 1e-10 * float(p.abs().sum())
    # pins: one per block of solid cells that reaches no Dirichlet side
    pins = int((op._direct.d > 0).sum())
    assert pins == {"channel disc": 1, "two discs, periodic": 2, "disc on a Dirichlet side": 0, "sphere": 1,
                    "closed box": 2}[name]
    # float32: the same solve in single precision
    p32, info32 = op.solve(rhs.float(), solve=Solve(rtol=1e-5))
    assert bool(info32.converged.all())
    torch.testing.assert_close(p32.double(), ref, rtol=0, atol=2e-5 * float(ref.abs().max()))


def test_direct_solve_is_chosen_at_construction_and_declines_what_it_cannot_do():
    from phisim.errors import ParameterError
    from phisim.solvers.linalg import Solve

    res, kinds = (16, 12), (("neumann", "dirichlet"), ("neumann", "neumann"))
    weights = _disc_weights(res, [(0.4, 0.35)], 0.15)
    rhs = torch.randn(1, *res, dtype=torch.float64, generator=torch.Generator().manual_seed(2))
    # the first solve already uses it: every solve of one operator takes the same path
    op = MaskedPoisson(weights, 1 / 16, kinds, direct=True)
    assert op.uses_direct_solve
    _, info = op.solve(rhs, solve=Solve(rtol=1e-10))
    assert int(info.iterations[0]) == 0 and op._direct.lu is not None
    assert not MaskedPoisson(weights, 1 / 16, kinds, direct=False).uses_direct_solve
    # 'auto': where it pays, k² <= MAX_RANK_SQUARED_PER_CELL cells for k cut faces
    from phisim.solvers.direct import MAX_RANK_SQUARED_PER_CELL

    k = op._direct.rank
    pays = k * k <= MAX_RANK_SQUARED_PER_CELL * 16 * 12
    assert MaskedPoisson(weights, 1 / 16, kinds).uses_direct_solve == pays
    # per-sample layouts, weights with gradient, two closed fluid regions: PCG, and direct=True is an error
    two = [torch.cat([w, torch.ones_like(w)]) for w in weights]
    grad = [w.clone().requires_grad_(True) for w in weights]
    closed = (("neumann", "neumann"), ("neumann", "neumann"))
    split = [w.clone() for w in weights]
    split[0][:, 8] = 0.0  # a closed box cut in two by a wall: two fluid regions, two constants in the null space
    for ws, k in ((two, kinds), (grad, kinds), (split, closed)):
        op = MaskedPoisson(ws, 1 / 16, k)
        assert not op.uses_direct_solve
        op.solve(rhs.expand(ws[0].shape[0], *res), solve=Solve(rtol=1e-8))
        assert op._direct is False
        with pytest.raises(ParameterError, match="direct=True"):
            MaskedPoisson(ws, 1 / 16, k, direct=True)
    with pytest.raises(ParameterError, match="direct must be"):
        MaskedPoisson(weights, 1 / 16, kinds, direct="yes")


def test_direct_solve_keeps_the_rhs_gradient():
    from phisim.solvers.linalg import Solve

    res, kinds = (8, 6), (("neumann", "dirichlet"), ("neumann", "neumann"))
    op = MaskedPoisson(_disc_weights(res, [(0.45, 0.35)], 0.2), 1 / 8, kinds, direct=True)
    rhs = torch.randn(1, *res, dtype=torch.float64, generator=torch.Generator().manual_seed(3), requires_grad=True)
    assert torch.autograd.gradcheck(lambda f: op.solve(f, solve=Solve(rtol=1e-12))[0], (rhs,))
    assert op._direct and op._direct.lu is not None


def _dense_box(res, dx, kinds):
    """The box operator ``Σ_a I ⊗ L_a ⊗ I`` as a dense matrix (C order, as the fields' flat index)."""
    import numpy as np

    from phisim.solvers.green import axis_operator

    total = 0
    for a in range(len(res)):
        mats = [np.eye(n) for n in res]
        mats[a] = axis_operator(res[a], dx[a], kinds[a])
        k = mats[0]
        for m in mats[1:]:
            k = np.kron(k, m)
        total = total + k
    return total


@pytest.mark.parametrize("res, kinds", [
    ((7, 5), (("neumann", "dirichlet"), ("neumann", "neumann"))),
    ((6, 5, 4), (("dirichlet", "neumann"), ("periodic", "periodic"), ("dirichlet", "dirichlet"))),
    ((5, 6), (("neumann", "neumann"), ("periodic", "periodic"))),
    ((4, 3, 5), (("neumann", "neumann"), ("neumann", "neumann"), ("neumann", "neumann"))),
])
def test_box_green_block_equals_the_dense_inverse(res, kinds):
    """The separable eigen-decomposition's block of ``B⁻¹`` equals the inverse of the assembled operator (a
    singular box made definite on its constant mode, as the box inverse does); and ``axis_operator`` is the box
    inverse's operator: the spectral box solve inverts the assembled matrix."""
    import math

    import numpy as np

    from phisim.ops.tensors import unravel
    from phisim.solvers.green import box_green_block

    dx = (0.3, 0.2, 0.25)[: len(res)]
    b = _dense_box(res, dx, kinds)
    n = math.prod(res)
    null = None
    if all("dirichlet" not in pair for pair in kinds):
        beta = float(np.linalg.eigvalsh(b)[1])
        null = 1.0 / beta
        b = b + beta * np.ones((n, n)) / n
    binv = np.linalg.inv(b)
    cells = torch.tensor(sorted({0, 3, n // 2, n - 2, n - 1}))
    g = box_green_block(res, dx, kinds, unravel(cells, res), null)
    ref = binv[np.ix_(cells.numpy(), cells.numpy())]
    assert float(np.abs(g.numpy() - ref).max()) <= 1e-12 * float(np.abs(ref).max())
    # the spectral box inverse (singular boxes made definite the same way) inverts the assembled matrix
    f = torch.randn(1, *res, dtype=torch.float64, generator=torch.Generator().manual_seed(4))
    x = torch.as_tensor(binv @ f.reshape(-1).numpy()).reshape(1, *res)
    ones = [torch.ones(1, *[m + (1 if b_ == a else 0) for b_, m in enumerate(res)], dtype=torch.float64)
            for a in range(len(res))]
    p = MaskedPoisson(ones, dx, kinds, direct=False)._box_inverse(f)
    torch.testing.assert_close(p, x, rtol=0, atol=1e-11 * float(x.abs().max()))


@pytest.mark.parametrize("name, res, centres, radius, kinds", DIRECT_CASES, ids=[c[0] for c in DIRECT_CASES])
def test_capacitance_by_spectrum_equals_the_box_solves(name, res, centres, radius, kinds):
    """The direct solve's coupling block ``Uᵀ B⁻¹ U`` from the box's eigen-decomposition equals the one from ``k``
    box solves, in every box of the direct-solve cases (Dirichlet, Neumann, periodic, closed)."""
    from phisim.solvers.direct import WoodburySolve

    weights = _disc_weights(res, centres, radius)
    dx = tuple(1.0 / res[0] for _ in res)
    op = MaskedPoisson(weights, dx, kinds, direct=False)
    solver = WoodburySolve(tuple(w[0] for w in op.weights), op.active[0], op.dx, op.kinds, op._box_inverse)
    fast = solver._coupling_by_spectrum()
    slow = solver._coupling_by_box_solves()
    assert fast is not None
    assert float((fast - slow).abs().max()) <= 1e-12 * float(slow.abs().max())


def test_capacitance_falls_back_to_box_solves_for_another_box_inverse():
    """A box inverse that is not the box's own fails the spectral build's check against two exact solves; the
    capacitance then comes from that inverse's solves, and the direct solve stays consistent with it."""
    from phisim.errors import SlowPathWarning
    from phisim.solvers.direct import WoodburySolve

    res, kinds = (16, 12), (("neumann", "dirichlet"), ("neumann", "neumann"))
    weights = _disc_weights(res, [(0.4, 0.35)], 0.15)
    op = MaskedPoisson(weights, 1 / 16, kinds, direct=False)
    twice = lambda f: 2.0 * op._box_inverse(f)  # noqa: E731
    solver = WoodburySolve(tuple(w[0] for w in op.weights), op.active[0], op.dx, op.kinds, twice)
    with pytest.warns(SlowPathWarning, match="box solves instead"):
        assert solver._coupling_by_spectrum() is None
    with pytest.warns(SlowPathWarning):
        solver.factor()
    expected = torch.linalg.lu_factor(solver._coupling_by_box_solves() + torch.diag(1.0 / solver.d))
    torch.testing.assert_close(solver.lu, expected[0], rtol=0, atol=1e-12)
