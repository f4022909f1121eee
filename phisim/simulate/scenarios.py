"""The scenarios of ``phisim simulate``: initial states, parameters and time steps of standard flows.

A :class:`Scenario` declares its parameters (:class:`Param`: a default and, for randomised parameters, a
range drawn once per output file) and builds a :class:`Simulation` for a batch of trajectories: the grid,
the boundary, the fields written per frame, constant fields (obstacle masks) and a ``step`` function.
Per-trajectory randomness (initial states, inflow positions) comes from the file's ``torch.Generator``, so a
file depends only on the seed and its index.

Scenarios (``SCENARIOS``):

* ``smoke``: buoyant smoke plume in a closed box around a spherical obstacle (2-D or 3-D);
* ``cavity``: lid-driven cavity (2-D), the lid moving in +x on the upper ``y`` wall;
* ``taylor_green``: the decaying Taylor-Green vortex on a periodic ``[0, 2π)^2`` box (analytic decay
  ``exp(-2 ν k² t)``);
* ``turbulence``: decaying turbulence from random divergence-free velocity, periodic (2-D or 3-D);
* ``heat``: diffusion of random hot rectangles (1-D, 2-D or 3-D; periodic or zero-Dirichlet walls);
* ``burgers``: viscous Burgers' equation ``u_t + (u·∇)u = ν ∇²u``, periodic (1-D or 2-D);
* ``karman``: a Kármán vortex street behind a cylinder in a channel (the DFG benchmark geometry), a parabolic
  inflow and an open outflow (:class:`phisim.boundary.Inflow`, :class:`phisim.fluid.Body`).

Schemes (see ``docs/SCHEMES.md``): ``cavity`` and ``taylor_green`` step with the second-order integrator
``'imex2'`` (Crank-Nicolson viscosity, central convection; their flows are resolved, cell Reynolds numbers of
a few, and the split step's first-order error in dt would otherwise shift decay rates and steady states
with the time step); ``smoke`` transports its density with the conservative scheme (the smoke in the box is
exactly what the inflow added, never negative) and keeps the robust split step with MacCormack for its
under-resolved velocity, as does ``turbulence`` (cell Reynolds numbers around 20, where central
convection would produce grid-scale wiggles).
"""

from __future__ import annotations

import inspect
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import torch

from phisim.boundary import Boundary, Dirichlet, Inflow, NoSlipWall, Open
from phisim.errors import ParameterError
from phisim.field import CenteredGrid, StaggeredGrid
from phisim.fluid import (
    Body,
    BurgersStepper,
    FluidState,
    FluidStepper,
    Obstacle,
    Sphere,
    cfl_dt,
    make_incompressible,
    obstacle_mask,
    solid_layout,
)
from phisim.grid import Grid
from phisim.pde import EQUATIONS, make_stepper, random_field
from phisim.simulate.noise import random_rectangles, spectral_noise
from phisim.solvers.heat import HeatStepper

__all__ = ["Param", "Simulation", "Scenario", "SCENARIOS", "COMMON_PARAMETERS"]


@dataclass(frozen=True)
class Param:
    """A scenario parameter.

    Attributes:
        default: Value used when the configuration leaves it unset and ``randomize`` is off.
        low: Lower end of the uniform range drawn per file when unset and ``randomize`` is on (None: fixed).
        high: Upper end of that range.
        help: One-line description with the unit.
    """

    default: Any
    low: float | None = None
    high: float | None = None
    help: str = ""


