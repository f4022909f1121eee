"""The pyfftw FFT engine: cached FFTW plans, and autograd wrappers whose backward applies the adjoint.

Plans are cached per (transform, shape, dtype, axes, kinds, threads, planner effort) in two bounded LRU caches
(:data:`PLANS` for single transforms, :data:`MULTIPLIER_PLANS` for fused pairs), each holding at most
:attr:`~phisim.spectral.settings.FFTSettings.plan_cache_size` plans (default 32). Plans are made through
:mod:`phisim.spectral.wisdom` on buffers aligned to :data:`ALIGNMENT` bytes whatever the CPU: with the default
``FFTW_ESTIMATE`` from an empty wisdom table (bit-reproducible), with a measured effort through the shared
wisdom file (opt-in, not reproducible across machines). Real-to-real kinds run as pocketfft one-axis passes
where :func:`phisim.spectral.pocket.use_pocket` says so (always with ``FFTW_ESTIMATE``).
:mod:`phisim.spectral.fft` validates the arguments and picks the engine; this module trusts them.
CPU tensors only; the adjoints are listed in :mod:`phisim.spectral.fft`'s docstring.
"""

from __future__ import annotations

import math
import threading

import numpy as np
import torch

from phisim.spectral import settings as _settings
from phisim.spectral import wisdom as _fftw_wisdom
from phisim.spectral.cache import LRUCache
from phisim.spectral.pocket import pocket_r2rn, use_pocket
from phisim.spectral.torch_r2r import axis_vector, edge_weight

try:  # pragma: no cover - depends on the environment
    import pyfftw as _pyfftw
except ImportError:  # pragma: no cover
    _pyfftw = None

#: FFTW's name of each real-to-real kind.
FFTW_KIND = {
    "dct2": "FFTW_REDFT10",
    "dct3": "FFTW_REDFT01",
    "dst2": "FFTW_RODFT10",
    "dst3": "FFTW_RODFT01",
    "dct4": "FFTW_REDFT11",
    "dst4": "FFTW_RODFT11",
    "dct1": "FFTW_REDFT00",
    "dst1": "FFTW_RODFT00",
}


#: Byte alignment of every plan buffer. FFTW's choice of SIMD codelets depends on the buffers' alignment (a
#: float32 real FFT planned on 4- or 8-byte aligned buffers gave other bits than on 16-byte aligned ones), so
#: the plans get their own buffers with one fixed alignment, the largest any SIMD extension asks for (AVX-512),
#: instead of pyfftw's per-CPU default; inputs of any alignment are copied in.
ALIGNMENT = 64


def _empty(shape, dtype) -> np.ndarray:
    return _pyfftw.empty_aligned(shape, dtype=dtype, n=ALIGNMENT)


class _Plan:
    """An FFTW plan with its own aligned buffers and a lock (plans are not re-entrant)."""

    def __init__(self, fftw, input_array, output_array):
        self.fftw = fftw
        self.input_array = input_array
        self.output_array = output_array
        self.lock = threading.Lock()

    def __call__(self, a: np.ndarray) -> np.ndarray:
        with self.lock:
            # Always copy into the plan's own buffer: FFTW may overwrite its input.
            self.input_array[...] = a
            self.fftw.execute()
            return self.output_array.copy()


#: The cached single-transform plans (least recently used evicted beyond ``plan_cache_size``).
PLANS: LRUCache[_Plan] = LRUCache(_settings.PLAN_CACHE_SIZE)


def get_plan(op: str, shape: tuple[int, ...], dtype: np.dtype, axes: tuple[int, ...], threads: int, effort: str,
             kinds: tuple[str, ...] = (), out_n: tuple[int, ...] = ()) -> _Plan:
    """The cached plan of one transform (``op`` ``'r2r'``, ``'rfft'`` or ``'irfft'``; for ``'irfft'``, ``shape``
    is the complex input's and ``out_n`` the real output sizes along ``axes``)."""
    key = (op, shape, np.dtype(dtype).str, axes, kinds, out_n, threads, effort)
    return PLANS.get(key, lambda: _make_plan(op, shape, dtype, axes, threads, effort, kinds, out_n),
                     _settings.get_fft_settings().plan_cache_size)


