"""The pressure on a no-slip surface read through the momentum equation along the normal.

Next to a no-slip wall the pressure varies on the viscous length of the flow, not on the length of the body: at a
stagnation point the pressure rises over a layer of thickness ``sqrt(nu / a)`` (``a`` the strain rate) by about
``nu a``, the normal viscous stress (plane stagnation flow, Hiemenz). On the DFG cylinder at D/20 that layer is two
cells thick (Re = 20) or less than one (Re = 100), and a polynomial through the pressures 1.5-3.5 cells out
(:func:`~phisim.fluid.probe_pressure`) misses the rise. The velocity carries it: integrating the normal component of
the momentum equation

    ``dp/dn = -du_n/dt - d(|u|^2/2)/dn + ((u x omega) . n) + nu (lap u) . n``

along the straight normal line from the surface point ``x_s`` (unit normal ``n``, kept fixed) to ``x_1 = x_s + d n``
gives

    ``p(x_s) = p(x_1) + (|u(x_1)|^2 - |u_s|^2) / 2 - int_0^d (u x omega) . n - nu (d_n u_n (x_1) + int_0^d lap_t u_n)
               + int_0^d du_n/dt``,

with ``u_n = u . n``. The normal-normal part of the viscous term integrates exactly to ``d_n u_n(x_1) - d_n u_n(x_s)``
and ``d_n u_n`` vanishes on a rigid no-slip surface (the tangential derivatives of ``u - u_s`` vanish there, and so
does the divergence); what is left under the integrals is smooth across the layer: the tangential Laplacian
``lap_t u_n``, the Lamb vector ``u x omega`` and the acceleration. The integrals use the three-point Gauss rule; the
velocity is sampled after :func:`~phisim.fluid.extension.extend_into_bodies` (the linear wall profile continued into
the body), the velocity gradient from its MAC differences (second order at their own positions, interpolated
multilinearly), the tangential Laplacian by central differences of the sampled gradient over one cell. The
acceleration comes from the previous step's velocity: at a moving body along the path of the body's points,
``(u(y) - u_old(y - u_s dt)) / dt - (u_s . grad) u``, so that the surface passing a fixed point does not enter the
difference (on a translating Couette flow 1.2-1.5 times smaller errors than the difference at fixed points).

**The wall shear** (:func:`momentum_wall_shear`) is read the same way: a polynomial through velocity samples one and
two probe distances out misses the curvature of a boundary layer as thin as the samples' distance (on Hiemenz flow
with a layer two cells thick the one-sided difference through 1.5 and 3 cells reads the shear 12 % low). At a no-slip
surface the fluid moves with the wall, ``Du/Dt = a_s`` (the acceleration of the surface point), so the momentum
equation there reads ``nu lap u = grad p + a_s`` (kinematic pressure). The relative velocity ``w = u - u_s`` vanishes
on the whole surface and the rigid ``u_s`` has no Laplacian, so along the normal ``lap u = d_nn w + K d_n w`` with
``K = div n`` the surface's total curvature. Along the normal line the tangential part of ``w`` is therefore

    ``w(s) = A s + (G - K A) s^2 / 2 + C s^3 + O(s^4)``,   ``G = (grad p + a_s)_t / nu``,

and the two samples give the wall gradient ``A`` and ``C``. ``G`` takes the tangential pressure gradient at the first
sample (central differences over one cell of the interpolated pressure; across a boundary layer the pressure varies
little), ``K`` central differences of the normal over half a cell, ``a_s`` central differences in time along the body
point's path. The samples' multilinear interpolation errs by ``O(h^2)``, which is ``O(h)`` in the gradient: it is
subtracted with the Hessian of the fitted profile in the surface's frame (one correction; on circular Couette flow
orders 2.4-2.8 from 24^2 to 96^2 where the uncorrected samples give first order; on the Hiemenz layers 2-3 % instead
of 5 %).
"""

from __future__ import annotations

import math

import torch

