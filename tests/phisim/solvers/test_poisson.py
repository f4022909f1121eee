"""Direct spectral Poisson solver and masked PCG against scipy.sparse.linalg.spsolve on the same stencil."""

import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as spl
import torch

from phisim.errors import BoundaryError, NonFiniteError, ParameterError, ShapeError
from phisim.solvers.linalg import Solve
from phisim.solvers.poisson import (
    masked_laplacian,
    masked_poisson_solve,
    masked_poisson_solve_with_info,
    solve_poisson,
    solve_poisson_with_info,
    spectral_poisson_solve,
    stencil_laplacian,
)
from phisim.spectral import fft

ENGINES = fft.available_engines()


@pytest.fixture(autouse=True)
def _fast_planning():
    with fft.fft_settings(planner_effort="FFTW_ESTIMATE"):
        yield


# ---- an independent sparse reference: the same stencil, assembled cell by cell ------------------


def _lap1d(n, dx, pair):
    A = sp.diags([np.ones(n - 1), -2 * np.ones(n), np.ones(n - 1)], [-1, 0, 1]).tolil()
    if pair[0] == "periodic":
        A[0, n - 1] += 1
        A[n - 1, 0] += 1
    else:  # ghost = -u (Dirichlet on the face) or +u (Neumann)
        A[0, 0] += -1 if pair[0] == "dirichlet" else 1
        A[n - 1, n - 1] += -1 if pair[1] == "dirichlet" else 1
    return A.tocsr() / dx**2


def _lapnd(res, dx, kinds):
    A = 0
    for a in range(len(res)):
        mats = [sp.identity(n, format="csr") for n in res]
        mats[a] = _lap1d(res[a], dx[a], kinds[a])
        K = mats[0]
        for M in mats[1:]:
            K = sp.kron(K, M, format="csr")
        A = A + K
    return A.tocsc()


def _rhs_with_boundary(f, dx, kinds, values):
    """Move boundary values to the rhs by hand: f - 2v/dx^2 (Dirichlet), f - g/dx (Neumann)."""
    f = f.copy()
    for a, pair in enumerate(kinds):
        for side, kind in enumerate(pair):
            v = values[a][side]
            if v is None:
                continue
            idx = [slice(None)] * f.ndim
            idx[a] = 0 if side == 0 else -1
            f[tuple(idx)] -= 2 * v / dx[a] ** 2 if kind == "dirichlet" else v / dx[a]
    return f


D, N, P = "dirichlet", "neumann", "periodic"
CASES = [
    ((12,), ((D, D),), ((0.7, -1.3),)),
    ((11,), ((N, D),), ((0.4, 2.0),)),
    ((10,), ((D, N),), ((1.0, -0.5),)),
    ((9, 8), ((D, D), (D, D)), ((1.5, -0.5), (0.3, 2.0))),
    ((9, 8), ((P, P), (D, D)), ((None, None), (1.0, -1.0))),
    ((8, 10), ((N, N), (D, N)), ((0.2, -0.7), (1.0, 0.5))),
    ((6, 5, 7), ((D, D), (N, N), (P, P)), ((1.0, 2.0), (0.5, -0.25), (None, None))),
    ((5, 6, 4), ((N, D), (D, D), (D, N)), ((0.3, 1.0), (-1.0, 0.2), (0.0, 0.7))),
]


@pytest.mark.parametrize("engine", ENGINES)
@pytest.mark.parametrize("res,kinds,values", CASES)
def test_direct_solver_matches_spsolve(engine, res, kinds, values):
    rng = np.random.default_rng(sum(res))
    dx = tuple(0.5 + rng.random() for _ in res)
    f = rng.standard_normal((2,) + res)
    got = spectral_poisson_solve(torch.from_numpy(f), dx, kinds, values, engine=engine).numpy()
    A = _lapnd(res, dx, kinds)
    for b in range(2):
        ref = spl.spsolve(A, _rhs_with_boundary(f[b], dx, kinds, values).ravel()).reshape(res)
        err = np.abs(got[b] - ref).max() / np.abs(ref).max()
        assert err < 1e-10, err


