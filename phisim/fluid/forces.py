"""Forces on bodies (drag and lift, pressure and viscous parts) and the pressure at probe points.

Call these after a step, with the velocity and the pressure potential it returned and the step's ``dt``.
The physical pressure is ``p_phys = density * p / dt`` (the projection's potential ``p`` carries ``dt``).

**Pressure force** ``F_p = -oint p n dS`` (``n`` the body's outward normal). With the fractional face weights
``theta`` of the body (:mod:`phisim.fluid.bodies`) the surface piece inside cell ``c`` has the area vector
``(int n dS)_c = sum_i (theta_{i, c+1/2} - theta_{i, c-1/2}) A_i e_i`` (divergence theorem on the fluid part of
the cell, ``A_i`` the area of a face normal to ``i``), so

    ``F_p = -sum_c p_phys,c sum_i (theta_{i, c+1/2} - theta_{i, c-1/2}) A_i e_i``,

the same weights the pressure solve uses; a constant pressure gives exactly zero force. ``pressure_at='surface'``
reads instead the pressure at each cut cell's surface point ``x_s = x_c - phi n``, extrapolated along the normal by
the quadratic through the pressures 1.5, 2.5 and 3.5 cells out (cut cells enter only through the interpolation of
the nearest probe):

    ``F_p = -sum_c p_phys(x_s,c) (int n dS)_c``,

second order on a smooth pressure with errors 8-20 times below the cells' reading (whose centres lie up to 0.7
cells off the surface, and whose pressures carry the cut cells' own error; ``docs/VALIDATION.md``).
``pressure_at='momentum'`` reads it at the same surface points through the momentum equation along the normal from
the pressure two cells out (:func:`wall_pressure`, :mod:`phisim.fluid.normal_momentum`): the pressure rise of a viscous
stagnation layer thinner than the probes' reach is then read from the velocity.

**Viscous force** ``F_v = oint tau n dS`` with ``tau = mu (grad u + grad u^T)``. On a rigid no-slip surface
``u - u_s`` vanishes, its tangential derivatives vanish and incompressibility removes its normal-normal
part, so ``tau n = mu d(u - u_s)/dn``. It is evaluated at one surface point per cut cell
(``x_s = x_c - phi n``, weight ``|(int n dS)_c|``) by the second-order one-sided difference
``(4 w(delta) - w(2 delta)) / (2 delta)`` of ``w = u - u_s`` sampled along the normal at ``delta = 1.5 dx``
and ``3 dx``, outside the band of blended faces. ``shear_at='momentum'`` fits the same two samples with the profile's
curvature taken from the momentum balance at the wall (tangential pressure gradient, surface curvature, the body's
acceleration; :func:`~phisim.fluid.normal_momentum.momentum_wall_shear`): for boundary layers as thin as the samples'
distance. Free-slip bodies have no viscous force.

Coefficients: ``c = 2 F / (density U^2 L)`` with a reference speed ``U`` and length ``L`` (2-D; in 3-D
``L`` is a reference area), see :meth:`BodyForces.coefficients`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from phisim.checks import check_positive
from phisim.errors import ParameterError, ShapeError
from phisim.field import CenteredGrid, StaggeredGrid
from phisim.fluid.bodies import Body, Obstacle, body_fraction, unit_normal
from phisim.fluid.geometry import Geometry
from phisim.fluid.normal_momentum import momentum_wall_pressure, momentum_wall_shear
from phisim.fluid.projection import check_velocity, pressure_values

__all__ = ["BodyForces", "body_forces", "probe_pressure", "wall_pressure"]


@dataclass(frozen=True)
class BodyForces:
    """Hydrodynamic force on one body, per sample.

    Attributes:
        pressure: Pressure part ``(B, d)``.
        viscous: Viscous part ``(B, d)``.
    """

    pressure: torch.Tensor
    viscous: torch.Tensor

    @property
    def total(self) -> torch.Tensor:
        """Pressure plus viscous force ``(B, d)``."""
        return self.pressure + self.viscous

    def coefficients(self, speed: float, length: float, density: float = 1.0) -> torch.Tensor:
        """Force coefficients ``2 F / (density speed^2 length)`` of the total force ``(B, d)``.

        Args:
            speed: Reference speed (e.g. the mean inflow velocity).
            length: Reference length (2-D, e.g. the diameter) or area (3-D).
            density: Fluid density.
        """
        return 2.0 * self.total / (density * speed**2 * length)


def _as_body(body) -> Body:
    if isinstance(body, Geometry):
        return Body(body)
    if isinstance(body, Obstacle):
        raise ParameterError("forces need a Body (a geometry with a surface), not a staircase Obstacle; build "
                             "the shape with phisim.fluid.Box / Sphere / SDF and wrap it in Body(...)")
    if not isinstance(body, Body):
        raise ParameterError(f"body must be a Body or a Geometry, got {type(body).__name__}")
    return body


def _surface(body: Body, grid, t: float, like: torch.Tensor):
    """Area vectors ``int n dS`` of the surface piece in each cell, ``(*res, d)`` (kept on a resting body)."""
    return body.derived(("surface", grid, like.dtype, str(like.device)),
                        lambda: _surface_vectors(body, grid, t, like))


def _surface_vectors(body: Body, grid, t: float, like: torch.Tensor):
    h = min(grid.dx)
    work = like.dtype
    area = []
    for i in range(grid.rank):
        th = body_fraction(body, grid.face_centers(i, work, like.device), t, h, i)
        n = grid.resolution[i]
        a_i = math.prod(d for k, d in enumerate(grid.dx) if k != i)
        area.append((th.narrow(i, 1, n) - th.narrow(i, 0, n)) * a_i)
    vec = torch.stack(area, -1)  # (*res, d): int n dS over the surface piece in each cell
    return vec


#: Where :func:`body_forces` reads the pressure of its pressure part.
PRESSURE_READINGS = ("cells", "surface", "momentum")
#: The readings of the wall shear (``shear_at`` of :func:`body_forces`).
SHEAR_READINGS = ("probes", "momentum")


def body_forces(velocity: StaggeredGrid, pressure: CenteredGrid, body, *, dt: float, viscosity: float,
                density: float = 1.0, time: float = 0.0, probe_distance: float = 1.5,
                pressure_at: str = "cells", previous_velocity: StaggeredGrid | None = None,
                shear_at: str = "probes") -> BodyForces:
    """Drag/lift on ``body`` from a step's velocity and pressure (formulas in the module docstring).

    Args:
        velocity: MAC velocity after the step.
        pressure: The step's pressure potential (CenteredGrid).
        body: A :class:`~phisim.fluid.bodies.Body` (or a Geometry: a resting no-slip body).
        dt: The step's time step (converts the potential to a pressure).
        viscosity: Kinematic viscosity (``mu = density * viscosity``).
        density: Fluid density.
        time: Time of the velocity (position of a moving body).
        probe_distance: Normal distance of the first viscous probe in cells.
        pressure_at: ``'cells'`` (default): each cut cell's own pressure times its surface area vector (the
            formula above); ``'surface'``: the pressure at the surface point of each cut cell (``x_s = x_c - phi
            n``), extrapolated along the normal by the quadratic through the pressures 1.5, 2.5 and 3.5 cells out
            (:func:`probe_pressure` with ``order=2``), times the same area vector (cut cells enter only through the
            interpolation of the nearest probe); ``'momentum'``: the pressure at the same surface points read through
            the momentum equation along the normal from two cells out (:func:`wall_pressure`; no-slip bodies; the
            reading uses ``viscosity``, so pass the fluid's even where only the pressure part is wanted).
        previous_velocity: With ``pressure_at='momentum'``: the velocity one step ``dt`` earlier, for the
            acceleration term of an unsteady flow (None: omitted, right for a steady flow).
        shear_at: ``'probes'`` (default): the wall gradient of ``u - u_s`` by the one-sided difference through
            the samples ``probe_distance`` and twice that out (the formula above); ``'momentum'``: the same samples
            with the momentum balance at the wall, which gives the profile's curvature (the tangential pressure
            gradient, the surface's curvature and the body's acceleration;
            :func:`~phisim.fluid.normal_momentum.momentum_wall_shear`): for boundary layers as thin as the samples'
            distance (on Hiemenz flow with a layer two cells thick 12 % off with the probes, 2 % with the momentum
            balance, which also removes the samples' interpolation error).

    Returns:
        :class:`BodyForces` with ``(B, d)`` tensors; differentiable.

    Raises:
        ParameterError: For a staircase Obstacle, non-positive dt or density, or mismatched fields.
    """
    check_velocity(velocity)
    body = _as_body(body)
    dt = check_positive(dt, "dt")
    density = check_positive(density, "density")
    if pressure_at not in PRESSURE_READINGS:
        raise ParameterError(f"pressure_at must be one of {PRESSURE_READINGS}, got {pressure_at!r}")
    if shear_at not in SHEAR_READINGS:
        raise ParameterError(f"shear_at must be one of {SHEAR_READINGS}, got {shear_at!r}")
    if previous_velocity is not None and pressure_at != "momentum":
        raise ParameterError("previous_velocity is read by pressure_at='momentum' alone")
    p = pressure_values(pressure, velocity) * (density / dt)
    grid = velocity.grid
    vec = _surface(body, grid, float(time), p)
    if pressure_at == "cells":
        fp = -(p.unsqueeze(-1) * vec.unsqueeze(0)).flatten(1, -2).sum(1)
    elif pressure_at == "momentum":
        _check_momentum(body, viscosity, previous_velocity, velocity)
        xs, n, area = _cut_surface_points(body, grid, vec, float(time))
        ps = _momentum_reading(velocity, pressure, body, xs, n, dt, viscosity, float(time), previous_velocity)
        fp = -(ps.unsqueeze(-1) * area.to(ps.dtype)).sum(1) * density
    else:
        fp = _surface_pressure_force(pressure, body, vec, float(time)) * (density / dt)
    fv = torch.zeros_like(fp)
    if body.no_slip and float(viscosity) != 0:
        if shear_at == "momentum":
            xs, n, area = _cut_surface_points(body, grid, vec, float(time))
            dwdn = momentum_wall_shear(velocity, pressure, body, xs, n, viscosity=float(viscosity), dt=dt,
                                       time=float(time), distance=probe_distance)
            fv = (dwdn * area.norm(dim=-1).to(dwdn.dtype)).sum(-1) * (density * float(viscosity))
        else:
            fv = _viscous(velocity, body, vec, float(time), probe_distance) * (density * float(viscosity))
    return BodyForces(fp, fv)


#: Distance of the pressure read by the momentum reading from the surface, in cells.
MOMENTUM_DISTANCE = 2.0


def _check_momentum(body: Body, viscosity, previous, velocity: StaggeredGrid) -> None:
    if not body.no_slip:
        raise ParameterError("the momentum reading of the wall pressure needs a no-slip body")
    if not math.isfinite(float(viscosity)) or float(viscosity) < 0:
        raise ParameterError(f"viscosity must be a finite number >= 0, got {viscosity!r}")
    if previous is not None:
        check_velocity(previous)
        if previous.grid != velocity.grid or previous.batch_size != velocity.batch_size:
            raise ShapeError("previous_velocity must be on the velocity's grid with its batch size")


def _momentum_reading(velocity, pressure: CenteredGrid, body: Body, xs, n, dt, viscosity, t, previous):
    """The kinematic wall pressure ``(B, S)`` at surface points ``xs`` (normals ``n``) by the momentum reading."""
    h = min(velocity.grid.dx)
    x1 = (xs + MOMENTUM_DISTANCE * h * n).to(pressure.dtype)
    p1 = pressure.sample(x1) / dt
    return momentum_wall_pressure(velocity, p1, body, xs, n, viscosity=viscosity, time=t, previous=previous, dt=dt,
                                  distance=MOMENTUM_DISTANCE)


def _cut_surface_points(body: Body, grid, vec: torch.Tensor, t: float):
    """Per cut cell (``|vec| > 0``): the surface point ``x_s = x_c - phi n`` of its centre, the unit normal there and
    the cell's area vector ``(int n dS)_c``."""
    h = min(grid.dx)
    mag = vec.norm(dim=-1)
    cut = mag > 1e-9 * mag.max().clamp_min(torch.finfo(mag.dtype).tiny)
    xc = grid.cell_centers(vec.dtype, vec.device)[cut]  # (S, d)
    phi = body.sdf(xc, t)
    n = unit_normal(body, xc, t, 1e-3 * h)
    return xc - phi.unsqueeze(-1) * n, n, vec[cut]


def _surface_pressure_force(pressure: CenteredGrid, body: Body, vec: torch.Tensor, t: float) -> torch.Tensor:
    """``-sum_c p(x_s) (int n dS)_c`` with ``p(x_s)`` the quadratic extrapolation along the normal (potential units)."""
    xs, n, area = _cut_surface_points(body, pressure.grid, vec, t)
    h = min(pressure.grid.dx)
    shift = torch.full_like(xs[:, 0], 1.5 * h)  # the surface points: the nodes 1.5, 2.5, 3.5 cells out
    ps = _extrapolated(pressure, xs.to(pressure.dtype), n.to(pressure.dtype), shift.to(pressure.dtype), 2)  # (B, S)
    return -(ps.unsqueeze(-1) * area.to(ps.dtype)).sum(1)


def _viscous(velocity: StaggeredGrid, body: Body, vec: torch.Tensor, t: float, probe: float) -> torch.Tensor:
    grid = velocity.grid
    h = min(grid.dx)
    xs, n, area = _cut_surface_points(body, grid, vec, t)
    weight = area.norm(dim=-1)
    d1 = probe * h
    pts = torch.cat([xs + d1 * n, xs + 2 * d1 * n], 0)
    u = velocity.sample(pts.to(velocity.dtype))  # (B, d, 2S)
    us = body.velocity_at(pts, t).to(velocity.dtype).T.unsqueeze(0) if not body.static else 0.0
    w = u - us
    s = xs.shape[0]
    dwdn = (4 * w[..., :s] - w[..., s:]) / (2 * d1)  # (B, d, S)
    return (dwdn * weight.to(velocity.dtype)).sum(-1)


def probe_pressure(pressure: CenteredGrid, points, *, dt: float, density: float = 1.0, bodies=None,
                   time: float = 0.0, order: int = 1) -> torch.Tensor:
    """Physical pressure ``density * p / dt`` at points, extrapolated to body surfaces where needed.

    Points farther than 1.5 cells from every body are interpolated multilinearly. Points closer (e.g.
    on a body's surface) take the extrapolation along the body's normal from points in the fluid, 1.5 and 2.5
    cells beyond the surface (linear, ``order=1``) or 1.5, 2.5 and 3.5 cells (quadratic, ``order=2``: exact for a
    pressure quadratic along the normal, second order at the surface where the linear one leaves ``h^2 p''``
    times about two), so that cells inside the body never enter (cut cells only through the multilinear
    interpolation of the nearest probe).

    Args:
        pressure: The pressure potential (CenteredGrid ``(B, *res)``).
        points: ``(P, d)`` physical coordinates.
        dt: The step's time step.
        density: Fluid density.
        bodies: Optional Body/Geometry or a sequence of them.
        time: Time of the pressure (positions of moving bodies).
        order: 1 (linear, default) or 2 (quadratic) extrapolation to points within 1.5 cells of a body.

    Returns:
        ``(B, P)`` pressures.
    """
    if not isinstance(pressure, CenteredGrid) or pressure.is_vector:
        raise ParameterError("pressure must be a scalar CenteredGrid")
    if order not in (1, 2):
        raise ParameterError(f"order must be 1 (linear) or 2 (quadratic), got {order!r}")
    dt = check_positive(dt, "dt")
    density = check_positive(density, "density")
    grid = pressure.grid
    x = _points(points, grid, pressure.values)
    h = min(grid.dx)
    if bodies is not None:
        blist = [bodies] if isinstance(bodies, (Body, Geometry)) else list(bodies)
        blist = [_as_body(b) for b in blist]
        phis = torch.stack([b.sdf(x, time) for b in blist], 0)
        near = phis.min(0)
        idx = near.indices
        phi = near.values
        n = torch.zeros_like(x)
        for k, b in enumerate(blist):
            sel = idx == k
            if bool(sel.any()):
                n[sel] = unit_normal(b, x[sel], time, 1e-3 * h)
        return _extrapolated(pressure, x, n, (1.5 * h - phi).clamp_min(0.0), order) * (density / dt)
    return pressure.sample(x) * (density / dt)


def _points(points, grid, like: torch.Tensor) -> torch.Tensor:
    """``points`` as a ``(P, d)`` tensor of ``like``'s dtype and device, checked for shape and finiteness."""
    x = torch.as_tensor(points, dtype=like.dtype, device=like.device)
    if x.ndim != 2 or x.shape[1] != grid.rank:
        raise ShapeError(f"points must have shape (P, {grid.rank}), got {tuple(x.shape)}")
    if not bool(torch.isfinite(x).all()):
        raise ParameterError("points contain NaN or Inf")
    return x


def _extrapolated(pressure: CenteredGrid, x: torch.Tensor, n: torch.Tensor, shift: torch.Tensor, order: int
                  ) -> torch.Tensor:
    """The pressure at points ``x`` ``(P, d)``: where ``shift > 0`` extrapolated along the unit normals ``n`` from
    the nodes ``shift``, ``shift + h`` (and ``shift + 2h`` for ``order=2``) beyond ``x`` (Lagrange weights at 0),
    elsewhere interpolated; ``(B, P)`` in the potential's units."""
    h = min(pressure.grid.dx)
    close = shift > 0
    q1 = x + shift.unsqueeze(-1) * n
    q2 = q1 + h * n
    v1, v2 = pressure.sample(q1), pressure.sample(q2)
    if order == 1:
        return torch.where(close, v1 + (v1 - v2) * shift / h, v1)
    v3 = pressure.sample(q1 + 2 * h * n)
    s0, s1, s2 = shift / h, shift / h + 1, shift / h + 2
    return torch.where(close, v1 * (s1 * s2 / 2) - v2 * (s0 * s2) + v3 * (s0 * s1 / 2), v1)


def wall_pressure(velocity: StaggeredGrid, pressure: CenteredGrid, body, points, *, dt: float, viscosity: float,
                  density: float = 1.0, time: float = 0.0, previous_velocity: StaggeredGrid | None = None
                  ) -> torch.Tensor:
    """Physical pressure on the surface of a no-slip body, read through the momentum equation along the normal.

    Each point is moved to the nearest surface point ``x_s = x - phi n``; the pressure there is the interpolated
    pressure two cells out along the normal plus the integral of the normal momentum equation back to the surface
    (:mod:`phisim.fluid.normal_momentum`): kinetic energy, Lamb vector, the viscous term (its normal-normal part
    exactly, the tangential Laplacian by quadrature) and, given ``previous_velocity``, the acceleration. Unlike
    :func:`probe_pressure`, which extrapolates the pressure alone, it reads a viscous pressure layer thinner than two
    cells (the stagnation points of the DFG cylinder: ``docs/VALIDATION.md``).

    Args:
        velocity: MAC velocity after the step.
        pressure: The step's pressure potential (CenteredGrid).
        body: A no-slip :class:`~phisim.fluid.bodies.Body` (or a Geometry: a resting one).
        points: ``(P, d)`` physical points on or near the body's surface.
        dt: The step's time step (converts the potential; the step of ``previous_velocity``).
        viscosity: Kinematic viscosity.
        density: Fluid density.
        time: Time of the velocity (position of a moving body).
        previous_velocity: The velocity one step earlier (the acceleration term of an unsteady flow), or None.

    Returns:
        ``(B, P)`` pressures; differentiable.

    Raises:
        ParameterError: For a free-slip body or an Obstacle, non-positive dt/density, negative viscosity, NaN points.
        ShapeError: For points of the wrong shape or fields on different grids.
    """
    check_velocity(velocity)
    body = _as_body(body)
    dt = check_positive(dt, "dt")
    density = check_positive(density, "density")
    pressure_values(pressure, velocity)
    _check_momentum(body, viscosity, previous_velocity, velocity)
    grid = velocity.grid
    x = _points(points, grid, velocity.values[0])
    h = min(grid.dx)
    t = float(time)
    n = unit_normal(body, x, t, 1e-3 * h)
    xs = x - body.sdf(x, t).unsqueeze(-1) * n
    n = unit_normal(body, xs, t, 1e-3 * h)
    return _momentum_reading(velocity, pressure, body, xs, n, dt, viscosity, t, previous_velocity) * density