#: Parameters every scenario accepts (the run's shape, storage and randomisation).
COMMON_PARAMETERS: dict[str, Param] = {
    "seed": Param(0, help="seed of every random draw (initial states and parameters)"),
    "trajectories": Param(8, help="number of trajectories in the dataset"),
    "trajectories_per_file": Param(4, help="trajectories per HDF5 file (one file = one parameter draw)"),
    "valid_fraction": Param(0.1, help="fraction of the files in data/valid"),
    "test_fraction": Param(0.1, help="fraction of the files in data/test"),
    "steps": Param(None, help="time steps per trajectory (scenario default when unset)"),
    "save_every": Param(1, help="write every n-th step as a frame"),
    "dt": Param(None, help="time step (scenario default when unset)"),
    "resolution": Param(None, help="cells per axis, an int or a list (scenario default when unset)"),
    "dim": Param(None, help="number of spatial dimensions (scenario default when unset)"),
    "randomize": Param(True, help="draw unset ranged parameters per file (else use their defaults)"),
    "dtype": Param("float32", help="float32 or float64 (simulation and storage)"),
    "device": Param("cpu", help="torch device of the simulation"),
}


@dataclass
class Simulation:
    """One batch of trajectories ready to run.

    Attributes:
        grid: The grid.
        boundary: The boundary written to the file.
        fields: Field name -> kind (``'scalar'``, ``'vector'``, ``'staggered'``).
        state: The initial state (anything ``step`` and ``frame`` understand).
        step: ``state -> state`` advancing one ``dt``.
        frame: ``state -> {field: value}`` to write.
        constant_fields: Name -> constant scalar field ``(B, *res)`` or ``(*res)`` (e.g. the obstacle mask).
    """

    grid: Grid
    boundary: Boundary
    fields: dict[str, str]
    state: Any
    step: Callable[[Any], Any]
    frame: Callable[[Any], dict]
    constant_fields: dict[str, torch.Tensor] = field(default_factory=dict)


@dataclass(frozen=True)
class Scenario:
    """A named scenario: its parameters, defaults of the common settings and the builder.

    Attributes:
        name: Name on the command line.
        description: One line.
        parameters: Scenario parameters.
        dims: Supported numbers of spatial dimensions (the first is the default).
        resolution: Default cells per axis.
        dt: Default time step.
        steps: Default number of steps.
        build: ``build(config, params, batch, generator, dtype, device) -> Simulation``.
        available: False for scenarios that cannot run yet (their ``description`` says why).
    """

    name: str
    description: str
    parameters: dict[str, Param]
    dims: tuple[int, ...]
    resolution: int
    dt: float
    steps: int
    build: Callable[..., Simulation]
    available: bool = True


def _resolution(cfg: dict, dim: int) -> tuple[int, ...]:
    r = cfg["resolution"]
    if isinstance(r, int):
        return (r,) * dim
    r = tuple(int(v) for v in r)
    if len(r) != dim:
        raise ParameterError(f"resolution {list(r)} has {len(r)} entries for a {dim}-D scenario")
    return r


def _uniform(g: torch.Generator, shape, lo: float, hi: float, dtype=torch.float64) -> torch.Tensor:
    return lo + (hi - lo) * torch.rand(shape, generator=g, dtype=dtype)


# ---- smoke plume ----------------------------------------------------------------------------------------


def _build_smoke(cfg, p, batch, g, dtype, device) -> Simulation:

    dim = cfg["dim"]
    n = _resolution(cfg, dim)
    res = (n[0], int(round(1.5 * n[1]))) + n[2:] if isinstance(cfg["resolution"], int) else n
    grid = Grid(res)
    walls = Boundary.create("wall", dim)
    size = grid.size
    centre = [0.5 * s for s in size]
    centre[0] += p["obstacle_offset"] * size[0]
    centre[1] = p["obstacle_height"] * size[1]
    obstacle = Obstacle.sphere(centre, p["obstacle_radius"] * size[0])
    solid = obstacle_mask([obstacle], grid, device)
    if solid is None:  # an obstacle smaller than a cell covers no cell
        solid = torch.zeros(grid.resolution, dtype=torch.bool, device=device)
    x = grid.cell_centers(dtype, device)
    # per trajectory: the inflow disc's sideways position
    shift = _uniform(g, (batch, dim), -0.15, 0.15)
    sources = []
    for b in range(batch):
        c = torch.tensor([0.5 * s for s in size], dtype=torch.float64)
        c[1] = 0.1 * size[1]
        for a in range(dim):
            if a != 1:
                c[a] += float(shift[b, a]) * size[a]
        c = c.to(dtype=dtype, device=device)
        sources.append((((x - c) ** 2).sum(-1) <= (0.08 * size[0]) ** 2).to(dtype))
    source = torch.stack(sources)
    marker = CenteredGrid.zeros(grid, walls.for_scalar(), batch, dtype=dtype, device=device)
    velocity = StaggeredGrid.zeros(grid, walls, batch, dtype=dtype, device=device)
    stepper = FluidStepper(grid, walls, obstacles=[obstacle], viscosity=p["viscosity"], buoyancy=p["buoyancy"],
                           marker_source=source, advection="maccormack", marker_advection="conservative",
                           dt=cfg["dt"], dtype=dtype, device=device)
    advance = stepper

    return Simulation(grid, walls, {"density": "scalar", "velocity": "staggered"},
                      FluidState(velocity, marker), advance,
                      lambda s: {"density": s.marker, "velocity": s.velocity},
                      {"obstacle_mask": solid.to(dtype).reshape(grid.resolution)})