from phisim.errors import ParameterError
from phisim.field import CenteredGrid, StaggeredGrid, sample_padded
from phisim.fluid.bodies import Body, unit_normal
from phisim.fluid.extension import extend_into_bodies

__all__ = ["momentum_wall_pressure", "momentum_wall_shear", "velocity_gradient"]

#: The three-point Gauss-Legendre rule on [0, 1]: nodes and weights.
_GAUSS = ((0.5 - 0.5 * math.sqrt(0.6), 5.0 / 18.0), (0.5, 8.0 / 18.0), (0.5 + 0.5 * math.sqrt(0.6), 5.0 / 18.0))


def velocity_gradient(velocity: StaggeredGrid) -> list[list[tuple[torch.Tensor, tuple[float, ...]]]]:
    """``G[i][j] = d u_i / d x_j`` of a MAC velocity as ``(values (B, *shape), offsets)``: node ``k`` of the values lies
    at ``lower + (k + offsets) dx``. The diagonal lives at cell centres, ``i != j`` on the edges between faces; all
    are central differences of neighbouring faces (second order at their nodes)."""
    grid = velocity.grid
    out = []
    for i in range(grid.rank):
        u = velocity.values[i]
        row = []
        for j in range(grid.rank):
            n = u.shape[j + 1]
            g = (u.narrow(j + 1, 1, n - 1) - u.narrow(j + 1, 0, n - 1)) / grid.dx[j]
            off = tuple((0.5 if a == j else 0.0) if a == i else (1.0 if a == j else 0.5) for a in range(grid.rank))
            row.append((g, off))
        out.append(row)
    return out


def _sample_nodes(values: torch.Tensor, offsets, grid, x: torch.Tensor) -> torch.Tensor:
    """Multilinear interpolation of node values ``(B, *shape)`` (node ``k`` at ``lower + (k + offsets) dx``) at
    points ``x`` ``(P, d)``; ``(B, P)`` (indices clamped to the array)."""
    lower = torch.tensor(grid.lower, dtype=x.dtype, device=x.device)
    dx = torch.tensor(grid.dx, dtype=x.dtype, device=x.device)
    off = torch.tensor(offsets, dtype=x.dtype, device=x.device)
    index = (x - lower) / dx - off
    b = values.shape[0]
    return sample_padded(values.unsqueeze(1), index.unsqueeze(0).expand(b, -1, -1).contiguous())[:, 0]


def _gradient_at(grad, grid, x: torch.Tensor) -> torch.Tensor:
    """The velocity gradient at points ``x`` ``(P, d)``: ``(B, P, d, d)``."""
    rows = [torch.stack([_sample_nodes(g, off, grid, x) for g, off in row], -1) for row in grad]
    return torch.stack(rows, -2)


def _tangents(n: torch.Tensor) -> list[torch.Tensor]:
    """Unit tangents orthogonal to the unit normals ``n`` ``(P, d)``: one in 2-D, two in 3-D."""
    if n.shape[-1] == 2:
        return [torch.stack([-n[:, 1], n[:, 0]], -1)]
    # a helper axis not parallel to n: the coordinate axis of n's smallest component
    helper = torch.zeros_like(n)
    helper.scatter_(1, n.abs().argmin(1, keepdim=True), 1.0)
    t1 = torch.linalg.cross(n, helper)
    t1 = t1 / t1.norm(dim=-1, keepdim=True)
    return [t1, torch.linalg.cross(n, t1)]


def _lamb_normal(u: torch.Tensor, g: torch.Tensor, n: torch.Tensor) -> torch.Tensor:
    """``(u x omega) . n`` from the velocity ``(B, d, P)`` and its gradient ``(B, P, d, d)``; ``(B, P)``."""
    if n.shape[-1] == 2:
        omega = g[..., 1, 0] - g[..., 0, 1]  # dv/dx - du/dy
        t = torch.stack([-n[:, 1], n[:, 0]], -1)
        return omega * (u * t.T.unsqueeze(0)).sum(1)
    omega = torch.stack([g[..., 2, 1] - g[..., 1, 2], g[..., 0, 2] - g[..., 2, 0], g[..., 1, 0] - g[..., 0, 1]], 1)
    return (torch.linalg.cross(u, omega, dim=1) * n.T.unsqueeze(0)).sum(1)


