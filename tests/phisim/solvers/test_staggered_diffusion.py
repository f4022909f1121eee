"""Tests of diffuse_staggered: exact box solves against dense references, bodies by PCG, orders, gradients."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.fft as sfft
import scipy.linalg
import torch

from phisim import Grid, NoSlipWall, StaggeredGrid
from phisim.boundary import Boundary, Dirichlet
from phisim.errors import ParameterError, ShapeError
from phisim.ops.differential import laplace
from phisim.solvers.diffusion import diffuse, diffuse_staggered
from phisim.spectral import fft

F64 = torch.float64

BOUNDARIES = [
    "wall",
    "periodic",
    "open",
    "free_slip",
    {"x": "periodic", "y": "wall"},
    {"x": ("wall", "open"), "y": ("open", "wall")},
    {"x": "wall", "y": ("wall", NoSlipWall(velocity=(1.0, 0.0)))},
    {"x": (Dirichlet((0.5, 0.2)), "open"), "y": "free_slip"},
]


@pytest.fixture(autouse=True)
def _fast_planning():
    with fft.fft_settings(planner_effort="FFTW_ESTIMATE"):
        yield


def _random_velocity(grid, boundary, batch=2, seed=0) -> StaggeredGrid:
    g = torch.Generator().manual_seed(seed)
    b = Boundary.create(boundary, grid.rank)
    values = tuple(torch.randn(batch, *grid.face_shape(i), generator=g, dtype=F64) for i in range(grid.rank))
    return StaggeredGrid(values, grid, b).with_boundary_faces()


def _free_system(v: StaggeredGrid, i: int, b: int):
    """Component ``i`` of sample ``b`` as an affine system on its free samples.

    Returns ``(A, c, y0, full)``: ``L x = A y + c`` on the free samples ``y``, their current values, and a
    function mapping free values to the full component (fixed samples from the boundary, face n = face 0 on
    a periodic axis).
    """
    comps = [c[b : b + 1] for c in v.values]
    probe = StaggeredGrid(tuple(torch.full_like(c, 7.0) if j == i else c for j, c in enumerate(comps)), v.grid,
                          v.boundary).with_boundary_faces().values[i][0]
    free = (probe == 7.0).numpy()
    if v.boundary.is_periodic(i):
        free[(slice(None),) * i + (-1,)] = False
    base = v.with_boundary_faces().values[i][b].numpy()
    f = free.reshape(-1)

    def full(y):
        x = base.reshape(-1).copy()
        x[f] = y
        x = x.reshape(base.shape)
        if v.boundary.is_periodic(i):
            idx = [slice(None)] * x.ndim
            idx[i] = -1
            src = [slice(None)] * x.ndim
            src[i] = 0
            x[tuple(idx)] = x[tuple(src)]
        return x

    def lap(y):
        x = torch.as_tensor(full(y))[None]
        field = StaggeredGrid(tuple(x if j == i else c for j, c in enumerate(comps)), v.grid, v.boundary)
        return laplace(field).values[i][0].numpy().reshape(-1)[f]

    m = int(f.sum())
    c = lap(np.zeros(m))
    A = np.stack([lap(np.eye(m)[k]) - c for k in range(m)], 1)
    return A, c, base.reshape(-1)[f], full


def _theta_reference(v: StaggeredGrid, alpha: float, theta: float):
    """Dense θ-scheme: ``(I - θαA) y' = y + (1-θ)α A y + α c`` on the free samples of every component."""
    out = []
    for i in range(v.rank):
        res = []
        for b in range(v.batch_size):
            A, c, y, full = _free_system(v, i, b)
            y1 = np.linalg.solve(np.eye(len(y)) - theta * alpha * A, y + (1 - theta) * alpha * A @ y + alpha * c)
            res.append(full(y1))
        out.append(np.stack(res))
    return out


# ---- the transforms used --------------------------------------------------------------------------------


