"""The second-order cell-centred stencil: one weighted face-flux kernel, and its argument handling.

Boundary kinds per axis side (``'periodic'``, ``'dirichlet'``, ``'neumann'``), cell sizes, right-hand sides and
boundary values are checked here; the stencil ``∇²_h u = L₀ u + b`` is split into its zero-value part ``L₀`` and
the boundary source ``b``.

The kernel is ``div(w grad u)`` with face weights ``w`` (1 in an open box, fluid fractions of cut faces at
bodies): :func:`face_gradient` (zero face values: the ghost is ``-u`` beside a Dirichlet side, the flux 0 beside a
Neumann side, periodic axes wrap), :func:`face_divergence`, and its fused form for weights that do not change,
:func:`weighted_diagonal` + :func:`face_couplings` + :func:`coupled_sum` (one product with the diagonal and two
shifted multiply-adds per axis, a third of the passes over memory). The plain Laplacian
(:func:`laplace_zero`, :func:`stencil_laplacian`), the masked operator of :mod:`phisim.solvers.masked` and the
fluid projection all use these functions.
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
    try:  # repeated specifications come from a small cache (an operator of a solve asks once per application)
        return _normalize_kinds_cached(kinds, rank)
    except TypeError:  # unhashable specification (a list): normalise without the cache
        return _normalize_kinds(kinds, rank)


def _normalize_kinds(kinds, rank: int) -> Kinds:
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


@lru_cache(maxsize=64)
def _normalize_kinds_cached(kinds, rank: int) -> Kinds:
    return _normalize_kinds(kinds, rank)


def normalize_dx(dx, rank: int) -> tuple[float, ...]:
    """``dx`` as one positive float per axis (a number is used for every axis); floats and tuples of floats are
    answered from a small cache."""
    if type(dx) is float or (type(dx) is tuple and all(type(d) is float for d in dx)):
        return _normalize_dx_cached(dx, rank)
    return _normalize_dx(dx, rank)


@lru_cache(maxsize=64)
def _normalize_dx_cached(dx, rank: int) -> tuple[float, ...]:
    return _normalize_dx(dx, rank)


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


def check_rhs(rhs: torch.Tensor, name: str = "rhs") -> int:
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


def is_zero(v) -> bool:
    return v is None or (isinstance(v, (int, float)) and v == 0)


def normalize_values(values, rank: int, kinds: Kinds):
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
        if kinds[axis][0] == "periodic" and not all(is_zero(p) for p in pair):
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
    dx = normalize_dx(dx, rank)
    values = normalize_values(values, rank, kinds)
    b = None
    for a in range(rank):
        for side, v in enumerate(values[a]):
            if is_zero(v):
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
        (Neumann) or the periodic image; same shape as ``u``. The zero-value part is the fused kernel
        (:func:`laplace_fused`: one product with the diagonal, two shifted additions per axis).

    Raises:
        BoundaryError, ParameterError, ShapeError: For invalid kinds, dx, values or shapes.
    """
    rank = check_rhs(u, "u")
    kinds = normalize_kinds(kinds, rank)
    dx = normalize_dx(dx, rank)
    out = laplace_fused(u, dx, kinds)
    if values is None:
        return out
    b = boundary_source(u, dx, kinds, values)
    return out if b is None else out + b


def negative_laplacian(u: torch.Tensor, dx=1.0, kinds="dirichlet") -> torch.Tensor:
    """``-∇²_h u`` with zero boundary values: the symmetric positive (semi-)definite operator of a Poisson solve
    by :func:`phisim.solvers.linalg.cg`, in the fused form of :func:`laplace_fused` with the sign folded into its
    coefficients (no separate negation pass).

    Args:
        u: Tensor ``(B, *resolution)``, float32 or float64.
        dx: Spacing (float or one per axis).
        kinds: Boundary kinds (see :func:`normalize_kinds`); ghost ``-u`` beside a Dirichlet side, ``u``
            beside a Neumann side, the periodic image on a periodic axis.

    Returns:
        ``-stencil_laplacian(u, dx, kinds)`` to rounding; same shape and dtype as ``u``.

    Raises:
        BoundaryError, ParameterError, ShapeError: For invalid kinds, dx or shapes.
    """
    rank = check_rhs(u, "u")
    return _fused(u, normalize_dx(dx, rank), normalize_kinds(kinds, rank), -1.0)


