"""Real-to-real transforms by scipy's pocketfft, one axis at a time, in place (internal to :mod:`phisim.spectral.fft`).

FFTW computes its REDFT/RODFT kinds with scalar pre- and post-processing around a real FFT; pocketfft (the
C++ library behind ``scipy.fft``) computes them from a real FFT vectorised across lines. On the development
CPU (1 thread) pocketfft measured faster for every float32 size of interest and for the float64 type-1 kinds;
:func:`use_pocket` encodes that choice. Pocketfft needs no plans, so its results are the same in every
process, which is why the default ``FFTW_ESTIMATE`` settings run every real-to-real kind here. Called through
``scipy.fft._pocketfft.pypocketfft`` (scipy up to 1.17; from 1.18 ``scipy.fft._duccfft.pyduccfft``, its successor
with the same calls) with an output buffer (in place, no per-call argument handling);
without that module :mod:`phisim.spectral.fft` keeps FFTW's transforms.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from phisim.spectral import settings as _settings

try:  # the C++ transforms behind scipy.fft: pocketfft up to scipy 1.17, its successor ducc (same calls) from 1.18
    from scipy.fft._pocketfft import pypocketfft as _pocket
except ImportError:  # pragma: no cover - depends on the scipy version
    try:
        from scipy.fft._duccfft import pyduccfft as _pocket
    except ImportError:
        _pocket = None

def use_pocket(dtype: torch.dtype, kinds: tuple[str, ...], lengths: tuple[int, ...] | None = None,
               effort: str = "FFTW_ESTIMATE") -> bool:
    """Whether these real-to-real kinds run on pocketfft rather than FFTW.

    With ``effort`` ``'FFTW_ESTIMATE'`` (the default settings): always, when pocketfft is there. pocketfft needs
    no plans (bit-reproducible) and beats FFTW's estimated real-to-real plans everywhere measured (float64
    DCT-II 512²: 2.3 vs 3.9 ms, DST-II 64³: 2.4 vs 4.1 ms; ``docs/BENCHMARKS.md``, "Deterministic plans").

    With a measured effort (opt-in), where pocketfft beats FFTW's measured plans (development CPU, 1 thread;
    transform, multiply and transform back):

    float32: always (2-D DCT-II 256²: 0.12 vs 0.28 ms, 128²: 0.03 vs 0.05 ms; 64³: 1.0 vs 1.1 ms). float64: with a
    type-1 kind, which FFTW computes slowly (DST-I x DST-II 255x256: 0.74 vs 0.82 ms, 127x128: 0.14 vs 0.17 ms), and
    where a length is not a power of two (440x82: 0.46 vs 0.70 ms, 660x123: 1.05 vs 1.61, 192x96: 0.12 vs 0.16,
    48³: 1.09 vs 1.41, 60x50x40: 1.02 vs 1.56). With powers of two only FFTW's plans are as fast or faster in
    float64 (256²: 0.61 vs 0.72-0.75 ms, 512²: 2.7 vs 4.0, 32³: 0.30 vs 0.43, 64³: 2.5 vs 4.2; 128² and 256x128
    within 10 %), and they keep it there.
    """
    if _pocket is None or not kinds:
        return False
    if effort == "FFTW_ESTIMATE" or dtype == torch.float32 or "dst1" in kinds or "dct1" in kinds:
        return True
    return lengths is not None and any(n & (n - 1) for n in lengths)


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
            and out.shape[-1] * out.shape[-2] * out.itemsize >= _settings.get_fft_settings().transpose_bytes):
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
    """The 2-D case of :func:`pocket_multiply` on large planes (at least
    :attr:`~phisim.spectral.settings.FFTSettings.transpose_bytes`, 384 KiB): the outer axis is transformed in a
    transposed copy, so every transform runs along contiguous lines.

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


def wall_transposes(shape, axis: int, itemsize: int) -> bool:
    """Whether :func:`wall_solve` runs the periodic FFT on a transposed copy; the caller then passes the
    multiplier and the Green's function with ``axis`` moved last.

    Measured on the development CPU (1 thread): only float64 gains, and only along the outermost axis after
    the batch axis of a large array (255x256: 0.64 -> 0.51 ms per component; 48³: 1.48 -> 1.12 ms). float32
    loses everywhere (64³: 1.70 -> 2.04 ms), and so does the middle axis of a 64³ float64 array (2.3 -> 3.0 ms).
    The size threshold is :attr:`~phisim.spectral.settings.FFTSettings.wall_transpose_bytes` (384 KiB).
    """
    return (itemsize == 8 and axis == 1 < len(shape) - 1
            and math.prod(shape) * itemsize >= _settings.get_fft_settings().wall_transpose_bytes)