# ---- lid-driven cavity ----------------------------------------------------------------------------------


def _divergence_free_noise(grid, boundary, batch, amplitude, g, dtype, device) -> StaggeredGrid:

    noise = spectral_noise(grid, batch, scale=4.0, channels=grid.rank, generator=g, dtype=dtype, device=device)
    v = CenteredGrid(amplitude * noise.values, grid, boundary).to_staggered()
    v, _ = make_incompressible(v)
    return v


def _build_cavity(cfg, p, batch, g, dtype, device) -> Simulation:

    res = _resolution(cfg, 2)
    grid = Grid(res, bounds=(1.0, 1.0))
    lid = NoSlipWall(velocity=(p["lid_velocity"], 0.0))
    boundary = Boundary.create({"x": NoSlipWall(), "y": (NoSlipWall(), lid)}, 2)
    v0 = _divergence_free_noise(grid, boundary, batch, p["initial_noise"] * p["lid_velocity"], g, dtype, device)
    advance = FluidStepper(grid, boundary, viscosity=p["viscosity"], integrator="imex2", dt=cfg["dt"], dtype=dtype,
                           device=device)
    return Simulation(grid, boundary, {"velocity": "staggered"}, FluidState(v0), advance,
                      lambda s: {"velocity": s.velocity})


# ---- periodic flows -------------------------------------------------------------------------------------


def _periodic_flow(grid, v0, p, dt, integrator: str = "split") -> Simulation:

    advance = FluidStepper(grid, "periodic", viscosity=p["viscosity"], advection="maccormack", integrator=integrator,
                           dt=dt, dtype=v0.dtype, device=v0.device)
    return Simulation(grid, advance.boundary, {"velocity": "staggered"}, FluidState(v0), advance,
                      lambda s: {"velocity": s.velocity})


def _build_taylor_green(cfg, p, batch, g, dtype, device) -> Simulation:
    res = _resolution(cfg, 2)
    grid = Grid(res, bounds=(2 * math.pi, 2 * math.pi))
    k = int(p["wavenumber"])
    amp = _uniform(g, (batch,), 0.5, 1.5).to(dtype=dtype, device=device)  # per trajectory
    shift = _uniform(g, (batch, 2), 0.0, 2 * math.pi).to(dtype=dtype, device=device)

    comps = []
    for i in range(2):
        pts = _face_points(grid, i, dtype, device)  # (*face_shape, 2)
        x = pts[..., 0][None] + shift[:, 0].reshape(-1, 1, 1)
        y = pts[..., 1][None] + shift[:, 1].reshape(-1, 1, 1)
        a = amp.reshape(-1, 1, 1)
        comps.append(a * torch.sin(k * x) * torch.cos(k * y) if i == 0 else -a * torch.cos(k * x) * torch.sin(k * y))
    v0 = StaggeredGrid(comps, grid, "periodic")
    return _periodic_flow(grid, v0, p, cfg["dt"], integrator="imex2")


