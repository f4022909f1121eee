"""Viscous diffusion of MAC velocities: explicit, implicit (backward Euler), Crank-Nicolson, exact.

Wall and inflow velocities enter through the ghost samples of the velocity boundary; bodies enter through
:func:`phisim.fluid.projection.impose_solids`, applied before this step, which puts each body's velocity on
the faces it covers, and (sharp no-slip bodies, ``solids=``) through the stencil of the faces next to them, which
takes the body's velocity where each stencil arm crosses the surface (:class:`phisim.fluid.bodies.SolidLayout`).
The work is done by :func:`phisim.solvers.diffusion.diffuse_staggered`: implicit schemes are solved exactly by one
DST/DCT/FFT pair per component (about the cost of an explicit step at small sizes; see ``docs/BENCHMARKS.md``).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import torch

from phisim.checks import check_dt, check_nonnegative
from phisim.errors import ParameterError
from phisim.field import StaggeredGrid
from phisim.fluid.extension import free_slip_ghosts
from phisim.fluid.projection import check_velocity
from phisim.ops.differential import laplace
from phisim.solvers.diffusion import diffuse_staggered, staggered_laplace
from phisim.solvers.linalg import Solve

if TYPE_CHECKING:  # annotations only
    from phisim.fluid.bodies import SolidLayout

__all__ = ["diffuse_velocity", "body_laplace", "VISCOSITY_SCHEMES"]

#: Schemes of :func:`diffuse_velocity` (the methods of :func:`phisim.solvers.diffusion.diffuse_staggered`).
VISCOSITY_SCHEMES = ("explicit", "implicit", "crank_nicolson", "spectral")


def diffuse_velocity(
    velocity: StaggeredGrid, dt, *, viscosity: float, scheme: str = "explicit", solve: Solve | None = None,
    fixed=None, solids=None, time: float = 0.0,
) -> StaggeredGrid:
    """Viscous diffusion ``du/dt = viscosity * lap(u)`` of a MAC velocity over one step ``dt``.

    Wall velocities enter through the ghost cells of :meth:`StaggeredGrid.padded_component`: a moving
    lid (``NoSlipWall(velocity=(1, 0))``) drags the tangential velocity next to it.

    Args:
        velocity: MAC velocity.
        dt: Time step ``>= 0``.
        viscosity: Kinematic viscosity ``>= 0``.
        scheme: ``'explicit'`` (forward Euler, first order in time, stable for
            ``viscosity * dt * sum(2 / dx_i^2) <= 1``), ``'implicit'`` (backward Euler, first order,
            unconditionally stable), ``'crank_nicolson'`` (second order, unconditionally stable) or
            ``'spectral'`` (exact in time; no ``fixed`` faces). Implicit schemes are exact box solves by
            DST/DCT/FFT (:func:`phisim.solvers.diffusion.diffuse_staggered`).
        solve: CG settings of the solve with ``fixed`` faces (unused otherwise).
        fixed: Optional per-component face masks held at their current value (bodies), see
            :func:`phisim.solvers.diffusion.diffuse_staggered`.
        solids: The rasterised solids (:class:`~phisim.fluid.bodies.SolidLayout`, after
            :func:`~phisim.fluid.projection.impose_solids`), or None. Faces they close are held, and sharp no-slip
            bodies enter the stencil of the faces next to them at their true surface (``SolidLayout.walls``); the
            direct capacitance solves of a persistent layout are kept on it. Free-slip bodies: the faces they close
            take ghost values of the free-slip condition first (:func:`~phisim.fluid.extension.free_slip_ghosts`).
        time: Time of ``solids`` (the velocity of moving free-slip bodies in their ghost values).

    Returns:
        The diffused velocity with boundary faces re-imposed.

    Raises:
        ParameterError: For negative dt/viscosity, an unknown scheme, or an explicit step beyond its
            stability limit.
        SolveError: If a solve with ``fixed`` faces does not converge.
    """
    check_velocity(velocity)
    dt = check_dt(dt)
    viscosity = check_nonnegative(viscosity, "viscosity")
    if scheme not in VISCOSITY_SCHEMES:
        raise ParameterError(f"viscosity scheme must be one of {VISCOSITY_SCHEMES}, got {scheme!r}")
    if float(viscosity) == 0 or float(dt) == 0:
        return velocity
    if scheme == "explicit":
        number = float(dt * viscosity) * sum(2.0 / d**2 for d in velocity.grid.dx)
        if number > 1.0:
            raise ParameterError(
                f"explicit viscosity is unstable: viscosity * dt * sum(2/dx^2) = {number:.3g} > 1; reduce dt or "
                "use scheme='implicit' or 'crank_nicolson'"
            )
    walls, capacitance = None, None
    if solids is not None and solids.slip is not None:
        velocity = free_slip_ghosts(velocity, solids, float(time), closed_only=False)
    if solids is not None and solids.walls is not None:
        walls = solids.walls
        held = held_faces(solids, beyond_cut=True)
        fixed = held if fixed is None else tuple(
            h if f is None else (torch.as_tensor(f, device=f.device if h is None else h.device) != 0) | (
                False if h is None else h) for f, h in zip(fixed, held))
        capacitance = solids.solvers if solids.direct else None
    return diffuse_staggered(velocity, dt, viscosity=viscosity, method=scheme, fixed=fixed, solve=solve,
                             walls=walls, capacitance=capacitance)


def held_faces(solids: SolidLayout, beyond_cut: bool = False) -> tuple:
    """Per component the faces the solids close (``theta <= 0``), or None where there are none. A layout kept by a
    stepper (its ``solvers`` dict) computes them once; its traced steps then read nothing back to the host.

    ``beyond_cut``: None also where every closed face is a cut face of a sharp body (``walls``), which the viscous
    step holds anyway: the held set is then the layout's ``cut`` mask itself (no union per step)."""
    cache = solids.solvers
    key = "held_faces_beyond_cut" if beyond_cut else "held_faces"
    if cache is not None and key in cache:
        return cache[key]
    held = held_faces(solids) if beyond_cut else tuple(
        m if bool(m.any()) else None for m in ((th <= 0) for th in solids.theta))
    if beyond_cut:
        walls = solids.walls
        held = tuple(h if h is None or w is None or w[0].shape[0] != h.shape[0] or bool((h & ~w[0]).any()) else None
                     for h, w in zip(held, walls))
    if cache is not None:
        cache[key] = held
    return held


def body_laplace(velocity: StaggeredGrid, solids=None) -> StaggeredGrid:
    """The vector Laplacian of a MAC velocity with the sharp no-slip bodies of ``solids`` at their true surface.

    Without sharp bodies this is :func:`phisim.ops.differential.laplace`. With them, every component is
    ``L_0 u - coef u + source`` on its free faces (the stencil of the viscous step, see
    :class:`~phisim.fluid.bodies.SolidLayout` ``walls``) and 0 on faces centred inside a body: the explicit part of
    a Crank-Nicolson or Runge-Kutta step that matches the implicit one.

    Args:
        velocity: MAC velocity.
        solids: The rasterised solids (:class:`~phisim.fluid.bodies.SolidLayout`) or None.

    Returns:
        The Laplacian as a StaggeredGrid (values on fixed boundary faces are not meaningful).
    """
    check_velocity(velocity)
    if solids is None or solids.walls is None:
        return laplace(velocity)
    return staggered_laplace(velocity, solids.walls)