@lru_cache(maxsize=64)
def stencil_diagonal(res: tuple[int, ...], dx: tuple[float, ...], kinds: Kinds, dtype: torch.dtype,
                     device: torch.device) -> torch.Tensor:
    """Diagonal of the zero-value stencil ``(*res)``: ``-2/dx²`` per axis, ``-3/dx²`` in a cell beside a
    Dirichlet side (ghost ``-u``), ``-1/dx²`` beside a Neumann side (ghost ``u``): :func:`weighted_diagonal` of
    unit weights, negated."""
    ones = tuple(torch.ones((1, *(n + 1 if b == a else n for b, n in enumerate(res))), dtype=torch.float64)
                 for a in range(len(res)))
    return (-weighted_diagonal(ones, dx, kinds)[0]).to(dtype=dtype, device=device)


@lru_cache(maxsize=64)
def _negated_diagonal(res: tuple[int, ...], dx: tuple[float, ...], kinds: Kinds, dtype: torch.dtype,
                      device: torch.device) -> torch.Tensor:
    return -stencil_diagonal(res, dx, kinds, dtype, device)


def laplace_fused(u: torch.Tensor, dx, kinds: Kinds) -> torch.Tensor:
    """The zero-value stencil in fused form: one product with the diagonal and two shifted multiply-adds per
    axis (plus two one-cell slabs per periodic axis), written into one output; the same sums as the face-flux
    form in a quarter of the passes. ``dx`` and ``kinds`` are normalised (:func:`normalize_dx`,
    :func:`normalize_kinds`)."""
    return _fused(u, dx, kinds, 1.0)


def _fused(u: torch.Tensor, dx, kinds: Kinds, sign: float) -> torch.Tensor:
    """``sign * ∇²_h u`` (zero values): ``u * (sign * diag)`` plus ``sign / dx²`` times each neighbour."""
    diag, steps = _fused_plan(tuple(u.shape[1:]), tuple(dx), kinds, u.dtype, u.device, sign)
    out = u * diag
    for dim, n, w, periodic in steps:
        if n > 1:
            out.narrow(dim, 0, n - 1).add_(u.narrow(dim, 1, n - 1), alpha=w)
            out.narrow(dim, 1, n - 1).add_(u.narrow(dim, 0, n - 1), alpha=w)
        if periodic:
            out.narrow(dim, 0, 1).add_(u.narrow(dim, n - 1, 1), alpha=w)
            out.narrow(dim, n - 1, 1).add_(u.narrow(dim, 0, 1), alpha=w)
    return out


@lru_cache(maxsize=64)
def _fused_plan(res: tuple[int, ...], dx: tuple[float, ...], kinds: Kinds, dtype: torch.dtype, device: torch.device,
                sign: float):
    """The diagonal of ``sign * ∇²_h`` and per axis ``(dim, n, sign / dx², periodic)``: what :func:`_fused` needs
    besides the field, looked up once per call."""
    diag = (stencil_diagonal if sign > 0 else _negated_diagonal)(res, dx, kinds, dtype, device)
    steps = tuple((1 + a, res[a], sign / (d * d), kinds[a][0] == "periodic") for a, d in enumerate(dx))
    return diag, steps


def laplace_zero(u: torch.Tensor, dx, kinds: Kinds, open_faces=None) -> torch.Tensor:
    """Stencil with zero boundary values; ``open_faces[a]`` (optional) weights the faces of axis ``a`` between
    cells: faces ``1..n-1`` (``n - 1`` along ``a``), or on a periodic axis faces ``1..n`` (``n``, face ``n`` being the
    wrap face). Without weights the fused form; with them ``div(w grad u)`` by :func:`face_gradient` and
    :func:`face_divergence`."""
    if open_faces is None and u.is_floating_point():
        return laplace_fused(u, dx, kinds)
    grads = face_gradient(u, dx, kinds)
    if open_faces is not None:
        weighted = []
        for a, g in enumerate(grads):
            dim, w = 1 + a, open_faces[a]
            if kinds[a][0] == "periodic":  # weights of faces 1..n; face 0 is face n
                n = w.shape[dim]
                full = torch.cat([w.narrow(dim, n - 1, 1), w], dim)
            else:
                shape = list(w.shape)
                shape[dim] = 1
                edge = torch.ones(shape, dtype=w.dtype, device=w.device)
                full = torch.cat([edge, w, edge], dim)
            weighted.append(g * full)
        grads = tuple(weighted)
    return face_divergence(grads, dx)


# ----------------------------------------------------------------------------------------------
# the weighted face-flux kernel


