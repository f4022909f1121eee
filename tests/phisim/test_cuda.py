"""The steppers on a GPU: the same results as on the CPU, and compiled steps (CUDA graphs) equal to eager ones.

Skipped without CUDA. ``PHISIM_TEST_DEVICE=cpu`` runs the same checks with the CPU as the second device (the
comparison is then trivial, the compiled checks are not): that keeps this module's own logic tested on machines
without a GPU.

* every fluid-step family (periodic fused and general, closed box with buoyant smoke, channel with inflow, rk3,
  imex2, 2-D and 3-D) and a resting no-slip body with the direct pressure solve: two steps agree with the CPU;
* resting, carried, spinning and path-driven bodies, no-slip and free-slip, 2-D and 3-D (the masked PCG with leaf
  elimination, rebuilt every step for moving bodies): three steps agree with the CPU; the drag's gradient with
  respect to a disc's radius, centre and velocity agrees with the CPU's;
* ``phisim.compile`` (``mode='reduce-overhead'`` on CUDA: CUDA graphs) equals the eager step over several steps
  and across a new state's values;
* heat, Burgers, the ETDRK steppers (Kuramoto-Sivashinsky, Navier-Stokes vorticity, Gray-Scott) agree with the
  CPU; a checkpointed rollout's gradient agrees with the CPU's.
"""

from __future__ import annotations

import os
import warnings

import pytest
import torch

import phisim
from phisim import CenteredGrid, Grid, StaggeredGrid
from phisim.boundary import Inflow, Open
from phisim.fluid import Body, BurgersStepper, FluidState, FluidStepper, Sphere
from phisim.pde import GrayScott, KuramotoSivashinsky, NavierStokesVorticity, random_field
from phisim.solvers.heat import HeatStepper

DEVICE = os.environ.get("PHISIM_TEST_DEVICE", "cuda")
pytestmark = [
    pytest.mark.cuda,
    pytest.mark.skipif(DEVICE.startswith("cuda") and not torch.cuda.is_available(), reason="needs CUDA"),
]
F32, F64 = torch.float32, torch.float64
CHANNEL = {"x": (Inflow((1.0, 0.0)), Open()), "y": "wall"}
CHANNEL3 = {"x": (Inflow((1.0, 0.0, 0.0)), Open()), "y": "wall", "z": "periodic"}

# (id, rank, boundary, stepper settings, with a marker)
FLUID_CASES = [
    ("periodic-fused", 2, "periodic", dict(viscosity=1e-3, advection="semi_lagrangian",
                                           viscosity_scheme="explicit"), False),
    ("periodic-general", 2, "periodic", dict(viscosity=1e-3, fused=False), False),
    ("periodic-3d", 3, "periodic", dict(viscosity=1e-3), False),
    ("box-smoke", 2, "wall", dict(viscosity=1e-3, buoyancy=0.5), True),
    ("box-smoke-3d", 3, "wall", dict(viscosity=1e-3, buoyancy=0.5), True),
    ("channel", 2, CHANNEL, dict(viscosity=1e-2), False),
    ("channel-3d", 3, CHANNEL3, dict(viscosity=1e-2), False),
    ("box-implicit", 2, "wall", dict(viscosity=1e-2, advection="semi_lagrangian", viscosity_scheme="implicit"),
     False),
    ("box-rk3", 2, "wall", dict(viscosity=1e-3, integrator="rk3"), False),
    ("channel-imex2", 2, CHANNEL, dict(viscosity=1e-2, integrator="imex2"), False),
    ("channel-split2", 2, CHANNEL, dict(viscosity=1e-2, integrator="split2"), False),
    ("periodic-3d-split2", 3, "periodic", dict(viscosity=1e-3, integrator="split2"), False),
]


def _tol(dtype):
    return dict(rtol=1e-4, atol=1e-5) if dtype == F32 else dict(rtol=1e-9, atol=1e-11)


def _start(grid, stepper, dtype, smoke, seed=0):
    g = torch.Generator().manual_seed(seed)
    v = StaggeredGrid.zeros(grid, stepper.boundary, dtype=dtype)
    v = v.with_values(tuple(0.2 * torch.randn(c.shape, generator=g, dtype=dtype) for c in v.values))
    marker = None
    if smoke:
        marker = CenteredGrid(torch.rand((1, *grid.resolution), generator=g, dtype=dtype), grid,
                              stepper.boundary.for_scalar())
    return FluidState(v, marker)


