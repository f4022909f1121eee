"""Velocities continued into bodies: for the self-advection of the split step (sharp no-slip bodies) and for the
viscous step (the ghost values of free-slip bodies, :func:`free_slip_ghosts`).

Semi-Lagrangian and MacCormack transport interpolate the velocity at the departure points of the faces next to a
body, and those interpolation stencils reach the faces centred inside it. A no-slip body stores its own velocity
``u_s`` there, which is the fluid's value at the surface, not at the face: the interpolated velocity between the
surface and the first fluid face is then off by ``O(dx |du/dn|)`` in a boundary layer (measured on circular Couette
flow with advection, ``examples/taylor_couette.py --advection``: near-surface errors 25-30 % lower with the
extension on 48^2 and 96^2).

:func:`extend_into_bodies` gives each face centred inside a sharp no-slip body, within :data:`BAND_CELLS` cells of
its surface, the linear no-slip profile continued through the surface: ``u_s(x) + phi(x) / d (u - u_s)(probe)``,
with ``phi < 0`` the signed distance of the face and ``probe`` the point ``d`` = two cells out along the normal (the
stencil of :func:`~phisim.fluid.bodies.extension_stencil`, multilinear in the fluid faces around it). Only the
transported field changes: the faces inside the body take ``u_s`` again before the viscous step and the
projection (:func:`~phisim.fluid.projection.impose_solids`).
"""

from __future__ import annotations

import math

import torch

from phisim.errors import warn_from_caller
from phisim.field import StaggeredGrid
from phisim.fluid.bodies import (
    FREE_SLIP_SUBFACES,
    PROBE_CELLS,
    Body,
    SolidLayout,
    as_solids,
    extension_stencil,
    face_normal,
    free_slip_cuts,
    planar_cut,
    sdf_gradient,
    set_from_probes,
    sharp_no_slip,
    unit_normal,
)

__all__ = ["BAND_CELLS", "extend_into_bodies", "free_slip_flux", "free_slip_ghosts"]

#: Depth of the band inside a body that gets the extended velocity, in cells (a departure point of a Courant
#: number up to 1 and its interpolation stencil reach one cell beyond the faces next to the surface).
BAND_CELLS = 2.0


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
    bodies = sharp_no_slip(layout.bodies if layout is not None else as_solids(obstacles))
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
    return velocity._with_components([u if st is None else set_from_probes(u, st)
                                      for u, st in zip(velocity.values, stencils)])


def _free_slip_bodies(solids) -> list:
    return [s for s in solids if isinstance(s, Body) and not s.no_slip]


def _mirror_geometry(bodies, grid, i: int, t: float, dtype, device, select) -> tuple | None:
    """``(index, x, normal, factors, probe, owner)`` of the faces of component ``i`` in ``select`` (flat indices, face
    centres, the nearest body's unit normal, the tangential and normal factors ``(1 + kappa phi) / (1 + kappa d)`` and
    ``phi / d``, the probe ``d`` beyond the surface along the normal, the nearest body), or None when ``select`` is
    empty."""
    index = select.flatten().nonzero().squeeze(1)
    if index.numel() == 0:
        return None
    h = min(grid.dx)
    x = grid.face_centers(i, dtype, device).reshape(-1, grid.rank)[index]
    phis = torch.stack([b.sdf(x, t) for b in bodies], 0)
    phi = phis.min(0).values
    owner = phis.argmin(0)
    normal = torch.zeros_like(x)
    kappa = torch.zeros_like(phi)
    e = 0.5 * h
    for k, b in enumerate(bodies):
        sel = (owner == k).nonzero().squeeze(1)
        if sel.numel() == 0:
            continue
        n = unit_normal(b, x[sel], t, 1e-3 * h)
        normal = normal.index_put((sel,), n)
        xs = x[sel] - phi[sel].unsqueeze(-1) * n  # the nearest surface point: the curvature there
        lap = torch.zeros_like(sel, dtype=dtype)
        for a in range(grid.rank):  # curvature: the Laplacian of the signed distance, per direction in the surface
            step = torch.zeros(grid.rank, dtype=dtype, device=device)
            step[a] = e
            lap = lap + (b.sdf(xs + step, t) - 2 * b.sdf(xs, t) + b.sdf(xs - step, t)) / e**2
        kappa = kappa.index_put((sel,), lap / max(grid.rank - 1, 1))
    # zero shear stress of the relative velocity on a surface of curvature kappa: d w_t / dn = kappa w_t, so w_t grows
    # as (1 + kappa s) with the distance s from the surface (exact for a rigid rotation about a circle's or a sphere's
    # centre); the normal part grows linearly from 0 (no flux through the surface). Both are read at a probe PROBE_CELLS
    # cells out along the normal, whose interpolation stencil stays in the fluid.
    d = PROBE_CELLS * h
    factor = (1 + kappa * phi) / (1 + kappa * d).clamp_min(0.25)
    probe = x + (d - phi).unsqueeze(-1) * normal
    return index, x, normal, torch.stack([factor, phi / d], -1), probe, owner