def _face_points(grid: Grid, axis: int, dtype, device) -> torch.Tensor:
    """Positions of the faces normal to ``axis`` (boundary faces included), ``(*face_shape(axis), rank)``."""
    coords = []
    for a in range(grid.rank):
        lo, hi = grid.bounds[a]
        n = grid.resolution[a]
        dx = (hi - lo) / n
        if a == axis:
            c = lo + dx * torch.arange(n + 1, dtype=torch.float64)
        else:
            c = lo + dx * (torch.arange(n, dtype=torch.float64) + 0.5)
        coords.append(c)
    return torch.stack(torch.meshgrid(*coords, indexing="ij"), dim=-1).to(dtype=dtype, device=device)


def _build_turbulence(cfg, p, batch, g, dtype, device) -> Simulation:
    dim = cfg["dim"]
    res = _resolution(cfg, dim)
    grid = Grid(res, bounds=[2 * math.pi] * dim)
    v0 = _divergence_free_noise(grid, Boundary.create("periodic", dim), batch, p["amplitude"], g, dtype, device)
    return _periodic_flow(grid, v0, p, cfg["dt"])


# ---- heat -----------------------------------------------------------------------------------------------


def _build_heat(cfg, p, batch, g, dtype, device) -> Simulation:

    dim = cfg["dim"]
    res = _resolution(cfg, dim)
    grid = Grid(res)
    if p["walls"]:
        boundary = Boundary.create(Dirichlet(0.0), dim)
    else:
        boundary = Boundary.create("periodic", dim)
    t0 = random_rectangles(grid, batch, max_half_size=max(1.0, min(res) / 6), boundary=boundary, generator=g,
                           dtype=dtype, device=device)
    advance = HeatStepper(grid, boundary, diffusivity=p["diffusivity"], dt=cfg["dt"], dtype=dtype, device=device)
    return Simulation(grid, boundary, {"temperature": "scalar"}, t0, advance, lambda s: {"temperature": s})


# ---- Burgers --------------------------------------------------------------------------------------------


def _build_burgers(cfg, p, batch, g, dtype, device) -> Simulation:

    dim = cfg["dim"]
    res = _resolution(cfg, dim)
    grid = Grid(res, bounds=[2 * math.pi] * dim)
    noise = spectral_noise(grid, batch, scale=p["scale"], channels=dim, generator=g, dtype=dtype, device=device)
    u0 = CenteredGrid(p["amplitude"] * noise.values, grid, "periodic")
    advance = BurgersStepper(grid, viscosity=p["viscosity"], dt=cfg["dt"], dtype=dtype)

    return Simulation(grid, Boundary.create("periodic", dim), {"velocity": "vector"}, u0, advance,
                      lambda u: {"velocity": u})


def _build_karman(cfg, p, batch, g, dtype, device) -> Simulation:
    """Flow past a cylinder in a channel (the DFG geometry, scaled by ``resolution`` cells across)."""

    height, length, diameter = 0.41, 2.2, 0.1
    ny = _resolution(cfg, 2)[1] if not isinstance(cfg["resolution"], int) else cfg["resolution"]
    dx = height / ny
    nx = int(round(length / dx)) if isinstance(cfg["resolution"], int) else _resolution(cfg, 2)[0]
    grid = Grid((nx, ny), bounds=[(0, nx * dx), (0, height)])
    umax = float(p["umax"])

    def profile(x):
        y = x[..., 1]
        return torch.stack([4 * umax * y * (height - y) / height**2, torch.zeros_like(y)], -1)

    body = Body(Sphere((0.2, float(p["cylinder_y"])), diameter / 2), name="cylinder")
    spec = {"x": (Inflow(profile), Open()), "y": "wall"}
    v = StaggeredGrid.from_function(profile, grid, spec, batch_size=batch, dtype=dtype, device=device)
    if p["initial_noise"] > 0:  # per trajectory: a random divergence-free disturbance (shifts the shedding)
        noise = spectral_noise(grid, batch, scale=4.0, channels=2, generator=g, dtype=dtype, device=device)
        v = v + CenteredGrid(p["initial_noise"] * umax * noise.values, grid, v.boundary).to_staggered()
    v, _ = make_incompressible(v, body)
    lay = solid_layout(body, grid, v.boundary, 0.0, dtype, device)
    solid = (lay.cell_fraction[0] < 0.5).to(dtype)
    nu, out_dt = float(p["viscosity"]), cfg["dt"]
    viscous_limit = 0.45 * min(grid.dx) ** 2 / (2 * grid.rank * nu)
    stepper = FluidStepper(grid, v.boundary, obstacles=body, viscosity=nu, advection="maccormack", dtype=dtype,
                           device=device)

    def advance(s):  # CFL sub-steps landing exactly on the output step
        target = s.time + out_dt
        while s.time < target - 1e-12 * max(1.0, target):
            dt = min(cfl_dt(s.velocity, 0.5, max_dt=out_dt), viscous_limit, target - s.time)
            if target - s.time - dt < 1e-3 * dt:
                dt = target - s.time
            s = stepper(s, dt)
        return FluidState(s.velocity, s.marker, s.pressure, target)

    return Simulation(grid, v.boundary, {"velocity": "staggered"}, FluidState(v), advance,
                      lambda s: {"velocity": s.velocity}, {"obstacle_mask": solid})