@pytest.mark.parametrize("kind", ["dct1", "dst1"])
@pytest.mark.parametrize("engine", ["torch", "pyfftw"])
def test_type1_transforms_match_scipy_and_gradcheck(kind, engine):
    if engine not in fft.available_engines():
        pytest.skip("pyfftw not installed")
    x = torch.randn(3, 7, 5, dtype=F64)
    y = fft.r2rn(x, (kind, kind), (1, 2), engine=engine)
    ref = (sfft.dctn if kind == "dct1" else sfft.dstn)(x.numpy(), type=1, axes=(1, 2))
    np.testing.assert_allclose(y.numpy(), ref, rtol=1e-12, atol=1e-12)
    xx = torch.randn(2, 6, 4, dtype=F64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda z: fft.r2rn(z, kind, (1, 2), engine=engine), (xx,))


# ---- exactness in a box ----------------------------------------------------------------------------------


@pytest.mark.parametrize("boundary", BOUNDARIES, ids=str)
@pytest.mark.parametrize("method, theta", [("implicit", 1.0), ("crank_nicolson", 0.5)])
def test_box_solve_equals_dense_theta_scheme(boundary, method, theta):
    grid = Grid((7, 5), bounds=[(0, 1.4), (0, 1.0)])
    v = _random_velocity(grid, boundary)
    alpha = 0.03
    out = diffuse_staggered(v, 1.5, viscosity=alpha / 1.5, method=method)
    ref = _theta_reference(v, alpha, theta)
    for a, r in zip(out.values, ref):
        np.testing.assert_allclose(a.numpy(), r, rtol=0, atol=1e-11)


@pytest.mark.parametrize("boundary", ["wall", {"x": "open", "y": ("wall", NoSlipWall(velocity=(1.0, 0.0)))},
                                      {"x": "periodic", "y": ("open", "free_slip")}], ids=str)
def test_spectral_method_is_the_matrix_exponential(boundary):
    grid = Grid((6, 5), bounds=[(0, 1.2), (0, 1.0)])
    v = _random_velocity(grid, boundary, batch=1)
    alpha = 0.02
    out = diffuse_staggered(v, 1.0, viscosity=alpha, method="spectral")
    for i in range(2):
        A, c, y, full = _free_system(v, i, 0)
        E = scipy.linalg.expm(alpha * A)
        expected = E @ y + np.linalg.solve(A, (E - np.eye(len(y))) @ c)  # u(t) = e^{tA} y + A^{-1}(e^{tA} - I) c
        np.testing.assert_allclose(out.values[i][0].numpy(), full(expected), rtol=0, atol=1e-11)


def test_3d_box_against_dense_reference_and_batch_one():
    grid = Grid((4, 3, 5), bounds=[(0, 1), (0, 0.75), (0, 1.25)])
    v = _random_velocity(grid, {"x": "periodic", "y": "wall", "z": ("open", "free_slip")}, batch=3)
    out = diffuse_staggered(v, 0.02, viscosity=1.0)
    for a, r in zip(out.values, _theta_reference(v, 0.02, 1.0)):
        np.testing.assert_allclose(a.numpy(), r, rtol=0, atol=1e-11)
    one = diffuse_staggered(v._map(lambda c: c[2:]), 0.02, viscosity=1.0)
    for a, r in zip(one.values, out.values):
        torch.testing.assert_close(a[0], r[2], rtol=0, atol=1e-13)


# ---- walls on both sides: periodic FFT plus a one-face correction instead of the DST-I -----------------------


@pytest.fixture(autouse=True)
def _restore_fft_settings():
    """Tests that choose the wall route through the FFT settings get the previous settings back."""
    previous = fft.get_fft_settings()
    yield
    fft.set_fft_settings(previous)


def _count_wall_solves(monkeypatch):
    """Force the wall path at any size (``wall_solve_min_samples=0``); return the list that records its calls."""
    fft.set_fft_settings(wall_solve_min_samples=0)
    calls = []
    real = fft.wall_solve

    def spy(*args, **kwargs):
        out = real(*args, **kwargs)
        calls.append(out is not None)
        return out

    monkeypatch.setattr(fft, "wall_solve", spy)
    return calls


@pytest.mark.skipif("pyfftw" not in fft.available_engines(), reason="the fast path runs with the pyfftw engine")
@pytest.mark.parametrize("res, boundary", [
    ((7, 5), "wall"), ((6, 9), "free_slip"), ((2, 3), "wall"), ((8, 6), {"x": "wall", "y": "open"}),
    ((7, 6), {"x": "wall", "y": ("wall", "open")}), ((4, 3, 5), "wall"),
    ((5, 4, 3), {"x": "open", "y": "wall", "z": "free_slip"})],
    ids=str)