def _mirror_fill(velocity: StaggeredGrid, bodies, t: float, geometry: tuple) -> StaggeredGrid:
    out = list(velocity.values)
    for i, geo in enumerate(geometry):
        if geo is None:
            continue
        index, x, normal, factor, mirror, owner = geo
        dtype = velocity.dtype
        u = velocity.sample(mirror.to(dtype))  # (B, d, K)
        us_x = torch.zeros_like(x)
        us_m = torch.zeros_like(x)
        for k, b in enumerate(bodies):
            if b.static:
                continue
            sel = (owner == k).nonzero().squeeze(1)
            us_x = us_x.index_put((sel,), b.velocity_at(x[sel], t))
            us_m = us_m.index_put((sel,), b.velocity_at(mirror[sel], t))
        n = normal.to(dtype).T.unsqueeze(0)  # (1, d, K)
        w = u - us_m.to(dtype).T.unsqueeze(0)
        wn = (w * n).sum(1, keepdim=True)
        ft, fn = factor.to(dtype).unbind(-1)
        ghost = us_x.to(dtype).T.unsqueeze(0) + ft * (w - wn * n) + fn * wn * n
        c = out[i]
        flat = c.reshape(c.shape[0], -1)
        value = ghost[:, i].expand(flat.shape[0], -1) if ghost.shape[0] != flat.shape[0] else ghost[:, i]
        out[i] = flat.index_copy(1, index, value).reshape(c.shape)
    return velocity._with_components(out)


