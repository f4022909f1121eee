"""Navier-Stokes time steps: self-advection, buoyancy, viscosity, projection; energy, CFL time step.

:func:`navier_stokes_step` composes pure functions: self-advection (:func:`phisim.ops.advection.advect`,
semi-Lagrangian or MacCormack), a body force (e.g. :func:`buoyancy`), the solids' velocity
(:func:`~phisim.fluid.projection.impose_solids`), viscosity (:func:`~phisim.fluid.viscosity.diffuse_velocity`,
explicit or implicit), projection (:func:`~phisim.fluid.projection.make_incompressible`), and optionally a
rescaling to the kinetic energy the step started with (:func:`normalize_energy`). :func:`step` advances a
:class:`FluidState` (velocity, marker, pressure, time) for smoke-like simulations and flows past bodies.
Past sharp no-slip bodies the viscous step's wall values carry the previous step's tangential pressure gradient
(:func:`anticipate_pressure`), so that the projection leaves no slip along the surface.
First order in time (operator splitting); second order in space with MacCormack advection.
``integrator='split2'`` keeps the split step and takes its advection to second order in time
(:func:`split2_advection`); ``'rk2'``, ``'rk3'`` or ``'imex2'`` select the second-/third-order integrators of
:mod:`phisim.fluid.integrators` instead (orders in time: split 1, split2 2, rk2 2, rk3 3, imex2 2).

References: Stam (1999), "Stable fluids", SIGGRAPH; Selle et al. (2008), J. Sci. Comput. 35 (MacCormack).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace

import torch

from phisim.boundary import Boundary, Inflow, pad
from phisim.checks import (
    all_finite,
    check_batch_compatible,
    check_dt,
    check_finite,
    check_finite_number,
    check_positive,
)
from phisim.errors import GridMismatchError, ParameterError, ShapeError
from phisim.field import CenteredGrid, StaggeredGrid
from phisim.fluid.bodies import SolidLayout, body_fraction, sharp_no_slip, solid_layout
from phisim.fluid.projection import check_velocity, impose_solids, make_incompressible, project_box, project_trusted
from phisim.fluid.viscosity import diffuse_velocity
from phisim.grid import Grid
from phisim.ops.advection import advect_trusted
from phisim.ops.differential import gradient
from phisim.padding import const

__all__ = ["buoyancy", "kinetic_energy", "normalize_energy", "rescale_energy", "cfl_dt", "FluidState", "to_time",
           "finish_step", "anticipate_pressure", "split2_advection", "split2_memory", "half_step_velocity",
           "scalar_values", "buoyancy_args", "apply_buoyancy"]


def scalar_values(marker, grid: Grid) -> tuple[torch.Tensor, Boundary | None]:
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
        direction: The "up" vector, one entry per axis; default: y, axis 1 (``+y`` in 2-D and 3-D, the axis
            pictures draw upwards; ``+x`` in 1-D).

    Returns:
        The accelerated velocity (same grid and boundary).

    Raises:
        ParameterError: For a negative dt or a direction of the wrong length.
        ShapeError, GridMismatchError: For a marker that does not fit the velocity.
    """
    check_velocity(velocity)
    dt = check_dt(dt)
    strength, direction = buoyancy_args(strength, direction, velocity.grid.rank)
    m, mb = scalar_values(marker, velocity.grid)
    check_batch_compatible(velocity, m, ("velocity", "marker"), "apply buoyancy")
    return apply_buoyancy(velocity, m, mb, dt, strength, direction)


def buoyancy_args(strength, direction, rank: int) -> tuple[float, tuple[float, ...]]:
    """Validated buoyancy strength and "up" direction (default: y, axis 1; the only axis in 1-D)."""
    strength = check_finite_number(strength, "buoyancy strength")
    up = min(1, rank - 1)
    direction = (tuple(float(c) for c in direction) if direction is not None
                 else tuple(1.0 if a == up else 0.0 for a in range(rank)))
    if len(direction) != rank:
        raise ParameterError(f"direction needs {rank} entries, got {direction}")
    return strength, direction