@pytest.mark.parametrize("method, theta", [("implicit", 1.0), ("crank_nicolson", 0.5)])
@pytest.mark.parametrize("transposed", [False, True])
def test_wall_solve_equals_dense_theta_scheme(res, boundary, method, theta, transposed, monkeypatch):
    # The periodic embedding is exact: it must reproduce the dense θ-scheme on the free faces to round-off,
    # for odd and even n, the smallest n (2: one unknown), 2-D and 3-D, with either layout of the FFT.
    calls = _count_wall_solves(monkeypatch)
    if transposed:
        fft.set_fft_settings(wall_transpose_bytes=0)  # restored by the _fast_planning fixture
    grid = Grid(res, bounds=[(0, 0.2 * n) for n in res])
    v = _random_velocity(grid, boundary, batch=2)
    alpha = 0.05
    out = diffuse_staggered(v, 1.0, viscosity=alpha, method=method)
    walls = [i for i in range(grid.rank) if v.boundary.sides[i][0].rule("normal", i)[0] == "odd"
             and v.boundary.sides[i][1].rule("normal", i)[0] == "odd"]
    assert calls == [True] * len(walls) and walls  # every component with walls on its own axis took the path
    for a, r in zip(out.values, _theta_reference(v, alpha, theta)):
        np.testing.assert_allclose(a.numpy(), r, rtol=0, atol=1e-11)


@pytest.mark.skipif("pyfftw" not in fft.available_engines(), reason="the fast path runs with the pyfftw engine")
@pytest.mark.parametrize("dtype", [torch.float32, F64])
@pytest.mark.parametrize("alpha", [1e-3, 2.0, 1e6])
def test_wall_solve_agrees_with_the_dst1_solve_at_any_viscosity(dtype, alpha, monkeypatch):
    # The correction subtracts G/G(0) times face 0 of the periodic answer; m = 1/(1 - cλ) <= 1 and G peaks at
    # its source, so nothing is amplified: float64 agrees with the DST-I route to 1e-13 even at ν dt/dx² = 1e6,
    # float32 to its own round-off.
    grid = Grid((40, 36), bounds=[(0, 1.0), (0, 0.9)])
    v = _random_velocity(grid, "wall", batch=1)
    v = v.with_values(tuple(c.to(dtype) for c in v.values))
    h = grid.dx[0] ** 2 * alpha
    with fft.fft_settings(wall_solve_min_samples=10**9):  # the DST-I route
        ref = diffuse_staggered(v, h, viscosity=1.0)
    calls = _count_wall_solves(monkeypatch)
    out = diffuse_staggered(v, h, viscosity=1.0)
    assert calls == [True, True]
    tol = 1e-13 if dtype == F64 else 1e-6
    for a, r in zip(out.values, ref.values):
        assert a.dtype == dtype
        torch.testing.assert_close(a, r, rtol=0, atol=tol * float(r.abs().max()))
        assert float(a[:, 0].abs().max()) == 0 or float(a[:, :, 0].abs().max()) == 0  # the walls stay exactly zero


def _built(cache: dict) -> list:
    """The capacitance solves kept in a caller's cache."""
    return [v[1] for k, v in cache.items() if k[0] == "capacitance" and v[1]]


@pytest.mark.skipif("pyfftw" not in fft.available_engines(), reason="the fast path runs with the pyfftw engine")
@pytest.mark.parametrize("rank", [2, 3])
def test_capacitance_with_the_wall_solve_equals_converged_cg(rank, monkeypatch):
    from phisim.solvers.linalg import Solve

    res = (10, 8) if rank == 2 else (6, 5, 7)
    grid = Grid(res, bounds=[(0, 0.1 * n) for n in res])
    v = _random_velocity(grid, "wall", batch=2)
    masks = _body_masks(grid)
    v = v.with_values(tuple(torch.where(m, torch.randn_like(c), c) for c, m in zip(v.values, masks)))
    cg = diffuse_staggered(v, 0.02, viscosity=1.0, method="crank_nicolson", fixed=masks, solve=Solve(rtol=1e-13))
    cache: dict = {}
    diffuse_staggered(v, 0.02, viscosity=1.0, method="crank_nicolson", fixed=masks, capacitance=cache)
    calls = _count_wall_solves(monkeypatch)
    out = diffuse_staggered(v, 0.02, viscosity=1.0, method="crank_nicolson", fixed=masks, capacitance=cache)
    assert calls[-2 * rank:] == [True] * (2 * rank)  # both box solves of every component
    for a, b in zip(out.values, cg.values):
        torch.testing.assert_close(a, b, rtol=0, atol=1e-11)