def free_slip_ghosts(velocity: StaggeredGrid, layout: SolidLayout | None, time: float = 0.0,
                     closed_only: bool = True) -> StaggeredGrid:
    """``velocity`` with the faces just inside free-slip bodies set to ghost values of the free-slip condition.

    A face centred inside a free-slip body (within :data:`BAND_CELLS` cells of its surface) takes the fluid's
    relative velocity at a probe ``d`` (two cells) beyond the surface along the normal, continued through the surface:
    the normal part linearly through 0 (``phi / d``, no flux), the tangential part as ``(1 + kappa phi) / (1 + kappa
    d)`` (zero shear stress on a surface of curvature ``kappa``, the Laplacian of the signed distance per surface
    direction: ``d w_t / dn = kappa w_t``). Stencils that
    read these faces (the viscous step) then see a surface without shear stress instead of the body's velocity.

    Args:
        velocity: MAC velocity with the solids imposed (:func:`~phisim.fluid.projection.impose_solids`).
        layout: The rasterised solids (None or no free-slip body: ``velocity`` is returned).
        time: Time of the layout (moving bodies).
        closed_only: Fill only the faces the solids close (``theta <= 0``: the viscous step holds them); False: all
            faces centred inside (the transported field).

    Returns:
        The velocity with the ghost values.
    """
    if layout is None:
        return velocity
    bodies = _free_slip_bodies(layout.bodies)
    if not bodies:
        return velocity
    grid = velocity.grid
    work = torch.float64 if velocity.dtype in (torch.float32, torch.float16, torch.bfloat16) else velocity.dtype
    cache = layout.solvers if all(b.static for b in bodies) else None
    key = ("free_slip_ghosts", closed_only, str(velocity.device))
    geometry = None if cache is None else cache.get(key)
    if geometry is None:
        h = min(grid.dx)
        geometry, cut_axes = [], []
        for i in range(grid.rank):
            x = grid.face_centers(i, work, velocity.device)
            phi = torch.stack([b.sdf(x, time) for b in bodies], 0).min(0).values.detach()
            band = (phi <= 0) & (phi > -BAND_CELLS * h)
            if _edge_inside_surface(phi, h, velocity.boundary, i):
                cut_axes.append(i)
            if closed_only:
                band = band & (layout.theta[i].detach()[0] <= 0)
            geometry.append(_mirror_geometry(bodies, grid, i, time, work, velocity.device, band))
        geometry = tuple(geometry)
        if cut_axes:
            warn_from_caller(f"the domain's edge normal to axis {cut_axes} passes within one cell inside a free-slip "
                             "body's surface: the free-slip condition's ghost values there lie beyond the edge; leave "
                             "at least about 1.5 cells between the edge and a free-slip surface, measured inside the "
                             "body", RuntimeWarning)
        if cache is not None:
            cache[key] = geometry
    return _mirror_fill(velocity, bodies, time, geometry)


def _edge_inside_surface(phi: torch.Tensor, h: float, boundary, axis: int) -> bool:
    """Whether the domain's edge normal to ``axis`` (not periodic) passes within one cell inside a free-slip body's
    surface (``phi``: the distance at the faces normal to ``axis``, whose first and last layers lie on that edge): the
    ghost values the viscous step reads there would lie beyond the edge (docs/VALIDATION.md, "Free-slip bodies in
    3-D": with the edge 0.9 cells beyond a free-slip sphere the error is 35 % at 16^3; 1.3-1.5 cells beyond, the
    errors are those of a larger box). False while tracing (no host reads)."""
    if torch.compiler.is_compiling() or boundary.is_periodic(axis):
        return False
    near = (phi <= 0) & (phi > -h)
    return bool(near.select(axis, 0).any()) or bool(near.select(axis, near.shape[axis] - 1).any())


