"""Every stepper's step traces as ONE graph: no host read, no Python branch on tensor values.

``torch.compile(stepper.advance, fullgraph=True, backend="eager")`` runs dynamo's tracing (no C++ compiler
needed) and raises on any graph break (``.item()``, ``float(tensor)``, ``bool(tensor)``, untraceable calls such as
pyfftw). Each case compares the traced step (``torch.fft`` inside the graph) with the eager step (pyfftw where
it is the engine) and checks that new state values do not trace a second graph.
"""

from __future__ import annotations

import warnings

import pytest
import torch
from torch._dynamo.utils import counters

from phisim import CenteredGrid, Grid, StaggeredGrid
from phisim.boundary import Inflow, Open
from phisim.errors import NonFiniteError, ParameterError
from phisim.fluid import AdvectionDiffusionStepper, Body, BurgersStepper, FluidState, FluidStepper, Sphere
from phisim.solvers.heat import HeatStepper

F32, F64 = torch.float32, torch.float64
#: Field steppers: float32 in the default run, float64 too in the slow one.
DTYPES_FIELD = [pytest.param(F32, id="f32"), pytest.param(F64, id="f64", marks=pytest.mark.slow)]
N = 10  # cells per axis: tracing cost does not depend on it


@pytest.fixture(autouse=True)
def _fresh_dynamo():
    torch._dynamo.reset()
    counters.clear()
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*lru_cache.*")  # dynamo's note on cached helpers
        warnings.filterwarnings("ignore", message=".*complex operators.*")
        yield
    torch._dynamo.reset()


def _trace(fn):
    return torch.compile(fn, fullgraph=True, backend="eager", dynamic=False)


def _tol(dtype):
    return dict(rtol=1e-4, atol=1e-5) if dtype == F32 else dict(rtol=1e-10, atol=1e-11)


def _velocity(grid, boundary, dtype, seed=0):
    g = torch.Generator().manual_seed(seed)
    v = StaggeredGrid.zeros(grid, boundary, dtype=dtype)
    return v.with_values(tuple(0.2 * torch.randn(c.shape, generator=g, dtype=dtype) for c in v.values))


CHANNEL = {"x": (Inflow((1.0, 0.0)), Open()), "y": "wall"}
CHANNEL3 = {"x": (Inflow((1.0, 0.0, 0.0)), Open()), "y": "wall", "z": "periodic"}

# (name, rank, boundary, stepper settings, with a marker)
FLUID_CASES = [
    ("periodic", 2, "periodic", dict(viscosity=1e-3), False),
    ("periodic", 3, "periodic", dict(viscosity=1e-3), False),
    ("closed box, buoyant smoke", 2, "wall", dict(viscosity=1e-3, buoyancy=0.5), True),
    ("closed box, buoyant smoke", 3, "wall", dict(viscosity=1e-3, buoyancy=0.5), True),
    ("channel inflow/outflow", 2, CHANNEL, dict(viscosity=1e-2), False),
    ("channel inflow/outflow", 3, CHANNEL3, dict(viscosity=1e-2), False),
    ("box, semi-Lagrangian, implicit viscosity", 2, "wall",
     dict(viscosity=1e-2, advection="semi_lagrangian", viscosity_scheme="implicit"), False),
    ("periodic, spectral viscosity, energy normalisation", 2, "periodic",
     dict(viscosity=1e-2, viscosity_scheme="spectral", energy_normalization=True), False),
    ("box, rk2", 2, "wall", dict(viscosity=1e-3, integrator="rk2"), False),
    ("box, rk3 smoke", 2, "wall", dict(viscosity=1e-3, integrator="rk3", buoyancy=0.5), True),
    ("channel, imex2", 2, CHANNEL, dict(viscosity=1e-2, integrator="imex2"), False),
    ("box, imex2", 3, "wall", dict(viscosity=1e-2, integrator="imex2"), False),
    ("channel, imex2, QUICK", 2, CHANNEL, dict(viscosity=1e-2, integrator="imex2", convection="quick"), False),
    ("channel, split2", 2, CHANNEL, dict(viscosity=1e-2, integrator="split2"), False),
    ("periodic, split2", 3, "periodic", dict(viscosity=1e-3, integrator="split2"), False),
]


def _fluid_params():
    """Every case in both dtypes; in the default run each case in one dtype (alternating), the other one slow."""
    out = []
    for k, case in enumerate(FLUID_CASES):
        for j, dtype in enumerate((F32, F64)):
            marks = (pytest.mark.slow,) if (j + k) % 2 else ()
            out.append(pytest.param(case, dtype, marks=marks, id=f"{case[0]}-{case[1]}d-{'f32' if j == 0 else 'f64'}"))
    return out