def test_wall_solve_is_bit_identical_in_fresh_processes():
    # 128² float32 takes the periodic wall path by default; two fresh processes must agree bit for bit.
    import hashlib
    import subprocess
    import sys

    code = ("import torch, hashlib; from phisim import Grid, StaggeredGrid; "
            "from phisim.solvers.diffusion import diffuse_staggered; g = torch.Generator().manual_seed(3); "
            "grid = Grid((128, 128), bounds=[(0, 1), (0, 1)]); "
            "v = StaggeredGrid(tuple(torch.randn(1, *grid.face_shape(i), generator=g) for i in range(2)), grid, "
            "'wall').with_boundary_faces(); "
            "out = diffuse_staggered(v, 1e-3, viscosity=1.0, method='crank_nicolson'); "
            "print(hashlib.sha256(b''.join(c.numpy().tobytes() for c in out.values)).hexdigest())")
    outs = [subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
            for _ in range(2)]
    assert outs[0] == outs[1] and len(outs[0].strip()) == len(hashlib.sha256().hexdigest())


def test_wall_solve_declines_and_checks(monkeypatch):
    grid = Grid((6, 5), bounds=[(0, 1.2), (0, 1)])
    v = _random_velocity(grid, "wall", batch=1)
    x = v.values[0][:, 1:6]
    mult = torch.ones(1, 4, 5, dtype=F64)
    green = torch.ones(1, 6, 5, dtype=F64)
    args = (1, ("dst2",), ("dst3",), (2,), mult, green)
    assert fft.wall_solve(x, torch.empty(1, 7, 5, dtype=F64), *args, engine="torch") is None
    assert fft.wall_solve(x.clone().requires_grad_(True), torch.empty(1, 7, 5, dtype=F64), *args) is None
    if "pyfftw" in fft.available_engines():
        with pytest.raises(ShapeError, match="out"):
            fft.wall_solve(x, torch.empty(1, 6, 5, dtype=F64), *args, engine="pyfftw")


def test_taylor_green_decay_orders_in_time():
    """Pure viscous decay of a periodic mode: BE first order, CN second order, spectral exact."""
    n = 16
    grid = Grid((n, n), bounds=[(0, 2 * np.pi), (0, 2 * np.pi)])

    def tg(x):
        return torch.stack([torch.sin(x[..., 0]) * torch.cos(x[..., 1]),
                            -torch.cos(x[..., 0]) * torch.sin(x[..., 1])], -1)

    v0 = StaggeredGrid.from_function(tg, grid, "periodic", dtype=F64)
    lam = -2 * (4 * np.sin(grid.dx[0] / 2) ** 2) / grid.dx[0] ** 2  # stencil eigenvalue of the mode
    nu, t_end = 0.5, 1.0
    exact = np.exp(nu * lam * t_end)
    errs = {}
    for method in ("implicit", "crank_nicolson", "spectral"):
        errs[method] = []
        for steps in (4, 8, 16):
            v = v0
            for _ in range(steps):
                v = diffuse_staggered(v, t_end / steps, viscosity=nu, method=method)
            errs[method].append(float((v.values[0] - exact * v0.values[0]).abs().max()))
    rate = {m: np.log2(np.array(e[:-1]) / np.array(e[1:])) for m, e in errs.items() if m != "spectral"}
    assert np.all(np.abs(rate["implicit"] - 1) < 0.15), rate
    assert np.all(np.abs(rate["crank_nicolson"] - 2) < 0.05), rate
    assert max(errs["spectral"]) < 1e-13


# ---- bodies: fixed faces solved by PCG ------------------------------------------------------------------


