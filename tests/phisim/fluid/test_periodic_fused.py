"""The fused periodic step (:class:`phisim.fluid.periodic.PeriodicStep`): the general split step to rounding,
divergence-free, differentiable, traceable, and used only where its settings hold."""

from __future__ import annotations

import pytest
import torch

from phisim import Grid, StaggeredGrid
from phisim.errors import ParameterError
from phisim.field import CenteredGrid
from phisim.fluid import Body, FluidState, FluidStepper, Sphere
from phisim.fluid.periodic import grid_sample_border
from phisim.ops.stencil import face_divergence

CASES = [((16, 12), [(0, 2), (0, 1.2)]), ((8, 10, 6), [(0, 1), (0, 1.25), (0, 0.9)])]


def _velocity(grid, boundary, batch, dtype, seed=0):
    gen = torch.Generator().manual_seed(seed)
    comps = tuple(torch.randn(batch, *grid.face_shape(i), generator=gen, dtype=dtype) for i in range(grid.rank))
    return StaggeredGrid(comps, grid, boundary).with_boundary_faces()


@pytest.mark.parametrize("res,bounds", CASES)
@pytest.mark.parametrize("advection", ["semi_lagrangian", "maccormack"])
@pytest.mark.parametrize("viscosity", [0.0, 0.02])
def test_fused_equals_general_step(res, bounds, advection, viscosity):
    grid = Grid(res, bounds=bounds)  # anisotropic cells, non-square
    kw = dict(viscosity=viscosity, advection=advection, dt=0.05, dtype=torch.float64)
    fused, general = FluidStepper(grid, "periodic", **kw), FluidStepper(grid, "periodic", fused=False, **kw)
    assert fused.fused is not None and general.fused is None
    a = b = FluidState(_velocity(grid, fused.boundary, 3, torch.float64))
    for _ in range(4):
        a, b = fused(a), general(b)
    for x, y in zip(a.velocity.values, b.velocity.values):
        assert x.shape == y.shape
        torch.testing.assert_close(x, y, rtol=0, atol=1e-12)
    torch.testing.assert_close(a.pressure.values, b.pressure.values, rtol=0, atol=1e-12)
    assert a.time == pytest.approx(b.time)
    # the step's velocity is divergence-free, with the periodic face duplicated exactly
    div = face_divergence(a.velocity.values, grid.dx)
    assert float(div.abs().max()) < 1e-10
    for i, c in enumerate(a.velocity.values):
        assert torch.equal(c.narrow(1 + i, 0, 1), c.narrow(1 + i, res[i], 1))


def test_fused_float32_close_to_general():
    grid = Grid((32, 32), bounds=[(0, 1), (0, 1)])
    kw = dict(viscosity=1e-3, advection="maccormack", dt=0.01)
    fused, general = FluidStepper(grid, "periodic", **kw), FluidStepper(grid, "periodic", fused=False, **kw)
    v = _velocity(grid, fused.boundary, 2, torch.float32)
    a, b = fused(FluidState(v)), general(FluidState(v))
    for x, y in zip(a.velocity.values, b.velocity.values):
        torch.testing.assert_close(x, y, rtol=1e-5, atol=1e-5)


def test_dt_of_a_call_and_a_large_courant_number():
    """A call's own dt (other constants), and departure points several periods away (the wrap)."""
    grid = Grid((12, 8), bounds=[(0, 1), (0, 1)])
    kw = dict(viscosity=0.0, advection="semi_lagrangian", dt=0.01, dtype=torch.float64)
    fused, general = FluidStepper(grid, "periodic", **kw), FluidStepper(grid, "periodic", fused=False, **kw)
    v = _velocity(grid, fused.boundary, 2, torch.float64, seed=3)
    for dt in (0.01, 0.7):  # 0.7: up to ~20 cells per step
        a, b = fused(FluidState(v), dt), general(FluidState(v), dt)
        for x, y in zip(a.velocity.values, b.velocity.values):
            torch.testing.assert_close(x, y, rtol=0, atol=1e-11)


def test_gradcheck_fused_step():
    grid = Grid((5, 4), bounds=[(0, 1), (0, 0.8)])
    st = FluidStepper(grid, "periodic", viscosity=0.01, advection="maccormack", dt=0.03, dtype=torch.float64)
    assert st.fused is not None
    shapes = [grid.face_shape(i) for i in range(2)]
    gen = torch.Generator().manual_seed(1)
    # compact values (the duplicated face is set from the first), so the perturbations stay periodic
    x0 = torch.randn(1, 5, 4, generator=gen, dtype=torch.float64, requires_grad=True)
    y0 = torch.randn(1, 5, 4, generator=gen, dtype=torch.float64, requires_grad=True)

    def f(x, y):
        u = torch.cat([x, x[:, :1]], dim=1)
        w = torch.cat([y, y[:, :, :1]], dim=2)
        assert tuple(u.shape[1:]) == shapes[0] and tuple(w.shape[1:]) == shapes[1]
        out = st(FluidState(StaggeredGrid((u, w), grid, st.boundary)))
        return tuple(out.velocity.values) + (out.pressure.values,)

    assert torch.autograd.gradcheck(f, (x0, y0))


