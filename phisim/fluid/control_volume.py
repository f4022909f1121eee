"""The force on everything inside a box, read from the momentum balance over the box (a control volume).

For a box ``V`` of the grid's cells with outer surface ``S`` (outward normal ``n``), the momentum balance of the
fluid in ``V`` gives the force of the fluid on the bodies inside it:

    ``F = -d/dt int_V rho u dV - oint_S rho u (u . n) dS - oint_S p n dS + oint_S tau n dS``,
    ``tau = mu (grad u + grad u^T)``.

Unlike :func:`~phisim.fluid.forces.body_forces` it reads nothing next to the bodies: only the flow on the box's
sides, where it is smooth, and the momentum inside (a body's interior holds its own velocity). So it needs no
surface (staircase obstacles too), and it reads the momentum the discrete flow actually gives up to the bodies,
whatever the near-body treatment does; the price is the flow's truncation error on the sides and a box that must
hold only the bodies meant.

Discretization on the MAC grid: the box's sides lie on face planes (``box`` is rounded to them); the momentum of
component ``c`` sums the ``c`` faces in the box, those on its two ``c`` sides with weight 1/2 (the trapezoid rule
across, the midpoint rule along); the side integrals use the midpoint rule at the centres of the side's faces, with
the normal velocity on them, the tangential velocities averaged from the four faces around, the pressure from the
two cells across and the derivatives by central differences: second order on smooth fields, and exact for the
pressure of a constant or linear field. With ``previous`` (the velocity one step ``dt`` earlier) the reading stands
at the half step: ``d/dt`` by ``(M(velocity) - M(previous)) / dt`` and the side fluxes the mean of the two time
levels, with the step's pressure (``'imex2'``'s incremental pressure stands at the half step); without it, the
steady balance at the velocity's time.

A moving body's interior holds the body's velocity, so the momentum change in the box then includes the body's
own, ``rho V_b a_b`` for a rigid body of volume ``V_b`` whose centre accelerates at ``a_b``: the force on the body
is the reading plus ``rho V_b a_b`` (zero for bodies at rest or in uniform motion; checked on an oscillating
cylinder in ``tests/phisim/fluid/test_control_volume.py`` and ``docs/VALIDATION.md``).

The pressure argument is the potential a step returns; the physical pressure is ``density * p / dt``, as for
:func:`~phisim.fluid.forces.body_forces`.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import torch

from phisim.checks import check_nonnegative, check_positive
from phisim.errors import GridMismatchError, ParameterError
from phisim.field import CenteredGrid, StaggeredGrid
from phisim.fluid.projection import check_velocity, pressure_values
from phisim.grid import Grid

__all__ = ["ControlVolumeForces", "control_volume_force", "control_volume_box"]


@dataclass(frozen=True)
class ControlVolumeForces:
    """The force on what lies inside a box, from the momentum balance over it, per sample ``(B, d)``.

    Attributes:
        unsteady: ``-d/dt int_V rho u dV`` (zero without a previous velocity).
        momentum_flux: ``-oint_S rho u (u . n) dS``.
        pressure: ``-oint_S p n dS``.
        viscous: ``oint_S tau n dS``.
        box: The box's face indices ``((lo, hi), ...)`` per axis, after rounding.
    """

    unsteady: torch.Tensor
    momentum_flux: torch.Tensor
    pressure: torch.Tensor
    viscous: torch.Tensor
    box: tuple[tuple[int, int], ...]

    @property
    def total(self) -> torch.Tensor:
        """The force ``(B, d)``: the sum of the four parts."""
        return self.unsteady + self.momentum_flux + self.pressure + self.viscous

    def coefficients(self, speed: float, length: float, density: float = 1.0) -> torch.Tensor:
        """Force coefficients ``2 F / (density speed^2 length)`` ``(B, d)`` (``length`` an area in 3-D)."""
        return 2.0 * self.total / (density * speed**2 * length)


def control_volume_box(grid: Grid, box: Sequence[Sequence[float]]) -> tuple[tuple[int, int], ...]:
    """``box`` (``((lo, hi), ...)`` in the grid's coordinates) rounded to face indices ``((i_lo, i_hi), ...)``.

    A side may lie on the domain's boundary (the side stencils, which reach one cell beyond the box, then read the
    ghost values the boundary conditions give: exact mirror images on a free-slip symmetry plane). Raises
    ``ParameterError`` for a box that leaves the domain or spans no cell along an axis."""
    if not isinstance(box, (list, tuple)) or len(box) != grid.rank:
        raise ParameterError(f"box must give (lo, hi) for each of the grid's {grid.rank} axes, got {box!r}")
    out = []
    for a, pair in enumerate(box):
        try:
            lo, hi = (float(v) for v in pair)
        except (TypeError, ValueError) as exc:
            raise ParameterError(f"box[{a}] must be a pair (lo, hi) of numbers, got {pair!r}") from exc
        if not (-math.inf < lo < math.inf and -math.inf < hi < math.inf):  # traceable where math.isfinite is not
            raise ParameterError(f"box[{a}] = {pair!r} is not finite")
        start, d, n = grid.bounds[a][0], grid.dx[a], grid.resolution[a]
        i_lo, i_hi = round((lo - start) / d), round((hi - start) / d)
        if not 0 <= i_lo < i_hi <= n:
            raise ParameterError(
                f"box[{a}] = ({lo:g}, {hi:g}) rounds to faces {i_lo}..{i_hi} of axis {a}; the box must span at least "
                f"one cell and lie in the domain (faces 0..{n})")
        out.append((i_lo, i_hi))
    return tuple(out)


def _product(values) -> float:
    """The product of a few floats (a loop: ``torch.compile`` traces it without a graph break)."""
    out = 1.0
    for v in values:
        out *= float(v)
    return out


def _take(x: torch.Tensor, ranges: dict[int, tuple[int, int]]) -> torch.Tensor:
    """``x[:, ...]`` with the spatial axis ``a`` restricted to ``ranges[a] = (start, stop)``."""
    index = [slice(None)] * x.ndim
    for a, (start, stop) in ranges.items():
        index[a + 1] = slice(start, stop)
    return x[tuple(index)]


def _momentum(values, box, dx) -> torch.Tensor:
    """``int_V u dV`` ``(B, d)``."""
    d = len(box)
    out = []
    for c in range(d):
        ranges = {k: (box[k][0], box[k][1] + (1 if k == c else 0)) for k in range(d)}
        u = _take(values[c], ranges)
        s = u.sum(tuple(range(1, d + 1)))
        ends = _take(values[c], {**ranges, c: (box[c][0], box[c][0] + 1)}).sum(tuple(range(1, d + 1)))
        ends = ends + _take(values[c], {**ranges, c: (box[c][1], box[c][1] + 1)}).sum(tuple(range(1, d + 1)))
        out.append(s - 0.5 * ends)
    return torch.stack(out, -1) * _product(dx)


def _side_fluxes(values, box, dx, nu: float) -> tuple[torch.Tensor, torch.Tensor]:
    """``(-oint u (u . n) dS, oint nu (grad u + grad u^T) n dS)``, each ``(B, d)``."""
    d = len(box)
    conv = [0.0] * d
    visc = [0.0] * d
    for a in range(d):
        area = _product([dx[k] for k in range(d) if k != a])
        cells = {k: box[k] for k in range(d) if k != a}  # the side's cells along the other axes
        for s, sign in ((box[a][1], 1.0), (box[a][0], -1.0)):
            ua = values[a]
            u_n = _take(ua, {**cells, a: (s, s + 1)})
            dn = (_take(ua, {**cells, a: (s + 1, s + 2)}) - _take(ua, {**cells, a: (s - 1, s)})) / (2 * dx[a])
            conv[a] = conv[a] - sign * area * (u_n * u_n).sum(tuple(range(1, d + 1)))
            visc[a] = visc[a] + sign * area * (2 * nu) * dn.sum(tuple(range(1, d + 1)))
            for c in range(d):
                if c == a:
                    continue
                uc = values[c]
                lo, hi = box[c]
                # u_c at the side's points: the four faces around (two cells across the side, two faces along c)
                quad = _take(uc, {**cells, c: (lo, hi + 1), a: (s - 1, s + 1)})
                centred = 0.5 * (quad.narrow(c + 1, 0, hi - lo) + quad.narrow(c + 1, 1, hi - lo))  # cells along c
                u_t = 0.5 * (centred.narrow(a + 1, 0, 1) + centred.narrow(a + 1, 1, 1))
                d_a_uc = (centred.narrow(a + 1, 1, 1) - centred.narrow(a + 1, 0, 1)) / dx[a]
                ua_c = _take(ua, {**cells, c: (lo - 1, hi + 1), a: (s, s + 1)})
                d_c_ua = (ua_c.narrow(c + 1, 2, hi - lo) - ua_c.narrow(c + 1, 0, hi - lo)) / (2 * dx[c])
                conv[c] = conv[c] - sign * area * (u_t * u_n).sum(tuple(range(1, d + 1)))
                visc[c] = visc[c] + sign * area * nu * (d_a_uc + d_c_ua).sum(tuple(range(1, d + 1)))
    return torch.stack(conv, -1), torch.stack(visc, -1)


def _pressure_force(p: torch.Tensor, box, dx) -> torch.Tensor:
    """``-oint_S p n dS`` with ``p`` at the cell centres ``(B, d)``."""
    d = len(box)
    out = []
    for a in range(d):
        area = _product([dx[k] for k in range(d) if k != a])
        cells = {k: box[k] for k in range(d) if k != a}
        total = 0.0
        for s, sign in ((box[a][1], 1.0), (box[a][0], -1.0)):
            side = _take(p, {**cells, a: (s - 1, s + 1)})
            total = total + sign * 0.5 * side.sum(tuple(range(1, d + 1)))
        out.append(-area * total)
    return torch.stack(out, -1)


def control_volume_force(velocity: StaggeredGrid, pressure: CenteredGrid, *, box: Sequence[Sequence[float]],
                         dt: float, viscosity: float, previous: StaggeredGrid | None = None,
                         density: float = 1.0) -> ControlVolumeForces:
    """The force of the fluid on whatever lies inside ``box``, from the momentum balance over the box.

    Args:
        velocity: The velocity after a step.
        pressure: The pressure potential the step returned (``density * p / dt`` is the physical pressure).
        box: ``((lo, hi), ...)`` per axis in the grid's coordinates, rounded to the nearest face planes
            (:func:`control_volume_box`); it should enclose the bodies to be read and no others. A side on the
            domain's boundary reads the ghost values of its conditions (on a mirror plane of a symmetric flow the
            box is then half of the whole flow's box, and the force half of the whole body's).
        dt: The step's time step.
        viscosity: Kinematic viscosity.
        previous: The velocity one step earlier: the reading then includes the momentum change in the box and
            stands at the half step. Without it, the steady balance. (An accelerating body's interior adds
            ``-rho V_b a_b`` to the reading; see the module's documentation.)
        density: Fluid density.

    Returns:
        :class:`ControlVolumeForces`: the four parts and their total ``(B, d)``.

    Raises:
        ParameterError: For a box that does not fit (:func:`control_volume_box`), non-positive ``dt`` or
            ``density``, or negative ``viscosity``.
        GridMismatchError: For a previous velocity on another grid.
        ShapeError: For a pressure on another grid.
    """
    check_velocity(velocity)
    dt = check_positive(dt, "dt")
    density = check_positive(density, "density")
    nu = check_nonnegative(viscosity, "viscosity")
    grid = velocity.grid
    p = pressure_values(pressure, velocity)
    if previous is not None:
        check_velocity(previous, "previous")
        if previous.grid != grid:
            raise GridMismatchError(f"previous velocity grid {previous.grid} differs from the velocity grid {grid}")
    cells = control_volume_box(grid, box)
    dx = grid.dx
    # a side on the domain's boundary reads the ghost values its conditions give (one layer, indices shifted by 1)
    ghosts = any(lo == 0 or hi == n for (lo, hi), n in zip(cells, grid.resolution))
    shifted = tuple((lo + 1, hi + 1) for lo, hi in cells) if ghosts else cells

    def components(v: StaggeredGrid):
        return tuple(v.padded_component(c, 1) for c in range(grid.rank)) if ghosts else v.values

    if ghosts:
        p = pressure.padded(1)
    values = components(velocity)
    conv, visc = _side_fluxes(values, shifted, dx, nu)
    if previous is not None:
        values0 = components(previous)
        conv0, visc0 = _side_fluxes(values0, shifted, dx, nu)
        conv, visc = 0.5 * (conv + conv0), 0.5 * (visc + visc0)
        unsteady = -(_momentum(values, shifted, dx) - _momentum(values0, shifted, dx)) / dt
    else:
        unsteady = torch.zeros_like(conv)
    return ControlVolumeForces(unsteady=density * unsteady, momentum_flux=density * conv,
                               pressure=_pressure_force(p * (density / dt), shifted, dx),
                               viscous=density * visc, box=cells)