@pytest.mark.parametrize("method, theta", [("implicit", 1.0), ("crank_nicolson", 0.5)])
def test_fixed_faces_satisfy_the_theta_scheme(method, theta):
    grid = Grid((10, 8), bounds=[(0, 1.25), (0, 1.0)])
    boundary = {"x": ("wall", "open"), "y": ("wall", NoSlipWall(velocity=(1.0, 0.0)))}
    v = _random_velocity(grid, boundary, batch=2)
    # a body: faces touching cells 3..5 x 2..4 keep their (moving) velocity
    solid = torch.zeros(10, 8, dtype=torch.bool)
    solid[3:6, 2:5] = True
    masks = []
    for i in range(2):
        m = torch.zeros(grid.face_shape(i), dtype=torch.bool)
        lo = [slice(3, 7), slice(2, 5)] if i == 0 else [slice(3, 6), slice(2, 6)]
        m[tuple(lo)] = True
        masks.append(m)
    values = tuple(torch.where(m, torch.full_like(c, 0.3 * (i + 1)), c)
                   for i, (c, m) in enumerate(zip(v.values, masks)))
    v = v.with_values(values)
    alpha = 0.05
    out = diffuse_staggered(v, alpha, viscosity=1.0, method=method, fixed=masks)
    box = diffuse_staggered(v, alpha, viscosity=1.0, method=method)
    lap_new, lap_old = laplace(out), laplace(v)
    for i in range(2):
        m = masks[i]
        torch.testing.assert_close(out.values[i][:, m], v.values[i][:, m], rtol=0, atol=0)
        # free interior faces (not on the boundary) satisfy the scheme
        resid = (out.values[i] - theta * alpha * lap_new.values[i]
                 - v.values[i] - (1 - theta) * alpha * lap_old.values[i])
        dim = 1 + i
        inner = resid.narrow(dim, 1, resid.shape[dim] - 2)
        inner_mask = ~m.narrow(i, 1, m.shape[i] - 2)
        assert float(inner[:, inner_mask].abs().max()) < 1e-8
        assert float((out.values[i] - box.values[i]).abs().max()) > 1e-3  # the body matters


def _body_masks(grid):
    masks = []
    for i in range(grid.rank):
        m = torch.zeros(grid.face_shape(i), dtype=torch.bool)
        m[tuple(slice(2, 4 + (a == i)) for a in range(grid.rank))] = True
        masks.append(m)
    return masks


@pytest.mark.parametrize("rank, boundary", [(2, "wall"), (2, "periodic"), (2, "open"),
                                            (2, {"x": ("wall", "open"), "y": ("open", "wall")}),
                                            (2, {"x": "wall", "y": ("wall", NoSlipWall(velocity=(1.0, 0.0)))}),
                                            (3, "wall"), (3, {"x": "periodic", "y": "free_slip", "z": "open"})])
@pytest.mark.parametrize("method", ["implicit", "crank_nicolson"])
def test_capacitance_solve_equals_converged_cg(rank, boundary, method):
    from phisim.solvers.linalg import Solve

    res = (10, 8) if rank == 2 else (6, 5, 7)
    grid = Grid(res, bounds=[(0, 0.1 * n) for n in res])
    v = _random_velocity(grid, boundary, batch=2)
    masks = _body_masks(grid)
    v = v.with_values(tuple(torch.where(m, torch.randn_like(c), c) for c, m in zip(v.values, masks)))
    tight = Solve(rtol=1e-13)
    first = diffuse_staggered(v, 0.02, viscosity=1.0, method=method, fixed=masks, solve=tight)  # PCG: no cache
    cache: dict = {}
    second = diffuse_staggered(v, 0.02, viscosity=1.0, method=method, fixed=masks, capacitance=cache)  # builds C
    assert len(_built(cache)) == rank
    third = diffuse_staggered(v, 0.02, viscosity=1.0, method=method, fixed=masks, capacitance=cache)  # kept C
    for a, b, c, m, u in zip(first.values, second.values, third.values, masks, v.values):
        torch.testing.assert_close(b, a, rtol=0, atol=1e-12)
        torch.testing.assert_close(c, b, rtol=0, atol=0)
        torch.testing.assert_close(b[:, m], u[:, m], rtol=0, atol=0)
    # float32: the same direct solve, to float32 round-off
    v32 = v.with_values(tuple(c.float() for c in v.values))
    out32 = diffuse_staggered(v32, 0.02, viscosity=1.0, method=method, fixed=masks, capacitance={})
    for a, b in zip(out32.values, second.values):
        assert a.dtype == torch.float32
        torch.testing.assert_close(a.double(), b, rtol=0, atol=2e-5 * float(b.abs().max()))