def face_gradient(u: torch.Tensor, dx, kinds: Kinds) -> tuple[torch.Tensor, ...]:
    """Face gradient ``(u_k - u_{k-1}) / dx`` per axis with zero boundary values, shapes ``(B, *face_shape(a))``.

    Dirichlet sides use the ghost ``-u`` (value 0 on the face), Neumann sides give 0, periodic axes wrap (face
    ``n`` repeats face ``0``).
    """
    out = []
    for a, (lo_k, hi_k) in enumerate(kinds):
        dim, n, d = 1 + a, u.shape[1 + a], dx[a]
        inner = (u.narrow(dim, 1, n - 1) - u.narrow(dim, 0, n - 1)) / d
        if lo_k == "periodic":
            g0 = (u.narrow(dim, 0, 1) - u.narrow(dim, n - 1, 1)) / d
            out.append(torch.cat([g0, inner, g0], dim))
            continue
        first, last = u.narrow(dim, 0, 1), u.narrow(dim, n - 1, 1)
        lo = 2 * first / d if lo_k == "dirichlet" else torch.zeros_like(first)
        hi = -2 * last / d if hi_k == "dirichlet" else torch.zeros_like(last)
        out.append(torch.cat([lo, inner, hi], dim))
    return tuple(out)


def face_divergence(flux, dx) -> torch.Tensor:
    """MAC divergence ``sum_a (f_{k+1} - f_k) / dx_a`` of face values ``(B, *face_shape(a))`` per axis."""
    out = None
    for a, f in enumerate(flux):
        dim = 1 + a
        n = f.shape[dim] - 1
        term = (f.narrow(dim, 1, n) - f.narrow(dim, 0, n)) / dx[a]
        out = term if out is None else out + term
    return out


def weighted_diagonal(weights, dx, kinds: Kinds) -> torch.Tensor:
    """Diagonal of ``-div(w grad)`` per cell, ``(B, *res)``: ``sum_a (w_lo + w_hi) / dx_a²`` with the faces on
    Dirichlet sides counted twice (the ghost is ``-u``) and those on Neumann sides not at all.

    Args:
        weights: Per axis ``a`` the face weights ``(B, *face_shape(a))`` (``n_a + 1`` faces along ``a``; on a
            periodic axis face ``n`` is face ``0``).
        dx: Spacing per axis.
        kinds: Normalised kinds.
    """
    d = 0
    for a, w in enumerate(weights):
        dim = 1 + a
        n = w.shape[dim] - 1
        lo, hi = w.narrow(dim, 0, n), w.narrow(dim, 1, n)
        lo_k, hi_k = kinds[a]
        if lo_k == "periodic":
            hi = torch.roll(lo, -1, dim)
        else:
            scale_lo = torch.ones(n, dtype=w.dtype, device=w.device)
            scale_hi = torch.ones(n, dtype=w.dtype, device=w.device)
            scale_lo[0] = 0.0 if lo_k == "neumann" else 2.0
            scale_hi[-1] = 0.0 if hi_k == "neumann" else 2.0
            shape = [1] * w.ndim
            shape[dim] = n
            lo, hi = lo * scale_lo.reshape(shape), hi * scale_hi.reshape(shape)
        d = d + (lo + hi) / dx[a] ** 2
    return d


def face_couplings(weights, dx, kinds: Kinds, dtype: torch.dtype):
    """Off-diagonal couplings of ``div(w grad)``: per axis the interior face weights over ``dx²``
    ``(B, *res with n_a - 1 along a)``, and the periodic wrap face's (None on other axes)."""
    couplings, wrap = [], []
    for a, w in enumerate(weights):
        dim = 1 + a
        n = w.shape[dim] - 1
        couplings.append((w.narrow(dim, 1, n - 1) / dx[a] ** 2).to(dtype).contiguous())
        periodic = kinds[a][0] == "periodic"
        wrap.append((w.narrow(dim, 0, 1) / dx[a] ** 2).to(dtype).contiguous() if periodic else None)
    return tuple(couplings), tuple(wrap)


def coupled_sum(u: torch.Tensor, diag, couplings, wrap, sign: float) -> torch.Tensor:
    """``diag * u + sign * sum_a c_a (u_{k+1} + u_{k-1})``: the fused stencil.

    ``couplings[a]``/``wrap[a]`` are tensors (:func:`face_couplings`) or plain numbers (uniform weights).
    """
    out = u * diag
    for a, c in enumerate(couplings):
        dim, n = 1 + a, u.shape[1 + a]
        pairs = [(out.narrow(dim, 0, n - 1), u.narrow(dim, 1, n - 1), c),
                 (out.narrow(dim, 1, n - 1), u.narrow(dim, 0, n - 1), c)] if n > 1 else []
        if wrap[a] is not None:
            pairs += [(out.narrow(dim, 0, 1), u.narrow(dim, n - 1, 1), wrap[a]),
                      (out.narrow(dim, n - 1, 1), u.narrow(dim, 0, 1), wrap[a])]
        for target, source, weight in pairs:
            if isinstance(weight, torch.Tensor):
                target.addcmul_(weight, source, value=sign)
            else:
                target.add_(source, alpha=sign * weight)
    return out
