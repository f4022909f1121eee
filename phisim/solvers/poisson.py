"""Poisson solves on uniform grids: a fast direct spectral solver and masked-domain PCG.

The discrete problem is ``∇²_h u = f`` with the standard second-order stencil (3 points per axis,
``(u_{i-1} - 2 u_i + u_{i+1}) / dx²``) on cell centres. Boundary values sit on the cell **face**
(phisim's convention, see :mod:`phisim.boundary`): a Dirichlet value ``v`` gives the ghost
``2 v - u_0``, a Neumann flux ``g`` (outward normal derivative) gives ``u_0 + g dx``. Each axis has a
``(lower, upper)`` pair of kinds, and the zero-value problem along it is diagonalised exactly by

==================  ===========  =================================================  ==========
lower / upper       transform    eigenvalue of mode ``k = 0..n-1`` (times dx²)     inverse
==================  ===========  =================================================  ==========
periodic            FFT          ``-4 sin²(π k / n)``                               iFFT
Dirichlet/Dirichlet DST-II       ``-4 sin²(π (k+1) / 2n)``                          DST-III/2n
Neumann/Neumann     DCT-II       ``-4 sin²(π k / 2n)``                              DCT-III/2n
Dirichlet/Neumann   DST-IV       ``-4 sin²(π (2k+1) / 4n)``                         DST-IV/2n
Neumann/Dirichlet   DCT-IV       ``-4 sin²(π (2k+1) / 4n)``                         DCT-IV/2n
==================  ===========  =================================================  ==========

so the solve is a forward transform, a division by the summed eigenvalues and the inverse transform:
``O(N log N)``, exact up to round-off (about 1e-13 relative in float64). Non-zero boundary values
enter the right-hand side: ``f_0 -= 2 v / dx²`` (Dirichlet) and ``f_0 -= g / dx`` (Neumann) in the
boundary cell. The solve is differentiable w.r.t. ``f`` and the boundary values (the operator is
symmetric, and the transforms' adjoints are transforms of the same family; see :mod:`phisim.spectral.fft`).

**Singular problems.** When no axis has a Dirichlet side (all periodic / Neumann), the operator
annihilates constants. A solution exists only if the effective right-hand side has zero sum
(``Σ f = Σ boundary fluxes / dx``). The solver checks this per sample: a mean within
``compat_rtol`` of the rhs's RMS is round-off and is removed; a larger one is reported by
``incompatible='raise'`` (default, :class:`~phisim.errors.ParameterError`), ``'warn'`` (warning, then
removed) or ``'project'`` (removed silently, at the caller's request). The returned solution is the
one with **zero mean**.

**Masked domains** (:func:`masked_poisson_solve`): cells where ``mask`` is False are obstacles,
excluded from the solve; the faces between fluid and obstacle cells are **zero-Neumann** (no flux —
what the pressure of an incompressible flow needs at solid obstacles), and the solution is 0 inside
obstacles. The system ``-∇²_h u = -f`` on the fluid cells is symmetric positive (semi-)definite and
is solved by :func:`phisim.solvers.linalg.cg` with the spectral solver of the obstacle-free box as
preconditioner (``M⁻¹ = mask · (-∇²_box)⁻¹ · mask``, symmetric positive definite on fluid cells).

Reference: the fast diagonalisation method, e.g. Schumann & Sweet (1988), "A direct method for the
solution of Poisson's equation with Neumann boundary conditions on a staggered grid of arbitrary
size", J. Comput. Phys. 75, and Strang (1999), "The discrete cosine transform", SIAM Review 41.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Sequence
from functools import lru_cache

import torch

from phisim.checks import all_finite
from phisim.errors import BoundaryError, NonFiniteError, ParameterError, ShapeError
from phisim.ops.stencil import (
    AXIS_KINDS,
    Kinds,
    _check_rhs,
    _laplace_zero,
    _normalize_dx,
    boundary_source,
    normalize_kinds,
    stencil_laplacian,
)
from phisim.spectral import fft as _fft

__all__ = [
    "AXIS_KINDS",
    "normalize_kinds",
    "laplacian_eigenvalues",
    "stencil_laplacian",
    "boundary_source",
    "spectral_poisson_solve",
    "spectral_apply",
    "masked_poisson_solve",
    "masked_laplacian",
    "solve_poisson",
    "field_kinds_and_values",
]

_TRANSFORM = {
    ("dirichlet", "dirichlet"): ("dst2", "dst3"),
    ("neumann", "neumann"): ("dct2", "dct3"),
    ("dirichlet", "neumann"): ("dst4", "dst4"),
    ("neumann", "dirichlet"): ("dct4", "dct4"),
}

# ----------------------------------------------------------------------------------------------
# eigenvalues and spectral application


def _axis_eigs(
    n: int, pair: tuple[str, str], dx: float, halved: bool, continuous: bool = False
) -> torch.Tensor:
    k = torch.arange(n, dtype=torch.float64)
    if continuous:  # eigenvalues -(wavenumber)^2 of the continuous Laplacian for the same modes
        if pair[0] == "periodic":
            lam = -((2 * math.pi * torch.minimum(k, n - k) / (n * dx)) ** 2)
            return lam[: n // 2 + 1] if halved else lam
        shift = {("dirichlet", "dirichlet"): 1.0, ("neumann", "neumann"): 0.0}.get(pair, 0.5)
        return -((math.pi * (k + shift) / (n * dx)) ** 2)
    if pair[0] == "periodic":
        lam = -4 * torch.sin(math.pi * k / n) ** 2
        if halved:
            lam = lam[: n // 2 + 1]
    elif pair == ("dirichlet", "dirichlet"):
        lam = -4 * torch.sin(math.pi * (k + 1) / (2 * n)) ** 2
    elif pair == ("neumann", "neumann"):
        lam = -4 * torch.sin(math.pi * k / (2 * n)) ** 2
    else:
        lam = -4 * torch.sin(math.pi * (2 * k + 1) / (4 * n)) ** 2
    return lam / dx**2


def _layout(kinds: Kinds) -> tuple[list[int], list[int]]:
    """Spatial axes transformed by real-to-real kinds, and the periodic ones (FFT)."""
    r2r = [a for a, p in enumerate(kinds) if p[0] != "periodic"]
    per = [a for a, p in enumerate(kinds) if p[0] == "periodic"]
    return r2r, per


def laplacian_eigenvalues(
    resolution: Sequence[int],
    dx,
    kinds,
    *,
    dtype: torch.dtype = torch.float64,
    device=None,
    halved: bool = True,
    spectrum: str = "stencil",
) -> torch.Tensor:
    """Eigenvalues of the face-boundary cell-centred Laplacian stencil in the solver's spectral layout.

    Args:
        resolution: Cells per axis.
        dx: Spacing (float or one per axis).
        kinds: Boundary kinds (see :func:`normalize_kinds`).
        dtype: Output dtype.
        device: Output device.
        halved: Whether the last periodic axis is stored as ``n//2 + 1`` rfft bins (solver layout).
        spectrum: ``'stencil'`` (eigenvalues of the discrete stencil, ``-4 sin²(θ/2)/dx²``) or
            ``'continuous'`` (``-κ²`` of the continuous Laplacian for the same modes, ``κ = θ/dx``).

    Returns:
        Tensor of shape ``resolution`` (last periodic axis halved when ``halved``) holding
        ``Σ_axes λ_axis(k_axis)`` (non-positive; units 1/length²).

    Raises:
        BoundaryError: For an invalid kinds specification.
        ParameterError: For an invalid dx.
    """
    resolution = tuple(int(n) for n in resolution)
    rank = len(resolution)
    kinds = normalize_kinds(kinds, rank)
    dx = _normalize_dx(dx, rank)
    _check_spectrum(spectrum)
    return _eigs_cached(
        resolution, dx, kinds, dtype, torch.device(device or "cpu"), halved, spectrum == "continuous"
    )


def _check_spectrum(spectrum: str) -> None:
    if spectrum not in ("stencil", "continuous"):
        raise ParameterError(f"spectrum must be 'stencil' or 'continuous', got {spectrum!r}")


@lru_cache(maxsize=128)
def _eigs_cached(resolution, dx, kinds, dtype, device, halved, continuous=False) -> torch.Tensor:
    _, per = _layout(kinds)
    last_per = per[-1] if per else None
    total = torch.zeros((), dtype=torch.float64)
    for a, n in enumerate(resolution):
        lam = _axis_eigs(n, kinds[a], dx[a], halved and a == last_per, continuous)
        shape = [1] * len(resolution)
        shape[a] = -1
        total = total + lam.reshape(shape)
    return total.to(dtype=dtype, device=device)


def _singular(kinds: Kinds) -> bool:
    return all("dirichlet" not in p for p in kinds)


def spectral_apply(
    x: torch.Tensor, dx, kinds, fn, *, engine: str | None = None, spectrum: str = "stencil"
) -> torch.Tensor:
    """Apply a function of the Laplacian, ``φ(∇²_h) x``, exactly by diagonalisation.

    Args:
        x: Tensor ``(B, *resolution)``, float32/float64.
        dx: Spacing (float or one per axis).
        kinds: Boundary kinds (see :func:`normalize_kinds`); boundary values are zero here.
        fn: Maps the eigenvalue tensor (solver layout, see :func:`laplacian_eigenvalues`, float64)
            to the per-mode multipliers (real, same shape, broadcastable).
        engine: FFT engine (see :func:`phisim.spectral.fft.resolve_engine`).
        spectrum: ``'stencil'`` or ``'continuous'`` eigenvalues (see :func:`laplacian_eigenvalues`).

    Returns:
        ``φ(∇²_h) x``, shape and dtype of ``x``; differentiable w.r.t. ``x``.

    Raises:
        BoundaryError, ParameterError, ShapeError: For invalid kinds, dx or shapes.
    """
    rank = _check_rhs(x, "x")
    kinds = normalize_kinds(kinds, rank)
    dx = _normalize_dx(dx, rank)
    _check_spectrum(spectrum)
    lam = _eigs_cached(tuple(x.shape[1:]), dx, kinds, torch.float64, x.device, True, spectrum == "continuous")
    mult = fn(lam)
    return _apply_multiplier(x, kinds, mult, engine)


def _transform_scale(res, kinds: Kinds) -> float:
    """Normalisation of an unnormalised forward + inverse real-to-real transform pair."""
    r2r, _ = _layout(kinds)
    return 1.0 / math.prod(2 * res[a] for a in r2r) if r2r else 1.0


def _apply_multiplier(x: torch.Tensor, kinds: Kinds, mult: torch.Tensor, engine, prescaled: bool = False
                      ) -> torch.Tensor:
    """Forward transforms, multiply by ``mult`` (multipliers in solver layout), inverse transforms.

    ``mult`` is float64 and gets the transforms' normalisation here, unless ``prescaled`` (then it already
    carries it and has ``x``'s dtype).
    """
    r2r, per = _layout(kinds)
    res = x.shape[1:]
    y = x
    if r2r:
        fwd = tuple(_TRANSFORM[kinds[a]][0] for a in r2r)
        y = _fft.r2rn(y, fwd, tuple(1 + a for a in r2r), engine=engine)
    m = mult if prescaled else (mult * _transform_scale(res, kinds)).to(x.dtype)
    if per:
        axes = tuple(1 + a for a in per)
        Y = _fft.rfftn(y, axes, engine=engine)
        y = _fft.irfftn(Y * m, tuple(res[a] for a in per), axes, engine=engine)
    elif r2r and not (torch.is_grad_enabled() and y.requires_grad):
        y = y.mul_(m)  # y is the transform's fresh output
    else:
        y = y * m
    if r2r:
        inv = tuple(_TRANSFORM[kinds[a]][1] for a in r2r)
        y = _fft.r2rn(y, inv, tuple(1 + a for a in r2r), engine=engine)
    return y


# ----------------------------------------------------------------------------------------------
# the direct solver


def _compat_tol(dtype: torch.dtype) -> float:
    return 1e-4 if dtype == torch.float32 else 1e-9


def _remove_mean(f: torch.Tensor, *, incompatible: str, compat_rtol: float | None, what: str) -> torch.Tensor:
    dims = tuple(range(1, f.ndim))
    mean = f.mean(dim=dims, keepdim=True)
    if incompatible == "project":  # removed silently: no diagnostics to compute
        return f - mean
    tol = _compat_tol(f.dtype) if compat_rtol is None else compat_rtol
    with torch.no_grad():
        rms = f.pow(2).mean(dim=dims).sqrt()
        bad = mean.flatten().abs() > tol * rms
    if bool(bad.any()):
        idx = [int(i) for i in torch.nonzero(bad).flatten()]
        ratio = (mean.flatten().abs() / rms.clamp_min(torch.finfo(f.dtype).tiny)).detach()
        msg = (
            f"{what}: the problem is singular (no Dirichlet side: solutions differ by a constant) and the "
            f"right-hand side including boundary fluxes is incompatible for samples {idx}: its mean is "
            f"{[f'{float(ratio[i]):.3g}' for i in idx]} x its RMS (tolerance {tol:g}). Its sum must equal the"
            " net boundary flux / dx. Fix the data, or pass incompatible='project' (remove the mean) or "
            "'warn'."
        )
        if incompatible == "raise":
            raise ParameterError(msg)
        if incompatible == "warn":
            warnings.warn(msg + " The mean was removed.", RuntimeWarning, stacklevel=3)
    return f - mean


def _check_incompatible(incompatible: str) -> None:
    if incompatible not in ("raise", "warn", "project"):
        raise ParameterError(f"incompatible must be 'raise', 'warn' or 'project', got {incompatible!r}")


def spectral_poisson_solve(
    rhs: torch.Tensor,
    dx=1.0,
    kinds="dirichlet",
    values=None,
    *,
    incompatible: str = "raise",
    compat_rtol: float | None = None,
    engine: str | None = None,
) -> torch.Tensor:
    """Solve ``∇²_h u = rhs`` directly on a rectangular grid (FFT / DST / DCT per axis).

    Exact up to round-off for the standard second-order stencil with boundary values on the cell face
    (see the module docstring for the transform per axis and the eigenvalues).

    Args:
        rhs: Right-hand side ``(B, *resolution)`` (1-3 spatial axes), float32/float64, any device.
        dx: Cell spacing, a float or one per axis.
        kinds: Per axis ``'periodic'``, ``'dirichlet'``, ``'neumann'`` or a ``(lower, upper)`` pair
            (e.g. ``('dirichlet', 'periodic')`` for a 2-D channel); a single string applies to all axes.
        values: None (zero boundary values) or per axis a ``(lower, upper)`` pair: the Dirichlet value
            on the face or the Neumann outward flux ``du/dn``; each None/0, a float, or a tensor
            broadcastable to the boundary slab (``rhs``'s shape with that axis of length 1).
        incompatible: For singular problems (no Dirichlet side): what to do when the effective rhs has
            a mean beyond ``compat_rtol`` x its RMS: ``'raise'`` (ParameterError), ``'warn'`` or
            ``'project'`` (remove the mean silently).
        compat_rtol: Tolerance of that check (default 1e-9 in float64, 1e-4 in float32).
        engine: FFT engine (see :func:`phisim.spectral.fft.resolve_engine`).

    Returns:
        ``u`` with ``rhs``'s shape, dtype and device; for singular problems the zero-mean solution.
        Differentiable w.r.t. ``rhs`` and tensor boundary values.

    Raises:
        ParameterError: Bad dtype/dx/option, or an incompatible rhs with ``incompatible='raise'``.
        BoundaryError: Invalid kinds or values.
        ShapeError: Wrong rhs rank or value shapes.
        NonFiniteError: NaN/Inf in ``rhs``.
    """
    rank = _check_rhs(rhs)
    kinds = normalize_kinds(kinds, rank)
    dx = _normalize_dx(dx, rank)
    _check_incompatible(incompatible)
    if not all_finite(rhs):
        raise NonFiniteError("spectral_poisson_solve: rhs contains NaN or Inf")
    f = rhs
    b = boundary_source(rhs, dx, kinds, values)
    if b is not None:
        f = f - b
    singular = _singular(kinds)
    if singular:
        f = _remove_mean(f, incompatible=incompatible, compat_rtol=compat_rtol, what="spectral_poisson_solve")
    inv = _solve_multiplier(tuple(rhs.shape[1:]), dx, kinds, rhs.device, rhs.dtype)
    return _apply_multiplier(f, kinds, inv, engine, prescaled=True)


def _solve_trusted(rhs: torch.Tensor, dx: tuple[float, ...], kinds: Kinds) -> torch.Tensor:
    """:func:`spectral_poisson_solve` with ``incompatible='project'`` and zero boundary values, for callers
    that pass a finite ``rhs``, normalised ``kinds`` and a float tuple ``dx`` (the pressure projection)."""
    f = rhs
    if _singular(kinds):
        f = f - f.mean(dim=tuple(range(1, f.ndim)), keepdim=True)
    inv = _solve_multiplier(tuple(rhs.shape[1:]), dx, kinds, rhs.device, rhs.dtype)
    return _apply_multiplier(f, kinds, inv, None, prescaled=True)


@lru_cache(maxsize=128)
def _solve_multiplier(resolution, dx, kinds, device, dtype) -> torch.Tensor:
    """Inverse eigenvalues times the transforms' normalisation, in the solve's dtype (cached)."""
    return (_inverse_eigs(resolution, dx, kinds, device) * _transform_scale(resolution, kinds)).to(dtype)


@lru_cache(maxsize=128)
def _inverse_eigs(resolution, dx, kinds, device) -> torch.Tensor:
    lam = _eigs_cached(resolution, dx, kinds, torch.float64, device, True)
    inv = torch.where(lam == 0, torch.zeros_like(lam), 1.0 / torch.where(lam == 0, torch.ones_like(lam), lam))
    if _singular(kinds):
        inv.reshape(-1)[0] = 0.0  # the constant mode (index 0 in every layout) is projected out
    return inv


# ----------------------------------------------------------------------------------------------
# masked domains


def _open_faces(mask: torch.Tensor, kinds: Kinds) -> list[torch.Tensor]:
    faces = []
    for a, (lo, _) in enumerate(kinds):
        dim = 1 + a
        n = mask.shape[dim]
        if lo == "periodic":
            faces.append(mask * torch.roll(mask, -1, dim))
        else:
            faces.append(mask.narrow(dim, 1, n - 1) * mask.narrow(dim, 0, n - 1))
    return faces


def masked_laplacian(u: torch.Tensor, mask: torch.Tensor, dx, kinds, values=None) -> torch.Tensor:
    """The stencil Laplacian on the fluid cells of a masked domain (zero flux through obstacle faces).

    Args:
        u: Tensor ``(B, *resolution)``.
        mask: Fluid indicator, bool or float, shape ``resolution`` or ``(B, *resolution)``; True = fluid.
        dx: Spacing (float or one per axis).
        kinds: Boundary kinds of the box (see :func:`normalize_kinds`).
        values: Boundary values of the box (see :func:`boundary_source`).

    Returns:
        ``∇²_h u`` on fluid cells (obstacle neighbours contribute no flux), 0 on obstacle cells.

    Raises:
        BoundaryError, ParameterError, ShapeError: For invalid arguments.
    """
    rank = _check_rhs(u, "u")
    kinds = normalize_kinds(kinds, rank)
    dx = _normalize_dx(dx, rank)
    m = _mask_tensor(mask, u)
    out = _laplace_zero(u * m, dx, kinds, _open_faces(m, kinds)) * m
    b = boundary_source(u, dx, kinds, values)
    return out if b is None else out + b * m


def _mask_tensor(mask, like: torch.Tensor) -> torch.Tensor:
    try:
        m = torch.as_tensor(mask, device=like.device)
    except (TypeError, ValueError, RuntimeError) as exc:
        raise ParameterError(f"mask must be a bool or 0/1 array, got {type(mask).__name__}") from exc
    if m.ndim == like.ndim - 1:
        m = m[None]
    if (
        m.ndim != like.ndim
        or tuple(m.shape[1:]) != tuple(like.shape[1:])
        or m.shape[0] not in (1, like.shape[0])
    ):
        raise ShapeError(
            f"mask must have shape {tuple(like.shape[1:])} or (B, *resolution) matching "
            f"{tuple(like.shape)}, got {tuple(m.shape)}"
        )
    if m.dtype != torch.bool:
        if m.is_complex() or not bool(((m == 0) | (m == 1)).all()):
            raise ParameterError(
                "mask must hold only 0/1 (False/True): a cell is fluid or not; a fractional mask would "
                "silently scale the operator. Threshold it first, e.g. mask > 0.5"
            )
    return m.to(like.dtype)


def _mask_face_weights(m: torch.Tensor, kinds: Kinds) -> tuple[torch.Tensor, ...]:
    """0/1 face weights of a cell mask: open between two fluid cells and on Dirichlet sides of a fluid cell."""
    out = []
    for a, (lo, hi) in enumerate(kinds):
        dim, n = 1 + a, m.shape[1 + a]
        if lo == "periodic":
            wrap = m.narrow(dim, n - 1, 1) * m.narrow(dim, 0, 1)
            out.append(torch.cat([wrap, m.narrow(dim, 1, n - 1) * m.narrow(dim, 0, n - 1), wrap], dim))
            continue
        inner = m.narrow(dim, 1, n - 1) * m.narrow(dim, 0, n - 1)
        first = m.narrow(dim, 0, 1) if lo == "dirichlet" else torch.zeros_like(m.narrow(dim, 0, 1))
        last = m.narrow(dim, n - 1, 1) if hi == "dirichlet" else torch.zeros_like(m.narrow(dim, 0, 1))
        out.append(torch.cat([first, inner, last], dim))
    return tuple(out)


def masked_poisson_solve(
    rhs: torch.Tensor,
    mask: torch.Tensor,
    dx=1.0,
    kinds="neumann",
    values=None,
    *,
    solve=None,
    x0: torch.Tensor | None = None,
    preconditioner: str | None = "spectral",
    incompatible: str = "raise",
    compat_rtol: float | None = None,
    return_info: bool = False,
    engine: str | None = None,
):
    """Solve ``∇²_h u = rhs`` on the fluid cells of a box with obstacles by preconditioned CG.

    Obstacle cells (``mask`` False) are excluded; faces between fluid and obstacle cells are
    zero-Neumann (no flux), the box sides follow ``kinds``/``values``; ``u`` is 0 in obstacles. The
    solve is :class:`phisim.solvers.masked.MaskedPoisson` with 0/1 face weights (the same operator the
    fluid projection uses): CG on ``-∇²_h`` (symmetric positive (semi-)definite on fluid cells, identity
    on obstacle cells), preconditioned by the exact spectral inverse of the obstacle-free box.

    Every connected fluid region that reaches no Dirichlet side is singular on its own (a closed box, or a
    pocket enclosed by obstacles): its rhs mean is checked as in :func:`spectral_poisson_solve` (per
    region) and the solution has zero mean over each such region.

    Args:
        rhs: Right-hand side ``(B, *resolution)``, float32/float64.
        mask: Fluid indicator (bool/float), shape ``resolution`` or ``(B, *resolution)``.
        dx: Cell spacing (float or one per axis).
        kinds: Box boundary kinds (see :func:`normalize_kinds`); default all Neumann (a closed box).
        values: Box boundary values (see :func:`boundary_source`).
        solve: :class:`phisim.solvers.linalg.Solve` settings (default ``Solve()``: rtol 1e-5).
        x0: Optional start iterate.
        preconditioner: ``'spectral'`` (default) or None (plain CG).
        incompatible: ``'raise'``, ``'warn'`` or ``'project'`` (see :func:`spectral_poisson_solve`).
        compat_rtol: Tolerance of the compatibility check.
        return_info: Also return the :class:`phisim.solvers.linalg.SolveInfo` (iterations per sample).
        engine: FFT engine of the preconditioner.

    Returns:
        ``u`` (shape of ``rhs``), or ``(u, info)`` with ``return_info``. Differentiable w.r.t. ``rhs``
        (implicit adjoint solve).

    Raises:
        SolveError: CG did not converge.
        ParameterError, BoundaryError, ShapeError, NonFiniteError: For invalid input.
    """
    from phisim.solvers.linalg import Solve

    rank = _check_rhs(rhs)
    kinds = normalize_kinds(kinds, rank)
    dx = _normalize_dx(dx, rank)
    _check_incompatible(incompatible)
    if preconditioner not in ("spectral", None):
        raise ParameterError(f"preconditioner must be 'spectral' or None, got {preconditioner!r}")
    if not all_finite(rhs):
        raise NonFiniteError("masked_poisson_solve: rhs contains NaN or Inf")
    solve = Solve() if solve is None else solve
    m = _mask_tensor(mask, rhs)
    if bool((m.flatten(1).sum(1) == 0).any()):
        raise ParameterError("masked_poisson_solve: the mask has no fluid cell in some sample")
    from phisim.solvers.masked import MaskedPoisson

    f = rhs
    b = boundary_source(rhs, dx, kinds, values)
    if b is not None:
        f = f - b
    f = f * m
    op = MaskedPoisson(_mask_face_weights(m, kinds), dx, kinds, engine=engine)
    if op.singular:  # every closed fluid region needs a compatible rhs of its own
        tol = _compat_tol(rhs.dtype) if compat_rtol is None else compat_rtol
        with torch.no_grad():
            z = (op.null > 0).to(f.dtype)
            count = z.flatten(2).sum(-1).clamp_min(1)
            mean = op.region_sums(f) / count
            rms = (op.region_sums(f**2) / count).sqrt()
            bad = (mean.abs() > tol * rms) & (count > 0) & (z.flatten(2).sum(-1) > 0)
        if bool(bad.any()):
            b_i, k_i = (int(v) for v in torch.nonzero(bad)[0])
            msg = (
                f"masked_poisson_solve: singular problem with an incompatible rhs: sample {b_i}, closed fluid "
                f"region {k_i + 1} of {op.null.shape[1]} (a pocket of "
                f"{int(count[min(b_i, count.shape[0] - 1), k_i])} cells, no Dirichlet side) has a rhs mean of "
                f"{float(mean[b_i, k_i]):.3g} (beyond {tol:g} x RMS {float(rms[b_i, k_i]):.3g}). Each region "
                "enclosed by obstacles and closed sides needs a zero net source of its own: fix the data, open "
                "the region, or pass incompatible='project'/'warn' "
                "(the mean of each region is then removed)."
            )
            if incompatible == "raise":
                raise ParameterError(msg)
            if incompatible == "warn":
                warnings.warn(msg, RuntimeWarning, stacklevel=2)
    x, info = op.solve(-f, solve=solve, x0=x0, preconditioned=preconditioner is not None)
    x = x * m
    return (x, info) if return_info else x


# ----------------------------------------------------------------------------------------------
# fields


def field_kinds_and_values(boundary, component: int | None = None) -> tuple[Kinds, tuple]:
    """Translate a :class:`phisim.boundary.Boundary` into per-side kinds and values.

    Each side's ghost rule for the quantity decides: an odd rule (Dirichlet, walls for a normal velocity)
    gives ``'dirichlet'`` with its face value, an even rule (Neumann, walls for a scalar, open)
    ``'neumann'`` with its outward flux, periodic stays periodic.

    Args:
        boundary: A :class:`phisim.boundary.Boundary`.
        component: ``None`` for a scalar; else the velocity component (normal to its own axis,
            tangential to the others).

    Returns:
        ``(kinds, values)`` as accepted by :func:`spectral_poisson_solve`.

    Raises:
        BoundaryError: For a rule this solver does not know.
    """
    kinds, values = [], []
    for axis, (lo, hi) in enumerate(boundary.sides):
        role = "scalar" if component is None else ("normal" if component == axis else "tangential")
        pk, pv = [], []
        for cond in (lo, hi):
            rule = cond.rule(role, component)
            if rule[0] == "periodic":
                pk.append("periodic")
                pv.append(None)
            elif rule[0] in ("odd", "even"):
                pk.append("dirichlet" if rule[0] == "odd" else "neumann")
                pv.append(rule[1])
            else:
                raise BoundaryError(f"boundary condition {cond!r} has an unknown ghost rule {rule!r}")
        kinds.append(tuple(pk))
        values.append(tuple(pv))
    return tuple(kinds), tuple(values)


def solve_poisson(
    rhs,
    *,
    mask=None,
    solve=None,
    incompatible: str = "raise",
    compat_rtol: float | None = None,
    engine: str | None = None,
    return_info: bool = False,
):
    """Solve ``∇² u = rhs`` for a scalar :class:`phisim.field.CenteredGrid`, boundary from the field.

    The solution takes the grid and boundary of ``rhs``: its boundary conditions (values on the cell
    face) are the ones the solution satisfies. Without ``mask`` the direct spectral solver is used
    (exact to round-off); with ``mask`` (True = fluid) masked PCG (:func:`masked_poisson_solve`).

    Args:
        rhs: Scalar CenteredGrid, values ``(B, *resolution)``.
        mask: Optional fluid indicator (``resolution`` or ``(B, *resolution)``), or a CenteredGrid of it.
        solve: :class:`phisim.solvers.linalg.Solve` settings for the masked solve.
        incompatible: Singular-problem policy (see :func:`spectral_poisson_solve`).
        compat_rtol: Tolerance of the compatibility check.
        engine: FFT engine.
        return_info: With a mask, also return the SolveInfo.

    Returns:
        The solution as a CenteredGrid (and the SolveInfo with ``mask`` and ``return_info``).

    Raises:
        ShapeError: For a vector field.
        ParameterError, BoundaryError, SolveError: See the tensor-level solvers.
    """
    from phisim.field import CenteredGrid

    if not isinstance(rhs, CenteredGrid):
        raise ParameterError(
            f"solve_poisson expects a CenteredGrid, got {type(rhs).__name__}; "
            "use spectral_poisson_solve for tensors"
        )
    if rhs.values.ndim != rhs.grid.rank + 1:
        raise ShapeError(
            "solve_poisson needs a scalar field (B, *resolution); solve vector components separately"
        )
    kinds, values = field_kinds_and_values(rhs.boundary)
    dx = rhs.grid.dx
    if mask is None:
        u = spectral_poisson_solve(
            rhs.values, dx, kinds, values, incompatible=incompatible, compat_rtol=compat_rtol, engine=engine
        )
        return rhs.with_values(u)
    if isinstance(mask, CenteredGrid):
        mask = mask.values
    out = masked_poisson_solve(
        rhs.values,
        mask,
        dx,
        kinds,
        values,
        solve=solve,
        incompatible=incompatible,
        compat_rtol=compat_rtol,
        return_info=return_info,
        engine=engine,
    )
    if return_info:
        return rhs.with_values(out[0]), out[1]
    return rhs.with_values(out)