@pytest.mark.parametrize(
    "res,kinds", [((16,), ((P, P),)), ((9, 8), ((N, N), (N, N))), ((6, 5, 4), ((P, P), (N, N), (P, P)))]
)
def test_singular_cases_zero_mean_solution_matches_spsolve(res, kinds):
    rng = np.random.default_rng(5)
    dx = tuple(0.5 + rng.random() for _ in res)
    values = tuple((None, None) if k[0] == P else (0.3, -0.1) for k in kinds)  # Neumann fluxes
    f = rng.standard_normal(res)
    f = _rhs_with_boundary(f, dx, kinds, values)
    f -= f.mean()  # compatible effective rhs
    f_user = f + (_rhs_with_boundary(np.zeros(res), dx, kinds, values) * -1)  # add the boundary part back
    got = spectral_poisson_solve(torch.from_numpy(f_user)[None], dx, kinds, values)[0].numpy()
    A = _lapnd(res, dx, kinds)
    # pin the constant: solve the bordered system [A 1; 1^T 0]
    n = f.size
    Ab = sp.bmat([[A, np.ones((n, 1))], [np.ones((1, n)), None]]).tocsc()
    ref = spl.spsolve(Ab, np.concatenate([f.ravel(), [0.0]]))[:n].reshape(res)
    assert abs(got.mean()) < 1e-12 * np.abs(got).max()
    assert np.abs(got - ref).max() < 1e-10 * np.abs(ref).max()


def test_incompatible_rhs_is_reported():
    f = torch.randn(2, 16, 16, dtype=torch.float64)
    f = f - f.mean(dim=(1, 2), keepdim=True)
    spectral_poisson_solve(f, 1.0, "neumann")  # compatible: fine
    bad = f.clone()
    bad[1] += 0.5
    with pytest.raises(ParameterError, match=r"incompatible for samples \[1\]"):
        spectral_poisson_solve(bad, 1.0, "neumann")
    with pytest.warns(RuntimeWarning, match="incompatible"):
        u = spectral_poisson_solve(bad, 1.0, "periodic", incompatible="warn")
    assert torch.allclose(u, spectral_poisson_solve(bad, 1.0, "periodic", incompatible="project"))
    # the solution solves the projected problem
    r = stencil_laplacian(u, 1.0, "periodic") - (bad - bad.mean(dim=(1, 2), keepdim=True))
    assert r.abs().max() < 1e-12


def test_bad_settings_raise():
    f = torch.zeros(1, 8, 8, dtype=torch.float64)
    with pytest.raises(BoundaryError):
        spectral_poisson_solve(f, 1.0, ("dirichlet",))
    with pytest.raises(BoundaryError):
        spectral_poisson_solve(f, 1.0, (("periodic", "dirichlet"), "dirichlet"))
    with pytest.raises(BoundaryError):
        spectral_poisson_solve(f, 1.0, ("robin", "dirichlet"))
    with pytest.raises(BoundaryError):
        spectral_poisson_solve(f, 1.0, ("periodic", "dirichlet"), values=((1.0, 0.0), (0.0, 0.0)))
    with pytest.raises(ParameterError):
        spectral_poisson_solve(f, -1.0, "dirichlet")
    with pytest.raises(ParameterError):
        spectral_poisson_solve(f, 1.0, "neumann", incompatible="ignore")
    with pytest.raises(ShapeError):
        spectral_poisson_solve(torch.zeros(8, dtype=torch.float64), 1.0, "dirichlet")
    with pytest.raises(ShapeError):
        spectral_poisson_solve(f, 1.0, "dirichlet", values=((torch.zeros(3), 0.0), (0.0, 0.0)))
    f[0, 1, 1] = float("nan")
    with pytest.raises(NonFiniteError):
        spectral_poisson_solve(f, 1.0, "dirichlet")


