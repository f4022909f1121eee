"""The fast paths of a smoke step agree with the general ones.

* Padding and boundary faces by cached gather plans (``phisim.padding``) against the per-side
  narrow/flip/concatenate path, for every boundary kind, 1-3 D, float32/float64, widths 1 and 2, all axes
  and single axes: bit-identical values, equal gradients, gradcheck in float64.
* The MacCormack limiter bounds from stacked indices against the per-axis formulation.
* ``fluid.step`` (validated once at its entry, trusted inner calls) against the same step composed of
  the public, validating functions: bit-identical; and its errors for bad input.
"""

from __future__ import annotations

import pickle

import pytest
import torch

import phisim.boundary as bmod
from phisim.boundary import (
    Boundary,
    Dirichlet,
    FreeSlipWall,
    Inflow,
    Neumann,
    NoSlipWall,
    Open,
    Periodic,
    pad,
    pad_staggered_component,
    set_boundary_faces,
)
from phisim.errors import GridMismatchError, NonFiniteError, ParameterError
from phisim.field import CenteredGrid, StaggeredGrid
from phisim.fluid import FluidState, buoyancy, make_incompressible, step
from phisim.grid import Grid
from phisim.ops.advection import _location, advect

CONDITIONS = [Dirichlet(0.0), Dirichlet(1.5), Neumann(0.0), Neumann(-0.3), NoSlipWall(), FreeSlipWall(), Open(),
              Inflow(0.7)]
RES = (5, 4, 3)
DX = (0.5, 1.0, 2.0)


def _boundaries(rank: int):
    """Every pair of conditions on axis x (and its mirror on y), periodic axes, a moving lid on the last axis."""
    pairs = [(Periodic(), Periodic())] + [(lo, hi) for lo in CONDITIONS for hi in CONDITIONS[::3]]
    for lo, hi in pairs:
        sides = [(lo, hi)]
        if rank >= 2:
            sides.append((hi, lo) if not isinstance(lo, Periodic) else (Neumann(0.2), Open()))
        if rank == 3:
            sides.append((Dirichlet(0.0), NoSlipWall((0.1, -0.2, 0.3))))
        yield Boundary(tuple(sides))


def _general(fn, *args, **kwargs):
    """``fn`` on the general (per-side) padding path."""
    old = bmod._FAST_PADDING
    bmod._FAST_PADDING = False
    try:
        return fn(*args, **kwargs)
    finally:
        bmod._FAST_PADDING = old


@pytest.mark.parametrize("rank", [1, 2, 3])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_padding_plans_are_bit_identical(rank, dtype):
    g = torch.Generator().manual_seed(rank)
    res, dx = RES[:rank], DX[:rank]
    count = 0
    for b in _boundaries(rank):
        for width in (1, 2):
            x = torch.randn(2, *res, generator=g, dtype=dtype)
            xv = torch.randn(2, rank, *res, generator=g, dtype=dtype)
            cases = [(pad, (x, b, dx, width), {}), (pad, (xv, b, dx, width), {"vector": True})]
            cases += [(pad, (x, b, dx, width), {"axes": [a]}) for a in range(rank)]
            for c in range(rank):
                shape = tuple(n + 1 if a == c else n for a, n in enumerate(res))
                xc = torch.randn(2, *shape, generator=g, dtype=dtype)
                cases.append((pad_staggered_component, (xc, c, b, dx, width), {}))
                cases += [(pad_staggered_component, (xc, c, b, dx, width), {"axes": [a]}) for a in range(rank)]
            for fn, args, kwargs in cases:
                fast, slow = fn(*args, **kwargs), _general(fn, *args, **kwargs)
                assert fast.shape == slow.shape
                assert torch.equal(fast, slow), (fn.__name__, b, width, kwargs)
                count += 1
        for c in range(rank):
            shape = tuple(n + 1 if a == c else n for a, n in enumerate(res))
            xc = torch.randn(2, *shape, generator=g, dtype=dtype)
            assert torch.equal(set_boundary_faces(xc, c, b), _general(set_boundary_faces, xc, c, b)), (b, c)
    assert count > 100


