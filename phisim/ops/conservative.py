"""Finite-volume flux-form transport of cell-centred fields (the ``'conservative'`` advection scheme).

Internal module behind :func:`phisim.ops.advection.conservative`; see its docstring for the scheme. Layout of
one axis of length ``n`` (cells ``0..n-1``, faces ``0..n``): face ``k`` lies between cells ``k-1`` and
``k``; the flux through it is ``u_k^+ L_k + u_k^- R_k`` with ``L_k`` the reconstructed value of cell
``k-1`` at its upper face and ``R_k`` that of cell ``k`` at its lower face.

References: van Leer (1979), "Towards the ultimate conservative difference scheme V", J. Comput. Phys. 32
(MUSCL, limited slopes); Gottlieb & Shu (1998), "Total variation diminishing Runge-Kutta schemes", Math.
Comp. 67 (SSP-RK2); positivity of MUSCL under a halved Courant number, e.g. LeVeque (2002), *Finite Volume
Methods for Hyperbolic Problems*, section 6.12 and 20.
"""

from __future__ import annotations

import math

import torch

from phisim.boundary import pad
from phisim.errors import ParameterError, ShapeError
from phisim.field import CenteredGrid, StaggeredGrid

_LIMITERS = ("van_leer", "mc", "minmod", None)


def _limited_slope(dm: torch.Tensor, dp: torch.Tensor, limiter: str | None) -> torch.Tensor:
    """Cell slope (a value difference across the cell) from the one-sided differences ``dm``, ``dp``."""
    if limiter is None:
        return 0.5 * (dm + dp)
    prod = dm * dp
    if limiter == "van_leer":
        # 2 dm dp / (dm + dp) where both have the same sign, else 0 (the denominator is then safe)
        same = prod > 0
        den = torch.where(same, dm + dp, torch.ones_like(dm))
        return torch.where(same, 2 * prod / den, torch.zeros_like(dm))
    sign = torch.sign(dm)
    same = (prod > 0).to(dm.dtype)
    if limiter == "minmod":
        return same * sign * torch.minimum(dm.abs(), dp.abs())
    # monotonised central: minmod(2 dm, (dm + dp) / 2, 2 dp)
    m = torch.minimum(torch.minimum(2 * dm.abs(), 2 * dp.abs()), 0.5 * (dm + dp).abs())
    return same * sign * m


def _face_velocity(velocity, axis: int, batch: int) -> torch.Tensor:
    """Normal velocity ``(B or 1, *face_shape(axis))`` on the faces normal to ``axis``."""
    if isinstance(velocity, StaggeredGrid):
        return velocity.values[axis]
    grid = velocity.grid
    p = pad(velocity.values, velocity.boundary, grid.dx, 1, vector=True, axes=[axis])[:, axis]
    dim = 1 + axis
    n = p.shape[dim] - 1
    return 0.5 * (p.narrow(dim, 0, n) + p.narrow(dim, 1, n))


class _AxisData:
    """What one axis needs for every stage: face velocity split by sign, boundary rules per channel."""

    def __init__(self, field: CenteredGrid, velocity, axis: int, vector_like: bool):
        self.axis = axis
        self.dim = 2 + axis  # values are (B, C, *res)
        self.periodic = field.boundary.is_periodic(axis)
        u = _face_velocity(velocity, axis, field.batch_size).to(field.dtype).unsqueeze(1)
        self.up = torch.clamp(u, min=0)
        self.um = torch.clamp(u, max=0)
        self.dx = field.grid.dx[axis]
        self.vector_like = vector_like
        if not self.periodic:
            channels = field.grid.rank if vector_like else 1
            odd = []
            for side in range(2):
                cond = field.boundary.sides[axis][side]
                rules = [cond.rule("scalar" if not vector_like else ("normal" if c == axis else "tangential"),
                                   c if vector_like else None) for c in range(channels)]
                odd.append([r[0] == "odd" for r in rules])
            self.odd = odd

    def outflow_rate(self) -> torch.Tensor:
        """Per cell ``(max(u_hi, 0) + max(-u_lo, 0)) / dx``, shape ``(B or 1, 1, *res)``."""
        n = self.up.shape[self.dim] - 1
        return (self.up.narrow(self.dim, 1, n) - self.um.narrow(self.dim, 0, n)) / self.dx

    def outside(self, q: torch.Tensor, boundary, grid_dx, side: int) -> torch.Tensor:
        """Inflow value beyond ``side``: the face value (odd rules) or the ghost (even rules)."""
        a, dim = self.axis, self.dim
        B, C = q.shape[:2]
        if self.vector_like:
            g = pad(q, boundary, grid_dx, 1, vector=True, axes=[a])
        else:
            g = pad(q.reshape(B * C, *q.shape[2:]), boundary, grid_dx, 1, axes=[a])
            g = g.reshape(B, C, *g.shape[1:])
        n = g.shape[dim]
        ghost = g.narrow(dim, 0 if side == 0 else n - 1, 1)
        inside = q.narrow(dim, 0 if side == 0 else q.shape[dim] - 1, 1)
        odd = self.odd[side]
        if all(odd):
            return 0.5 * (ghost + inside)
        if not any(odd):
            return ghost
        mask = torch.tensor(odd, device=q.device).reshape(1, -1, *([1] * (q.ndim - 2)))
        return torch.where(mask, 0.5 * (ghost + inside), ghost)


