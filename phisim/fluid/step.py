"""Navier-Stokes time steps: self-advection, buoyancy, viscosity, projection; energy, CFL time step.

:func:`navier_stokes_step` composes pure functions: self-advection (:func:`phisim.ops.advection.advect`,
semi-Lagrangian or MacCormack), a body force (e.g. :func:`buoyancy`), the solids' velocity
(:func:`~phisim.fluid.projection.impose_solids`), viscosity (:func:`~phisim.fluid.viscosity.diffuse_velocity`,
explicit or implicit), projection (:func:`~phisim.fluid.projection.make_incompressible`), and optionally a
rescaling to the kinetic energy the step started with (:func:`normalize_energy`). :func:`step` advances a
:class:`FluidState` (velocity, marker, pressure, time) for smoke-like simulations and flows past bodies.
First order in time (operator splitting); second order in space with MacCormack advection.
``integrator='rk2'``, ``'rk3'`` or ``'imex2'`` selects the second-/third-order integrators of
:mod:`phisim.fluid.integrators` instead (orders in time: split 1, rk2 2, rk3 3, imex2 2).

References: Stam (1999), "Stable fluids", SIGGRAPH; Selle et al. (2008), J. Sci. Comput. 35 (MacCormack).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace

import torch

from phisim.boundary import Boundary, Inflow, pad
from phisim.checks import all_finite, check_dt, check_finite, check_finite_number, check_positive
from phisim.errors import GridMismatchError, ParameterError, ShapeError
from phisim.field import CenteredGrid, StaggeredGrid
from phisim.fluid.bodies import solid_layout
from phisim.fluid.projection import _check_velocity, _project_box, impose_solids, make_incompressible
from phisim.fluid.viscosity import diffuse_velocity
from phisim.grid import Grid
from phisim.ops.advection import SCALAR_SCHEMES, SCHEMES, _advect, advect
from phisim.ops.advection import _validate as _validate_advection
from phisim.padding import const
from phisim.solvers.linalg import Solve

__all__ = [
    "buoyancy",
    "kinetic_energy",
    "normalize_energy",
    "cfl_dt",
    "navier_stokes_step",
    "FluidState",
    "step",
]


def _scalar_values(marker, grid: Grid) -> tuple[torch.Tensor, Boundary | None]:
    if isinstance(marker, CenteredGrid):
        if marker.is_vector:
            raise ShapeError("the marker must be a scalar CenteredGrid (B, *res)")
        if marker.grid != grid:
            raise GridMismatchError(f"marker grid {marker.grid} differs from the velocity grid {grid}")
        return marker.values, marker.boundary
    m = torch.as_tensor(marker)
    if m.ndim != grid.rank + 1 or tuple(m.shape[1:]) != grid.resolution:
        raise ShapeError(
            f"marker must have shape (B, {', '.join(map(str, grid.resolution))}), got {tuple(m.shape)}"
        )
    return m, None


def buoyancy(
    velocity: StaggeredGrid, marker, dt, *, strength: float = 1.0, direction: Sequence[float] | None = None
) -> StaggeredGrid:
    """Add the Boussinesq buoyancy force ``dt * strength * marker * direction`` to a MAC velocity.

    The marker (smoke density or temperature) is averaged from the two cells adjacent to each face (on
    boundary faces the marker's ghost cell is used: its own boundary, or zero flux for a plain tensor).
    Walls stay impermeable: boundary faces are reset afterwards.

    Args:
        velocity: MAC velocity ``(B, *face_shape(i))`` per component.
        marker: Scalar CenteredGrid or tensor ``(B, *res)`` on the velocity's grid (batch 1 broadcasts).
        dt: Time step ``>= 0``.
        strength: Buoyancy per unit marker (acceleration); negative values sink.
        direction: The "up" vector, one entry per axis; default the last axis (``+y`` in 2-D, ``+z`` in 3-D).

    Returns:
        The accelerated velocity (same grid and boundary).

    Raises:
        ParameterError: For a negative dt or a direction of the wrong length.
        ShapeError, GridMismatchError: For a marker that does not fit the velocity.
    """
    _check_velocity(velocity)
    dt = check_dt(dt)
    strength, direction = _buoyancy_args(strength, direction, velocity.grid.rank)
    m, mb = _scalar_values(marker, velocity.grid)
    return _buoyancy(velocity, m, mb, dt, strength, direction)


def _buoyancy_args(strength, direction, rank: int) -> tuple[float, tuple[float, ...]]:
    """Validated buoyancy strength and "up" direction (default: the last axis)."""
    strength = check_finite_number(strength, "buoyancy strength")
    direction = tuple(float(c) for c in direction) if direction is not None else (0.0,) * (rank - 1) + (1.0,)
    if len(direction) != rank:
        raise ParameterError(f"direction needs {rank} entries, got {direction}")
    return strength, direction


def _buoyancy(velocity: StaggeredGrid, m: torch.Tensor, mb: Boundary | None, dt, strength: float,
              direction: tuple[float, ...]) -> StaggeredGrid:
    """:func:`buoyancy` on validated arguments (marker values ``m`` and boundary ``mb`` on the velocity's grid)."""
    grid = velocity.grid
    m = m.to(dtype=velocity.dtype, device=velocity.device)
    mb = mb if mb is not None else velocity.boundary.for_scalar()
    comps = []
    for i, c in enumerate(velocity.values):
        if direction[i] == 0.0:
            comps.append(c)
            continue
        p = pad(m, mb, grid.dx, 1, axes=[i])
        dim = 1 + i
        n = p.shape[dim] - 1
        face = (p.narrow(dim, 0, n) + p.narrow(dim, 1, n)) * const(0.5, m.dtype, m.device)
        comps.append(c + (dt * strength * direction[i]) * face)
    if m.shape[0] != velocity.batch_size:  # a marker batch broadcasting the velocity's: validate the shapes
        return velocity.with_values(tuple(comps)).with_boundary_faces()
    return velocity._with_components(comps).with_boundary_faces()


def kinetic_energy(velocity: StaggeredGrid) -> torch.Tensor:
    """Per-sample ``E = sum_i mean(u_i^2)`` over the face values of each component (the E5 ``mean(v^2)``).

    Args:
        velocity: MAC velocity.

    Returns:
        ``(B,)`` tensor, differentiable.
    """
    _check_velocity(velocity)
    return sum(c.flatten(1).pow(2).mean(1) for c in velocity.values)


def normalize_energy(velocity: StaggeredGrid, energy: torch.Tensor) -> StaggeredGrid:
    """Rescale each sample of ``velocity`` so that :func:`kinetic_energy` equals ``energy``.

    Args:
        velocity: MAC velocity.
        energy: Target energies ``(B,)`` (or a scalar). Samples at rest are left at rest.

    Returns:
        The rescaled velocity ``u * sqrt(energy / E(u))`` (differentiable in both arguments).
    """
    _check_velocity(velocity)
    e = kinetic_energy(velocity)
    target = torch.as_tensor(energy, dtype=e.dtype, device=e.device)
    if not all_finite(target) or bool((target.detach() < 0).any()):
        raise ParameterError(f"normalize_energy: the target energy must be finite and >= 0, got {energy!r}")
    tiny = torch.finfo(e.dtype).tiny
    factor = torch.where(e > tiny, torch.sqrt(target / e.clamp_min(tiny)), torch.ones_like(e))
    return velocity.with_values(tuple(c * factor.reshape(-1, *([1] * (c.ndim - 1))) for c in velocity.values))


def cfl_dt(velocity: StaggeredGrid, cfl: float = 0.5, *, max_dt: float = math.inf) -> float:
    """A stable time step from the Courant number: ``dt = cfl / max_b sum_i (max|u_i| / dx_i)``.

    Args:
        velocity: MAC velocity (all samples are considered; the most restrictive one decides).
        cfl: Courant number ``> 0`` (cells travelled per step); ``<= 1`` for explicit schemes, semi-Lagrangian
            advection is stable beyond but loses accuracy.
        max_dt: Upper limit, returned for a fluid at rest.

    Returns:
        The time step as a Python float.

    Raises:
        ParameterError: For a non-positive ``cfl`` or ``max_dt``.
        NonFiniteError: For a velocity containing NaN/Inf.
    """
    _check_velocity(velocity)
    cfl = check_positive(cfl, "cfl")
    if isinstance(max_dt, (str, bytes)) or not max_dt > 0:
        raise ParameterError(f"max_dt must be > 0, got {max_dt}")
    with torch.no_grad():
        rate = 0.0
        for i, c in enumerate(velocity.values):
            check_finite(c, f"velocity component {i}")
            rate = rate + c.flatten(1).abs().max(1).values / velocity.grid.dx[i]
        r = float(rate.max())
    return min(max_dt, cfl / r) if r > 0 else max_dt


def navier_stokes_step(
    velocity: StaggeredGrid,
    dt,
    *,
    viscosity: float = 0.0,
    advection: str = "semi_lagrangian",
    viscosity_scheme: str = "explicit",
    force: StaggeredGrid | None = None,
    obstacles=None,
    solve: Solve | None = None,
    pressure_guess: CenteredGrid | torch.Tensor | None = None,
    energy_normalization: bool = False,
    time: float = 0.0,
    integrator: str = "split",
) -> tuple[StaggeredGrid, CenteredGrid]:
    """One incompressible Navier-Stokes step: advect, force, diffuse, project (and optionally renormalise).

    ``u* = A(u; u, dt) + dt f``, the boundary (inflow profiles) and the bodies taken to time ``time + dt``,
    the bodies' velocity imposed on the faces they cover (:func:`impose_solids`, so that viscosity sees
    each body's velocity at its surface), ``u** = diffuse(u*)``, ``u_new, p = make_incompressible(u**)``; with
    ``energy_normalization`` the result is rescaled to the kinetic energy of ``u`` (E5 of the paper).
    First order in time (operator splitting); second order in space with MacCormack advection. With
    ``integrator`` other than ``'split'`` the step is :func:`~phisim.fluid.integrators.navier_stokes_rk_step`
    (second order in time; central convection, so ``advection`` and ``viscosity_scheme`` do not apply).

    Args:
        velocity: MAC velocity ``(B, *face_shape(i))`` per component.
        dt: Time step ``>= 0``.
        viscosity: Kinematic viscosity ``>= 0`` (0 skips diffusion).
        advection: ``'semi_lagrangian'`` or ``'maccormack'`` self-advection.
        viscosity_scheme: ``'explicit'``, ``'implicit'``, ``'crank_nicolson'`` or ``'spectral'`` (see
            :func:`diffuse_velocity`; the implicit ones are exact spectral solves, about as cheap as explicit).
        force: Optional body force (acceleration) as a StaggeredGrid on the same grid.
        obstacles: Obstacles (see :func:`make_incompressible`).
        solve: CG settings of the masked pressure solve and of implicit viscosity.
        pressure_guess: Previous pressure, the warm start of the CG pressure solve.
        energy_normalization: Rescale the result to ``kinetic_energy(velocity)``.
        time: Simulation time at the start of the step (moving bodies, time-dependent inflows).
        integrator: ``'split'`` (this function's first-order step, default), ``'rk2'``, ``'rk3'`` or
            ``'imex2'`` (see :mod:`phisim.fluid.integrators`; ``'imex2'`` treats viscosity implicitly and
            needs the previous pressure as ``pressure_guess`` for second order at walls).

    Returns:
        ``(velocity, pressure)`` after the step.

    Raises:
        ParameterError: For invalid parameters or schemes.
        GridMismatchError: If ``velocity``/``force`` are not matching StaggeredGrids.
        SolveError: If a CG solve does not converge.
    """
    _check_velocity(velocity)
    dt = check_dt(dt)
    if advection not in SCHEMES:
        raise ParameterError(f"unknown advection scheme {advection!r}; choose one of {SCHEMES}")
    if integrator != "split":
        from phisim.fluid.integrators import navier_stokes_rk_step

        if force is not None:
            _check_velocity(force, "force")
        return navier_stokes_rk_step(velocity, dt, viscosity=viscosity, integrator=integrator, force=force,
                                     time=time, obstacles=obstacles, solve=solve, pressure_guess=pressure_guess,
                                     energy_normalization=energy_normalization)
    e0 = kinetic_energy(velocity) if energy_normalization else None
    v = advect(velocity, velocity, dt, scheme=advection)
    v = _to_time(v, float(time) + float(dt))
    if force is not None:
        _check_velocity(force, "force")
        if force.grid != v.grid:
            raise GridMismatchError(f"force grid {force.grid} differs from the velocity grid {v.grid}")
        v = v + dt * force.with_boundary(v.boundary)
    return _finish_step(v, dt, e0, viscosity, viscosity_scheme, obstacles, solve, pressure_guess,
                        float(time) + float(dt))


def _to_time(v: StaggeredGrid, t: float) -> StaggeredGrid:
    """``v`` with its boundary's inflow functions evaluated at time ``t``."""
    if not v.boundary._memo("varying", lambda: any(isinstance(c, Inflow) and c.varying
                                                     for pair in v.boundary.sides for c in pair)):
        return v
    b = v.boundary.at(v.grid, t, v.dtype, v.device)
    return v if b is v.boundary else v.with_boundary(b)


def _finish_step(v, dt, e0, viscosity, viscosity_scheme, obstacles, solve, pressure_guess, t_new=0.0,
                 faces_set: bool = False):
    """The part of a step after advection and forcing: solids, viscosity, projection, energy.

    ``faces_set``: ``v`` already has its boundary faces imposed (then not imposed again without solids).
    """
    layout = None if obstacles is None else solid_layout(obstacles, v.grid, v.boundary, t_new, v.dtype, v.device)
    if layout is not None or not faces_set:
        v = impose_solids(v, layout)
    if float(viscosity) != 0:
        v = diffuse_velocity(v, dt, viscosity=viscosity, scheme=viscosity_scheme,
                             solve=solve if viscosity_scheme == "implicit" else None)
    if layout is None:  # no re-validation; boundary faces already set unless viscosity changed them
        v, p = _project_box(v if float(viscosity) == 0 else v.with_boundary_faces(), check=True)
    else:
        v, p = make_incompressible(v, layout, solve=solve, pressure_guess=pressure_guess, time=t_new)
    if e0 is not None:
        v = normalize_energy(v, e0)
    return v, p


@dataclass(frozen=True, eq=False)
class FluidState:
    """The state of a smoke-like simulation.

    Attributes:
        velocity: MAC velocity.
        marker: Passive scalar (smoke density / temperature) as a scalar CenteredGrid, or None.
        pressure: Last pressure (warm start of the next CG solve), or None.
        time: Simulated time.
    """

    velocity: StaggeredGrid
    marker: CenteredGrid | None = None
    pressure: CenteredGrid | None = None
    time: float = 0.0


def step(
    state: FluidState,
    dt,
    *,
    viscosity: float = 0.0,
    buoyancy_strength: float = 0.0,
    buoyancy_direction: Sequence[float] | None = None,
    advection: str = "maccormack",
    viscosity_scheme: str = "explicit",
    marker_source: CenteredGrid | torch.Tensor | None = None,
    obstacles=None,
    solve: Solve | None = None,
    energy_normalization: bool = False,
    integrator: str = "split",
    marker_advection: str | None = None,
) -> FluidState:
    """Advance a smoke simulation by ``dt``: marker transport, buoyancy, Navier-Stokes step.

    Order: ``marker <- A(marker; u) + dt * source`` (zeroed in cells entirely inside solids),
    ``u <- A(u; u)``, buoyancy from the new marker, the solids' velocity imposed (moving bodies at
    ``time + dt``), viscosity, projection (warm-started from ``state.pressure``), optional energy rescaling.

    Args:
        state: Current :class:`FluidState`.
        dt: Time step ``>= 0``.
        viscosity: Kinematic viscosity.
        buoyancy_strength: Buoyancy per unit marker (see :func:`buoyancy`); needs a marker.
        buoyancy_direction: "Up" vector (default the last axis).
        advection: ``'semi_lagrangian'`` or ``'maccormack'`` (for the velocity of the split step, and for
            the marker unless ``marker_advection`` says otherwise).
        viscosity_scheme: ``'explicit'``, ``'implicit'``, ``'crank_nicolson'`` or ``'spectral'`` (split step).
        marker_source: Marker added per unit time (an inflow), CenteredGrid or tensor ``(B or 1, *res)``.
        obstacles: Obstacles (see :func:`make_incompressible`).
        solve: CG settings.
        energy_normalization: Rescale the velocity to its energy at the start of the step.
        integrator: ``'split'`` (first order, default), ``'rk2'``, ``'rk3'`` or ``'imex2'`` (second order in
            time for the velocity; see :mod:`phisim.fluid.integrators`). The buoyancy of the new marker is
            then a force held constant over the step.
        marker_advection: Scheme of the marker transport: one of
            :data:`phisim.ops.advection.SCALAR_SCHEMES`; ``'conservative'`` keeps the total marker to round-off
            in closed boxes and periodic domains and never makes it negative. Default: ``advection``.

    Returns:
        The new state (``time + dt``).

    Raises:
        ParameterError, ShapeError, GridMismatchError, SolveError: See the functions it composes.
    """
    dt = check_dt(dt)
    v0 = state.velocity
    _check_velocity(v0)
    if advection not in SCHEMES:
        raise ParameterError(f"unknown advection scheme {advection!r}; choose one of {SCHEMES}")
    marker_advection = advection if marker_advection is None else marker_advection
    if marker_advection not in SCALAR_SCHEMES:
        raise ParameterError(f"unknown marker advection scheme {marker_advection!r}; choose one of {SCALAR_SCHEMES}")
    e0 = kinetic_energy(v0) if energy_normalization else None
    marker = state.marker
    # validated once here (types, grids, dt, a finite velocity); the inner calls take the trusted paths
    if marker is not None:
        _validate_advection(marker, v0, dt, marker_advection, "euler", "minmax")
    else:
        _validate_advection(v0, v0, dt, advection, "euler", "minmax")
    if marker is not None:
        marker = _advect(marker, v0, dt, scheme=marker_advection)
        if marker_source is not None:
            src, _ = _scalar_values(marker_source, marker.grid)
            marker = marker + dt * src.to(dtype=marker.dtype, device=marker.device)
        layout = None if obstacles is None else solid_layout(obstacles, v0.grid, v0.boundary,
                                                             state.time + float(dt), marker.dtype, marker.device)
        if layout is not None:  # no marker in cells entirely inside a solid
            marker = marker * (layout.cell_fraction > 0).to(marker.dtype)
    elif buoyancy_strength != 0:
        raise ParameterError("buoyancy_strength needs a marker in the state")
    lift = marker is not None and buoyancy_strength != 0
    if lift:
        strength, direction = _buoyancy_args(buoyancy_strength, buoyancy_direction, v0.grid.rank)
        _scalar_values(state.marker, v0.grid)  # a scalar CenteredGrid on the velocity's grid
    t_new = state.time + float(dt)
    if integrator != "split":
        from phisim.fluid.integrators import navier_stokes_rk_step

        force = None
        if marker is not None and buoyancy_strength != 0:
            force = buoyancy(StaggeredGrid.zeros(v0.grid, v0.boundary, v0.batch_size, dtype=v0.dtype,
                                                 device=v0.device), marker, 1.0, strength=buoyancy_strength,
                             direction=buoyancy_direction)
        v, p = navier_stokes_rk_step(v0, dt, viscosity=viscosity, integrator=integrator, force=force,
                                     time=state.time, obstacles=obstacles, solve=solve,
                                     pressure_guess=state.pressure, energy_normalization=energy_normalization)
        return replace(state, velocity=v, marker=marker, pressure=p, time=t_new)
    v = _advect(v0, v0, dt, scheme=advection)
    v = _to_time(v, t_new)
    if lift:  # sets the boundary faces
        v = _buoyancy(v, marker.values, marker.boundary, dt, strength, direction)
    v, p = _finish_step(v, dt, e0, viscosity, viscosity_scheme, obstacles, solve, state.pressure, t_new,
                        faces_set=lift)
    return replace(state, velocity=v, marker=marker, pressure=p, time=state.time + float(dt))