def test_padding_plan_is_used_and_cached():
    b = Boundary.create("wall", 2)
    x = torch.randn(1, 6, 5)
    pad(x, b, (1.0, 1.0))
    keys = [k for k in b._derived if k[0] == "pad"]
    assert len(keys) == 1 and b._derived[keys[0]]  # a plan (not False) for constant rules
    # a tensor-valued Dirichlet side is not constant: the general path, still correct
    bt = Boundary(((Dirichlet(torch.tensor(0.5)), Neumann(0.0)), (NoSlipWall(), NoSlipWall())))
    assert torch.equal(pad(x, bt, (1.0, 1.0)), _general(pad, x, bt, (1.0, 1.0)))
    assert not any(v for k, v in bt._derived.items() if k[0] == "pad")


@pytest.mark.parametrize("rank", [2, 3])
def test_padding_gradients_agree_and_gradcheck(rank):
    res, dx = RES[:rank], DX[:rank]
    b = Boundary(tuple([(Dirichlet(1.5), Neumann(-0.3)), (NoSlipWall(), Open()), (Periodic(), Periodic())][:rank]))
    g = torch.Generator().manual_seed(0)
    x = torch.randn(2, *res, generator=g, dtype=torch.float64, requires_grad=True)
    xv = torch.randn(2, rank, *res, generator=g, dtype=torch.float64, requires_grad=True)
    xc = torch.randn(2, *(n + 1 if a == 1 else n for a, n in enumerate(res)), generator=g, dtype=torch.float64,
                     requires_grad=True)
    fns = [lambda t: pad(t, b, dx, 2), lambda t: pad(t, b, dx, 1, vector=True),
           lambda t: pad_staggered_component(t, 1, b, dx, 2), lambda t: set_boundary_faces(t, 1, b)]
    for fn, inp in zip(fns, (x, xv, xc, xc)):
        w = torch.randn(fn(inp).shape, generator=g, dtype=torch.float64)
        (ga,) = torch.autograd.grad((fn(inp) * w).sum(), inp)
        (gb,) = torch.autograd.grad((_general(fn, inp) * w).sum(), inp)
        torch.testing.assert_close(ga, gb, rtol=1e-14, atol=1e-14)
        assert torch.autograd.gradcheck(fn, (inp,))


def test_boundary_memo_is_not_pickled_and_hash_is_stable():
    b = Boundary.create({"x": "open", "y": "wall"}, 2)
    pb = b.for_pressure()
    assert b.for_pressure() is pb  # memoised
    pad(torch.zeros(1, 4, 4), b, (1.0, 1.0))
    c = pickle.loads(pickle.dumps(b))
    assert "_derived" not in c.__dict__ and "_hash" not in c.__dict__
    assert c == b and hash(c) == hash(b) == hash(Boundary.create({"x": "open", "y": "wall"}, 2))
    assert c.for_pressure() == pb


@pytest.mark.parametrize("rank", [1, 2, 3])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_stacked_limiter_bounds_match_per_axis_bounds(rank, dtype):
    grid = Grid(RES[:rank])
    b = Boundary.create("wall", rank)
    for face_axis in (None, 0):
        loc = _location(grid, b, face_axis)
        g = torch.Generator().manual_seed(1)
        # values rounded to a few levels: many ties, where the gradient's tie-breaking shows
        padded = torch.randint(0, 3, (2, 1, *loc.padded_shape), generator=g).to(dtype).requires_grad_(True)
        index = [torch.rand(2, *loc.shape, generator=g, dtype=dtype) * (n + 4) - 2.5 for n in loc.shape]
        lo, hi = loc.stencil_bounds(padded, index)
        lo2, hi2 = loc.bounds_stacked(padded, loc.stack(index))
        assert torch.equal(lo, lo2) and torch.equal(hi, hi2)
        w = torch.randn(lo.shape, generator=g, dtype=dtype)
        ga = torch.autograd.grad((lo * w).sum() + (hi * w * 2).sum(), padded)[0]
        gb = torch.autograd.grad((lo2 * w).sum() + (hi2 * w * 2).sum(), padded)[0]
        torch.testing.assert_close(ga, gb)
        if rank > 1:
            p = padded.detach()
            assert torch.equal(loc.sample(p, index), loc.sample_stacked(p, loc.stack(index)))


