"""Argument handling and the second-order cell-centred stencil behind :mod:`phisim.solvers.poisson` (internal).

Boundary kinds per axis side (``'periodic'``, ``'dirichlet'``, ``'neumann'``), cell sizes, right-hand sides and
boundary values are checked here; the stencil ``∇²_h u = L₀ u + b`` is split into its zero-value part ``L₀`` and
the boundary source ``b``. :mod:`phisim.solvers.poisson` re-exports the public names (``AXIS_KINDS``,
``normalize_kinds``, ``boundary_source``, ``stencil_laplacian``).
"""

from __future__ import annotations

import math
from functools import lru_cache

import numpy as np
import torch

from phisim.checks import all_finite
from phisim.errors import BoundaryError, NonFiniteError, ParameterError, ShapeError

#: Kinds accepted per side of an axis.
AXIS_KINDS = ("periodic", "dirichlet", "neumann")

# ----------------------------------------------------------------------------------------------
# argument handling

Kinds = tuple[tuple[str, str], ...]


def normalize_kinds(kinds, rank: int) -> Kinds:
    """Bring a boundary-kind specification into the form ``((lower, upper), ...)`` per axis.

    Args:
        kinds: One kind for all axes (``'periodic'``, ``'dirichlet'``, ``'neumann'``), or a sequence
            with one entry per axis, each a kind or a ``(lower, upper)`` pair of kinds.
        rank: Number of spatial axes.

    Returns:
        A tuple of ``(lower, upper)`` kind pairs, one per axis.

    Raises:
        BoundaryError: For unknown kinds, a wrong number of axes, or periodic on one side only.
    """
    if isinstance(kinds, str):
        kinds = (kinds,) * rank
    kinds = tuple(kinds)
    if len(kinds) != rank:
        raise BoundaryError(f"kinds has {len(kinds)} entries for {rank} spatial axes: {kinds}")
    out = []
    for axis, k in enumerate(kinds):
        pair = (k, k) if isinstance(k, str) else tuple(k)
        if len(pair) != 2:
            raise BoundaryError(f"axis {axis}: expected a kind or a (lower, upper) pair, got {k!r}")
        pair = tuple(str(p).lower() for p in pair)
        for p in pair:
            if p not in AXIS_KINDS:
                raise BoundaryError(f"axis {axis}: unknown boundary kind {p!r}; expected one of {AXIS_KINDS}")
        if (pair[0] == "periodic") != (pair[1] == "periodic"):
            raise BoundaryError(f"axis {axis}: periodic must be used on both sides, got {pair}")
        out.append(pair)
    return tuple(out)


def _normalize_dx(dx, rank: int) -> tuple[float, ...]:
    if isinstance(dx, torch.Tensor) and dx.numel() == 1:
        dx = float(dx)
    if isinstance(dx, (int, float, np.number)) and not isinstance(dx, bool):
        dx = (float(dx),) * rank
    try:
        dx = tuple(float(d) for d in dx)
    except (TypeError, ValueError) as exc:
        raise ParameterError(f"dx must be a positive number or one per axis, got {dx!r}") from exc
    if len(dx) != rank:
        raise ParameterError(f"dx has {len(dx)} entries for {rank} spatial axes")
    for d in dx:
        if not math.isfinite(d) or d <= 0:
            raise ParameterError(f"dx must be finite and > 0, got {dx}")
        if d < _MIN_DX:
            raise ParameterError(
                f"dx = {d:g} is so small that 1/dx^2 overflows float32 (the stencil would give NaN); "
                "rescale the domain, e.g. work in units where dx is near 1"
            )
    return dx


#: Smallest accepted cell size: ``1/dx**2`` must stay finite in float32 with room for the stencil sums.
_MIN_DX = 1e-18


def _check_rhs(rhs: torch.Tensor, name: str = "rhs") -> int:
    if not isinstance(rhs, torch.Tensor):
        raise ParameterError(
            f"{name} must be a torch.Tensor of shape (B, *resolution), got {type(rhs).__name__}"
        )
    if rhs.dtype not in (torch.float32, torch.float64):
        raise ParameterError(f"{name} must be float32 or float64, got {rhs.dtype}")
    rank = rhs.ndim - 1
    if rhs.numel() == 0 and rhs.ndim >= 1:
        raise ShapeError(f"{name} is empty (shape {tuple(rhs.shape)}); it needs at least one sample and one cell")
    if not 1 <= rank <= 3:
        raise ShapeError(
            f"{name} must have shape (B, *resolution) with 1-3 spatial axes, got {tuple(rhs.shape)}; "
            "add a batch axis with rhs[None] if needed"
        )
    return rank