def apply_buoyancy(velocity: StaggeredGrid, m: torch.Tensor, mb: Boundary | None, dt, strength: float,
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
    check_velocity(velocity)
    return sum(c.flatten(1).pow(2).mean(1) for c in velocity.values)


def normalize_energy(velocity: StaggeredGrid, energy: torch.Tensor) -> StaggeredGrid:
    """Rescale each sample of ``velocity`` so that :func:`kinetic_energy` equals ``energy``.

    Args:
        velocity: MAC velocity.
        energy: Target energies ``(B,)`` (or a scalar). Samples at rest are left at rest.

    Returns:
        The rescaled velocity ``u * sqrt(energy / E(u))`` (differentiable in both arguments).
    """
    check_velocity(velocity)
    e = kinetic_energy(velocity)
    target = torch.as_tensor(energy, dtype=e.dtype, device=e.device)
    if target.numel() not in (1, e.numel()) or target.ndim > 1:
        raise ShapeError(f"normalize_energy: the target energy must be a number or one per sample ({e.numel()}), "
                         f"got shape {tuple(target.shape)}")
    if not all_finite(target) or bool((target.detach() < 0).any()):
        raise ParameterError(f"normalize_energy: the target energy must be finite and >= 0, got {energy!r}")
    return rescale_energy(velocity, target)


def rescale_energy(velocity: StaggeredGrid, energy: torch.Tensor) -> StaggeredGrid:
    """:func:`normalize_energy` of a validated target ``(B,)`` tensor (a step's starting energy): no host read."""
    e = sum(c.flatten(1).pow(2).mean(1) for c in velocity.values)
    target = energy.to(dtype=e.dtype)
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
    check_velocity(velocity)
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


def to_time(v: StaggeredGrid, t: float) -> StaggeredGrid:
    """``v`` with its boundary's inflow functions evaluated at time ``t``."""
    if not v.boundary._memo("varying", lambda: any(isinstance(c, Inflow) and c.varying
                                                     for pair in v.boundary.sides for c in pair)):
        return v
    b = v.boundary.at(v.grid, t, v.dtype, v.device)
    return v if b is v.boundary else v.with_boundary(b)


#: Per viscosity scheme, the part of a face's wall weight ``sum 1 / (s dx^2)`` that reads the intermediate velocity.
ANTICIPATED_PART = {"implicit": 1.0, "crank_nicolson": 0.5}


def anticipate_pressure(layout: SolidLayout | None, pressure: CenteredGrid | torch.Tensor | None,
                        velocity: StaggeredGrid, time: float = 0.0, dt: float = 0.0,
                        viscosity_scheme: str = "implicit") -> SolidLayout | None:
    """``layout`` with the wall values of its sharp no-slip surfaces moved by the previous step's tangential pressure
    gradient.

    The split step imposes the body's velocity ``u_s`` in the viscous step and then projects; the projection changes
    the velocity next to the surface by ``-G p`` (``p`` the pressure potential, ``dt p_phys / rho``), so the stored
    velocity slips along the surface by ``dt dp/ds``, an error that does not vanish at a steady state and grows with
    ``nu dt / dx^2`` (``docs/VALIDATION.md``, "Flow driven through a body"). Giving the viscous step the wall value
    ``u_s + (G p^n)_t`` instead, with the tangential part of the previous step's gradient, leaves after the projection
    a slip of the change of the pressure over a step (Kim & Moin 1985, J. Comput. Phys. 59: the boundary condition of
    the intermediate velocity). The normal part is left out: the viscous step keeps the body's normal velocity at the
    surface, and the projection's flux constraint holds the normal flow there.

    On each face with an arm to the surface (:attr:`~phisim.fluid.bodies.SolidLayout.tangents`) the face gradient of
    ``p^n`` and the other components' gradients averaged from the four faces around it (those with a wetted part)
    give ``G p``; its tangential part ``g_t = G p - (G p . n) n`` enters the viscous stencil as ``source += g_t *
    w``; the rest of the step is unchanged. ``w`` is the part of the stencil that acts on the intermediate velocity
    (the one the projection then shifts by ``G p``): the whole wall weight ``sum 1 / (s dx^2)`` for an implicit step,
    half of it for Crank-Nicolson, and for an explicit step the diagonal ``coef = sum (1/s - 1) / dx^2`` alone, which
    it treats point-implicitly (the rest of its stencil reads the stored velocity, whose wall value is ``u_s``).
    The whole weight in an explicit step over-corrects: the split step's steady state then depends on ``dt``
    (``docs/VALIDATION.md``, DFG 2D-1). ``p^n`` carries the previous step's ``dt``: with a constant ``dt``
    it is the gradient the projection will apply; a changing ``dt`` scales the correction by the ratio of the steps.
    Moving bodies: the previous pressure is read where each cell was relative to the body a step earlier, at ``x -
    u_s dt`` (multilinear, from the cells that held fluid then: a cell the body covered holds no fluid pressure).

    Args:
        layout: The rasterised solids at the new time (:class:`~phisim.fluid.bodies.SolidLayout`) or None.
        pressure: The previous step's pressure potential (CenteredGrid or tensor ``(B, *res)``), or None.
        velocity: The velocity of the step (its grid, and its boundary, from which the pressure's follows).
        time: The new time (the layout's).
        dt: The step (moving bodies).
        viscosity_scheme: The viscous step's scheme: ``'implicit'`` (default), ``'crank_nicolson'`` or
            ``'explicit'``.

    Returns:
        The layout with the corrected wall sources (``layout`` itself without sharp no-slip bodies or pressure).

    Raises:
        GridMismatchError: For a pressure on another grid than the velocity.
        ShapeError: For a pressure tensor that is not ``(B, *res)`` or ``(*res)``.
        ParameterError: For another viscosity scheme (``'spectral'`` takes no bodies).
    """
    if layout is None or layout.walls is None or layout.tangents is None or pressure is None:
        return layout
    if viscosity_scheme not in ANTICIPATED_PART and viscosity_scheme != "explicit":
        raise ParameterError(f"viscosity_scheme must be 'implicit', 'crank_nicolson' or 'explicit' with sharp bodies, "
                             f"got {viscosity_scheme!r}")
    grid = velocity.grid
    if isinstance(pressure, CenteredGrid) and pressure.grid != grid:
        raise GridMismatchError(f"pressure grid {pressure.grid} differs from the velocity grid {grid}")
    p = pressure.values if isinstance(pressure, CenteredGrid) else torch.as_tensor(pressure)
    p = p.to(dtype=velocity.dtype, device=velocity.device)
    q = CenteredGrid(p if p.ndim == grid.rank + 1 else p[None], grid, velocity.boundary.for_pressure())
    q = pressure_in_body_frame(q, layout, velocity, float(time), float(dt))
    grads = [g.reshape(g.shape[0], -1) for g in gradient(q, at="face").values]
    walls = []
    for i, (wall, stencil) in enumerate(zip(layout.walls, layout.tangents)):
        if wall is None or stencil is None:
            walls.append(wall)
            continue
        index, weight, normal, neighbours = stencil
        normal = normal.to(grads[i].dtype)
        own = grads[i][:, index]  # (B, P)
        dot = normal[:, i] * own
        for j, nb in enumerate(neighbours):
            if nb is not None:
                corners, w = nb
                dot = dot + normal[:, j] * (grads[j][:, corners] * w.to(own.dtype)).sum(-1)
        cut, coef, source = wall
        if viscosity_scheme == "explicit":
            part = coef.reshape(coef.shape[0], -1)[:, index].to(own.dtype)
        else:
            part = weight.to(own.dtype) * ANTICIPATED_PART[viscosity_scheme]
        tangential = (own - normal[:, i] * dot) * part
        flat = torch.zeros_like(grads[i]).index_copy(1, index, tangential)
        extra = flat.reshape(flat.shape[0], *grid.face_shape(i))
        walls.append((cut, coef, extra if source is None else source + extra))
    return replace(layout, walls=tuple(walls))


def half_step_velocity(velocity: StaggeredGrid, rate: StaggeredGrid | None, dt) -> StaggeredGrid:
    """``velocity + dt/2 rate``: the velocity extrapolated to the middle of the step (``velocity`` without a rate)."""
    if rate is None:
        return velocity
    return velocity._with_components([u + (0.5 * dt) * r for u, r in zip(velocity.values, rate.values)])


def split2_advection(src: StaggeredGrid, state: FluidState, dt, scheme: str) -> StaggeredGrid:
    """The self-advection of the ``'split2'`` step: ``src`` (the velocity extended into the bodies) plus ``dt/2`` times
    the previous step's acceleration by everything but the advection (:attr:`FluidState.acceleration`: pressure,
    viscosity, forces), transported by the velocity extrapolated to the half step, ``u^n + dt/2 du/dt``
    (:attr:`FluidState.velocity_rate`), less that half acceleration.

    The split step advects ``u`` and then adds the other terms, so that the advection misses their transport during
    the step, ``dt^2/2 (u . grad) f``, and traces with ``u^n`` instead of ``u^{n+1/2}``: two errors of first order in
    time. Without a previous step (no rate, no acceleration) this is the split step's advection. The marker of a
    ``'split2'`` step is transported by the same extrapolated velocity."""
    carrier = half_step_velocity(src, state.velocity_rate, dt)
    if state.acceleration is None:
        return advect_trusted(src, carrier, dt, scheme=scheme)
    half = [(0.5 * dt) * a for a in state.acceleration.values]
    moved = src._with_components([u + h for u, h in zip(src.values, half)])
    v = advect_trusted(moved, carrier, dt, scheme=scheme)
    return v._with_components([u - h for u, h in zip(v.values, half)])


def split2_memory(new: StaggeredGrid, old: StaggeredGrid, advected: StaggeredGrid, dt,
                  layout: SolidLayout | None) -> tuple[StaggeredGrid, StaggeredGrid]:
    """What a ``'split2'`` step keeps for the next: the velocity's rate ``(new - old) / dt`` and the acceleration by
    everything but the advection, ``(new - advected) / dt``, zero on the faces inside solids (``theta = 0`` in
    ``layout``, the solids at the new time), where the stored velocity is the solid's."""
    rate = new._with_components([(a - b) / dt for a, b in zip(new.values, old.values)])
    acc = [(a - b) / dt for a, b in zip(new.values, advected.values)]
    if layout is not None:
        acc = [a * (th > 0).to(a.dtype) for a, th in zip(acc, layout.theta)]
    return rate, new._with_components(acc)


def pressure_in_body_frame(q: CenteredGrid, layout: SolidLayout | None, velocity: StaggeredGrid, t: float,
                           dt: float) -> CenteredGrid:
    """The previous pressure ``q`` read at ``x - u_s(x) dt`` in every cell (``u_s`` the velocity of the nearest sharp
    no-slip body of ``layout``), multilinear over the cells whose fluid fraction was positive at ``t - dt`` (the others
    hold no fluid pressure): near a moving body its pressure field moves with it. ``q`` itself where ``layout`` has
    no moving sharp no-slip body or ``dt`` is 0."""
    bodies = [] if layout is None else sharp_no_slip(layout.bodies)
    if all(b.static for b in bodies) or float(dt) == 0:
        return q
    grid = velocity.grid
    work = velocity.dtype
    x = grid.cell_centers(work, velocity.device)
    h = min(grid.dx)
    with torch.no_grad():
        old = torch.stack([body_fraction(b, x, t - dt, h) for b in bodies], 0).amin(0)
        valid = (old > 0).to(work)
    flat = x.reshape(-1, grid.rank)
    if len(bodies) == 1:  # every cell's nearest body
        us = bodies[0].velocity_at(flat, t).to(work)
    else:
        phis = torch.stack([b.sdf(flat, t) for b in bodies], 0)
        owner = phis.detach().argmin(0)
        us = torch.zeros_like(flat)
        for k, b in enumerate(bodies):
            sel = (owner == k).nonzero().squeeze(1)
            if not b.static and sel.numel():
                us = us.index_put((sel,), b.velocity_at(flat[sel], t).to(work))
    pts = flat - dt * us
    p = q.values
    num = q.with_values(p * valid).sample(pts)
    den = q.with_values(valid.expand(p.shape).contiguous()).sample(pts)
    out = torch.where(den > 1e-3, num / den.clamp_min(1e-3), p.reshape(p.shape[0], -1))
    return q.with_values(out.reshape(p.shape))


def finish_step(v, dt, e0, viscosity, viscosity_scheme, obstacles, solve, pressure_guess, t_new=0.0,
                 faces_set: bool = False, trusted: bool = False):
    """The part of a step after advection and forcing: solids, viscosity, projection, energy.

    ``faces_set``: ``v`` already has its boundary faces imposed (then not imposed again without solids).
    ``trusted``: the settings were validated when a stepper was built; no check reads a value back to the host.
    """
    layout = None if obstacles is None else solid_layout(obstacles, v.grid, v.boundary, t_new, v.dtype, v.device)
    if layout is not None or not faces_set:
        v = impose_solids(v, layout, moved=(t_new - float(dt), t_new))
    if float(viscosity) != 0:
        walls = anticipate_pressure(layout, pressure_guess, v, t_new, float(dt), viscosity_scheme)
        v = diffuse_velocity(v, dt, viscosity=viscosity, scheme=viscosity_scheme,
                             solve=solve if viscosity_scheme == "implicit" else None, solids=walls, time=t_new)
    if layout is None:  # no re-validation; boundary faces already set unless viscosity changed them
        v, p = project_box(v if float(viscosity) == 0 else v.with_boundary_faces(), check=not trusted)
    elif trusted:
        v, p = project_trusted(v, layout, solve=solve, pressure_guess=pressure_guess)
    else:
        v, p = make_incompressible(v, layout, solve=solve, pressure_guess=pressure_guess, time=t_new)
    if e0 is not None:
        v = rescale_energy(v, e0) if trusted else normalize_energy(v, e0)
    return v, p


@dataclass(frozen=True, eq=False)
class FluidState:
    """The state of a smoke-like simulation.

    Attributes:
        velocity: MAC velocity.
        marker: Passive scalar (smoke density / temperature) as a scalar CenteredGrid, or None.
        pressure: Last pressure (warm start of the next CG solve), or None.
        time: Simulated time.
        velocity_rate: The velocity's change per unit time over the last step, kept by the ``'split2'`` integrator
            (its half-step extrapolation of the advecting velocity), or None.
        acceleration: The last step's acceleration by everything but the advection (pressure, viscosity, forces),
            kept by the ``'split2'`` integrator, or None.
    """

    velocity: StaggeredGrid
    marker: CenteredGrid | None = None
    pressure: CenteredGrid | None = None
    time: float = 0.0
    velocity_rate: StaggeredGrid | None = None
    acceleration: StaggeredGrid | None = None

    def resampled(self, grid) -> FluidState:
        """This state on another resolution of the same box, at the same time: every field it holds resampled
        (:meth:`StaggeredGrid.resampled`, :meth:`CenteredGrid.resampled`; multilinear). The velocity is not
        divergence-free on the new grid in general; the next step's projection makes it so. For grid sequencing, where
        a coarse run's state starts a fine one.

        Raises:
            GridMismatchError: ``grid`` covers another box or has another number of axes.
        """
        def move(field):
            return None if field is None else field.resampled(grid)

        return FluidState(self.velocity.resampled(grid), move(self.marker), move(self.pressure), self.time,
                          move(self.velocity_rate), move(self.acceleration))