def _state(rank, boundary, dtype, seed=0):
    grid = Grid((12, 10, 8)[:rank])
    g = torch.Generator().manual_seed(seed)
    v = StaggeredGrid([torch.randn(2, *grid.face_shape(i), generator=g, dtype=dtype) for i in range(rank)], grid,
                      boundary).with_boundary_faces()
    m = CenteredGrid(torch.rand(2, *grid.resolution, generator=g, dtype=dtype), grid, v.boundary.for_scalar())
    return FluidState(v, m)


@pytest.mark.parametrize("rank", [2, 3])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("spec", ["wall", "periodic", "mixed"])
def test_step_equals_composition_of_public_functions(rank, dtype, spec):
    if spec == "mixed":
        spec = {"x": "open", "y": ("wall", NoSlipWall((0.3,) * rank)), "z": "free_slip"}
        spec = {k: v for k, v in spec.items() if "xyz".index(k) < rank}
    st = _state(rank, spec, dtype)
    for scheme in ("maccormack", "semi_lagrangian"):
        new = step(st, 0.4, buoyancy_strength=0.5, advection=scheme)
        v0, m0 = st.velocity, st.marker
        m = advect(m0, v0, 0.4, scheme=scheme)
        v = advect(v0, v0, 0.4, scheme=scheme)
        v = buoyancy(v, m, 0.4, strength=0.5)
        v, p = make_incompressible(v)
        assert torch.equal(new.marker.values, m.values)
        assert all(torch.equal(a, b) for a, b in zip(new.velocity.values, v.values))
        assert torch.equal(new.pressure.values, p.values)
        # without buoyancy the step imposes the boundary faces itself (periodic copies included)
        new = step(st, 0.4, advection=scheme)
        v, _ = make_incompressible(advect(v0, v0, 0.4, scheme=scheme))
        assert all(torch.equal(a, b) for a, b in zip(new.velocity.values, v.values))


def test_step_gradients_match_composition():
    st = _state(2, "wall", torch.float64)
    v0 = st.velocity.with_values([c.detach().requires_grad_(True) for c in st.velocity.values])
    st = FluidState(v0, st.marker)
    a = step(st, 0.4, buoyancy_strength=0.5)
    m = advect(st.marker, v0, 0.4, scheme="maccormack")
    v, _ = make_incompressible(buoyancy(advect(v0, v0, 0.4, scheme="maccormack"), m, 0.4, strength=0.5))
    ga = torch.autograd.grad(sum((c ** 2).sum() for c in a.velocity.values) + (a.marker.values ** 2).sum(),
                             v0.values)
    gb = torch.autograd.grad(sum((c ** 2).sum() for c in v.values) + (m.values ** 2).sum(), v0.values)
    for x, y in zip(ga, gb):
        torch.testing.assert_close(x, y, rtol=0, atol=0)