# ---- spectral (ETDRK) equations -------------------------------------------------------------------------

#: Per equation: (scenario name, dims, field names per channel or "velocity" for a vector, physical
#: parameters of the scenario, initial state (amplitude, mean, max_wavenumber), steps, description).
_PDE = {
    "advection": ("advection", (1, 2, 3), ("u",), {"velocity": Param(1.0, help="advection speed")},
                  (1.0, 0.0, 4.0), 100, "linear advection u_t + c·∇u = 0 (spectral, exact in time)"),
    "diffusion": ("diffusion_spectral", (1, 2, 3), ("u",), {"diffusivity": Param(0.01, 0.005, 0.02, "ν")},
                  (1.0, 0.0, 4.0), 100, "diffusion u_t = ν∇²u (spectral, exact in time)"),
    "dispersion": ("dispersion", (1, 2, 3), ("u",), {"dispersivity": Param(0.01, help="a in u_t = a Σ∂³u")},
                   (1.0, 0.0, 4.0), 100, "dispersion u_t = a Σ ∂³u/∂x³ (spectral, exact in time)"),
    "hyper_diffusion": ("hyper_diffusion", (1, 2, 3), ("u",), {"hyperdiffusivity": Param(1e-4, help="ν")},
                        (1.0, 0.0, 4.0), 100, "hyper-diffusion u_t = -ν∇⁴u (spectral, exact in time)"),
    "wave": ("wave", (1, 2, 3), ("u", "v"), {"speed": Param(1.0, 0.5, 1.5, "wave speed c")},
             (1.0, 0.0, 4.0), 100, "wave equation u_tt = c²∇²u, state (u, u_t) (spectral, exact in time)"),
    "burgers": ("burgers_spectral", (1, 2), "velocity", {"viscosity": Param(0.02, 0.01, 0.05, "ν")},
                (1.0, 0.0, 4.0), 100, "viscous Burgers on [0, 2π)^d, ETDRK4 with 2/3 dealiasing"),
    "kdv": ("kdv", (1,), ("u",), {}, (1.0, 0.0, 4.0), 200, "Korteweg-de Vries u_t + 6uu_x + u_xxx = 0, ETDRK4"),
    "kuramoto_sivashinsky": ("kuramoto_sivashinsky", (1, 2), ("u",), {}, (1.0, 0.0, 4.0), 200,
                             "Kuramoto-Sivashinsky on L = 64 (1-D) / combustion form (2-D), ETDRK4"),
    "allen_cahn": ("allen_cahn", (1, 2), ("u",), {"diffusivity": Param(1e-3, 5e-4, 2e-3, "D"),
                                                  "reactivity": Param(1.0, help="r")},
                   (0.5, 0.0, 8.0), 100, "Allen-Cahn u_t = D∇²u + r(u - u³), ETDRK4"),
    "cahn_hilliard": ("cahn_hilliard", (1, 2), ("u",), {"gamma": Param(2.5e-3, help="interface energy γ")},
                      (0.1, 0.0, 8.0), 100, "Cahn-Hilliard u_t = M∇²(u³ - u - γ∇²u), ETDRK4 (mass conserved)"),
    "fisher_kpp": ("fisher_kpp", (1, 2), ("u",), {"diffusivity": Param(1e-3, help="D"),
                                                  "reactivity": Param(10.0, 5.0, 15.0, "r")},
                   (0.1, 0.2, 8.0), 100, "Fisher-KPP u_t = D∇²u + r u(1 - u), ETDRK4"),
    "swift_hohenberg": ("swift_hohenberg", (1, 2), ("u",), {"reactivity": Param(0.7, 0.5, 0.9, "r")},
                        (0.1, 0.0, 8.0), 100, "Swift-Hohenberg pattern formation on L = 20π, ETDRK4"),
    "gray_scott": ("gray_scott", (2,), ("u", "v"), {"feed": Param(0.04, help="F"), "kill": Param(0.06, help="k")},
                   (0.05, (0.9, 0.1), 8.0), 100, "Gray-Scott reaction-diffusion (Pearson), ETDRK4"),
    "kolmogorov": ("kolmogorov", (2,), ("vorticity",), {}, (1.0, 0.0, 4.0), 200,
                   "2-D Navier-Stokes vorticity with Kolmogorov forcing (k_f = 4, drag 0.1), ETDRK4"),
    "decaying_turbulence": ("decaying_turbulence", (2,), ("vorticity",), {"viscosity": Param(1e-3, help="ν")},
                            (1.0, 0.0, 4.0), 200, "2-D decaying turbulence in vorticity form, ETDRK4"),
}


