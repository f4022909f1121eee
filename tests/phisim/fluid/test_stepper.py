"""FluidStepper: settings checked once, operators owned by the stepper, results independent of what ran before."""

from __future__ import annotations

import pytest
import torch

from phisim import Grid, Inflow, Open, StaggeredGrid
from phisim.errors import GridMismatchError, ParameterError
from phisim.fluid import Body, Box, FluidState, FluidStepper, Obstacle, Sphere, navier_stokes_step, step
from phisim.solvers import Solve


def _channel(dtype, body_y=0.45):
    grid = Grid((40, 20), bounds=[(0, 2.0), (0, 1.0)])
    spec = {"x": (Inflow((1.0, 0.0)), Open()), "y": "wall"}
    v0 = StaggeredGrid.from_function(lambda x: torch.stack([1 + 0 * x[..., 0], 0 * x[..., 0]], -1), grid, spec,
                                     dtype=dtype)
    return grid, v0, Body(Sphere((0.5, body_y), 0.15))


def _run_a(dtype, steps=12):
    grid, v0, body = _channel(dtype)
    stepper = FluidStepper(grid, v0.boundary, obstacles=body, viscosity=1e-2, dt=0.02, dtype=dtype)
    state = FluidState(v0)
    for _ in range(steps):
        state = stepper(state)
    return state


def _run_b(dtype, steps=8):
    grid = Grid((24, 24), bounds=[(0, 1.0), (0, 1.0)])
    v0 = StaggeredGrid.from_function(lambda x: torch.stack([x[..., 1] - 0.5, 0.5 - x[..., 0]], -1), grid, "wall",
                                     dtype=dtype)
    stepper = FluidStepper(grid, v0.boundary, obstacles=[Obstacle.box((0.3, 0.3), (0.5, 0.6)),
                                                         Body(Box((0.6, 0.2), (0.8, 0.4)))],
                           viscosity=1e-3, viscosity_scheme="implicit", dt=0.05, dtype=dtype)
    state = FluidState(v0)
    for _ in range(steps):
        state = stepper(state)
    return state


def _bits(state):
    return [c.clone() for c in state.velocity.values] + [state.pressure.values.clone()]


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_flow_a_then_b_then_a_again_is_bit_identical(dtype):
    # a static body: the stepper uses the direct pressure solve from its first step, so nothing that ran
    # before (another flow, another stepper of the same flow) can change the numbers
    first = _bits(_run_a(dtype))
    _run_b(dtype)
    again = _bits(_run_a(dtype))
    for x, y in zip(first, again):
        assert torch.equal(x, y)


def test_pure_step_a_then_b_then_a_again_is_bit_identical():
    grid, v0, body = _channel(torch.float64)

    def run():
        state = FluidState(v0)
        for _ in range(6):
            state = step(state, 0.02, viscosity=1e-2, obstacles=body)
        return _bits(state)

    first = run()
    _run_b(torch.float64)
    for x, y in zip(first, run()):
        assert torch.equal(x, y)


def test_stepper_equals_the_pure_step_without_solids_bit_for_bit():
    grid = Grid((32, 32), bounds=[(0, 1), (0, 1)])
    v0 = StaggeredGrid.from_function(lambda x: torch.stack([torch.sin(6.28 * x[..., 1]), 0 * x[..., 0]], -1), grid,
                                     "periodic", dtype=torch.float64)
    # the general path of the stepper is the pure step's computation, bit for bit; the fused periodic step
    # (the default here) is the same computation in another order, equal to rounding
    kw = dict(viscosity=1e-3, advection="semi_lagrangian", dtype=torch.float64)
    general = FluidStepper(grid, "periodic", fused=False, **kw)
    a = general(FluidState(v0), 0.01)
    b = step(FluidState(v0), 0.01, viscosity=1e-3, advection="semi_lagrangian")
    for x, y in zip(a.velocity.values, b.velocity.values):
        assert torch.equal(x, y)
    c = FluidStepper(grid, "periodic", **kw)(FluidState(v0), 0.01)
    for x, y in zip(c.velocity.values, b.velocity.values):
        torch.testing.assert_close(x, y, rtol=0, atol=1e-13)