def test_step_validates_at_its_entry():
    st = _state(2, "wall", torch.float64)
    bad = st.velocity.with_values([st.velocity.values[0].clone(), st.velocity.values[1].clone()])
    bad.values[1][0, 3, 4] = float("nan")
    with pytest.raises(NonFiniteError, match="velocity component 1"):
        step(FluidState(bad, st.marker), 0.1)
    with pytest.raises(ParameterError):
        step(st, -0.1)
    other = CenteredGrid(torch.zeros(2, 8, 8, dtype=torch.float64), Grid((8, 8)), "neumann")
    with pytest.raises(GridMismatchError):
        step(FluidState(st.velocity, other), 0.1)
    with pytest.raises(ParameterError, match="buoyancy strength"):
        step(st, 0.1, buoyancy_strength=float("nan"))
    with pytest.raises(ParameterError, match="direction"):
        step(st, 0.1, buoyancy_strength=1.0, buoyancy_direction=(0.0, 1.0, 0.0))
    # no marker: the conservative marker scheme does not apply to the velocity
    out = step(FluidState(st.velocity), 0.1, marker_advection="conservative")
    assert out.marker is None
    # the projection called directly still rejects a non-finite velocity
    with pytest.raises(NonFiniteError):
        make_incompressible(bad)


@pytest.mark.parametrize("rank", [1, 2, 3])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_advection_fast_padding_matches_general_padding(rank, dtype):
    """advect with the cached per-location padders equals advect on the general padding path."""
    for spec in ("wall", "periodic", ("open", Dirichlet(0.5))):
        st = _state(rank, spec if isinstance(spec, str) else [spec] * rank, dtype, seed=3)
        for scheme in ("semi_lagrangian", "maccormack"):
            for field in (st.marker, st.velocity):
                a = advect(field, st.velocity, 0.3, scheme=scheme)
                b = _general(advect, field, st.velocity, 0.3, scheme=scheme)
                va = a.values if isinstance(a.values, tuple) else (a.values,)
                vb = b.values if isinstance(b.values, tuple) else (b.values,)
                assert all(torch.equal(x, y) for x, y in zip(va, vb)), (spec, scheme, type(field).__name__)


def test_advection_gradcheck_through_fast_paths():
    st = _state(2, [("open", Dirichlet(0.5)), "wall"], torch.float64, seed=4)
    grid, b = st.velocity.grid, st.velocity.boundary
    m = st.marker

    def f(u0, u1, q):
        v = StaggeredGrid._trusted((u0, u1), grid, b)
        out = advect(v, v, 0.3, scheme="maccormack")
        mq = advect(CenteredGrid._trusted(q, grid, m.boundary), v, 0.3, scheme="maccormack")
        return (*out.values, mq.values)

    inputs = tuple(t[:1].detach().clone().requires_grad_(True) for t in (*st.velocity.values, m.values))
    assert torch.autograd.gradcheck(f, inputs, atol=1e-7)


def test_large_arrays_take_the_general_path_with_the_same_numbers():
    from phisim.boundary import pad, pad_staggered_component, set_boundary_faces

    n = 150  # 150 * 151 samples per batch entry: above the plans' size limit
    assert n * (n + 1) > bmod._FAST_PADDING_MAX and not bmod._fast_padding((n, n + 1))
    assert bmod._fast_padding((16, 17))
    boundary = Boundary(((NoSlipWall(), Open()), (Dirichlet(0.3), Neumann(0.2))))
    g = torch.Generator().manual_seed(11)
    cells = torch.randn(2, n, n, dtype=torch.float64, generator=g)
    faces = torch.randn(2, n + 1, n, dtype=torch.float64, generator=g)
    old = bmod._FAST_PADDING_MAX
    bmod._FAST_PADDING_MAX = 10**9  # force the plans
    try:
        planned = (pad(cells, boundary, (1.0, 0.5), 2), pad_staggered_component(faces, 0, boundary, (1.0, 0.5), 2),
                   set_boundary_faces(faces, 0, boundary))
    finally:
        bmod._FAST_PADDING_MAX = old
    general = (pad(cells, boundary, (1.0, 0.5), 2), pad_staggered_component(faces, 0, boundary, (1.0, 0.5), 2),
               set_boundary_faces(faces, 0, boundary))
    for a, b in zip(planned, general):
        assert torch.equal(a, b)
