"""The Laplacian on a box, diagonalised: eigenvalues per boundary kind, the transform layout, multipliers.

The cell-centred Laplacian with face boundary values (:mod:`phisim.ops.stencil`) is diagonal in a real FFT
along periodic axes and in a DCT/DST along axes with Dirichlet or Neumann sides (types II/III for equal sides,
IV for mixed ones). This module holds that one eigen-decomposition; the spectral Poisson solve, the masked
operator's preconditioner and direct solve, and the box viscosity solves all apply their multipliers through
:func:`apply_multiplier`. Eigenvalue tables are cached by value (resolution, spacing, kinds, dtype, device) in
bounded LRU caches.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from functools import lru_cache

import torch

from phisim.errors import ParameterError
from phisim.ops.stencil import Kinds, check_rhs, normalize_dx, normalize_kinds
from phisim.spectral import fft as _fft

__all__ = [
    "TRANSFORMS", "axis_eigenvalues", "transform_layout", "laplacian_eigenvalues", "check_spectrum",
    "eigenvalues_cached", "is_singular", "spectral_apply", "transform_scale", "apply_multiplier", "box_solve",
    "solve_multiplier", "inverse_eigenvalues",
]

#: Forward and inverse real-to-real transform per (low, high) side kinds of an axis.
TRANSFORMS = {
    ("dirichlet", "dirichlet"): ("dst2", "dst3"),
    ("neumann", "neumann"): ("dct2", "dct3"),
    ("dirichlet", "neumann"): ("dst4", "dst4"),
    ("neumann", "dirichlet"): ("dct4", "dct4"),
}

def axis_eigenvalues(
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


def transform_layout(kinds: Kinds) -> tuple[list[int], list[int]]:
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
    dx = normalize_dx(dx, rank)
    check_spectrum(spectrum)
    return eigenvalues_cached(
        resolution, dx, kinds, dtype, torch.device(device or "cpu"), halved, spectrum == "continuous"
    )


def check_spectrum(spectrum: str) -> None:
    if spectrum not in ("stencil", "continuous"):
        raise ParameterError(f"spectrum must be 'stencil' or 'continuous', got {spectrum!r}")


@lru_cache(maxsize=128)
def eigenvalues_cached(resolution, dx, kinds, dtype, device, halved, continuous=False) -> torch.Tensor:
    _, per = transform_layout(kinds)
    last_per = per[-1] if per else None
    total = torch.zeros((), dtype=torch.float64)
    for a, n in enumerate(resolution):
        lam = axis_eigenvalues(n, kinds[a], dx[a], halved and a == last_per, continuous)
        shape = [1] * len(resolution)
        shape[a] = -1
        total = total + lam.reshape(shape)
    return total.to(dtype=dtype, device=device)


def is_singular(kinds: Kinds) -> bool:
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
    rank = check_rhs(x, "x")
    kinds = normalize_kinds(kinds, rank)
    dx = normalize_dx(dx, rank)
    check_spectrum(spectrum)
    lam = eigenvalues_cached(tuple(x.shape[1:]), dx, kinds, torch.float64, x.device, True, spectrum == "continuous")
    mult = fn(lam)
    return apply_multiplier(x, kinds, mult, engine)


def transform_scale(res, kinds: Kinds) -> float:
    """Normalisation of an unnormalised forward + inverse real-to-real transform pair."""
    r2r, _ = transform_layout(kinds)
    count = 1
    for a in r2r:  # a plain loop: traceable by torch.compile (math.prod of a generator is not)
        count *= 2 * res[a]
    return 1.0 / count


def apply_multiplier(x: torch.Tensor, kinds: Kinds, mult: torch.Tensor, engine, prescaled: bool = False
                      ) -> torch.Tensor:
    """Forward transforms, multiply by ``mult`` (multipliers in solver layout), inverse transforms.

    ``mult`` is float64 and gets the transforms' normalisation here, unless ``prescaled`` (then it already
    carries it and has ``x``'s dtype).
    """
    r2r, per = transform_layout(kinds)
    res = x.shape[1:]
    y = x
    if r2r:
        fwd = tuple(TRANSFORMS[kinds[a]][0] for a in r2r)
        y = _fft.r2rn(y, fwd, tuple(1 + a for a in r2r), engine=engine)
    m = mult if prescaled else (mult * transform_scale(res, kinds)).to(x.dtype)
    if per:
        axes = tuple(1 + a for a in per)
        Y = _fft.rfftn(y, axes, engine=engine)
        y = _fft.irfftn(Y * m, tuple(res[a] for a in per), axes, engine=engine)
    elif r2r and not (torch.is_grad_enabled() and y.requires_grad):
        y = y.mul_(m)  # y is the transform's fresh output
    else:
        y = y * m
    if r2r:
        inv = tuple(TRANSFORMS[kinds[a]][1] for a in r2r)
        y = _fft.r2rn(y, inv, tuple(1 + a for a in r2r), engine=engine)
    return y


def box_solve(rhs: torch.Tensor, dx: tuple[float, ...], kinds: Kinds) -> torch.Tensor:
    """:func:`spectral_poisson_solve` with ``incompatible='project'`` and zero boundary values, for callers
    that pass a finite ``rhs``, normalised ``kinds`` and a float tuple ``dx`` (the pressure projection)."""
    f = rhs
    if is_singular(kinds):
        f = f - f.mean(dim=tuple(range(1, f.ndim)), keepdim=True)
    inv = solve_multiplier(tuple(rhs.shape[1:]), dx, kinds, rhs.device, rhs.dtype)
    return apply_multiplier(f, kinds, inv, None, prescaled=True)


@lru_cache(maxsize=128)
def solve_multiplier(resolution, dx, kinds, device, dtype) -> torch.Tensor:
    """Inverse eigenvalues times the transforms' normalisation, in the solve's dtype (cached)."""
    return (inverse_eigenvalues(resolution, dx, kinds, device) * transform_scale(resolution, kinds)).to(dtype)


@lru_cache(maxsize=128)
def inverse_eigenvalues(resolution, dx, kinds, device) -> torch.Tensor:
    lam = eigenvalues_cached(resolution, dx, kinds, torch.float64, device, True)
    inv = torch.where(lam == 0, torch.zeros_like(lam), 1.0 / torch.where(lam == 0, torch.ones_like(lam), lam))
    if is_singular(kinds):
        inv.reshape(-1)[0] = 0.0  # the constant mode (index 0 in every layout) is projected out
    return inv