def _acceleration(v: StaggeredGrid, old: StaggeredGrid, g: torch.Tensor, body: Body, y: torch.Tensor, t: float,
                  dt: float) -> torch.Tensor:
    """``du/dt`` at points ``y`` ``(B, d, P)`` from the velocity ``v`` and the one a step ``dt`` earlier (both
    continued into the body). At a resting body the backward difference at ``y``; at a moving one the difference along
    the path of the body's points, ``(v(y) - old(y - u_s dt)) / dt - (u_s . grad) v`` (``g`` the gradient of ``v`` at
    ``y``), so that the surface, which passes the fixed point ``y``, does not enter the difference."""
    if body.static:
        return (v.sample(y) - old.sample(y)) / dt
    us = body.velocity_at(y, t).to(y.dtype)  # (P, d)
    moved = (v.sample(y) - old.sample(y - dt * us)) / dt
    return moved - torch.einsum("bpij,pj->bip", g, us)


def momentum_wall_pressure(velocity: StaggeredGrid, pressure: torch.Tensor | None, body: Body, xs: torch.Tensor,
                           n: torch.Tensor, *, viscosity: float, time: float = 0.0,
                           previous: StaggeredGrid | None = None, dt: float | None = None,
                           distance: float = 2.0) -> torch.Tensor:
    """The kinematic pressure (pressure over density) at surface points of a no-slip ``body`` (module docstring).

    Args:
        velocity: MAC velocity.
        pressure: ``(B, P)`` kinematic pressure at ``xs + distance * h * n`` (sampled by the caller), or None for the
            correction alone (what is added to the pressure there).
        body: The body whose surface carries the points (its velocity on the surface; a sharp no-slip body's velocity
            is continued into it before sampling).
        xs: ``(P, d)`` points on the surface.
        n: ``(P, d)`` unit outward normals of the body there.
        viscosity: Kinematic viscosity.
        time: Time of ``velocity``.
        previous: The velocity one step ``dt`` earlier (the acceleration term), or None (a steady flow: omitted).
        dt: The step between ``previous`` and ``velocity``.
        distance: ``d`` in cells (of the smallest spacing).

    Returns:
        ``(B, P)``.
    """
    grid = velocity.grid
    h = min(grid.dx)
    d = distance * h
    work = velocity.dtype
    xs, n = xs.to(work), n.to(work)
    v = extend_into_bodies(velocity, [body], time)
    grad = velocity_gradient(v)
    x1 = xs + d * n
    u1 = v.sample(x1)  # (B, d, P)
    g1 = _gradient_at(grad, grid, x1)
    us = body.velocity_at(xs, time).to(work).T.unsqueeze(0) if not body.static else torch.zeros_like(u1)
    out = 0.5 * ((u1 * u1).sum(1) - (us * us).sum(1))
    out = out - float(viscosity) * torch.einsum("bpij,pi,pj->bp", g1, n, n)
    tangents = _tangents(n)
    old = None
    if previous is not None:
        old = extend_into_bodies(previous, [body], time - float(dt))
    for s, weight in _GAUSS:
        y = xs + (s * d) * n
        u = v.sample(y)
        g = _gradient_at(grad, grid, y)
        term = -_lamb_normal(u, g, n)
        for t in tangents:  # d/ds of d u_n / ds along the tangent t, central over one cell
            plus = _gradient_at(grad, grid, y + h * t)
            minus = _gradient_at(grad, grid, y - h * t)
            lap = (torch.einsum("bpij,pi,pj->bp", plus, n, t) - torch.einsum("bpij,pi,pj->bp", minus, n, t)) / (2 * h)
            term = term - float(viscosity) * lap
        if old is not None:
            term = term + (_acceleration(v, old, g, body, y, time, float(dt)) * n.T.unsqueeze(0)).sum(1)
        out = out + (weight * d) * term
    return out if pressure is None else pressure + out