@pytest.mark.parametrize(("case", "dtype"), _fluid_params())
def test_fluid_step_traces_as_one_graph(case, dtype):
    name, rank, boundary, settings, smoke = case
    grid = Grid((N,) * rank, bounds=[(0, 1)] * rank)
    stepper = FluidStepper(grid, boundary, dt=0.02, dtype=dtype, **settings)
    marker = None
    if smoke:
        g = torch.Generator().manual_seed(1)
        marker = CenteredGrid(torch.rand((1, *grid.resolution), generator=g, dtype=dtype), grid,
                              stepper.boundary.for_scalar())
    state = stepper(FluidState(_velocity(grid, stepper.boundary, dtype), marker))  # a projected start
    traced = _trace(stepper.advance)
    stepper._advance = traced  # the stepper's calls now run the traced step
    a = stepper(state)
    b = stepper(a)
    eager = FluidStepper(grid, boundary, dt=0.02, dtype=dtype, **settings)
    ea = eager(state)
    eb = eager(ea)
    for x, y in zip(b.velocity.values, eb.velocity.values):
        torch.testing.assert_close(x, y, **_tol(dtype))
    if smoke:
        torch.testing.assert_close(b.marker.values, eb.marker.values, **_tol(dtype))
    torch.testing.assert_close(b.pressure.values, eb.pressure.values, **_tol(dtype))
    assert b.time == eb.time
    if not stepper.uses_pressure:  # imex2 traces once without a previous pressure, then with one
        assert counters["stats"]["unique_graphs"] == 1, f"{name}: new state values traced a new graph"


def _static_body_params():
    """Each integrator in both dtypes, with no-slip and free-slip bodies; ``imex2`` in float64 in the slow run."""
    out = []
    for integrator in ("split", "split2", "imex2"):
        for dtype, dname in ((F32, "f32"), (F64, "f64")):
            for no_slip, bname in ((True, "no_slip"), (False, "free_slip")):
                marks = (pytest.mark.slow,) if integrator == "imex2" and dtype == F64 else ()
                # in 3-D the direct solve does not pay at these sizes: PCG, not traced
                out.append(pytest.param(integrator, 2, dtype, no_slip, marks=marks,
                                        id=f"{integrator}-2-{dname}-{bname}"))
    return out


@pytest.mark.parametrize(("integrator", "rank", "dtype", "no_slip"), _static_body_params())
def test_static_body_step_traces_as_one_graph(integrator, rank, dtype, no_slip):
    """A resting body with the direct pressure solve: the traced step takes the exact capacitance solve alone (the
    eager step lets CG check and polish it, a host loop). Free-slip bodies: their ghost values and flux correction
    keep their stencils on the stepper's layout. ``imex2``: its Crank-Nicolson solves find the layout's direct
    viscous solves (no-slip: the sharp capacitance; free-slip: the held faces' capacitance) by the very masks the
    eager steps built them from."""
    grid = Grid((12,) * rank, bounds=[(0, 1)] * rank)
    body = Body(Sphere((0.55,) + (0.5,) * (rank - 1), 0.2), no_slip=no_slip)
    stepper = FluidStepper(grid, "wall", obstacles=body, viscosity=1e-2, dt=0.02, dtype=dtype, integrator=integrator)
    assert stepper.obstacles.solvers is not None
    state = stepper(FluidState(_velocity(grid, stepper.boundary, dtype)))
    eager = stepper(stepper(state))
    stepper._advance = _trace(stepper.advance)
    traced = stepper(stepper(state))
    tol = dict(rtol=1e-3, atol=1e-4) if dtype == F32 else dict(rtol=1e-6, atol=1e-8)
    for x, y in zip(traced.velocity.values, eager.velocity.values):
        torch.testing.assert_close(x, y, **tol)
    assert counters["stats"]["unique_graphs"] == 1