def _pde_builder(equation: str):
    """The ``build`` of the scenario of one :mod:`phisim.pde` equation (periodic; sample ``j`` at ``j L / N``)."""
    _, _, names, params, (amplitude, mean, max_wavenumber), _, _ = _PDE[equation]
    accepted = set(inspect.signature(EQUATIONS[equation]).parameters)

    def build(cfg, p, batch, g, dtype, device) -> Simulation:
        dim = cfg["dim"]
        kwargs = {k: p[k] for k in params}
        kwargs.update(dt=cfg["dt"], dtype=dtype, device=device)
        if "ndim" in accepted:
            kwargs["ndim"] = dim
        if cfg["resolution"] is not None or "resolution" not in accepted:
            kwargs["resolution"] = _resolution(cfg, dim) if cfg["resolution"] is not None else None
        kwargs = {k: v for k, v in kwargs.items() if v is not None}
        stepper = make_stepper(equation, **kwargs)
        seed = int(torch.randint(0, 2**31 - 1, (1,), generator=g))
        u0 = random_field(stepper, batch, amplitude=amplitude, mean=mean, max_wavenumber=max_wavenumber, seed=seed)
        sg = stepper.grid
        grid = Grid(sg.resolution, bounds=[(-0.5 * length / n, length - 0.5 * length / n)
                                           for length, n in zip(sg.domain, sg.resolution)])
        boundary = Boundary.create("periodic", grid.rank)
        if names == "velocity":
            fields = {"velocity": "vector"}

            def frame(u):
                return {"velocity": CenteredGrid(u, grid, boundary)}
        else:
            fields = {n: "scalar" for n in names}

            def frame(u):
                return {n: u[:, c] for c, n in enumerate(names)}

        return Simulation(grid, boundary, fields, u0, stepper, frame)

    return build


def _pde_scenarios() -> dict[str, Scenario]:
    out = {}
    for equation, (name, dims, _, params, _, steps, description) in _PDE.items():
        sig = inspect.signature(EQUATIONS[equation]).parameters
        target = inspect.signature(EQUATIONS["navier_stokes"]).parameters if equation in (
            "kolmogorov", "decaying_turbulence") else sig
        default = {k: (sig[k].default if k in sig else target[k].default) for k in ("resolution", "dt")}
        resolution = default["resolution"] if isinstance(default["resolution"], int) else 128
        out[name] = Scenario(name, description + " (phisim.pde)", dict(params), dims, resolution,
                             float(default["dt"]), steps, _pde_builder(equation))
    return out

