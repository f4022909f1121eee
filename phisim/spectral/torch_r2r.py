"""The torch engine's real-to-real transforms, and small tensor helpers both FFT engines share.

DCT/DST of types 2 and 3 come from one real FFT of a permuted sequence (Makhoul 1980, "A fast cosine
transform in one and multiple dimensions", IEEE TASSP 28(1)); types 1 from an even / odd extension; types 4
from a dense symmetric matrix (O(N²) per line). Everything runs on any device and is differentiated by torch's
autograd. :func:`phisim.spectral.fft.r2rn` documents the definitions; it validates the arguments before calling here.

Caches: bounded LRUs of constant tensors per (length, dtype, device): :data:`TWIDDLE_CACHE_SIZE` twiddle vectors
(``n/2 + 1`` complex entries each) and :data:`TYPE4_CACHE_SIZE` dense type-4 matrices (``n²`` entries each: 2 MiB
for n = 512 in float64, so this one is kept small).
"""

from __future__ import annotations

import math
from functools import lru_cache

import torch

from phisim.errors import ParameterError


def axis_vector(w: torch.Tensor, ndim: int, axis: int) -> torch.Tensor:
    """``w`` reshaped to broadcast along ``axis`` of an ``ndim``-dimensional tensor."""
    shape = [1] * ndim
    shape[axis] = -1
    return w.reshape(shape)


def edge_weight(n: int, kind: str, value: float, dtype, device) -> torch.Tensor:
    """Vector of ones with ``value`` at index 0 (DCT kinds) or at index n-1 (DST kinds)."""
    w = torch.ones(n, dtype=dtype, device=device)
    w[0 if kind.startswith("dct") else n - 1] = value
    return w


#: Twiddle vectors kept by :func:`_twiddle` (least recently used evicted first).
TWIDDLE_CACHE_SIZE = 256
#: Dense type-4 transform matrices kept by :func:`_type4_matrix` (least recently used evicted first).
TYPE4_CACHE_SIZE = 16


@lru_cache(maxsize=TWIDDLE_CACHE_SIZE)
def _twiddle(n: int, sign: int, dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    k = torch.arange(n // 2 + 1, dtype=torch.float64)
    w = torch.polar(torch.ones_like(k), sign * math.pi * k / (2 * n))
    cdtype = torch.complex64 if dtype == torch.float32 else torch.complex128
    return w.to(device=device, dtype=cdtype)


def _torch_dct2_last(x: torch.Tensor) -> torch.Tensor:
    n = x.shape[-1]
    v = torch.cat([x[..., ::2], x[..., 1::2].flip(-1)], dim=-1)
    z = torch.fft.rfft(v, dim=-1) * _twiddle(n, -1, x.dtype, x.device)
    lower = 2 * z.real
    upper = (-2 * z.imag[..., 1 : n - n // 2]).flip(-1)
    return torch.cat([lower, upper], dim=-1)


def _torch_dct3_last(c: torch.Tensor) -> torch.Tensor:
    n = c.shape[-1]
    h = n // 2 + 1
    # Z_k = (c_k - i c_{N-k}) / 2 for k = 0..N//2, with c_N := 0.
    rev = torch.cat([torch.zeros_like(c[..., :1]), c[..., 1:].flip(-1)], dim=-1)[..., :h]
    z = torch.complex(c[..., :h], -rev) * _twiddle(n, 1, c.dtype, c.device)
    v = torch.fft.irfft(z, n=n, dim=-1) * n  # (2N * idct2) = N * irfft(Z * W) * 2 / 2
    m = (n + 1) // 2
    out = torch.empty_like(v)
    out[..., ::2] = v[..., :m]
    out[..., 1::2] = v[..., m:].flip(-1)
    return out


def _alternate(n: int, dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    a = torch.ones(n, dtype=dtype, device=device)
    a[1::2] = -1
    return a


@lru_cache(maxsize=TYPE4_CACHE_SIZE)
def _type4_matrix(n: int, kind: str, dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    i = torch.arange(n, dtype=torch.float64) + 0.5
    arg = math.pi * i[:, None] * i[None, :] / n
    m = 2 * (torch.cos(arg) if kind == "dct4" else torch.sin(arg))
    return m.to(dtype=dtype, device=device)


def r2r_last(x: torch.Tensor, kind: str) -> torch.Tensor:
    n = x.shape[-1]
    if kind == "dst1":  # odd extension [0, x, 0, -x reversed] of length 2(n+1): y_k = -Im FFT_{k+1}
        z = torch.zeros_like(x[..., :1])
        ext = torch.cat([z, x, z, -x.flip(-1)], dim=-1)
        return -torch.fft.rfft(ext, dim=-1).imag[..., 1 : n + 1]
    if kind == "dct1":  # even extension [x, x_{n-2} .. x_1] of length 2(n-1): y_k = Re FFT_k
        ext = torch.cat([x, x[..., 1 : n - 1].flip(-1)], dim=-1)
        return torch.fft.rfft(ext, dim=-1).real
    if kind in ("dct4", "dst4"):
        # Type-4 transforms (mixed Dirichlet/Neumann axes) as a dense symmetric matrix: O(n^2) per line.
        return x @ _type4_matrix(n, kind, x.dtype, x.device)
    if kind == "dct2":
        return _torch_dct2_last(x)
    if kind == "dct3":
        return _torch_dct3_last(x)
    alt = _alternate(n, x.dtype, x.device)
    if kind == "dst2":
        return _torch_dct2_last(x * alt).flip(-1)
    if kind == "dst3":
        return _torch_dct3_last(x.flip(-1)) * alt
    raise ParameterError(f"unknown real-to-real kind {kind!r}")


def r2rn(x: torch.Tensor, kinds: tuple[str, ...], axes: tuple[int, ...]) -> torch.Tensor:
    for kind, axis in zip(kinds, axes):
        x = r2r_last(x.movedim(axis, -1), kind).movedim(-1, axis)
    return x