@pytest.mark.parametrize("dtype", [torch.float32, F64])
def test_capacitance_with_the_torch_engine_matches_pyfftw(dtype):
    # the composed, differentiable transforms (the path accelerators take) give the same direct solve
    grid = Grid((9, 8), bounds=[(0, 0.9), (0, 0.8)])
    v = _random_velocity(grid, "wall", batch=2)
    v = v.with_values(tuple(c.to(dtype) for c in v.values))
    masks = _body_masks(grid)
    outs = {}
    for engine in ("torch", None):
        cache: dict = {}
        outs[engine] = diffuse_staggered(v, 0.03, viscosity=1.0, method="crank_nicolson", fixed=masks,
                                         engine=engine, capacitance=cache)
        assert _built(cache)
    tol = 1e-12 if dtype == F64 else 2e-6
    for a, b in zip(outs["torch"].values, outs[None].values):
        torch.testing.assert_close(a, b, rtol=0, atol=tol * float(b.abs().max()))


def test_capacitance_declines_what_it_cannot_do():
    grid = Grid((8, 6), bounds=[(0, 1), (0, 0.75)])
    v = _random_velocity(grid, "wall", batch=2)
    masks = _body_masks(grid)
    cache: dict = {}
    per_sample = [torch.stack([m, torch.zeros_like(m)]) for m in masks]  # a different body per sample
    a = diffuse_staggered(v, 0.05, viscosity=1.0, fixed=per_sample, capacitance=cache)
    nu = torch.tensor(1.0, dtype=F64)
    diffuse_staggered(v, 0.05, viscosity=nu, fixed=masks, capacitance=cache)  # a tensor viscosity: CG (gradient)
    assert not _built(cache)
    # sample 1 has no body: the box solve
    box = diffuse_staggered(v, 0.05, viscosity=1.0)
    for x, y in zip(a.values, box.values):
        torch.testing.assert_close(x[1], y[1], rtol=0, atol=1e-9)
    # a changed body (same shape) is a new matrix, not a stale one
    b = diffuse_staggered(v, 0.05, viscosity=1.0, fixed=masks, capacitance=cache)
    moved = [torch.roll(m, 1, 0) for m in masks]
    c = diffuse_staggered(v, 0.05, viscosity=1.0, fixed=moved, capacitance=cache)
    ref = diffuse_staggered(v, 0.05, viscosity=nu, fixed=moved)  # CG
    for x, y, z in zip(b.values, c.values, ref.values):
        assert float((x - y).abs().max()) > 1e-3
        torch.testing.assert_close(y, z, rtol=0, atol=1e-8)


def test_capacitance_is_built_at_the_first_request_of_its_owner_and_never_without_one():
    grid = Grid((12, 10), bounds=[(0, 1.2), (0, 1)])
    v = _random_velocity(grid, "wall", batch=1)
    mask = torch.zeros(grid.face_shape(0), dtype=torch.bool)
    mask[3:8, 2:7] = True  # surface: the faces of the block's rim
    cg = diffuse_staggered(v, 0.05, viscosity=1.0, fixed=(mask, None))
    cache: dict = {}
    out = diffuse_staggered(v, 0.05, viscosity=1.0, fixed=(mask, None), capacitance=cache)
    (solver,) = _built(cache)
    assert solver.surface.numel() == 5 * 5 - 3 * 3  # the rim of a 5 x 5 block of faces
    for a, b in zip(out.values, cg.values):
        torch.testing.assert_close(a, b, rtol=0, atol=1e-8)


