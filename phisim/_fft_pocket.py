"""Real-to-real transforms by scipy's pocketfft, one axis at a time, in place (internal to :mod:`phisim.fft`).

FFTW computes its REDFT/RODFT kinds with scalar pre- and post-processing around a real FFT; pocketfft (the
C++ library behind ``scipy.fft``) computes them from a real FFT vectorised across lines. On the development
CPU (1 thread) pocketfft measured faster for every float32 size of interest and for the float64 type-1 kinds;
:func:`use_pocket` encodes that choice. Pocketfft needs no plans, so its results are the same in every
process. Called through ``scipy.fft._pocketfft.pypocketfft`` with an output buffer (in place, no per-call
argument handling); without that module :mod:`phisim.fft` keeps FFTW's transforms.
"""

from __future__ import annotations

import numpy as np
import torch

try:  # the C++ transforms behind scipy.fft
    from scipy.fft._pocketfft import pypocketfft as _pocket
except ImportError:  # pragma: no cover - depends on the scipy version
    _pocket = None

#: Planes of at least this many bytes take a type-1 strided axis in a transposed copy (see
#: :func:`_multiply_transposed`).
TRANSPOSE_BYTES = 384 * 1024


def use_pocket(dtype: torch.dtype, kinds: tuple[str, ...]) -> bool:
    """Whether pocketfft beats FFTW for these real-to-real kinds (measured on the development CPU, 1 thread).

    float32: always (2-D DCT-II 256²: 0.12 vs 0.28 ms, 128²: 0.03 vs 0.05 ms; 64³: 1.0 vs 1.1 ms). float64: only
    with a type-1 kind, which FFTW computes slowly (DST-I x DST-II 255x256: 0.74 vs 0.82 ms, 127x128: 0.14 vs 0.17
    ms); for the other float64 kinds FFTW's plans are as fast or faster (DCT-II 256²: 0.28 vs 0.35 ms; 64³: 1.2 vs
    2.0 ms).
    """
    return _pocket is not None and bool(kinds) and (dtype == torch.float32 or "dst1" in kinds or "dct1" in kinds)


def _r2r(y: np.ndarray, kind: str, axis: int, threads: int, src: np.ndarray | None = None) -> None:
    """One unnormalised real-to-real kind along one axis of ``src`` (default ``y``) into ``y``."""
    fn = _pocket.dct if kind.startswith("dct") else _pocket.dst
    fn(y if src is None else src, int(kind[3]), (axis,), 0, y, threads)


def pocket_r2rn(a: np.ndarray, kinds, axes, threads: int = 1) -> np.ndarray:
    """Unnormalised real-to-real kinds (FFTW/scipy definitions) along ``axes`` of ``a`` into a new array."""
    out = np.empty(a.shape, dtype=a.dtype)
    src = a
    for kind, ax in zip(reversed(kinds), reversed(axes)):  # the innermost axis first
        _r2r(out, kind, ax, threads, src)
        src = out
    return out


def pocket_multiply(a: np.ndarray, kinds, inverse, axes, mult: np.ndarray, pre: np.ndarray | None,
                    out: np.ndarray | None = None, threads: int = 1) -> np.ndarray:
    """``inverse(forward(a * pre) * mult)`` by one-axis transforms in place on ``out`` (or a new array).

    FFTW's real-to-real kinds (REDFT/RODFT) measured up to 2.5x slower than pocketfft's at 128²-256² on the
    development CPU in float32 (a 2-D DST-I x DST-II of 255x256: 0.42 ms vs 0.17 ms), see :func:`use_pocket`.
    """
    if out is None:
        out = np.empty(a.shape, dtype=a.dtype)
    src = a  # the first transform reads the input and writes ``out`` (no separate copy)
    if pre is not None:
        src = np.multiply(a, pre, out=out)
    nd = out.ndim
    if (len(axes) == 2 and axes == (nd - 2, nd - 1) and kinds[0] in ("dct1", "dst1")
            and out.shape[-1] * out.shape[-2] * out.itemsize >= TRANSPOSE_BYTES):
        return _multiply_transposed(src, out, kinds, inverse, mult, threads)
    for kind, ax in zip(reversed(kinds), reversed(axes)):  # the innermost axis first
        _r2r(out, kind, ax, threads, src)
        src = out
    np.multiply(out, mult, out=out)
    for kind, ax in zip(inverse, axes):
        _r2r(out, kind, ax, threads)
    return out


def _multiply_transposed(src: np.ndarray, out: np.ndarray, kinds, inverse, mult: np.ndarray,
                         threads: int) -> np.ndarray:
    """The 2-D case of :func:`pocket_multiply` on large planes: the outer axis is transformed in a transposed
    copy, so every transform runs along contiguous lines.

    Along a strided axis pocketfft gathers a few columns at a time; for the type-1 kinds (computed from a real
    FFT of twice the length) on a plane that outgrows the cache this costs up to twice a contiguous transform
    (255x256 float64: DST-I 0.34 ms strided vs 0.17 ms contiguous), more than the two transposed copies
    (0.03 ms each through torch): 0.90 -> 0.74 ms for a DST-I x DST-II solve of that size. For the other kinds,
    and for float32 planes of 256², the strided transform measured faster than the copies.
    """
    last = out.ndim - 1
    _r2r(out, kinds[1], last, threads, src)
    o = torch.from_numpy(out)
    t = torch.empty((*out.shape[:-2], out.shape[-1], out.shape[-2]), dtype=o.dtype)
    t.copy_(o.transpose(-1, -2))
    tn = t.numpy()
    _r2r(tn, kinds[0], last, threads)
    np.multiply(tn, np.swapaxes(np.broadcast_to(mult, out.shape), -1, -2), out=tn)
    _r2r(tn, inverse[0], last, threads)
    o.copy_(t.transpose(-1, -2))
    _r2r(out, inverse[1], last, threads)
    return out