def test_tensor_boundary_values_and_gradcheck():
    rng = torch.Generator().manual_seed(0)
    f = torch.randn(2, 6, 5, dtype=torch.float64, generator=rng, requires_grad=True)
    v = torch.randn(2, 1, 5, dtype=torch.float64, generator=rng, requires_grad=True)
    kinds = ("dirichlet", ("neumann", "dirichlet"))

    def solve(f, v):
        return spectral_poisson_solve(f, (0.5, 0.7), kinds, ((v, 1.0), (0.2, None)))

    u = solve(f, v)
    # the solution satisfies the stencil with those boundary values
    r = stencil_laplacian(u, (0.5, 0.7), kinds, ((v, 1.0), (0.2, None))) - f
    assert r.abs().max() < 1e-11
    assert torch.autograd.gradcheck(solve, (f, v))
    fp = torch.randn(1, 6, 8, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(
        lambda f: spectral_poisson_solve(f, 1.0, ("neumann", "periodic"), incompatible="project"), (fp,)
    )


@pytest.mark.skipif("pyfftw" not in ENGINES, reason="pyfftw not installed")
def test_torch_engine_equals_pyfftw_engine():
    f = torch.randn(3, 12, 10, 6, dtype=torch.float64)
    kinds = ("dirichlet", "periodic", ("neumann", "dirichlet"))
    a = spectral_poisson_solve(f, 1.0, kinds, engine="torch")
    b = spectral_poisson_solve(f, 1.0, kinds, engine="pyfftw")
    torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-12)


def _obstacle_mask(n):
    mask = torch.ones(n, n, dtype=torch.bool)
    mask[int(0.25 * n) : int(0.4 * n), int(0.3 * n) : int(0.45 * n)] = False
    mask[int(0.6 * n) : int(0.75 * n), int(0.15 * n) : int(0.28 * n)] = False
    mask[int(0.45 * n) : int(0.55 * n), int(0.7 * n) : int(0.92 * n)] = False
    return mask


def _masked_matrix(mask, dx, kinds):
    """Assemble -laplacian on fluid cells, zero flux into obstacles, identity on obstacle cells."""
    nx, ny = mask.shape
    idx = lambda i, j: i * ny + j  # noqa: E731
    rows, cols, vals = [], [], []
    for i in range(nx):
        for j in range(ny):
            c = idx(i, j)
            if not mask[i, j]:
                rows.append(c), cols.append(c), vals.append(1.0)
                continue
            diag = 0.0
            for a, (di, dj) in enumerate(((1, 0), (0, 1))):
                for s in (-1, 1):
                    ii, jj = i + s * di, j + s * dj
                    n = (nx, ny)[a]
                    pos = (ii, jj)[a]
                    h2 = dx[a] ** 2
                    if 0 <= pos < n or kinds[a][0] == P:
                        ii, jj = ii % nx, jj % ny
                        if mask[ii, jj]:
                            diag += 1 / h2
                            rows.append(c), cols.append(idx(ii, jj)), vals.append(-1 / h2)
                    elif kinds[a][0 if s < 0 else 1] == D:
                        diag += 2 / h2
            rows.append(c), cols.append(c), vals.append(diag)
    return sp.csc_matrix((vals, (rows, cols)), shape=(nx * ny, nx * ny))


def test_masked_solve_matches_spsolve():
    n = 20
    mask = _obstacle_mask(n)
    kinds = ((D, N), (P, P))
    dx = (0.8, 1.1)
    f = torch.randn(2, n, n, dtype=torch.float64)
    u = masked_poisson_solve(f, mask, dx, kinds, solve=Solve(rtol=1e-12))
    A = _masked_matrix(mask.numpy(), dx, kinds)
    for b in range(2):
        ref = spl.spsolve(A, -(f[b] * mask).numpy().ravel()).reshape(n, n)
        assert np.abs(u[b].numpy() - ref).max() < 1e-9 * np.abs(ref).max()
    assert (u[:, ~mask] == 0).all()