def _to(state: FluidState, device) -> FluidState:
    return FluidState(state.velocity.to(device), None if state.marker is None else state.marker.to(device))


def _compare_states(a: FluidState, b: FluidState, dtype):
    for x, y in zip(a.velocity.values, b.velocity.values):
        torch.testing.assert_close(x.cpu(), y.cpu(), **_tol(dtype))
    if a.marker is not None:
        torch.testing.assert_close(a.marker.values.cpu(), b.marker.values.cpu(), **_tol(dtype))
    torch.testing.assert_close(a.pressure.values.cpu(), b.pressure.values.cpu(), **_tol(dtype))


@pytest.mark.parametrize("dtype", [F32, F64], ids=["f32", "f64"])
@pytest.mark.parametrize("case", FLUID_CASES, ids=[c[0] for c in FLUID_CASES])
def test_fluid_steps_agree_with_the_cpu(case, dtype):
    name, rank, boundary, settings, smoke = case
    grid = Grid((12,) * rank, bounds=[(0, 1)] * rank)
    cpu = FluidStepper(grid, boundary, dt=0.02, dtype=dtype, **settings)
    dev = FluidStepper(grid, boundary, dt=0.02, dtype=dtype, device=DEVICE, **settings)
    start = _start(grid, cpu, dtype, smoke)
    a = cpu(cpu(start))
    b = dev(dev(_to(start, DEVICE)))
    assert b.velocity.values[0].device.type == torch.device(DEVICE).type
    _compare_states(a, b, dtype)


@pytest.mark.parametrize("integrator", ["split", "split2"])
@pytest.mark.parametrize("dtype", [F32, F64], ids=["f32", "f64"])
def test_a_resting_body_with_the_direct_pressure_solve_agrees_with_the_cpu(dtype, integrator):
    grid = Grid((16, 16), bounds=[(0, 1), (0, 1)])
    body = Body(Sphere((0.55, 0.5), 0.2))
    kw = dict(obstacles=body, viscosity=1e-2, dt=0.01, dtype=dtype, integrator=integrator)
    cpu = FluidStepper(grid, CHANNEL, **kw)
    dev = FluidStepper(grid, CHANNEL, device=DEVICE, **kw)
    assert dev.obstacles.solvers is not None
    start = _start(grid, cpu, dtype, False)
    a = cpu(cpu(start))
    b = dev(dev(_to(start, DEVICE)))
    # the eager step checks the direct solve with CG (rtol 1e-6) and polishes it where needed: the two devices
    # agree to that tolerance, not to rounding
    tol = dict(rtol=1e-3, atol=1e-4) if dtype == F32 else dict(rtol=1e-5, atol=1e-7)
    for x, y in zip(a.velocity.values, b.velocity.values):
        torch.testing.assert_close(x, y.cpu(), **tol)


# (id, rank, body); moving and 3-D bodies take the masked PCG (leaf elimination), free-slip bodies the sub-cut
# fractions and centroids; every one of them on the device's own tensors
BODY_CASES = [
    ("carried-no-slip", 2, lambda: Body(Sphere((0.45, 0.5), 0.18), velocity=(0.3, -0.1))),
    ("carried-free-slip", 2, lambda: Body(Sphere((0.45, 0.5), 0.18), velocity=(0.3, -0.1), no_slip=False)),
    ("spinning", 2, lambda: Body(Sphere((0.5, 0.5), 0.2), angular_velocity=2.0)),
    ("path", 2, lambda: Body(Sphere((0.4, 0.5), 0.15), path=lambda t: (0.2 * t, 0.05 * t))),
    ("resting-free-slip", 2, lambda: Body(Sphere((0.55, 0.5), 0.2), no_slip=False)),
    ("sphere-3d", 3, lambda: Body(Sphere((0.5, 0.5, 0.5), 0.22))),
    ("carried-sphere-3d", 3, lambda: Body(Sphere((0.45, 0.5, 0.5), 0.2), velocity=(0.2, 0.0, 0.1))),
    ("free-slip-sphere-3d", 3, lambda: Body(Sphere((0.5, 0.5, 0.5), 0.22), no_slip=False)),
]