def _make_plan(op, shape, dtype, axes, threads, effort, kinds, out_n) -> _Plan:
    real = np.dtype(dtype)
    cplx = np.result_type(real, np.complex64)
    if op == "r2r":
        a = _empty(shape, real)
        b = _empty(shape, real)
        direction = [FFTW_KIND[k] for k in kinds]
    elif op == "rfft":
        a = _empty(shape, real)
        oshape = list(shape)
        oshape[axes[-1]] = shape[axes[-1]] // 2 + 1
        b = _empty(tuple(oshape), cplx)
        direction = "FFTW_FORWARD"
    elif op == "irfft":
        # shape is the complex input shape; out_n the real output sizes along axes
        oshape = list(shape)
        for ax, n in zip(axes, out_n):
            oshape[ax] = n
        a = _empty(shape, cplx)
        b = _empty(tuple(oshape), real)
        direction = "FFTW_BACKWARD"
    else:  # pragma: no cover - internal
        raise AssertionError(op)
    fftw = _fftw_wisdom.plan(_pyfftw, lambda e: _pyfftw.FFTW(
        a, b, axes=axes, direction=direction, flags=(e, "FFTW_DESTROY_INPUT"), threads=threads), effort)
    return _Plan(fftw, a, b)


def as_numpy(x: torch.Tensor) -> np.ndarray:
    return x.detach().contiguous().numpy()


_ADJOINT = {"dct2": "dct3", "dct3": "dct2", "dst2": "dst3", "dst3": "dst2", "dct4": "dct4", "dst4": "dst4",
            "dct1": "dct1", "dst1": "dst1"}


def _dct1_edges(n: int, value: float, dtype, device) -> torch.Tensor:
    """Vector of ones with ``value`` at both ends."""
    w = torch.ones(n, dtype=dtype, device=device)
    w[0] = value
    w[n - 1] = value
    return w


class PyfftwR2R(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x, kinds, axes, threads, effort):
        ctx.kinds, ctx.axes, ctx.threads, ctx.effort = kinds, axes, threads, effort
        if use_pocket(x.dtype, kinds, tuple(x.shape[a] for a in axes), effort):  # one-axis pocketfft transforms
            return torch.from_numpy(pocket_r2rn(x.detach().numpy(), kinds, axes, threads))
        plan = get_plan("r2r", tuple(x.shape), np_dtype(x.dtype), axes, threads, effort, kinds)
        return torch.from_numpy(plan(as_numpy(x)))

    @staticmethod
    def backward(ctx, g):
        kinds, axes = ctx.kinds, ctx.axes
        g = g.contiguous()
        # pre-weights of the adjoint (for type-2 kinds): double the edge entry
        for kind, ax in zip(kinds, axes):
            if kind in ("dct2", "dst2"):
                g = g * axis_vector(edge_weight(g.shape[ax], kind, 2.0, g.dtype, g.device), g.ndim, ax)
            elif kind == "dct1":  # DCT-I = C diag(1, 2, .., 2, 1) with C symmetric
                g = g * axis_vector(_dct1_edges(g.shape[ax], 2.0, g.dtype, g.device), g.ndim, ax)
        out = PyfftwR2R.apply(g, tuple(_ADJOINT[k] for k in kinds), axes, ctx.threads, ctx.effort)
        for kind, ax in zip(kinds, axes):
            if kind in ("dct3", "dst3"):
                out = out * axis_vector(
                    edge_weight(out.shape[ax], kind, 0.5, out.dtype, out.device), out.ndim, ax
                )
            elif kind == "dct1":
                out = out * axis_vector(_dct1_edges(out.shape[ax], 0.5, out.dtype, out.device), out.ndim, ax)
        return out, None, None, None, None