SCENARIOS: dict[str, Scenario] = {
    "smoke": Scenario(
        "smoke", "buoyant smoke plume around a spherical obstacle in a closed box (2-D/3-D)",
        {"buoyancy": Param(0.5, 0.3, 0.8, "buoyancy per unit density"),
         "viscosity": Param(0.01, help="kinematic viscosity (cells^2 per time unit)"),
         "obstacle_radius": Param(0.1, 0.06, 0.14, "obstacle radius / box width"),
         "obstacle_height": Param(0.45, 0.35, 0.6, "obstacle centre height / box height"),
         "obstacle_offset": Param(0.05, -0.15, 0.15, "sideways offset of the obstacle / box width")},
        (2, 3), 32, 0.5, 60, _build_smoke),
    "cavity": Scenario(
        "cavity", "lid-driven cavity on the unit square (lid on the upper y wall, moving in +x)",
        {"lid_velocity": Param(1.0, 0.5, 1.5, "lid speed"),
         "viscosity": Param(0.01, 0.005, 0.02, "kinematic viscosity (Re = lid_velocity / viscosity)"),
         "initial_noise": Param(0.1, help="amplitude of the random initial velocity / lid speed")},
        (2,), 32, 0.005, 100, _build_cavity),
    "taylor_green": Scenario(
        "taylor_green", "decaying Taylor-Green vortices on a periodic [0, 2π)^2 box, random amplitude and shift",
        {"viscosity": Param(0.05, 0.01, 0.1, "kinematic viscosity"),
         "wavenumber": Param(1, help="vortex wavenumber k (energy decays like exp(-4 ν k² t))")},
        (2,), 32, 0.05, 40, _build_taylor_green),
    "turbulence": Scenario(
        "turbulence", "decaying turbulence from random divergence-free velocity, periodic [0, 2π)^d",
        {"viscosity": Param(0.01, 0.002, 0.02, "kinematic viscosity"),
         "amplitude": Param(1.0, help="standard deviation of the initial velocity components")},
        (2, 3), 32, 0.05, 40, _build_turbulence),
    "heat": Scenario(
        "heat", "diffusion of random hot rectangles (periodic, or zero-temperature walls with walls=true)",
        {"diffusivity": Param(0.5, 0.1, 1.0, "diffusivity (cells^2 per time unit)"),
         "walls": Param(False, help="zero-Dirichlet walls instead of a periodic box")},
        (2, 1, 3), 32, 0.5, 40, _build_heat),
    "burgers": Scenario(
        "burgers", "viscous Burgers' equation u_t + (u·∇)u = ν∇²u on a periodic [0, 2π)^d box",
        {"viscosity": Param(0.05, 0.01, 0.1, "kinematic viscosity"),
         "amplitude": Param(1.0, help="standard deviation of the initial velocity"),
         "scale": Param(2.0, help="wavenumber scale of the initial noise (larger: finer)")},
        (1, 2), 64, 0.02, 50, _build_burgers),
    "karman": Scenario(
        "karman", "Kármán vortex street: parabolic inflow past a no-slip cylinder in a 2.2 x 0.41 channel "
        "(resolution = cells across)",
        {"viscosity": Param(1e-3, 5e-4, 1.67e-3, "kinematic viscosity (Re = (2/3) umax 0.1 / viscosity)"),
         "umax": Param(1.5, help="peak inflow speed of the parabolic profile"),
         "cylinder_y": Param(0.2, 0.17, 0.24, "height of the cylinder centre (diameter 0.1)"),
         "initial_noise": Param(0.02, help="random initial disturbance / umax, per trajectory")},
        (2,), 24, 0.05, 100, _build_karman),
}
SCENARIOS.update(_pde_scenarios())