def test_traced_step_is_differentiable():
    grid = Grid((N, N), bounds=[(0, 1), (0, 1)])
    stepper = FluidStepper(grid, "wall", dt=0.02, viscosity=1e-2, dtype=F64)
    v0 = tuple(c.requires_grad_() for c in _velocity(grid, stepper.boundary, F64).values)
    state = FluidState(StaggeredGrid.zeros(grid, stepper.boundary, dtype=F64).with_values(v0))

    def loss(fn):
        return sum(c.pow(2).sum() for c in fn(state, 0.02).velocity.values)

    g_eager = torch.autograd.grad(loss(stepper.advance), v0)
    g_traced = torch.autograd.grad(loss(_trace(stepper.advance)), v0)
    for x, y in zip(g_traced, g_eager):
        torch.testing.assert_close(x, y, rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("dtype", DTYPES_FIELD)
@pytest.mark.parametrize("rank", [2, 3])
@pytest.mark.parametrize("boundary", ["periodic", "dirichlet", "neumann"])
@pytest.mark.parametrize("method", ["spectral", "implicit"])
def test_heat_step_traces_as_one_graph(method, boundary, rank, dtype):
    grid = Grid((N,) * rank, bounds=[(0, 1)] * rank)
    heat = HeatStepper(grid, boundary, diffusivity=0.01, dt=0.1, method=method, dtype=dtype)
    g = torch.Generator().manual_seed(2)
    u = CenteredGrid(torch.rand((2, *grid.resolution), generator=g, dtype=dtype), grid, boundary)
    eager = heat(u)
    heat._advance = _trace(heat.advance)
    torch.testing.assert_close(heat(u).values, eager.values, **_tol(dtype))
    torch.testing.assert_close(heat(eager).values, heat.advance(eager).values, **_tol(dtype))
    assert counters["stats"]["unique_graphs"] == 1


@pytest.mark.parametrize("dtype", DTYPES_FIELD)
@pytest.mark.parametrize("rank", [1, 2, 3])
@pytest.mark.parametrize("advection", ["maccormack", "semi_lagrangian"])
def test_burgers_step_traces_as_one_graph(advection, rank, dtype):
    grid = Grid((N,) * rank, bounds=[(0, 1)] * rank)
    burgers = BurgersStepper(grid, viscosity=0.02, dt=0.02, advection=advection, dtype=dtype)
    g = torch.Generator().manual_seed(3)
    u = CenteredGrid(0.3 * torch.randn((1, rank, *grid.resolution), generator=g, dtype=dtype), grid, "periodic")
    eager = burgers(u)
    burgers._advance = _trace(burgers.advance)
    torch.testing.assert_close(burgers(u).values, eager.values, **_tol(dtype))
    torch.testing.assert_close(burgers(eager).values, burgers.advance(eager).values, **_tol(dtype))
    assert counters["stats"]["unique_graphs"] == 1


@pytest.mark.parametrize("dtype", DTYPES_FIELD)
@pytest.mark.parametrize("rank", [2, 3])
@pytest.mark.parametrize("diffusion", ["spectral", "implicit", "explicit"])
def test_advection_diffusion_step_traces_as_one_graph(diffusion, rank, dtype):
    grid = Grid((N,) * rank, bounds=[(0, 1)] * rank)
    v = _velocity(grid, "wall", dtype, seed=4)
    step = AdvectionDiffusionStepper(grid, v, diffusivity=1e-3, dt=0.02, diffusion=diffusion, dtype=dtype)
    g = torch.Generator().manual_seed(5)
    c = CenteredGrid(torch.rand((1, *grid.resolution), generator=g, dtype=dtype), grid, "neumann")
    eager = step(c)
    step._advance = _trace(step.advance)
    torch.testing.assert_close(step(c).values, eager.values, **_tol(dtype))
    torch.testing.assert_close(step(eager).values, step.advance(eager, v).values, **_tol(dtype))
    assert counters["stats"]["unique_graphs"] == 1


def test_finiteness_check_is_an_option():
    grid = Grid((N, N), bounds=[(0, 1), (0, 1)])
    v = _velocity(grid, "periodic", F64)
    bad = FluidState(v.with_values((v.values[0].clone().fill_(float("nan")), v.values[1])))
    FluidStepper(grid, "periodic", dt=0.02, dtype=F64)(bad)  # default: nothing read back, no check
    checked = FluidStepper(grid, "periodic", dt=0.02, dtype=F64, check=2)
    state = checked(bad)  # checks every second call
    with pytest.raises(NonFiniteError):
        checked(state)
    with pytest.raises(ParameterError, match="check"):
        FluidStepper(grid, "periodic", dt=0.02, check=-1)


def test_construction_checks_what_the_step_does_not():
    grid = Grid((N, N), bounds=[(0, 1), (0, 1)])
    with pytest.raises(ParameterError, match="balance"):  # inflow without an outflow
        FluidStepper(grid, {"x": (Inflow((1.0, 0.0)), "wall"), "y": "wall"}, dt=0.02)
    with pytest.raises(ParameterError, match="unstable"):
        FluidStepper(grid, "wall", dt=1.0, viscosity=1.0, integrator="rk2")


def test_compile_without_inductor_warns_and_runs_eager(monkeypatch):
    import phisim
    from phisim import compiled

    monkeypatch.setattr(compiled, "inductor_available", lambda device_type="cpu": False)
    grid = Grid((N, N), bounds=[(0, 1), (0, 1)])
    with pytest.warns(RuntimeWarning, match="runs eager"):
        heat = phisim.compile(HeatStepper(grid, "periodic", diffusivity=0.01, dt=0.1))
    assert heat._advance == heat.advance
    with pytest.warns(RuntimeWarning, match="runs eager"):
        stepper = FluidStepper(grid, "periodic", dt=0.02, compile=True)
    assert stepper._advance == stepper.advance
    with pytest.raises(ParameterError):
        phisim.compile(object())