@pytest.mark.parametrize("case", BODY_CASES, ids=[c[0] for c in BODY_CASES])
def test_bodies_agree_with_the_cpu(case):
    """Resting, carried, spinning and path-driven bodies, no-slip and free-slip, 2-D and 3-D: three float64 steps
    (the moving ones on the PCG with leaf elimination, rebuilt every step) agree with the CPU to the solve's
    tolerance."""
    name, rank, make = case
    grid = Grid((16,) * rank if rank == 2 else (12,) * rank, bounds=[(0, 1)] * rank)
    boundary = CHANNEL if rank == 2 else CHANNEL3
    kw = dict(viscosity=1e-2, dt=0.01, dtype=F64, pressure=phisim.solvers.Solve(rtol=1e-10, atol=1e-12,
                                                                                max_iter=2000))
    cpu = FluidStepper(grid, boundary, obstacles=make(), **kw)
    dev = FluidStepper(grid, boundary, obstacles=make(), device=DEVICE, **kw)
    start = _start(grid, cpu, F64, False)
    a, b = start, _to(start, DEVICE)
    for _ in range(3):
        a, b = cpu(a), dev(b)
    assert b.velocity.values[0].device.type == torch.device(DEVICE).type
    assert a.time == pytest.approx(0.03) and b.time == pytest.approx(0.03)
    for x, y in zip(a.velocity.values, b.velocity.values):
        assert torch.isfinite(x).all()
        torch.testing.assert_close(x, y.cpu(), rtol=1e-7, atol=1e-9)


@pytest.mark.parametrize("no_slip", [True, False], ids=["no-slip", "free-slip"])
def test_gradients_wrt_body_shape_and_motion_agree_with_the_cpu(no_slip):
    """The drag after two steps, differentiated with respect to a disc's radius, centre and velocity."""
    from phisim.fluid import body_forces

    grid = Grid((16, 12), bounds=[(0, 1.25), (0, 1)])
    kw = dict(viscosity=0.05, dt=0.02, dtype=F64, pressure=phisim.solvers.Solve(rtol=1e-12, atol=1e-14,
                                                                                  max_iter=2000))

    def grad(device):
        r = torch.tensor(0.2, dtype=F64, device=device, requires_grad=True)
        c = torch.tensor([0.55, 0.5], dtype=F64, device=device, requires_grad=True)
        w = torch.tensor([0.1, -0.05], dtype=F64, device=device, requires_grad=True)
        body = Body(Sphere(c, r), velocity=w, no_slip=no_slip)
        stepper = FluidStepper(grid, CHANNEL, obstacles=body, device=device, **kw)
        s = FluidState(StaggeredGrid.zeros(grid, stepper.boundary, dtype=F64, device=device))
        for _ in range(2):
            s = stepper(s)
        f = body_forces(s.velocity, s.pressure, body, dt=kw["dt"], viscosity=kw["viscosity"], time=s.time)
        return [g.cpu() for g in torch.autograd.grad(f.total[..., 0].sum(), (r, c, w))]

    a, b = grad("cpu"), grad(DEVICE)
    assert all(bool(torch.isfinite(g).all()) for g in a) and float(a[0].abs()) > 0
    for x, y in zip(a, b):
        torch.testing.assert_close(x, y, rtol=1e-6, atol=1e-9)


@pytest.mark.parametrize("case", [c for c in FLUID_CASES if c[0] in ("periodic-fused", "periodic-general",
                                                                     "box-smoke", "channel", "periodic-3d")],
                         ids=lambda c: c[0])
def test_compiled_steps_equal_eager_steps(case):
    """``phisim.compile`` on the device (CUDA graphs on a GPU): four steps from two different starts."""
    name, rank, boundary, settings, smoke = case
    grid = Grid((12,) * rank, bounds=[(0, 1)] * rank)
    eager = FluidStepper(grid, boundary, dt=0.02, dtype=F32, device=DEVICE, **settings)
    compiled = phisim.compile(FluidStepper(grid, boundary, dt=0.02, dtype=F32, device=DEVICE, **settings))
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*(lru_cache|complex operators|skipping cudagraphs).*")
        for seed in (0, 1):
            a = b = _to(_start(grid, eager, F32, smoke, seed=seed), DEVICE)
            kept = []
            for _ in range(4):  # each compiled state fed straight back, and every one kept
                a, b = eager(a), compiled(b)
                kept.append((a, b))
            for x, y in kept:  # earlier results are not overwritten by later replays of a CUDA graph
                _compare_states(x, y, F32)


