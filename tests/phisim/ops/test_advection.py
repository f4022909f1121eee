"""Tests of phisim.ops.advection: convergence orders, extrema, invariants, boundaries, 3-D, gradients, errors."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from phisim import CenteredGrid, Dirichlet, Grid, Neumann, NoSlipWall, StaggeredGrid
from phisim.errors import GridMismatchError, NonFiniteError, ParameterError, ShapeError
from phisim.ops.advection import advect, maccormack, semi_lagrangian

F64 = torch.float64


def _gauss(x: torch.Tensor, centre, sigma: float, size) -> torch.Tensor:
    """Periodic-image Gaussian (nearest image) at points ``(..., d)``."""
    r2 = 0
    for a in range(x.shape[-1]):
        d = torch.remainder(x[..., a] - centre[a] + 0.5 * size[a], size[a]) - 0.5 * size[a]
        r2 = r2 + d ** 2
    return torch.exp(-r2 / (2 * sigma ** 2))


def _translation_error(n: int, scheme: str, rank: int, courant: float = 0.5, sigma: float = 0.1) -> float:
    """RMS error of translating a Gaussian by a uniform velocity on the periodic unit box."""
    grid = Grid((n,) * rank, bounds=[(0.0, 1.0)] * rank)
    vel = (1.0, 0.5, 0.25)[:rank]
    vmax = max(abs(v) for v in vel)
    dt = courant * grid.dx[0] / vmax
    steps = int(round(0.25 / dt))
    centre = (0.4,) * rank
    q = CenteredGrid.from_function(lambda x: _gauss(x, centre, sigma, grid.size), grid, "periodic", dtype=F64)
    v = StaggeredGrid.uniform(vel, grid, "periodic", dtype=F64)
    for _ in range(steps):
        q = advect(q, v, dt, scheme=scheme)
    t = steps * dt
    shifted = tuple(c + u * t for c, u in zip(centre, vel))
    exact = _gauss(grid.cell_centers(F64), shifted, sigma, grid.size)
    return float(((q.values[0] - exact) ** 2).mean().sqrt())


def _order(ns, errors) -> float:
    """Least-squares slope of log(error) against log(dx)."""
    return float(-np.polyfit(np.log(ns), np.log(errors), 1)[0])


# ---- convergence ---------------------------------------------------------------------------------------


def test_semi_lagrangian_first_order_1d_measured_0_98():
    ns = [128, 256, 512, 1024]
    errs = [_translation_error(n, "semi_lagrangian", 1) for n in ns]
    order = _order(ns, errs)
    assert 0.8 <= order <= 1.3, (order, errs)


def test_maccormack_second_order_1d_measured_1_89():
    ns = [64, 128, 256, 512]
    errs = [_translation_error(n, "maccormack", 1) for n in ns]
    order = _order(ns, errs)
    assert order >= 1.7, (order, errs)
    assert order <= 2.4, (order, errs)


def test_orders_2d_diagonal_translation_measured_0_92_and_1_99():
    ns = [32, 64, 128]
    sl = [_translation_error(n, "semi_lagrangian", 2, sigma=0.12) for n in ns]
    mc = [_translation_error(n, "maccormack", 2, sigma=0.12) for n in ns]
    assert 0.8 <= _order(ns, sl) <= 1.3, sl
    assert _order(ns, mc) >= 1.7, mc
    assert all(m < s for m, s in zip(mc, sl))


def test_3d_translation_maccormack_beats_semi_lagrangian():
    e_sl = _translation_error(16, "semi_lagrangian", 3, sigma=0.15)
    e_mc = _translation_error(16, "maccormack", 3, sigma=0.15)
    e_mc2 = _translation_error(32, "maccormack", 3, sigma=0.15)
    assert e_mc < 0.6 * e_sl
    assert e_mc2 < 0.35 * e_mc  # second order: ~4x per refinement


# ---- invariants ----------------------------------------------------------------------------------------


def _swirl(grid: Grid, boundary, amplitude: float = 1.0, dtype=F64) -> StaggeredGrid:
    """A smooth, non-uniform staggered velocity that vanishes on the boundary faces of the unit box."""
    def fn(x):
        s = [torch.sin(math.pi * x[..., a] / grid.size[a]) for a in range(grid.rank)]
        c = [torch.cos(2 * math.pi * x[..., a] / grid.size[a]) for a in range(grid.rank)]
        comps = []
        for a in range(grid.rank):
            other = (a + 1) % grid.rank
            comps.append(amplitude * s[a] * (c[other] + 0.3))
        return torch.stack(comps, dim=-1)
    return StaggeredGrid.from_function(fn, grid, boundary, dtype=dtype)


def test_maccormack_creates_no_new_extrema_on_discontinuous_field():
    grid = Grid((40, 40))
    x = grid.cell_centers(F64)
    box = ((x[..., 0] > 10) & (x[..., 0] < 25) & (x[..., 1] > 12) & (x[..., 1] < 30)).to(F64)
    q0 = CenteredGrid((2.0 * box - 0.5)[None], grid, Neumann(0.0))
    v = _swirl(grid, "wall", amplitude=1.3)
    q, q_free = q0, q0
    for _ in range(12):
        q = maccormack(q, v, 1.0)
        q_free = maccormack(q_free, v, 1.0, clamp=None)
    assert float(q.values.max()) <= 1.5 + 1e-12
    assert float(q.values.min()) >= -0.5 - 1e-12
    # the test is meaningful: without the limiter the scheme does overshoot
    assert float(q_free.values.max()) > 1.5 + 1e-3 or float(q_free.values.min()) < -0.5 - 1e-3
    # revert variant respects the bounds as well (semi-Lagrangian values lie within the stencil)
    q_rev = q0
    for _ in range(12):
        q_rev = maccormack(q_rev, v, 1.0, clamp="revert")
    assert -0.5 - 1e-12 <= float(q_rev.values.min()) and float(q_rev.values.max()) <= 1.5 + 1e-12


@pytest.mark.parametrize("scheme", ["semi_lagrangian", "maccormack"])
@pytest.mark.parametrize("boundary", ["periodic", Dirichlet(2.5), Neumann(0.0), "wall", "free_slip", "open",
                                      {"x": "periodic", "y": ("wall", Dirichlet(2.5))}])
def test_constant_field_unchanged_for_every_boundary(scheme, boundary):
    grid = Grid((12, 10), bounds=[(0, 3), (-1, 1.5)])
    q = CenteredGrid(torch.full((2, 12, 10), 2.5, dtype=F64), grid, boundary)
    # a velocity that carries points across the boundary (non-zero on the boundary faces)
    v = StaggeredGrid.from_function(lambda x: torch.stack([1.0 + 0.3 * torch.sin(x[..., 1]),
                                                           -0.7 + 0.2 * torch.cos(x[..., 0])], -1),
                                    grid, "open", batch_size=2, dtype=F64)
    out = advect(q, v, 0.4, scheme=scheme)
    torch.testing.assert_close(out.values, q.values, rtol=0, atol=1e-13)


@pytest.mark.parametrize("scheme", ["semi_lagrangian", "maccormack"])
def test_constant_vector_and_staggered_fields_unchanged(scheme):
    grid = Grid((9, 11))
    v = _swirl(grid, "wall", amplitude=0.8)
    vec = CenteredGrid(torch.tensor([0.3, -1.2], dtype=F64).reshape(1, 2, 1, 1).expand(1, 2, 9, 11), grid,
                       Dirichlet((0.3, -1.2)))
    torch.testing.assert_close(advect(vec, v, 1.5, scheme=scheme).values, vec.values, rtol=0, atol=1e-13)
    three = CenteredGrid(torch.full((1, 3, 9, 11), -4.0, dtype=F64), grid, "open")  # non-velocity channels
    torch.testing.assert_close(advect(three, v, 1.5, scheme=scheme).values, three.values, rtol=0, atol=1e-13)
    stag = StaggeredGrid.uniform((0.4, -0.2), grid, "open", dtype=F64)
    out = advect(stag, v, 1.5, scheme=scheme)
    for a, b in zip(out.values, stag.values):
        torch.testing.assert_close(a, b, rtol=0, atol=1e-13)


@pytest.mark.parametrize("scheme", ["semi_lagrangian", "maccormack"])
@pytest.mark.parametrize("boundary", ["periodic", "open"])
@pytest.mark.parametrize("resolution", [(16, 12), (6, 7, 5)])
def test_staggered_self_advection_of_uniform_velocity_is_exact(scheme, boundary, resolution):
    grid = Grid(resolution, bounds=[(0, 2 * n) for n in resolution])
    u = StaggeredGrid.uniform((0.7, -1.9, 0.4)[: grid.rank], grid, boundary, batch_size=2, dtype=F64)
    out = advect(u, u, 1.3, scheme=scheme)
    for a, b in zip(out.values, u.values):
        torch.testing.assert_close(a, b, rtol=0, atol=1e-13)


def test_staggered_self_advection_translates_a_shear_flow():
    """u_x(y) = sin(2 pi y) carried by itself stays put (u . grad u = 0); adding a uniform u_y shifts it."""
    grid = Grid((16, 64), bounds=[(0, 1), (0, 1)])
    fn = lambda x: torch.stack([torch.sin(2 * math.pi * x[..., 1]), 0.5 + 0 * x[..., 0]], -1)  # noqa: E731
    u = StaggeredGrid.from_function(fn, grid, "periodic", dtype=F64)
    dt, steps = 0.25 / 64, 64  # translate by 0.5 * 0.25 in y
    out = u
    for _ in range(steps):
        out = maccormack(out, out, dt)
    y = grid.face_centers(0, F64)[..., 1]
    exact = torch.sin(2 * math.pi * (y - 0.5 * dt * steps))
    assert float((out.values[0][0] - exact).abs().max()) < 5e-3
    torch.testing.assert_close(out.values[1], u.values[1], rtol=0, atol=1e-12)


def test_centred_and_staggered_uniform_velocity_agree():
    grid = Grid((20, 16))
    q = CenteredGrid.from_function(lambda x: torch.sin(0.3 * x[..., 0]) * torch.cos(0.2 * x[..., 1]), grid,
                                   Dirichlet(0.2), dtype=F64)
    vs = StaggeredGrid.uniform((0.6, -0.35), grid, "open", dtype=F64)
    vc = CenteredGrid(torch.tensor([0.6, -0.35], dtype=F64).reshape(1, 2, 1, 1).expand(1, 2, 20, 16), grid, "open")
    for scheme in ("semi_lagrangian", "maccormack"):
        torch.testing.assert_close(advect(q, vs, 1.7, scheme=scheme).values,
                                   advect(q, vc, 1.7, scheme=scheme).values, rtol=0, atol=1e-13)


def test_dirichlet_value_enters_through_the_face():
    """Zero field, inflow from a Dirichlet(1) side, trace half a cell outside: the face value 1 is met."""
    grid = Grid((8,))
    q = CenteredGrid(torch.zeros(1, 8, dtype=F64), grid, [(Dirichlet(1.0), Neumann(0.0))])
    v = StaggeredGrid.uniform((1.0,), grid, "open", dtype=F64)
    out = semi_lagrangian(q, v, 0.5)  # cell 0 traces to the boundary face x = 0
    assert float(out.values[0, 0]) == pytest.approx(1.0, abs=1e-14)  # the face value, between ghost 2 and 0
    out = semi_lagrangian(q, v, 1.0)  # cell 0 traces to x = -0.5: the ghost, 2*1 - 0 = 2
    assert float(out.values[0, 0]) == pytest.approx(2.0, abs=1e-14)
    torch.testing.assert_close(out.values[0, 1:], torch.zeros(7, dtype=F64))


def test_moving_lid_enters_tangential_velocity():
    grid = Grid((6, 6))
    bc = {"x": "wall", "y": ("wall", NoSlipWall(velocity=(1.0, 0.0)))}
    v = StaggeredGrid.zeros(grid, bc, dtype=F64)
    drift = StaggeredGrid.uniform((0.0, -1.0), grid, "open", dtype=F64)  # carries the lid's values down
    out = semi_lagrangian(v, drift, 0.5)  # top row traces to the lid face y = 6
    torch.testing.assert_close(out.values[0][0, 1:-1, -1], torch.ones(5, dtype=F64))
    assert float(out.values[0][0, :, :-1].abs().max()) == 0.0
    assert float(out.values[1].abs().max()) == 0.0


def test_batch_is_independent_and_velocity_batch_one_broadcasts():
    grid = Grid((10, 8))
    torch.manual_seed(0)
    q = CenteredGrid(torch.randn(3, 10, 8, dtype=F64), grid, "periodic")
    v = StaggeredGrid(tuple(0.8 * torch.randn(3, *grid.face_shape(i), dtype=F64) for i in range(2)), grid,
                      "periodic")
    out = maccormack(q, v, 0.9)
    for b in range(3):
        qb = CenteredGrid(q.values[b:b + 1], grid, "periodic")
        vb = StaggeredGrid(tuple(c[b:b + 1] for c in v.values), grid, "periodic")
        torch.testing.assert_close(out.values[b:b + 1], maccormack(qb, vb, 0.9).values, rtol=0, atol=1e-14)
    v1 = StaggeredGrid(tuple(c[:1] for c in v.values), grid, "periodic")
    shared = semi_lagrangian(q, v1, 0.9)
    torch.testing.assert_close(shared.values[2:3], semi_lagrangian(CenteredGrid(q.values[2:3], grid, "periodic"),
                                                                   v1, 0.9).values, rtol=0, atol=1e-14)


def test_rk2_exact_for_uniform_and_better_for_rotation():
    grid = Grid((48, 48), bounds=[(-1, 1), (-1, 1)])
    u = StaggeredGrid.uniform((0.3, 0.2), grid, "periodic", dtype=F64)
    torch.testing.assert_close(semi_lagrangian(u, u, 2.0, trace="midpoint").values[0], u.values[0],
                               rtol=0, atol=1e-13)
    # rigid rotation, a large time step: the Euler trace drifts outward, the midpoint trace much less
    rot = StaggeredGrid.from_function(lambda x: torch.stack([-x[..., 1], x[..., 0]], -1), grid, "open", dtype=F64)
    centre, sigma, angle = (0.45, 0.0), 0.15, 0.4
    q0 = CenteredGrid.from_function(lambda x: _gauss(x, centre, sigma, (10.0, 10.0)), grid, "open", dtype=F64)
    exact_c = (centre[0] * math.cos(angle), centre[0] * math.sin(angle))
    exact = _gauss(grid.cell_centers(F64), exact_c, sigma, (10.0, 10.0))
    err = {}
    for integ in ("euler", "midpoint"):
        q = q0
        for _ in range(2):
            q = maccormack(q, rot, angle / 2, trace=integ)
        err[integ] = float((q.values[0] - exact).abs().max())
    assert err["midpoint"] < 0.5 * err["euler"], err


def test_vector_field_channels_advected_together():
    grid = Grid((12, 9))
    torch.manual_seed(1)
    vals = torch.randn(2, 2, 12, 9, dtype=F64)
    vec = CenteredGrid(vals, grid, "periodic")
    v = StaggeredGrid(tuple(0.5 * torch.randn(2, *grid.face_shape(i), dtype=F64) for i in range(2)), grid,
                      "periodic")
    out = maccormack(vec, v, 1.0)
    for c in range(2):
        sc = maccormack(CenteredGrid(vals[:, c], grid, "periodic"), v, 1.0)
        torch.testing.assert_close(out.values[:, c], sc.values, rtol=0, atol=1e-14)


def test_1d_and_dtype_preserved():
    grid = Grid(32)
    q = CenteredGrid.from_function(lambda x: torch.sin(2 * math.pi * x[..., 0] / 32), grid, "periodic")
    v = StaggeredGrid.uniform((1.0,), grid, "periodic")
    out = maccormack(q, v, 1.0)  # exactly one cell: the shifted array
    assert out.dtype == torch.float32
    torch.testing.assert_close(out.values, torch.roll(q.values, 1, dims=1), rtol=0, atol=1e-6)


def test_gradient_wrt_tensor_dt_is_the_negative_transport_term():
    grid = Grid((16,), bounds=[(0, 2 * math.pi)])
    q = CenteredGrid.from_function(lambda x: torch.sin(x[..., 0]), grid, "periodic", dtype=F64)
    v = StaggeredGrid.uniform((0.5,), grid, "periodic", dtype=F64)
    dt = torch.tensor(0.1, dtype=F64, requires_grad=True)
    out = semi_lagrangian(q, v, dt)
    (g,) = torch.autograd.grad(out.values.sum(), dt)
    # d/dt q(x - v t) = -v q'(x): piecewise-linear interpolation of q' integrates to ~0 over a period
    assert abs(float(g)) < 1e-10
    out = semi_lagrangian(q, v, dt)
    (g,) = torch.autograd.grad(out.values[0, 0], dt)
    # slope of the linear interpolant between the two cells around the trace: -v * (q_0 - q_-1) / dx
    dx = grid.dx[0]
    expected = -0.5 * float(q.values[0, 0] - q.values[0, -1]) / dx
    assert float(g) == pytest.approx(expected, rel=1e-10)


# ---- gradients -----------------------------------------------------------------------------------------


def _rand_staggered(grid, boundary, batch, scale, seed):
    g = torch.Generator().manual_seed(seed)
    return tuple((scale * torch.randn(batch, *grid.face_shape(i), generator=g, dtype=F64)).requires_grad_()
                 for i in range(grid.rank))


@pytest.mark.parametrize("boundary", ["periodic", {"x": Dirichlet(0.3), "y": ("open", Neumann(0.2))}])
@pytest.mark.parametrize("scheme", ["semi_lagrangian", "maccormack"])
def test_gradcheck_centred_field_wrt_values_and_velocity(scheme, boundary):
    grid = Grid((5, 4), bounds=[(0, 2.5), (0, 2)])
    g = torch.Generator().manual_seed(3)
    vals = torch.randn(2, 5, 4, generator=g, dtype=F64, requires_grad=True)
    comps = _rand_staggered(grid, boundary, 2, 0.4, 4)

    def fn(q, *vel):
        return advect(CenteredGrid(q, grid, boundary), StaggeredGrid(vel, grid, "open"), 0.7, scheme=scheme).values

    assert torch.autograd.gradcheck(fn, (vals, *comps), eps=1e-6, atol=1e-7)


@pytest.mark.parametrize("scheme", ["semi_lagrangian", "maccormack"])
def test_gradcheck_staggered_self_advection(scheme):
    grid = Grid((4, 5))
    comps = _rand_staggered(grid, "periodic", 1, 0.6, 5)

    def fn(*vel):
        u = StaggeredGrid(vel, grid, "periodic")
        return torch.cat([c.reshape(-1) for c in advect(u, u, 0.8, scheme=scheme).values])

    assert torch.autograd.gradcheck(fn, comps, eps=1e-6, atol=1e-7)


def test_gradcheck_centred_velocity_3d_and_rk2():
    grid = Grid((3, 4, 3))
    g = torch.Generator().manual_seed(7)
    vals = torch.randn(1, 3, 4, 3, generator=g, dtype=F64, requires_grad=True)
    vel = (0.4 * torch.randn(1, 3, 3, 4, 3, generator=g, dtype=F64)).requires_grad_()

    def fn(q, v):
        return semi_lagrangian(CenteredGrid(q, grid, "periodic"), CenteredGrid(v, grid, "periodic"), 0.6,
                               trace="midpoint").values

    assert torch.autograd.gradcheck(fn, (vals, vel), eps=1e-6, atol=1e-7)


# ---- bad input -----------------------------------------------------------------------------------------


def _simple():
    grid = Grid((6, 5))
    return grid, CenteredGrid(torch.zeros(2, 6, 5), grid, "periodic"), StaggeredGrid.zeros(grid, "periodic", 2)


@pytest.mark.parametrize("dt", [-0.1, float("nan"), float("inf"), "soon"])
def test_bad_dt_raises(dt):
    _, q, v = _simple()
    with pytest.raises(ParameterError):
        advect(q, v, dt)


def test_mismatched_grids_and_bad_velocity_raise():
    grid, q, v = _simple()
    other = StaggeredGrid.zeros(Grid((6, 5), bounds=[2, 2]), "periodic", 2)
    with pytest.raises(GridMismatchError):
        advect(q, other, 0.1)
    with pytest.raises(GridMismatchError):
        advect(q, q.values, 0.1)
    with pytest.raises(GridMismatchError):
        advect(q.values, v, 0.1)
    with pytest.raises(ShapeError):
        advect(q, q, 0.1)  # a scalar is no velocity
    with pytest.raises(ShapeError):
        advect(q, StaggeredGrid.zeros(grid, "periodic", 3), 0.1)  # batch 3 vs 2
    with pytest.raises(ParameterError):
        advect(q, v, 0.1, scheme="upwind")
    with pytest.raises(ParameterError):
        advect(q, v, 0.1, trace="rk4")
    with pytest.raises(ParameterError):
        maccormack(q, v, 0.1, clamp="soft")


def test_nan_velocity_raises():
    grid, q, v = _simple()
    bad = v.values[1].clone()
    bad[0, 2, 2] = float("nan")
    with pytest.raises(NonFiniteError):
        advect(q, StaggeredGrid((v.values[0], bad), grid, "periodic"), 0.1)


def test_boundary_with_list_values_is_accepted():
    grid = Grid((5, 4))
    lid = {"x": "wall", "y": ("wall", NoSlipWall(velocity=[1.0, 0.0]))}
    v = StaggeredGrid.zeros(grid, lid, dtype=F64)
    out = semi_lagrangian(v, StaggeredGrid.uniform((0.0, -1.0), grid, "open", dtype=F64), 0.5)
    torch.testing.assert_close(out.values[0][0, 1:-1, -1], torch.ones(4, dtype=F64))


def test_former_integrator_keyword_maps_to_trace_with_a_warning():
    grid = Grid((8, 8))
    q = CenteredGrid.from_function(lambda x: torch.sin(x[..., 0]), grid, "periodic", dtype=torch.float64)
    v = CenteredGrid(torch.ones(1, 2, 8, 8, dtype=torch.float64) * 0.3, grid, "periodic")
    with pytest.warns(DeprecationWarning, match="trace="):
        old = semi_lagrangian(q, v, 0.5, integrator="rk2")
    new = semi_lagrangian(q, v, 0.5, trace="midpoint")
    torch.testing.assert_close(old.values, new.values, rtol=0, atol=0)