def wall_solve(src: np.ndarray, out: np.ndarray, axis: int, kinds, inverse, axes, mult: np.ndarray,
               green: np.ndarray, threads: int = 1, subtract: bool = False) -> np.ndarray:
    """``(I - c L)⁻¹`` with zero values on two wall faces along ``axis``, by a periodic FFT and one correction.

    The DST-I that diagonalises the wall-to-wall axis is computed from a real FFT of twice its length, the
    most expensive pass of the box solve. Here that axis is solved as periodic over the ``n`` faces ``0..n-1``
    instead (an FFT of length ``n``), with face 0 standing for both walls; per transverse mode one source on
    face 0, ``-w_0 / G(0)`` times the periodic Green's function ``G``, brings face 0 back to zero. The faces
    ``1..n-1`` then obey exactly the wall problem (their stencils see zero on face 0 and on face n = 0), so
    the result equals the DST-I solve to round-off: 0.26 ms instead of 0.33 ms for a 255x256 float32
    component on the development CPU, 0.48 ms instead of 0.72 ms in float64.

    Args:
        src: The unknowns, ``n - 1`` samples along ``axis`` (faces ``1..n-1``); not overwritten.
        out: The full component, ``n + 1`` samples along ``axis``; receives the result with both wall faces 0.
        axis: The wall-to-wall axis.
        kinds, inverse, axes: Forward and inverse real-to-real kinds of the other (transverse) axes.
        mult: ``m / n`` times the transverse normalisation, on the half spectrum along ``axis`` (``n//2 + 1``)
            and the transverse spectrum, where ``m = 1 / (1 - c λ)`` (or any real multiplier even in the
            periodic wavenumber).
        green: ``G / G(0)``, ``n`` samples along ``axis``, with ``G`` the inverse real FFT of ``m``.
            Both ``mult`` and ``green`` have ``axis`` moved last when :func:`wall_transposes` says so.
        threads: pocketfft threads.
        subtract: Return ``result - src`` (Crank-Nicolson: ``2 (I - c L)⁻¹ f - f`` with ``mult`` doubled).
    """
    n = out.shape[axis] - 1
    ndim = out.ndim
    last = ndim - 1

    def sl(start, stop, ax=axis):
        return (slice(None),) * ax + (slice(start, stop),) + (slice(None),) * (ndim - ax - 1)

    inner, work = out[sl(1, n)], out[sl(0, n)]
    if axes:
        s = src
        for kind, ax in zip(reversed(kinds), reversed(axes)):  # the innermost axis first
            _r2r(inner, kind, ax, threads, s)
            s = inner
    else:
        np.copyto(inner, src)
    out[sl(0, 1)] = 0
    out[sl(n, n + 1)] = 0
    transposed = wall_transposes(work.shape, axis, work.itemsize)
    # along a strided axis of a large array the FFT gathers a few lines at a time: there it runs on a copy with
    # the axis last, and the first inverse transverse transform reads that copy back (float64 255x256: 0.36 ms
    # strided against 0.15 ms contiguous plus a copy of 0.07 ms)
    w = torch.from_numpy(work).movedim(axis, -1).contiguous().numpy() if transposed else work
    ax = last if transposed else axis
    shape = list(w.shape)
    shape[ax] = n // 2 + 1
    spec = np.empty(shape, dtype=np.result_type(out.dtype, np.complex64))
    _pocket.r2c(w, (ax,), True, 0, spec, threads)
    np.multiply(spec, mult, out=spec)
    _pocket.c2r(spec, (ax,), n, False, 0, w, threads)
    tw = torch.from_numpy(w)
    tw.narrow(ax, 1, n - 1).addcmul_(torch.from_numpy(green[sl(1, n, ax)]), tw.narrow(ax, 0, 1).clone(), value=-1)
    if transposed:
        back = torch.from_numpy(w).movedim(-1, axis).numpy()[sl(1, n)]
        if axes:
            _r2r(inner, inverse[0], axes[0], threads, back)
            for kind, a in zip(inverse[1:], axes[1:]):
                _r2r(inner, kind, a, threads)
        else:
            np.copyto(inner, back)
    else:
        out[sl(0, 1)] = 0
        for kind, a in zip(inverse, axes):
            _r2r(inner, kind, a, threads)
    if subtract:
        torch.from_numpy(inner).sub_(torch.from_numpy(src))
    return out