def _is_zero(v) -> bool:
    return v is None or (isinstance(v, (int, float)) and v == 0)


def _normalize_values(values, rank: int, kinds: Kinds):
    if values is None:
        return tuple((None, None) for _ in range(rank))
    values = tuple(values)
    if len(values) != rank:
        raise BoundaryError(
            f"values has {len(values)} entries for {rank} spatial axes; give one "
            "(lower, upper) pair per axis (None for zero)"
        )
    out = []
    for axis, v in enumerate(values):
        pair = (None, None) if v is None else tuple(v)
        if len(pair) != 2:
            raise BoundaryError(f"values[{axis}] must be a (lower, upper) pair, got {v!r}")
        if kinds[axis][0] == "periodic" and not all(_is_zero(p) for p in pair):
            raise BoundaryError(f"axis {axis} is periodic and cannot carry boundary values {pair}")
        out.append(pair)
    return tuple(out)


# ----------------------------------------------------------------------------------------------
# boundary terms and the stencil


def _slab(x: torch.Tensor, dim: int, index: int) -> torch.Tensor:
    return x.narrow(dim, index, 1)


def boundary_source(like: torch.Tensor, dx, kinds, values) -> torch.Tensor | None:
    """The contribution of non-zero boundary values to the stencil: ``∇²_h u = L₀ u + b``.

    ``b`` is non-zero only in boundary cells: ``2 v / dx²`` for a Dirichlet value ``v`` on the face,
    ``g / dx`` for a Neumann flux ``g`` (outward normal derivative).

    Args:
        like: Tensor ``(B, *resolution)`` giving shape, dtype and device.
        dx: Spacing (float or one per axis).
        kinds: Boundary kinds (see :func:`normalize_kinds`).
        values: None, or per axis a ``(lower, upper)`` pair of values (None/0, a float, or a tensor
            broadcastable to the boundary slab ``(B, *resolution)`` with the axis of length 1).

    Returns:
        ``b`` with the shape of ``like``, or None when every value is zero.

    Raises:
        BoundaryError: For values on periodic axes or malformed values.
        ShapeError: If a value tensor does not broadcast to its boundary slab.
    """
    rank = like.ndim - 1
    kinds = normalize_kinds(kinds, rank)
    dx = _normalize_dx(dx, rank)
    values = _normalize_values(values, rank, kinds)
    b = None
    for a in range(rank):
        for side, v in enumerate(values[a]):
            if _is_zero(v):
                continue
            kind = kinds[a][side]
            coef = 2.0 / dx[a] ** 2 if kind == "dirichlet" else 1.0 / dx[a]
            slab_shape = list(like.shape)
            slab_shape[1 + a] = 1
            try:
                vt = torch.as_tensor(v, dtype=like.dtype, device=like.device)
            except (TypeError, ValueError, RuntimeError) as exc:
                raise BoundaryError(
                    f"boundary value on axis {a} side {'lower' if side == 0 else 'upper'} must be a number or "
                    f"a real tensor, got {v!r}"
                ) from exc
            if not all_finite(vt):
                raise NonFiniteError(
                    f"boundary value on axis {a} side {'lower' if side == 0 else 'upper'} contains NaN or Inf"
                )
            try:
                vt = torch.broadcast_to(vt, slab_shape)
            except RuntimeError as exc:
                raise ShapeError(
                    f"boundary value on axis {a} side {'lower' if side == 0 else 'upper'} has shape "
                    f"{tuple(vt.shape)}, not broadcastable to the slab {tuple(slab_shape)}"
                ) from exc
            pads = [0, 0] * rank
            n = like.shape[1 + a]
            # F.pad lists the last axis first
            j = 2 * (rank - 1 - a)
            pads[j + (0 if side == 0 else 1)] = 0
            pads[j + (1 if side == 0 else 0)] = n - 1
            term = torch.nn.functional.pad(vt * coef, pads)
            b = term if b is None else b + term
    return b