def _halved_axis_weight(n: int, value: float, dtype, device) -> torch.Tensor:
    """Weights over the rfft bins 0..n//2 of the halved axis: ``value`` on interior bins, 1 on 0 and n/2."""
    w = torch.full((n // 2 + 1,), value, dtype=dtype, device=device)
    w[0] = 1.0
    if n % 2 == 0:
        w[-1] = 1.0
    return w


class PyfftwRfftn(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x, axes, threads, effort):
        ctx.axes, ctx.threads, ctx.effort = axes, threads, effort
        ctx.s = tuple(x.shape[a] for a in axes)
        plan = get_plan("rfft", tuple(x.shape), np_dtype(x.dtype), axes, threads, effort)
        return torch.from_numpy(plan(as_numpy(x)))

    @staticmethod
    def backward(ctx, g):
        axes, s = ctx.axes, ctx.s
        real = g.real.dtype
        w = _halved_axis_weight(s[-1], 0.5, real, g.device)
        g = g * axis_vector(w, g.ndim, axes[-1])
        return PyfftwIrfftn.apply(g, s, axes, ctx.threads, ctx.effort) * math.prod(s), None, None, None


class PyfftwIrfftn(torch.autograd.Function):
    @staticmethod
    def forward(ctx, X, s, axes, threads, effort):
        ctx.axes, ctx.s, ctx.threads, ctx.effort = axes, s, threads, effort
        real = torch.float32 if X.dtype == torch.complex64 else torch.float64
        plan = get_plan("irfft", tuple(X.shape), np_dtype(real), axes, threads, effort, (), s)
        # FFTW's execute() is unnormalised; scale by 1/prod(s) here.
        return torch.from_numpy(plan(as_numpy(X))) / math.prod(s)

    @staticmethod
    def backward(ctx, g):
        axes, s = ctx.axes, ctx.s
        G = PyfftwRfftn.apply(g.contiguous(), axes, ctx.threads, ctx.effort)
        w = _halved_axis_weight(s[-1], 2.0, g.dtype, g.device) / math.prod(s)
        return G * axis_vector(w, G.ndim, axes[-1]), None, None, None, None


class _MultiplierPlan:
    """A forward and an inverse plan sharing one spectrum buffer: ``x -> inverse(forward(x) * m)``.

    Real FFT pair (``kinds`` empty: rfft then irfft) or real-to-real pair (``kinds`` the forward kinds,
    ``inverse`` the inverse kinds). Two copies per call (in and out) instead of four, no intermediate tensors.
    """

    def __init__(self, shape, dtype, axes, threads, effort, kinds=(), inverse=()):
        real = np.dtype(dtype)
        self.inp = _empty(shape, real)
        self.out = _empty(shape, real)
        if kinds:
            self.spec = _empty(shape, real)
            fwd_dir, inv_dir = [FFTW_KIND[k] for k in kinds], [FFTW_KIND[k] for k in inverse]
        else:
            hshape = list(shape)
            hshape[axes[-1]] = shape[axes[-1]] // 2 + 1
            self.spec = _empty(tuple(hshape), np.result_type(real, np.complex64))
            fwd_dir, inv_dir = "FFTW_FORWARD", "FFTW_BACKWARD"
        self.fwd = _fftw_wisdom.plan(_pyfftw, lambda e: _pyfftw.FFTW(
            self.inp, self.spec, axes=axes, direction=fwd_dir, flags=(e, "FFTW_DESTROY_INPUT"),
            threads=threads), effort)
        self.inv = _fftw_wisdom.plan(_pyfftw, lambda e: _pyfftw.FFTW(
            self.spec, self.out, axes=axes, direction=inv_dir, flags=(e, "FFTW_DESTROY_INPUT"),
            threads=threads), effort)
        self.lock = threading.Lock()

    def __call__(self, a: np.ndarray, mult: np.ndarray, pre: np.ndarray | None = None) -> np.ndarray:
        with self.lock:
            if pre is None:
                self.inp[...] = a
            else:
                np.multiply(a, pre, out=self.inp)
            self.fwd.execute()
            np.multiply(self.spec, mult, out=self.spec)
            self.inv.execute()
            return self.out.copy()


def multiplier_plan(shape, dtype, axes, threads: int, effort: str, kinds=(), inverse=()) -> _MultiplierPlan:
    """The cached :class:`_MultiplierPlan` of these arguments."""
    key = (tuple(shape), np.dtype(dtype).str, tuple(axes), tuple(kinds), tuple(inverse), threads, effort)
    return MULTIPLIER_PLANS.get(key, lambda: _MultiplierPlan(tuple(shape), dtype, tuple(axes), threads, effort,
                                                            tuple(kinds), tuple(inverse)),
                                _settings.get_fft_settings().plan_cache_size)


#: The cached fused plans of :func:`multiplier_plan` (least recently used evicted beyond ``plan_cache_size``).
MULTIPLIER_PLANS: LRUCache[_MultiplierPlan] = LRUCache(_settings.PLAN_CACHE_SIZE)


def clear_plans() -> None:
    """Drop every cached FFTW plan (both caches)."""
    PLANS.clear()
    MULTIPLIER_PLANS.clear()


class PyfftwFourierMultiply(torch.autograd.Function):
    """``irfft(rfft(x) * m)`` for an even real multiplier: a symmetric operator, so backward = forward."""

    @staticmethod
    def forward(ctx, x, mult, axes, threads, effort):
        plan = multiplier_plan(tuple(x.shape), np_dtype(x.dtype), axes, threads, effort)
        m = (mult / math.prod(x.shape[a] for a in axes)).to(x.dtype)  # FFTW's inverse is unnormalised
        ctx.mult, ctx.axes, ctx.threads, ctx.effort = mult, axes, threads, effort
        return torch.from_numpy(plan(as_numpy(x), m.numpy()))

    @staticmethod
    def backward(ctx, g):
        return (PyfftwFourierMultiply.apply(g.contiguous(), ctx.mult, ctx.axes, ctx.threads, ctx.effort),
                None, None, None, None)


def np_dtype(dtype: torch.dtype) -> np.dtype:
    return np.dtype("float32") if dtype == torch.float32 else np.dtype("float64")