def _rate(q: torch.Tensor, field: CenteredGrid, axes: list[_AxisData], limiter) -> torch.Tensor:
    """``-∇·(u q)`` of values ``(B, C, *res)`` by limited upwind fluxes."""
    out = None
    for ax in axes:
        dim = ax.dim
        n = q.shape[dim]
        if ax.periodic:
            ext = torch.cat([q.narrow(dim, n - 2, 2), q, q.narrow(dim, 0, 2)], dim=dim)  # cells -2..n+1
        else:
            lo, hi = q.narrow(dim, 0, 1), q.narrow(dim, n - 1, 1)
            ext = torch.cat([lo, lo, q, hi, hi], dim=dim)  # replicated: boundary cells get zero slope
        d = ext.narrow(dim, 1, n + 3) - ext.narrow(dim, 0, n + 3)  # d[j] = ext[j+1] - ext[j]
        s = _limited_slope(d.narrow(dim, 0, n + 2), d.narrow(dim, 1, n + 2), limiter)  # cells -1..n
        c = ext.narrow(dim, 1, n + 2)
        upper = c + 0.5 * s  # value of cell k-1 at face k (k = 0..n+1)
        lower = c - 0.5 * s  # value of cell k at face k
        left = upper.narrow(dim, 0, n + 1)
        right = lower.narrow(dim, 1, n + 1)
        if not ax.periodic:
            left = torch.cat([ax.outside(q, field.boundary, field.grid.dx, 0), left.narrow(dim, 1, n)], dim=dim)
            right = torch.cat([right.narrow(dim, 0, n), ax.outside(q, field.boundary, field.grid.dx, 1)],
                              dim=dim)
        flux = ax.up * left + ax.um * right
        div = (flux.narrow(dim, 1, n) - flux.narrow(dim, 0, n)) / ax.dx
        out = -div if out is None else out - div
    return out


def conservative_step(field: CenteredGrid, velocity, dt, *, limiter: str | None, cfl: float) -> CenteredGrid:
    """The conservative scheme of :func:`phisim.ops.advection.conservative` (arguments validated by ``advect``).

    Raises:
        ParameterError: For an unknown limiter or a bad ``cfl``.
        ShapeError: For mismatched batch sizes.
    """
    if limiter not in _LIMITERS:
        raise ParameterError(f"unknown limiter {limiter!r}; choose one of {_LIMITERS}")
    if not (isinstance(cfl, (int, float)) and math.isfinite(cfl) and cfl > 0):
        raise ParameterError(f"cfl must be a finite number > 0, got {cfl!r}")
    grid = field.grid
    values = field.values if field.is_vector else field.values.unsqueeze(1)
    vector_like = field.is_vector and values.shape[1] == grid.rank
    vb = velocity.batch_size
    if vb not in (1, field.batch_size):
        raise ShapeError(
            f"velocity batch size {vb} does not match the field's batch size {field.batch_size} (nor is it 1)"
        )
    axes = [_AxisData(field, velocity, a, vector_like) for a in range(grid.rank)]
    if float(dt) == 0:
        return field
    with torch.no_grad():
        rate = sum(ax.outflow_rate() for ax in axes)
        courant = float(rate.max()) * float(dt)
    substeps = max(1, math.ceil(courant / cfl - 1e-12))
    h = dt / substeps
    q = values
    for _ in range(substeps):
        q1 = q + h * _rate(q, field, axes, limiter)
        q = 0.5 * (q + q1 + h * _rate(q1, field, axes, limiter))
    # The update keeps a non-negative field non-negative in exact arithmetic (cfl <= 1/2). Round-off in the flux
    # differences can still leave values like -1e-80 where a nearly empty cell borders fuller ones; negatives
    # within 64 ulp of the field's largest value are set to zero (a change of the total below its round-off).
    # Larger ones (a Courant number beyond the bound) are left visible.
    if float(values.detach().min()) >= 0:
        tol = 64 * torch.finfo(q.dtype).eps * float(values.detach().max())
        q = q.masked_fill((q < 0) & (q >= -tol), 0.0)
    return field.with_values(q if field.is_vector else q[:, 0])