def stencil_laplacian(u: torch.Tensor, dx, kinds, values=None) -> torch.Tensor:
    """The second-order cell-centred Laplacian ``∇²_h u`` with face boundary conditions.

    Args:
        u: Tensor ``(B, *resolution)``.
        dx: Spacing (float or one per axis).
        kinds: Boundary kinds (see :func:`normalize_kinds`).
        values: Boundary values (see :func:`boundary_source`); None for zero.

    Returns:
        ``Σ_axes (u_{i-1} - 2 u_i + u_{i+1}) / dx²`` with ghosts ``2v - u`` (Dirichlet), ``u + g dx``
        (Neumann) or the periodic image; same shape as ``u``.

    Raises:
        BoundaryError, ParameterError, ShapeError: For invalid kinds, dx, values or shapes.
    """
    rank = _check_rhs(u, "u")
    kinds = normalize_kinds(kinds, rank)
    dx = _normalize_dx(dx, rank)
    out = _laplace_zero(u, dx, kinds)
    b = boundary_source(u, dx, kinds, values)
    return out if b is None else out + b


@lru_cache(maxsize=64)
def _stencil_diagonal(res: tuple[int, ...], dx: tuple[float, ...], kinds: Kinds, dtype: torch.dtype,
                      device: torch.device) -> torch.Tensor:
    """Diagonal of the zero-value stencil ``(*res)``: ``-2/dx²`` per axis, ``-3/dx²`` in a cell beside a
    Dirichlet side (ghost ``-u``), ``-1/dx²`` beside a Neumann side (ghost ``u``)."""
    diag = torch.zeros(res, dtype=torch.float64)
    for a, (lo, hi) in enumerate(kinds):
        d = torch.full((res[a],), -2.0, dtype=torch.float64)
        if lo != "periodic":
            d[0] += -1.0 if lo == "dirichlet" else 1.0
            d[-1] += -1.0 if hi == "dirichlet" else 1.0
        shape = [1] * len(res)
        shape[a] = res[a]
        diag = diag + d.reshape(shape) / dx[a] ** 2
    return diag.to(dtype=dtype, device=device)


def _laplace_fused(u: torch.Tensor, dx, kinds: Kinds) -> torch.Tensor:
    """The zero-value stencil as one product with its diagonal plus two shifted adds per axis (periodic
    axes two more for the wrap): the same sums as the face-flux form, in a quarter of the passes."""
    res = tuple(u.shape[1:])
    out = u * _stencil_diagonal(res, tuple(dx), kinds, u.dtype, u.device)
    for a, (lo, _) in enumerate(kinds):
        dim, n, h = 1 + a, res[a], 1.0 / dx[a] ** 2
        if n > 1:
            out.narrow(dim, 0, n - 1).add_(u.narrow(dim, 1, n - 1), alpha=h)
            out.narrow(dim, 1, n - 1).add_(u.narrow(dim, 0, n - 1), alpha=h)
        if lo == "periodic":
            out.narrow(dim, 0, 1).add_(u.narrow(dim, n - 1, 1), alpha=h)
            out.narrow(dim, n - 1, 1).add_(u.narrow(dim, 0, 1), alpha=h)
    return out


def _laplace_zero(u: torch.Tensor, dx, kinds: Kinds, open_faces=None) -> torch.Tensor:
    """Stencil with zero boundary values; ``open_faces[a]`` (optional) weights interior faces of axis a."""
    if open_faces is None and u.is_floating_point():
        return _laplace_fused(u, dx, kinds)
    out = torch.zeros_like(u)
    for a, (lo, hi) in enumerate(kinds):
        dim = 1 + a
        n = u.shape[dim]
        if lo == "periodic":
            flux = (torch.roll(u, -1, dim) - u) / dx[a] ** 2  # face i+1/2, i = 0..n-1 (last wraps)
            if open_faces is not None:
                flux = flux * open_faces[a]
            out = out + flux - torch.roll(flux, 1, dim)
            continue
        inner = (u.narrow(dim, 1, n - 1) - u.narrow(dim, 0, n - 1)) / dx[a] ** 2  # faces 1..n-1
        if open_faces is not None:
            inner = inner * open_faces[a]
        # face differences (u_i - u_{i-1}) / dx^2 at faces 0..n; zero-value ghosts -u (Dirichlet), u (Neumann)
        zero = torch.zeros_like(_slab(u, dim, 0))
        lo_flux = 2 * _slab(u, dim, 0) / dx[a] ** 2 if lo == "dirichlet" else zero
        hi_flux = -2 * _slab(u, dim, n - 1) / dx[a] ** 2 if hi == "dirichlet" else zero
        faces = torch.cat([lo_flux, inner, hi_flux], dim=dim)
        out = out + faces.narrow(dim, 1, n) - faces.narrow(dim, 0, n)
    return out