def test_traces_as_one_graph():
    grid = Grid((8, 8, 8), bounds=[(0, 1)] * 3)
    st = FluidStepper(grid, "periodic", viscosity=1e-3, advection="maccormack", dt=0.01)
    state = FluidState(_velocity(grid, st.boundary, 2, torch.float32))
    compiled = torch.compile(st.advance, fullgraph=True, backend="eager")
    out = compiled(state, 0.01)
    ref = st.advance(state, 0.01)
    for x, y in zip(out.velocity.values, ref.velocity.values):
        torch.testing.assert_close(x, y)


def test_used_only_where_the_settings_allow():
    grid = Grid((8, 8), bounds=[(0, 1), (0, 1)])
    assert FluidStepper(grid, "periodic", dt=0.1).fused is not None
    assert FluidStepper(grid, {"x": "periodic", "y": "wall"}, dt=0.1).fused is None
    assert FluidStepper(grid, "periodic", obstacles=Body(Sphere((0.5, 0.5), 0.2)), dt=0.1).fused is None
    assert FluidStepper(grid, "periodic", buoyancy=1.0, dt=0.1).fused is None
    assert FluidStepper(grid, "periodic", integrator="rk2", dt=0.1).fused is None
    assert FluidStepper(grid, "periodic", viscosity=0.01, viscosity_scheme="implicit", dt=0.1).fused is None
    assert FluidStepper(grid, "periodic", energy_normalization=True, dt=0.1).fused is None
    with pytest.raises(ParameterError, match="fused"):
        FluidStepper(grid, "periodic", fused="yes")


def test_a_state_with_a_marker_takes_the_general_step():
    grid = Grid((8, 6), bounds=[(0, 1), (0, 0.75)])
    kw = dict(viscosity=0.01, dt=0.05, dtype=torch.float64)
    fused, general = FluidStepper(grid, "periodic", **kw), FluidStepper(grid, "periodic", fused=False, **kw)
    v = _velocity(grid, fused.boundary, 1, torch.float64)
    m = CenteredGrid(torch.rand(1, 8, 6, dtype=torch.float64), grid, fused.boundary.for_scalar())
    a, b = fused(FluidState(v, m)), general(FluidState(v, m))
    assert torch.equal(a.marker.values, b.marker.values)
    for x, y in zip(a.velocity.values, b.velocity.values):
        assert torch.equal(x, y)


def test_the_opaque_sampler_matches_grid_sampler_with_its_gradients():
    gen = torch.Generator().manual_seed(2)
    for shape, pts in [((2, 1, 5, 6), (2, 3, 4, 2)), ((1, 1, 4, 5, 3), (1, 2, 3, 2, 3))]:
        src = torch.randn(*shape, generator=gen, dtype=torch.float64, requires_grad=True)
        coords = (torch.rand(*pts, generator=gen, dtype=torch.float64) * 1.8 - 0.9).requires_grad_(True)
        torch.testing.assert_close(grid_sample_border(src, coords), torch.grid_sampler(src, coords, 0, 1, True))
        assert torch.autograd.gradcheck(grid_sample_border, (src, coords))


# 3-D compiles for about 30 s: a long validation (the 2-D case stays in the default run)
@pytest.mark.parametrize("dim", [2, pytest.param(3, marks=pytest.mark.slow)])
def test_the_compiled_graph_matches_the_eager_step_forward_and_backward(dim):
    """``aot_eager`` runs what inductor receives (the concatenation wraps, the opaque sampler and its backward)
    without a C++ compiler."""
    res = (8, 6) if dim == 2 else (6, 4, 5)
    grid = Grid(res, bounds=[(0, 1)] * dim)
    st = FluidStepper(grid, "periodic", viscosity=0.01, advection="maccormack", dt=0.02, dtype=torch.float64)
    v = _velocity(grid, st.boundary, 2, torch.float64, seed=4)
    compiled = torch.compile(st.advance, fullgraph=True, backend="aot_eager")

    def run(fn):
        comps = tuple(c.detach().requires_grad_(True) for c in v.values)
        out = fn(FluidState(StaggeredGrid(comps, grid, st.boundary)), 0.02)
        loss = sum((c ** 2).sum() for c in out.velocity.values) + out.pressure.values.pow(2).sum()
        loss.backward()
        return [c.detach() for c in out.velocity.values], [c.grad for c in comps]

    (a, ga), (b, gb) = run(compiled), run(st.advance)
    for x, y in zip(a + ga, b + gb):
        torch.testing.assert_close(x, y, rtol=1e-10, atol=1e-12)