def test_masked_closed_box_singular_and_residual():
    n = 24
    mask = _obstacle_mask(n)
    f = torch.randn(1, n, n, dtype=torch.float64) * mask
    f = f - f.sum() / mask.sum() * mask
    u = masked_poisson_solve(f, mask, 1.0, "neumann", solve=Solve(rtol=1e-10))
    r = masked_laplacian(u, mask, 1.0, "neumann") - f
    assert r.norm() < 1e-9 * f.norm()
    assert abs(float(u[0][mask].mean())) < 1e-12
    with pytest.raises(ParameterError, match="incompatible"):
        masked_poisson_solve(f + 0.3 * mask, mask, 1.0, "neumann")


def test_spectral_preconditioner_cuts_iterations_fivefold_128():
    n = 128
    mask = _obstacle_mask(n)
    f = torch.randn(2, n, n, dtype=torch.float64, generator=torch.Generator().manual_seed(1)) * mask
    f = f - f.sum(dim=(1, 2), keepdim=True) / mask.sum() * mask
    settings = Solve(rtol=1e-6)
    _, pre = masked_poisson_solve_with_info(f, mask, 1.0, "neumann", solve=settings)
    _, plain = masked_poisson_solve_with_info(f, mask, 1.0, "neumann", solve=settings, preconditioner=None)
    assert pre.all_converged and plain.all_converged
    assert (pre.iterations * 5 <= plain.iterations).all(), (pre.iterations, plain.iterations)


