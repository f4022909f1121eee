"""Viscous diffusion of MAC velocities: explicit (forward Euler) and implicit (backward Euler, CG).

Wall and inflow velocities enter through the ghost samples of the velocity boundary; bodies enter through
:func:`phisim.fluid.projection.impose_solids`, applied before this step, which puts each body's velocity on
the faces it covers, so the viscous stencil sees it at the body's surface.
"""

from __future__ import annotations

import torch

from ..boundary import Boundary, pad_staggered_component, set_boundary_faces
from ..checks import check_dt, check_nonnegative
from ..differential import laplace
from ..errors import ParameterError
from ..field import StaggeredGrid
from ..linalg import Solve, cg
from .projection import _check_velocity

__all__ = ["diffuse_velocity"]


def diffuse_velocity(
    velocity: StaggeredGrid, dt, *, viscosity: float, scheme: str = "explicit", solve: Solve | None = None
) -> StaggeredGrid:
    """Viscous diffusion ``du/dt = viscosity * lap(u)`` of a MAC velocity over one step ``dt``.

    Wall velocities enter through the ghost cells of :meth:`StaggeredGrid.padded_component`: a moving
    lid (``NoSlipWall(velocity=(1, 0))``) drags the tangential velocity next to it.

    Args:
        velocity: MAC velocity.
        dt: Time step ``>= 0``.
        viscosity: Kinematic viscosity ``>= 0``.
        scheme: ``'explicit'`` (forward Euler, first order in time, stable for
            ``viscosity * dt * sum(2 / dx_i^2) <= 1``) or ``'implicit'`` (backward Euler, unconditionally
            stable; each component solved by CG, symmetric stencil with boundary faces treated exactly).
        solve: CG settings of the implicit scheme (default ``Solve(rtol=1e-8)``).

    Returns:
        The diffused velocity with boundary faces re-imposed.

    Raises:
        ParameterError: For negative dt/viscosity, an unknown scheme, or an explicit step beyond its
            stability limit.
        SolveError: If the implicit solve does not converge.
    """
    _check_velocity(velocity)
    dt = check_dt(dt)
    viscosity = check_nonnegative(viscosity, "viscosity")
    if scheme not in ("explicit", "implicit"):
        raise ParameterError(f"viscosity scheme must be 'explicit' or 'implicit', got {scheme!r}")
    if float(viscosity) == 0 or float(dt) == 0:
        return velocity
    alpha = dt * viscosity
    if scheme == "explicit":
        number = float(alpha) * sum(2.0 / d**2 for d in velocity.grid.dx)
        if number > 1.0:
            raise ParameterError(
                f"explicit viscosity is unstable: viscosity * dt * sum(2/dx^2) = {number:.3g} > 1; reduce dt"
                " or "
                "use scheme='implicit'"
            )
        return (velocity + alpha * laplace(velocity)).with_boundary_faces()
    if solve is None:  # (1 - alpha L) is well conditioned: float64 reaches 1e-8, float32 about 1e-6
        solve = Solve(rtol=1e-8 if velocity.dtype == torch.float64 else 1e-6)
    return _implicit_diffusion(velocity, alpha, solve)


def _implicit_diffusion(velocity: StaggeredGrid, alpha, solve: Solve) -> StaggeredGrid:
    """Backward Euler ``(1 - alpha L) u_new = u`` per component by CG.

    Unknowns are the free face samples. Samples fixed by the boundary (wall/Dirichlet boundary faces, and
    face ``n`` of a periodic axis, a copy of face 0) are excluded from the operator. Free boundary faces of
    open sides (ghost mirrored about the face sample) get half weight, which makes the stencil symmetric.
    """
    grid, boundary = velocity.grid, velocity.boundary
    out = []
    for i, u in enumerate(velocity.values):
        dim = 1 + i
        n = grid.resolution[i]
        fixed = torch.zeros((1, *grid.face_shape(i)), dtype=u.dtype, device=u.device)
        weight = torch.ones_like(fixed)
        periodic = boundary.is_periodic(i)
        if periodic:
            fixed.narrow(dim, n, 1).fill_(1.0)
        else:
            for side, pos in ((0, 0), (1, n)):
                rule = boundary.sides[i][side].rule("normal", i)
                if rule[0] == "odd":
                    fixed.narrow(dim, pos, 1).fill_(1.0)
                else:
                    weight.narrow(dim, pos, 1).fill_(0.5)
        free = 1.0 - fixed

        def complete(x, i=i, dim=dim, n=n, periodic=periodic):
            if periodic:
                return torch.cat([x.narrow(dim, 0, n), x.narrow(dim, 0, 1)], dim=dim)
            return x

        def lap(x, i=i):
            return _component_laplace(x, i, boundary, grid.dx)

        fixed_vals = set_boundary_faces(torch.zeros_like(u), i, boundary) * fixed
        zero_lap = lap(torch.zeros_like(u))
        rhs = weight * free * (u + alpha * lap(fixed_vals)) + fixed * fixed_vals

        def operator(x, free=free, weight=weight, fixed=fixed, complete=complete, lap=lap, zero_lap=zero_lap):
            y = complete(x * free)
            return weight * free * (x - alpha * (lap(y) - zero_lap)) + fixed * x

        x = cg(operator, rhs, u.detach() * free + fixed_vals, solve=solve)
        out.append(complete(x * free) + fixed_vals)
    return velocity.with_values(tuple(out)).with_boundary_faces()


def _component_laplace(x: torch.Tensor, component: int, boundary: Boundary, dx) -> torch.Tensor:
    """The (2d+1)-point Laplacian of one MAC component, ghosts from the velocity boundary."""
    p = pad_staggered_component(x, component, boundary, dx, 1)
    out = 0
    for a in range(boundary.rank):
        dim = 1 + a
        d2 = (
            p.narrow(dim, 2, p.shape[dim] - 2)
            - 2 * p.narrow(dim, 1, p.shape[dim] - 2)
            + p.narrow(dim, 0, p.shape[dim] - 2)
        )
        for b in range(boundary.rank):
            if b != a:
                d2 = d2.narrow(1 + b, 1, d2.shape[1 + b] - 2)
        out = out + d2 / dx[a] ** 2
    return out
