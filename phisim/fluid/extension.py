"""The fluid velocity extended into sharp no-slip bodies, for the self-advection of the split step.

Semi-Lagrangian and MacCormack transport interpolate the velocity at the departure points of the faces next to a
body, and those interpolation stencils reach the faces centred inside it. A no-slip body stores its own velocity
``u_s`` there, which is the fluid's value at the surface, not at the face: the interpolated velocity between the
surface and the first fluid face is then off by ``O(dx |du/dn|)``, and in a boundary layer that is a first-order
error in the transported velocity (measured on circular Couette flow with advection: velocity near the surfaces
converges at order 1.2 with ``u_s`` inside, 1.9 with the extension; ``examples/taylor_couette.py --advection``).

:func:`extend_into_bodies` gives each face centred inside a sharp no-slip body, within :data:`BAND_CELLS` cells of
its surface, the linear no-slip profile continued through the surface: ``u_s(x) + phi(x) / d (u - u_s)(probe)``,
with ``phi < 0`` the signed distance of the face and ``probe`` the point ``d`` = two cells out along the normal (the
stencil of :func:`~phisim.fluid.bodies.extension_stencil`, multilinear in the fluid faces around it). Only the
transported field changes: the faces inside the body take ``u_s`` again before the viscous step and the
projection (:func:`~phisim.fluid.projection.impose_solids`).
"""

from __future__ import annotations

import torch

from phisim.field import StaggeredGrid
from phisim.fluid.bodies import Body, SolidLayout, as_solids, extension_stencil

__all__ = ["BAND_CELLS", "extend_into_bodies"]

#: Depth of the band inside a body that gets the extended velocity, in cells (a departure point of a Courant
#: number up to 1 and its interpolation stencil reach one cell beyond the faces next to the surface).
BAND_CELLS = 2.0


def _sharp_bodies(solids) -> list:
    return [s for s in solids if isinstance(s, Body) and s.no_slip and s.sharp]


def _stencils(bodies, grid, t: float, dtype, device) -> tuple:
    """Per component, ``(index, corners, weights, factor, base)`` of the faces in the band inside ``bodies`` (or
    None where there are none), in ``dtype``."""
    work = torch.float64 if dtype in (torch.float32, torch.float16, torch.bfloat16) else dtype
    h = min(grid.dx)
    out = []
    for i in range(grid.rank):
        x = grid.face_centers(i, work, device)
        phi = torch.stack([b.sdf(x, t) for b in bodies], 0).min(0).values
        band = (phi.detach() <= 0) & (phi.detach() > -BAND_CELLS * h)
        ext = extension_stencil(bodies, grid, i, t, work, device, band)
        out.append(None if ext is None else (ext[0], ext[1], ext[2].to(dtype), ext[3].to(dtype), ext[4].to(dtype)))
    return tuple(out)


def extend_into_bodies(velocity: StaggeredGrid, obstacles, time: float = 0.0) -> StaggeredGrid:
    """``velocity`` with the faces just inside sharp no-slip bodies set to the extended no-slip profile.

    Args:
        velocity: MAC velocity (the fluid's faces as stored by a step).
        obstacles: The solids as a step takes them: a :class:`~phisim.fluid.bodies.SolidLayout` (its stencils are
            kept on it when it is persistent), bodies, geometries, obstacles, or None.
        time: Time of ``velocity`` (positions and velocities of moving bodies).

    Returns:
        The velocity with the band inside sharp no-slip bodies extended (unchanged without such bodies).
    """
    if obstacles is None:
        return velocity
    layout = obstacles if isinstance(obstacles, SolidLayout) else None
    bodies = _sharp_bodies(layout.bodies if layout is not None else as_solids(obstacles))
    if not bodies:
        return velocity
    dtype, device = velocity.dtype, velocity.device
    cache = None if layout is None else layout.solvers
    key = ("inside_extension", dtype, str(device))
    stencils = None if cache is None else cache.get(key)
    if stencils is None:
        stencils = _stencils(bodies, velocity.grid, float(time), dtype, device)
        if cache is not None:
            cache[key] = stencils
    out = []
    for u, st in zip(velocity.values, stencils):
        if st is None:
            out.append(u)
            continue
        index, corners, weights, factor, base = st
        flat = u.reshape(u.shape[0], -1)
        value = base + factor * (flat[:, corners] * weights).sum(-1)
        out.append(flat.index_copy(1, index, value).reshape(u.shape))
    return velocity._with_components(out)