def test_gradcheck_capacitance_path():
    grid = Grid((5, 4), bounds=[(0, 1), (0, 0.8)])
    b = Boundary.create({"x": "wall", "y": "open"}, 2)
    mask = (torch.zeros(6, 4, dtype=torch.bool).index_fill_(0, torch.tensor([2]), True), None)
    u0 = torch.randn(1, 6, 4, dtype=F64, requires_grad=True)
    w0 = torch.randn(1, 5, 5, dtype=F64, requires_grad=True)
    cache: dict = {}

    def fn(u, w):
        v = StaggeredGrid((u, w), grid, b).with_boundary_faces()
        return diffuse_staggered(v, 0.1, viscosity=0.7, method="crank_nicolson", fixed=mask, capacitance=cache).values

    fn(u0.detach(), w0.detach())
    assert _built(cache)
    assert torch.autograd.gradcheck(fn, (u0, w0))


def test_gradcheck_spectral_and_cg_paths():
    grid = Grid((4, 3), bounds=[(0, 1), (0, 0.75)])
    b = Boundary.create({"x": "open", "y": "wall"}, 2)
    u0 = torch.randn(1, 5, 3, dtype=F64, requires_grad=True)
    w0 = torch.randn(1, 4, 4, dtype=F64, requires_grad=True)
    mask = (torch.zeros(5, 3, dtype=torch.bool).index_fill_(0, torch.tensor([2]), True), None)

    def fn(u, w, nu):
        v = StaggeredGrid((u, w), grid, b).with_boundary_faces()
        a = diffuse_staggered(v, 0.1, viscosity=nu, method="crank_nicolson").values
        c = diffuse_staggered(v, 0.1, viscosity=nu, fixed=mask).values
        return a + c

    nu = torch.tensor(0.7, dtype=F64, requires_grad=True)
    assert torch.autograd.gradcheck(fn, (u0, w0, nu))


@pytest.mark.parametrize("method", ["implicit", "crank_nicolson", "spectral"])
def test_gradient_reaches_the_viscosity_when_only_it_requires_grad(method):
    # A velocity without gradient and a viscosity with one: the box fast paths must not detach the multiplier.
    grid = Grid((6, 5), bounds=[(0, 1.2), (0, 1)])
    v = _random_velocity(grid, "wall", batch=1)

    def fn(nu):
        return sum((c**2).sum() for c in diffuse_staggered(v, 0.05, viscosity=nu, method=method).values)

    nu = torch.tensor(0.7, dtype=F64, requires_grad=True)
    out = fn(nu)
    assert out.requires_grad
    assert torch.autograd.gradcheck(fn, (nu,))


# ---- API -------------------------------------------------------------------------------------------------


def test_diffuse_dispatches_staggered_and_explicit_matches_laplace():
    grid = Grid((8, 6), bounds=[(0, 1), (0, 1)])
    v = _random_velocity(grid, "wall")
    a = diffuse(v, 0.001, viscosity=1.0, method="spectral")
    b = diffuse_staggered(v, 0.001, viscosity=1.0, method="spectral")
    for x, y in zip(a.values, b.values):
        torch.testing.assert_close(x, y, rtol=0, atol=0)
    e = diffuse_staggered(v, 0.001, viscosity=1.0, method="explicit")
    ref = (v + 0.001 * laplace(v)).with_boundary_faces()
    for x, y in zip(e.values, ref.values):
        torch.testing.assert_close(x, y, rtol=0, atol=1e-14)


def test_bad_arguments():
    grid = Grid((8, 6), bounds=[(0, 1), (0, 1)])
    v = _random_velocity(grid, "wall")
    with pytest.raises(ParameterError, match="method"):
        diffuse_staggered(v, 0.1, viscosity=1.0, method="rk4")
    with pytest.raises(ParameterError, match="unstable"):
        diffuse_staggered(v, 1.0, viscosity=1.0, method="explicit")
    with pytest.raises(ParameterError, match="viscosity"):
        diffuse_staggered(v, 0.1, viscosity=-1.0)
    with pytest.raises(ParameterError, match="StaggeredGrid"):
        diffuse_staggered(1.0, 0.1, viscosity=1.0)
    masks = (torch.ones(9, 6, dtype=torch.bool), torch.ones(8, 7, dtype=torch.bool))
    with pytest.raises(ParameterError, match="spectral"):
        diffuse_staggered(v, 0.1, viscosity=1.0, method="spectral", fixed=masks)
    with pytest.raises(ShapeError, match="fixed"):
        diffuse_staggered(v, 0.1, viscosity=1.0, fixed=(torch.ones(3, 3), None))