def test_gradients_through_compiled_steps_equal_eager_ones():
    """Backpropagation through five compiled steps (CUDA graphs on a GPU: five forward replays before the backward)
    equals it through five eager steps."""
    grid = Grid((12, 12), bounds=[(0, 1), (0, 1)])
    settings = dict(viscosity=1e-3, advection="semi_lagrangian", viscosity_scheme="explicit")
    eager = FluidStepper(grid, "periodic", dt=0.02, dtype=F32, device=DEVICE, **settings)
    compiled = phisim.compile(FluidStepper(grid, "periodic", dt=0.02, dtype=F32, device=DEVICE, **settings))
    start = _to(_start(grid, eager, F32, False), DEVICE)

    def grad(stepper):
        v0 = tuple(c.detach().clone().requires_grad_() for c in start.velocity.values)
        s = FluidState(start.velocity.with_values(v0))
        for _ in range(5):
            s = stepper(s)
        return torch.autograd.grad(sum(c.pow(2).sum() for c in s.velocity.values), v0)

    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*(lru_cache|complex operators|skipping cudagraphs).*")
        for _ in range(2):  # the second pass replays the recorded graphs
            for x, y in zip(grad(compiled), grad(eager)):
                torch.testing.assert_close(x, y, rtol=1e-4, atol=1e-5)



@pytest.mark.parametrize("method", ["spectral", "implicit"])
@pytest.mark.parametrize("boundary", ["periodic", "dirichlet", "neumann"])
def test_heat_steps_agree_with_the_cpu(boundary, method):
    grid = Grid((16, 12), bounds=[(0, 1), (0, 1)])
    u = CenteredGrid(torch.rand((2, 16, 12), generator=torch.Generator().manual_seed(2), dtype=F64), grid, boundary)
    cpu = HeatStepper(grid, boundary, diffusivity=0.01, dt=0.1, method=method, dtype=F64)
    dev = HeatStepper(grid, boundary, diffusivity=0.01, dt=0.1, method=method, dtype=F64, device=DEVICE)
    a = cpu(cpu(u))
    b = dev(dev(u.with_values(u.values.to(DEVICE))))
    torch.testing.assert_close(a.values, b.values.cpu(), rtol=1e-9, atol=1e-11)


def test_burgers_rollout_gradient_agrees_with_the_cpu():
    grid = Grid((16, 16), bounds=[(0, 1), (0, 1)])
    u = CenteredGrid(0.2 * torch.randn((1, 2, 16, 16), generator=torch.Generator().manual_seed(3), dtype=F64),
                     grid, "periodic")

    def grad(device):
        burgers = BurgersStepper(grid, viscosity=0.02, dt=0.02, dtype=F64)  # runs where its field lies
        x = u.values.to(device).requires_grad_()
        tr = phisim.rollout(burgers, u.with_values(x), 6, every=3, checkpoint=2)
        return torch.autograd.grad(tr.values.pow(2).sum(), x)[0]

    torch.testing.assert_close(grad("cpu"), grad(DEVICE).cpu(), rtol=1e-9, atol=1e-11)


@pytest.mark.parametrize("equation", ["ks", "ns", "gray_scott"])
def test_etdrk_steppers_agree_with_the_cpu(equation):
    def make(device):
        if equation == "ks":
            return KuramotoSivashinsky(domain=22.0, resolution=64, dt=0.25, dtype=F64, device=device)
        if equation == "ns":
            return NavierStokesVorticity(viscosity=1e-3, resolution=32, dt=0.01, dtype=F64, device=device)
        return GrayScott(ndim=2, resolution=24, dtype=F64, device=device)

    cpu, dev = make("cpu"), make(DEVICE)
    start = dict(amplitude=0.2, mean=[1.0, 0.0]) if equation == "gray_scott" else {}  # near the uniform state
    u0 = random_field(cpu, 2, seed=0, **start)
    a = cpu.repeat(u0, 10)
    assert torch.isfinite(a).all() and a.std() > 1e-3
    torch.testing.assert_close(a, dev.repeat(u0.to(DEVICE), 10).cpu(), rtol=1e-9, atol=1e-10)