def _slip_flux_stencil(bodies, layout: SolidLayout, grid, i: int, dtype, device, t: float):
    """``(index, neighbours, weights)`` of the free-slip flux correction of component ``i`` (or None): for each face
    cut by a free-slip body, the neighbours one face towards the fluid along each axis ``j != i`` and the weights
    ``theta c_j * sign / dx_j``, ``c`` the wetted part's centroid relative to the face centre: ``(E[phi_+] / theta -
    phi_F) g / |g|^2`` for one planar cut, the sub-cuts' within a cell of the surface (see :func:`free_slip_flux`)."""
    h = min(grid.dx)
    th = layout.theta[i].detach()[0]
    x = grid.face_centers(i, dtype, device)
    phis = torch.stack([b.sdf(x, t) for b in bodies], 0)
    phi = phis.min(0).values
    cut = (th > 0) & (th < 1) & (phi.detach() < 1.5 * h)
    index = cut.flatten().nonzero().squeeze(1)
    if index.numel() == 0:
        return None
    shape = th.shape
    xs = x.reshape(-1, grid.rank)[index]
    pf = phi.reshape(-1)[index]
    owner = phis.reshape(len(bodies), -1)[:, index].argmin(0)
    grad = torch.zeros_like(xs)
    for k, b in enumerate(bodies):
        sel = (owner == k).nonzero().squeeze(1)
        if sel.numel():
            grad = grad.index_put((sel,), sdf_gradient(b, xs[sel], t, 1e-3 * h))
    g = face_normal(grad, i)
    centroid = planar_cut(pf, g, h)[1]  # the wetted part's centroid relative to the face centre
    # faces within a cell of the surface: the centroid of the sub-cuts the layout's fraction comes from
    if FREE_SLIP_SUBFACES[grid.rank] > 1:
        for k, b in enumerate(bodies):
            sel = ((owner == k) & (pf.detach().abs() < h)).nonzero().squeeze(1)
            if sel.numel():
                centroid = centroid.index_put((sel,), free_slip_cuts(b, xs[sel], t, h, i, grad[sel])[1])
    # theta times the centroid's offset along axis j; theta the layout's (the wetted fraction the projection weighs
    # the face with, from sub-cuts on curved free-slip surfaces), so that the correction vanishes with it
    amount = layout.theta[i][0].reshape(-1)[index].to(dtype)
    strides = [math.prod(shape[a + 1:]) for a in range(grid.rank)]
    coords = torch.stack([(index // strides[a]) % shape[a] for a in range(grid.rank)], -1)
    neighbours, weights = [], []
    for j in range(grid.rank):
        if j == i:
            continue
        sign = torch.where(g[:, j] >= 0, 1, -1)
        cj = coords[:, j] + sign
        ok = (cj >= 0) & (cj < shape[j])
        sign = torch.where(ok, sign, -sign)  # at the grid's edge: the other side
        neighbours.append(index + sign * strides[j])
        weights.append(amount * centroid[:, j] * sign.to(dtype) / grid.dx[j])
    return index, torch.stack(neighbours, 1), torch.stack(weights, 1).to(dtype)


def free_slip_flux(values, layout: SolidLayout | None, grid, time: float | None = None):
    """Per component ``(index, value)`` of the flux the blend ``theta u`` misses on faces cut by free-slip bodies
    (None without free-slip bodies): the fluid velocity is not constant over a face, and its mean over the wetted part
    is its value at the wetted part's centroid, ``u_F + (grad u . g) (E[phi_+] - theta phi_F) / |g|^2`` for a planar
    cut (``g`` the unit normal's part in the face, ``E[phi_+]`` the face's mean positive distance,
    :func:`~phisim.fluid.geometry.cut_fractions`), the in-face derivative taken one face towards the fluid. Faces
    within a cell of the surface take the centroid of the sub-cuts their wetted fraction comes from
    (:func:`~phisim.fluid.bodies.free_slip_cuts`): one planar cut misplaces it on faces nearly parallel to a curved
    surface, which held the 3-D free-slip errors near first order (docs/VALIDATION.md, "Free-slip bodies"). Without
    the correction the cut cells' divergence is off by O(1) and the velocity next to a curved free-slip surface does
    not converge (the no-slip bodies' counterpart is :func:`~phisim.fluid.projection.flux_correction`). ``time``: where
    moving bodies are (default: the layout's own time; the correction must see the bodies where ``theta`` saw
    them)."""
    if layout is None or layout.slip is None:
        return None
    bodies = _free_slip_bodies(layout.bodies)
    if not bodies:
        return None
    time = layout.time if time is None else time
    like = values[0]
    grid_key = ("free_slip_flux", like.dtype, str(like.device))
    cache = layout.solvers if all(b.static for b in bodies) else None
    stencils = None if cache is None else cache.get(grid_key)
    if stencils is None:
        stencils = tuple(_slip_flux_stencil(bodies, layout, grid, i, like.dtype, like.device, float(time))
                         for i in range(len(values)))
        if cache is not None:
            cache[grid_key] = stencils
    out = []
    for u, st in zip(values, stencils):
        if st is None:
            out.append(None)
            continue
        index, neighbours, weights = st
        flat = u.reshape(u.shape[0], -1)
        diff = flat[:, neighbours] - flat[:, index].unsqueeze(-1)
        out.append((index, (diff * weights).sum(-1)))
    return out