def test_masked_gradient_flows_to_rhs():
    n = 8
    mask = _obstacle_mask(n)
    f = torch.randn(1, n, n, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(
        lambda f: masked_poisson_solve(f, mask, 1.0, "dirichlet", solve=Solve(rtol=1e-12)), (f,)
    )


def test_field_wrapper_uses_field_boundary():
    from phisim import Boundary, CenteredGrid, Dirichlet, Grid, Neumann

    grid = Grid((12, 10), bounds=[(0, 2.4), (0, 1)])
    boundary = Boundary.create([(Dirichlet(1.0), Neumann(0.5)), "periodic"], 2)
    f = CenteredGrid(torch.randn(2, 12, 10, dtype=torch.float64), grid, boundary)
    u = solve_poisson(f)
    assert isinstance(u, CenteredGrid) and u.boundary == boundary
    ref = spectral_poisson_solve(f.values, grid.dx, ((D, N), P), ((1.0, 0.5), (None, None)))
    torch.testing.assert_close(u.values, ref)
    # the laplacian of the solution, with the field's own ghost cells, is the rhs
    from phisim import pad

    p = pad(u.values, boundary, grid.dx)
    lap = sum(
        (p.narrow(1 + a, 2, s[a]) - 2 * p.narrow(1 + a, 1, s[a]) + p.narrow(1 + a, 0, s[a])).narrow(
            2 - a, 1, s[1 - a]
        )
        / grid.dx[a] ** 2
        for a, s in [(0, (12, 10)), (1, (12, 10))]
    )
    assert (lap - f.values).abs().max() < 1e-10


def test_masked_solve_handles_enclosed_pockets_per_region():
    """A ring of obstacle cells encloses a pocket: each closed region gets its own compatibility and gauge."""
    from phisim.solvers.poisson import masked_laplacian, masked_poisson_solve

    _t = torch

    n = 16
    m = _t.ones(n, n, dtype=_t.bool)
    m[4:12, 4] = m[4:12, 11] = m[4, 4:12] = m[11, 4:12] = False  # the ring; cells 5..10 form the pocket
    g = _t.Generator().manual_seed(0)
    rhs = _t.randn(1, n, n, generator=g, dtype=_t.float64) * m
    inner = _t.zeros(n, n, dtype=_t.bool)
    inner[5:11, 5:11] = True
    outer = m & ~inner
    for region in (inner, outer):  # zero net source in each region
        rhs[0][region] -= rhs[0][region].mean()
    u = masked_poisson_solve(rhs, m, 1.0, "neumann", solve=Solve(rtol=1e-12))
    assert _t.allclose(masked_laplacian(u, m, 1.0, "neumann"), rhs, atol=1e-9)
    assert abs(float(u[0][inner].mean())) < 1e-12 and abs(float(u[0][outer].mean())) < 1e-12
    bad = rhs.clone()
    bad[0][inner] += 1.0  # the pocket alone is incompatible (the total still could be anything)
    with pytest.raises(ParameterError, match="pocket"):
        masked_poisson_solve(bad, m, 1.0, "neumann")
    u2 = masked_poisson_solve(bad, m, 1.0, "neumann", incompatible="project", solve=Solve(rtol=1e-12))
    assert _t.allclose(u2, u, atol=1e-9)  # the pocket's mean was removed, nothing else changed


@pytest.mark.parametrize("kinds,shape", [
    ("dirichlet", (2, 7, 5)), ("neumann", (2, 7, 5)), ("periodic", (2, 7, 5)), ("dirichlet", (1, 1, 4)),
    ("neumann", (1, 1, 4)), ("periodic", (1, 1, 4)),
    ((("dirichlet", "neumann"), ("periodic", "periodic")), (3, 6, 4)),
    ((("neumann", "dirichlet"), ("dirichlet", "dirichlet"), ("periodic", "periodic")), (2, 3, 4, 5)),
])
def test_fused_stencil_equals_face_flux_form(kinds, shape):
    from phisim.ops.stencil import laplace_zero
    from phisim.solvers.poisson import _open_faces, normalize_kinds

    rank = len(shape) - 1
    k = normalize_kinds(kinds, rank)
    dx = (0.7, 1.3, 0.9)[:rank]
    u = torch.randn(*shape, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    ones = _open_faces(torch.ones(shape, dtype=torch.float64), k)  # all faces open: the face-flux form
    ref = laplace_zero(u, dx, k, ones)
    torch.testing.assert_close(stencil_laplacian(u, dx, kinds), ref, rtol=1e-13, atol=1e-13)
    torch.testing.assert_close(stencil_laplacian(u.float(), dx, kinds), ref.float(), rtol=1e-5, atol=1e-5)
    v = u[:1].clone().requires_grad_(True)
    assert torch.autograd.gradcheck(lambda t: stencil_laplacian(t, dx, kinds), (v,))


def test_one_return_type_and_the_with_info_variants():
    n = 16
    mask = torch.ones(n, n, dtype=torch.bool)
    mask[6:10, 6:10] = False
    f = torch.randn(1, n, n, dtype=torch.float64, generator=torch.Generator().manual_seed(3)) * mask
    f = f - f.sum() / mask.sum() * mask
    u = masked_poisson_solve(f, mask, 1.0, "neumann")
    assert isinstance(u, torch.Tensor)
    out = masked_poisson_solve_with_info(f, mask, 1.0, "neumann")
    torch.testing.assert_close(out.solution, u, rtol=0, atol=0)
    assert out.info.all_converged
    with pytest.raises(ParameterError, match="return_info was removed"):
        masked_poisson_solve(f, mask, 1.0, "neumann", return_info=True)
    from phisim import CenteredGrid, Grid

    rhs = CenteredGrid(f, Grid((n, n)), "neumann")
    field, info = solve_poisson_with_info(rhs, mask=mask)
    torch.testing.assert_close(field.values, solve_poisson(rhs, mask=mask).values, rtol=0, atol=0)
    assert info.all_converged
    assert solve_poisson_with_info(rhs).info is None  # the exact spectral solve