def test_stepper_with_a_static_body_agrees_with_the_pure_step_to_the_solver_tolerance():
    grid, v0, body = _channel(torch.float64)
    tight = Solve(rtol=1e-12)
    stepper = FluidStepper(grid, v0.boundary, obstacles=body, viscosity=1e-2, pressure=tight, dtype=torch.float64)
    a = b = FluidState(v0)
    for _ in range(5):
        a = stepper(a, 0.02)
        b = step(b, 0.02, viscosity=1e-2, obstacles=body, solve=tight)
    for x, y in zip(a.velocity.values, b.velocity.values):
        torch.testing.assert_close(x, y, rtol=0, atol=1e-9)


def test_stepper_with_a_moving_body_equals_the_pure_step():
    grid, v0, _ = _channel(torch.float64)
    moving = Body(Sphere((0.5, 0.45), 0.15), velocity=(0.2, 0.0))
    stepper = FluidStepper(grid, v0.boundary, obstacles=moving, viscosity=1e-2, integrator="rk2",
                           dtype=torch.float64)
    a = b = FluidState(v0)
    for _ in range(3):
        a = stepper(a, 0.02)
        b = step(b, 0.02, viscosity=1e-2, obstacles=moving, integrator="rk2")
    assert a.time == pytest.approx(0.06)
    for x, y in zip(a.velocity.values, b.velocity.values):
        assert torch.equal(x, y)


def test_navier_stokes_step_and_step_are_one_step():
    grid, v0, body = _channel(torch.float64)
    a = step(FluidState(v0), 0.02, viscosity=1e-2, obstacles=body, advection="semi_lagrangian")
    v, p = navier_stokes_step(v0, 0.02, viscosity=1e-2, obstacles=body, advection="semi_lagrangian")
    for x, y in zip(a.velocity.values, v.values):
        assert torch.equal(x, y)


@pytest.mark.parametrize("setting, value, match", [
    ("advection", "upwind", "advection"),
    ("marker_advection", "spline", "marker_advection"),
    ("viscosity_scheme", "implicit_euler", "viscosity_scheme"),
    ("integrator", "rk4", "integrator"),
    ("viscosity", -1.0, "viscosity"),
    ("viscosity", float("nan"), "viscosity"),
    ("buoyancy", "up", "buoyancy"),
    ("buoyancy_direction", (0.0, 1.0, 0.0), "direction"),
    ("pressure", 1e-6, "pressure"),
    ("dt", -0.1, "dt"),
    ("dtype", torch.int32, "dtype"),
    ("energy_normalization", "yes", "energy_normalization"),
])
def test_settings_are_checked_once_at_construction(setting, value, match):
    grid = Grid((8, 8))
    with pytest.raises(ParameterError, match=match):
        FluidStepper(grid, "wall", **{setting: value})


def test_a_state_that_does_not_fit_the_stepper_is_a_clear_error():
    grid = Grid((8, 8))
    stepper = FluidStepper(grid, "wall", dt=0.1)
    with pytest.raises(GridMismatchError, match="grid"):
        stepper(FluidState(StaggeredGrid.zeros(Grid((8, 6)), "wall")))
    with pytest.raises(ParameterError, match="float32"):
        stepper(FluidState(StaggeredGrid.zeros(grid, "wall", dtype=torch.float64)))
    with pytest.raises(ParameterError, match="FluidState"):
        stepper(StaggeredGrid.zeros(grid, "wall"))
    with pytest.raises(ParameterError, match="no dt"):
        FluidStepper(grid, "wall")(FluidState(StaggeredGrid.zeros(grid, "wall")))
    with pytest.raises(ParameterError, match="outside the domain"):
        FluidStepper(grid, "wall", obstacles=Body(Sphere((20.0, 20.0), 1.0)))