def _surface_acceleration(body: Body, xs: torch.Tensor, t: float, eps: float = 1e-4) -> torch.Tensor:
    """The acceleration ``(P, d)`` of the body's points at ``xs`` (central differences in time along their paths)."""
    us = body.velocity_at(xs, t).to(xs.dtype)
    ahead = body.velocity_at(xs + eps * us, t + eps).to(xs.dtype)
    behind = body.velocity_at(xs - eps * us, t - eps).to(xs.dtype)
    return (ahead - behind) / (2 * eps)


def _curvature(body: Body, xs: torch.Tensor, t: float, h: float) -> torch.Tensor:
    """``div n`` ``(P,)`` at ``xs``: central differences of the unit normal over ``h / 2``."""
    e = 0.5 * h
    k = torch.zeros_like(xs[:, 0])
    for i in range(xs.shape[1]):
        step = torch.zeros_like(xs[0])
        step[i] = e
        k = k + (unit_normal(body, xs + step, t, 1e-3 * h)[:, i] - unit_normal(body, xs - step, t, 1e-3 * h)[:, i]) / (
            2 * e)
    return k


def momentum_wall_shear(velocity: StaggeredGrid, pressure: CenteredGrid, body: Body, xs: torch.Tensor,
                        n: torch.Tensor, *, viscosity: float, dt: float, time: float = 0.0,
                        distance: float = 1.5) -> torch.Tensor:
    """``d(u - u_s)/dn`` at surface points of a no-slip ``body``, read with the momentum balance at the wall (module
    docstring): ``(B, d, P)``, tangential to the surface (its normal part vanishes on a rigid no-slip surface).

    Args:
        velocity: MAC velocity.
        pressure: The step's pressure potential ``dt * p / density``.
        body: The body whose surface carries the points.
        xs: ``(P, d)`` points on the surface.
        n: ``(P, d)`` unit outward normals there.
        viscosity: Kinematic viscosity ``> 0``.
        dt: The step of ``pressure``'s potential.
        time: Time of ``velocity``.
        distance: The first sample's distance from the surface in cells (of the smallest spacing); the second is
            twice as far.

    Raises:
        ParameterError: For a viscosity that is not a positive finite number.
    """
    if not math.isfinite(float(viscosity)) or float(viscosity) <= 0:
        raise ParameterError(f"the momentum reading of the wall shear needs a viscosity > 0, got {viscosity!r}")
    grid = velocity.grid
    h = min(grid.dx)
    work = velocity.dtype
    xs, n = xs.to(work), n.to(work)
    d1, d2 = distance * h, 2 * distance * h
    x1, x2 = xs + d1 * n, xs + d2 * n
    if body.static:
        us1 = us2 = 0.0
        acc = torch.zeros_like(xs)
    else:
        us1 = body.velocity_at(x1, time).to(work).T.unsqueeze(0)
        us2 = body.velocity_at(x2, time).to(work).T.unsqueeze(0)
        acc = _surface_acceleration(body, xs, float(time))
    nt = n.T.unsqueeze(0)  # (1, d, P)

    def tangential(w):
        return w - (w * nt).sum(1, keepdim=True) * nt

    raw1, raw2 = velocity.sample(x1) - us1, velocity.sample(x2) - us2  # (B, d, P)
    g = acc.T.unsqueeze(0).to(work)  # kinematic pressure gradient plus the wall's acceleration, (B, d, P)
    tangents = _tangents(n)
    for t in tangents:
        ds = (pressure.sample(x1 + h * t) - pressure.sample(x1 - h * t)) / (2 * h * float(dt))  # (B, P)
        g = g + ds.unsqueeze(1) * t.T.unsqueeze(0)
    g = tangential(g) / float(viscosity)
    k = _curvature(body, xs, float(time), h)  # (P,)
    e1, e2 = d1 - k * d1 * d1 / 2, d2 - k * d2 * d2 / 2
    den = e1 * d2**3 - e2 * d1**3

    def fit(w1, w2):
        """``A`` and ``C`` of ``r_j = A (d_j - K d_j^2 / 2) + C d_j^3`` (``r_j`` the samples less ``G d_j^2 / 2``)."""
        r1 = tangential(w1) - g * (d1 * d1 / 2)
        r2 = tangential(w2) - g * (d2 * d2 / 2)
        return (r1 * d2**3 - r2 * d1**3) / den, (e1 * r2 - e2 * r1) / den

    a, c = fit(raw1, raw2)
    # the multilinear interpolation of a sample reads w + sum_i f_i (1 - f_i) h_i^2 / 2 d_ii w: O(h^2) in w, O(h) in
    # the gradient; one correction with the Hessian of w from the fit, in the frame (n, t_k) of the surface point:
    # d_nn w from the profile (tangential part) and from w_n = beta s^2 + gamma s^3 (normal part; d_n w_n = 0 on a
    # rigid no-slip surface), d_tt w = kappa_k d_n w (a tangent line leaves the parallel surface through the sample
    # by kappa t^2 / 2; kappa_k its normal curvatures, taken as K / (d - 1) / (1 + s K / (d - 1)): exact on circles and
    # spheres) and d_nt w = -kappa_k (A . t_k) n (the tangent turns along the surface)
    wn1, wn2 = (raw1 * nt).sum(1, keepdim=True), (raw2 * nt).sum(1, keepdim=True)
    beta = (wn1 * d2**3 - wn2 * d1**3) / (d1 * d1 * d2**3 - d2 * d2 * d1**3)
    gamma = (wn2 - beta * d2 * d2) / d2**3
    kt = k / (grid.rank - 1)

    def corrected(raw, x, dist):
        om = _interpolation_weights(grid, x)  # (d_j, d_i, P)
        dnn = g - k * a + 6 * c * dist + (2 * beta + 6 * gamma * dist) * nt
        err = torch.einsum("jip,pi->jp", om, n * n).unsqueeze(0) * dnn
        dn = a + (g - k * a) * dist + 3 * c * dist * dist + 2 * beta * dist * nt  # d_n w at the sample
        ks = kt / (1 + kt * dist)  # the curvature of the parallel surface through the sample
        for t in tangents:
            err = err + (ks * torch.einsum("jip,pi->jp", om, t * t)).unsqueeze(0) * dn
            turn = -(ks * (a * t.T.unsqueeze(0)).sum(1))  # (B, P)
            err = err + 2 * turn.unsqueeze(1) * torch.einsum("jip,pi->jp", om, n * t).unsqueeze(0) * nt
        return raw - err

    a, _ = fit(corrected(raw1, x1, d1), corrected(raw2, x2, d2))
    return a


def _interpolation_weights(grid, x: torch.Tensor) -> torch.Tensor:
    """``(d_j, d_i, P)``: ``f_i (1 - f_i) h_i^2 / 2`` with ``f_i`` the fractional position of ``x`` along axis ``i``
    in component ``j``'s interpolation cell (faces along ``j``, cell centres along the others): the multilinear
    interpolation of component ``j`` reads ``w_j + sum_i (this) d_ii w_j``."""
    out = []
    for j in range(grid.rank):
        per_axis = []
        for i in range(grid.rank):
            lo, dx = grid.bounds[i][0], grid.dx[i]
            pos = (x[:, i] - lo) / dx - (0.0 if i == j else 0.5)
            f = pos - pos.detach().floor()
            per_axis.append(f * (1 - f) * dx * dx / 2)
        out.append(torch.stack(per_axis, 0))
    return torch.stack(out, 0)
