"""FFT engines behind one interface: torch.fft (autograd, any device) and pyfftw (CPU, planned).

Every transform here takes and returns torch tensors, is differentiable (also twice), and follows
scipy.fft's definitions and normalisation names, so ``dctn(x, type=2, norm='ortho')`` equals
``scipy.fft.dctn(x, type=2, norm='ortho')``:

* ``rfftn`` / ``irfftn`` — real-to-complex FFT over the chosen axes (last axis halved);
* ``dctn`` / ``idctn`` and ``dstn`` / ``idstn`` — discrete cosine / sine transforms of types 2 and 3
  (the cell-centred transforms: DCT-II diagonalises the Neumann Laplacian and DST-II the Dirichlet
  Laplacian when the boundary sits on the cell face);
* ``r2rn`` — the unnormalised real-to-real transforms (FFTW's REDFT10/REDFT01/RODFT10/RODFT01),
  one kind per axis, mixed in one call.

Engines:

* ``'torch'``: ``torch.fft``; DCT/DST are computed from one real FFT of a permuted sequence
  (Makhoul 1980, "A fast cosine transform in one and multiple dimensions", IEEE TASSP 28(1)),
  so they run on CUDA and are differentiated by torch's autograd.
* ``'pyfftw'``: FFTW plans made by pyfftw, cached per (transform, shape, dtype, axes, threads, planner effort)
  in bounded LRU caches (``FFTSettings.plan_cache_size``, default 32 plans per cache); the real-to-real kinds
  run on scipy's pocketfft (:mod:`phisim.spectral.pocket`) with the default planner, and where pocketfft
  measured faster with a measured planner. Results are
  differentiable through ``torch.autograd.Function`` wrappers whose backward applies the adjoint transform:
  ``DCT-II^T = DCT-III·diag(2,1,…,1)``, ``DCT-III^T = diag(1/2,1,…,1)·DCT-II``,
  ``DST-II^T = DST-III·diag(1,…,1,2)``, ``DST-III^T = diag(1,…,1,1/2)·DST-II``; the adjoint of
  ``rfftn`` is ``N·irfftn`` with the interior bins of the halved axis halved, the adjoint of
  ``irfftn`` is ``rfftn/N`` with those bins doubled. CPU tensors only.
* ``'auto'`` (default): ``'torch'`` for tensors on an accelerator; on the CPU ``'pyfftw'`` when
  it is installed (it measured fastest here, see ``docs/BENCHMARKS.md`` / the module notes in
  ``benchmarks/bench_spectral.py``), else ``'torch'`` with a one-time warning.
* Under ``torch.compile`` (while dynamo traces, :func:`torch.compiler.is_compiling`) every engine resolves to
  ``'torch'``: pyfftw calls cannot be traced, so a compiled step runs ``torch.fft`` and eager calls keep pyfftw.

Planner effort and reproducibility: the default ``FFTSettings.planner_effort='FFTW_ESTIMATE'`` is
bit-reproducible: the same seed and settings give the same bits in fresh processes, with any number of
worker processes, on a machine without FFTW wisdom and under heavy load. DCT/DST run on pocketfft (no plans);
real FFTs on FFTW plans chosen by FFTW's cost model, each built from an empty wisdom table (wisdom in memory
would change an estimated plan) on 64-byte aligned buffers (alignment changes FFTW's SIMD codelets), so the
plan depends only on the transform, the thread count and the CPU's SIMD instructions; nothing is timed and no
wisdom file is read or written. Cost against measured plans (``benchmarks/bench_spectral.py --deterministic``,
``docs/BENCHMARKS.md`` "Deterministic plans"): a few per cent to 1.5x on single transforms, none where
pocketfft ran already. ``planner_effort='FFTW_MEASURE'`` (or ``PHISIM_FFT_PLANNER=measure``) is the opt-in
for measured plans, shared per machine through a wisdom file (:mod:`phisim.spectral.wisdom`); they are
**not bit-reproducible** across machines or between a machine without wisdom and one with it. The torch
engine (``torch.fft``, pocketfft on the CPU) needs no plans either.

Modules: this one holds the settings, the argument checks and the public transforms; the engines live in
:mod:`phisim.spectral.torch_r2r` (Makhoul transforms, shared tensor helpers), :mod:`phisim.spectral.fftw` (plans and
autograd wrappers) and :mod:`phisim.spectral.pocket` (pocketfft one-axis passes).

Thread count: ``FFTSettings.threads`` (default 1). On the 2-core development machine two FFTW
threads were not faster than one for 64²…128³ transforms (0.32 ms vs 0.32 ms for a 256² DST-II,
18.3 ms vs 18.5 ms for 128³), so one thread is the default.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Sequence

import torch

from phisim.errors import ParameterError, ShapeError

try:  # pragma: no cover - exercised implicitly
    import pyfftw as _pyfftw

    _HAVE_PYFFTW = True
except ImportError:  # pragma: no cover - depends on the environment
    _pyfftw = None
    _HAVE_PYFFTW = False

from phisim.spectral import fftw as _fftw
from phisim.spectral import torch_r2r as _fft_torch
from phisim.spectral.pocket import pocket_multiply as _pocket_multiply
from phisim.spectral.pocket import use_pocket as _use_pocket
from phisim.spectral.pocket import wall_solve as _pocket_wall_solve
from phisim.spectral.settings import (
    ENGINES,
    FFTSettings,
    fft_settings,
    get_fft_settings,
    set_fft_settings,
)
from phisim.spectral.torch_r2r import axis_vector, edge_weight

__all__ = [
    "FFTSettings",
    "get_fft_settings",
    "set_fft_settings",
    "fft_settings",
    "available_engines",
    "resolve_engine",
    "r2r_multiply",
    "wall_solve",
    "rfftn",
    "irfftn",
    "dctn",
    "idctn",
    "dstn",
    "idstn",
    "r2rn",
    "fourier_multiply",
    "R2R_KINDS",
]

#: Real-to-real kinds accepted by :func:`r2rn` (unnormalised, scipy/FFTW definitions).
R2R_KINDS = ("dct2", "dct3", "dst2", "dst3", "dct4", "dst4", "dct1", "dst1")
_ENGINES = ENGINES
_WARNED_NO_PYFFTW = False


def available_engines() -> tuple[str, ...]:
    """Return the names of the engines usable in this environment (``'torch'`` always)."""
    return ("torch", "pyfftw") if _HAVE_PYFFTW else ("torch",)


def resolve_engine(x: torch.Tensor, engine: str | None = None) -> str:
    """Decide which engine transforms ``x``.

    Args:
        x: The tensor to transform (its device decides for ``'auto'``).
        engine: ``None`` (use the default settings), ``'auto'``, ``'torch'`` or ``'pyfftw'``.

    Returns:
        ``'torch'`` or ``'pyfftw'``.

    Raises:
        ParameterError: For an unknown engine, or ``'pyfftw'`` with a tensor not on the CPU.
    """
    global _WARNED_NO_PYFFTW
    engine = get_fft_settings().engine if engine is None else engine
    if engine not in _ENGINES:
        raise ParameterError(f"FFT engine must be one of {_ENGINES}, got {engine!r}")
    if engine == "torch" or torch.compiler.is_compiling():  # pyfftw cannot be traced: torch.fft in a graph
        return "torch"
    if engine == "pyfftw":
        if x.device.type != "cpu":
            raise ParameterError(
                f"the pyfftw engine works on CPU tensors only, got device {x.device}; "
                "use engine='torch' or 'auto'"
            )
        if not _HAVE_PYFFTW:
            if not _WARNED_NO_PYFFTW:
                warnings.warn("pyfftw is not installed; falling back to the torch FFT engine", stacklevel=3)
                _WARNED_NO_PYFFTW = True
            return "torch"
        return "pyfftw"
    # auto
    if x.device.type != "cpu":
        return "torch"
    if not _HAVE_PYFFTW:
        if not _WARNED_NO_PYFFTW:
            warnings.warn(
                "pyfftw is not installed; using torch.fft on the CPU (slower real-to-real transforms)",
                stacklevel=3,
            )
            _WARNED_NO_PYFFTW = True
        return "torch"
    return "pyfftw"


# ----------------------------------------------------------------------------------------------
# argument handling


def _threads() -> int:
    return get_fft_settings().threads


def _effort() -> str:
    return get_fft_settings().planner_effort


def _norm_axes(x: torch.Tensor, axes: Sequence[int] | int | None) -> tuple[int, ...]:
    if axes is None:
        return tuple(range(x.ndim))
    if isinstance(axes, int):
        axes = (axes,)
    out = []
    for a in axes:
        if not -x.ndim <= a < x.ndim:
            raise ShapeError(f"axis {a} out of range for a tensor of {x.ndim} dimensions")
        out.append(a % x.ndim)
    if len(set(out)) != len(out):
        raise ShapeError(f"repeated axes {tuple(axes)}")
    return tuple(out)


def _check_real(x: torch.Tensor, name: str) -> None:
    if not isinstance(x, torch.Tensor):
        raise ParameterError(f"{name} expects a torch.Tensor, got {type(x).__name__}")
    if x.dtype not in (torch.float32, torch.float64):
        raise ParameterError(f"{name} expects a float32 or float64 tensor, got {x.dtype}")

# ----------------------------------------------------------------------------------------------
# transform, multiply, transform back: fused fast path and Fourier multipliers


def r2r_multiply(x: torch.Tensor, kinds: Sequence[str], inverse: Sequence[str], axes: Sequence[int],
                 mult: torch.Tensor, pre: torch.Tensor | None = None, *, engine: str | None = None,
                 out: torch.Tensor | None = None) -> torch.Tensor | None:
    """``inverse_r2r(forward_r2r(x * pre) * mult)`` in one pass without autograd, or None.

    A fast path for operators applied many times without autograd (preconditioners, exact box solves). The
    real-to-real kinds run as one-axis pocketfft transforms (scipy's C++ FFT) in place on one array where that
    measured faster (float32, and float64 with a type-1 kind or a length that is not a power of two: 1.2-2.5x
    faster than FFTW's REDFT/RODFT kinds on the development CPU, see :func:`phisim.spectral.pocket.use_pocket`; no
    plans, so the same round-off in every process); otherwise two FFTW plans share their buffers. ``kinds``
    empty means a real FFT pair (``mult`` on the half spectrum). It returns None when it does not apply (pyfftw
    missing or not the resolved engine, a non-CPU tensor, any of ``x``, ``mult``, ``pre`` requiring grad, or a
    dtype other than float32/float64); the caller then composes :func:`r2rn` calls itself.

    Args:
        x: Real tensor (float32/float64) on the CPU; any strides.
        kinds: Forward real-to-real kind per axis (see :func:`r2rn`).
        inverse: Inverse kind per axis.
        axes: Transformed axes.
        mult: Real multiplier of ``x``'s shape (broadcastable), already carrying the transforms' normalisation
            and ``x``'s dtype.
        pre: Optional factor applied to ``x`` before the forward transform (e.g. a mask), ``x``'s shape.
        engine: FFT engine (see :func:`resolve_engine`); only ``'pyfftw'`` takes this path.
        out: Optional CPU tensor of ``x``'s shape and dtype (a view is fine, e.g. the interior of a larger
            array) that receives the result; it must not overlap ``x``.

    Returns:
        ``out``, or a new tensor of ``x``'s shape and dtype; None when the fast path does not apply.

    Raises:
        ShapeError: For an ``out`` of another shape or dtype.
    """
    if (x.dtype not in (torch.float32, torch.float64) or x.device.type != "cpu" or x.requires_grad
            or mult.requires_grad or (pre is not None and pre.requires_grad) or resolve_engine(x, engine) != "pyfftw"):
        return None
    if out is not None and (out.shape != x.shape or out.dtype != x.dtype or out.device.type != "cpu"):
        raise ShapeError(f"r2r_multiply: out must be a CPU tensor of shape {tuple(x.shape)} and dtype {x.dtype}, "
                         f"got {tuple(out.shape)} {out.dtype} on {out.device}")
    axes = _norm_axes(x, axes)
    kinds, inverse = tuple(kinds), tuple(inverse)
    m = mult.detach().numpy()
    cfg = get_fft_settings()
    if _use_pocket(x.dtype, kinds + inverse, tuple(x.shape[a] for a in axes), cfg.planner_effort):
        y = _pocket_multiply(x.detach().numpy(), kinds, inverse, axes, m,
                             None if pre is None else pre.detach().numpy(),
                             None if out is None else out.detach().numpy(), cfg.threads)
        return out if out is not None else torch.from_numpy(y)
    plan = _fftw.multiplier_plan(tuple(x.shape), _fftw.np_dtype(x.dtype), axes, cfg.threads,
                                 cfg.planner_effort, kinds, inverse)
    y = torch.from_numpy(plan(_fftw.as_numpy(x), m, None if pre is None else _fftw.as_numpy(pre)))
    return y if out is None else out.copy_(y)


def wall_solve(x: torch.Tensor, out: torch.Tensor, axis: int, kinds: Sequence[str], inverse: Sequence[str],
               axes: Sequence[int], mult: torch.Tensor, green: torch.Tensor, *, subtract: bool = False,
               engine: str | None = None) -> torch.Tensor | None:
    """A box solve with two walls along ``axis`` by a periodic FFT and a one-face correction, or None.

    The fast path of an exact ``(I - c L)⁻¹`` whose wall-to-wall axis would need a DST-I (see
    :func:`phisim.spectral.pocket.wall_solve` for the method and the arguments): ``x`` holds the ``n - 1`` interior
    samples along ``axis``, ``out`` the ``n + 1`` samples with both wall faces (set to zero). It returns None
    when it does not apply (pocketfft missing, an engine other than pyfftw, a non-CPU or grad-requiring
    tensor, a dtype other than float32/float64); the caller then takes the DST-I route.

    Raises:
        ShapeError: For an ``out`` whose shape does not match ``x`` (two more samples along ``axis``).
    """
    if (not _use_pocket(x.dtype, ("dst1",)) or x.device.type != "cpu" or x.requires_grad or mult.requires_grad
            or green.requires_grad or resolve_engine(x, engine) != "pyfftw"):
        return None
    want = list(x.shape)
    want[axis] += 2
    if list(out.shape) != want or out.dtype != x.dtype or out.device.type != "cpu":
        raise ShapeError(f"wall_solve: out must be a CPU tensor of shape {tuple(want)} and dtype {x.dtype}, "
                         f"got {tuple(out.shape)} {out.dtype} on {out.device}")
    _pocket_wall_solve(x.detach().numpy(), out.detach().numpy(), axis, tuple(kinds), tuple(inverse), tuple(axes),
                       mult.detach().numpy(), green.detach().numpy(), get_fft_settings().threads, subtract)
    return out


def fourier_multiply(
    x: torch.Tensor,
    mult: torch.Tensor,
    axes: Sequence[int] | int | None = None,
    *,
    engine: str | None = None,
) -> torch.Tensor:
    """Apply a real Fourier multiplier: ``irfftn(rfftn(x) * mult)`` (e.g. the heat operator).

    With pyfftw the two transforms share their spectrum buffer (two copies per call instead of four).

    Args:
        x: Real tensor (float32/float64).
        mult: Real multiplier on the half spectrum, broadcastable to ``rfftn(x, axes)``'s shape. It must be
            even (``m(k) = m(-k)``, e.g. a function of ``|k|``): the operator is then symmetric, and its
            gradient is the same operator.
        axes: Axes to transform (default: all).
        engine: FFT engine (see :func:`resolve_engine`).

    Returns:
        Real tensor of ``x``'s shape, differentiable w.r.t. ``x``.

    Raises:
        ParameterError: For a non-float tensor or an unknown engine.
        ShapeError: For an out-of-range or repeated axis.
    """
    _check_real(x, "fourier_multiply")
    axes = _norm_axes(x, axes)
    if not axes:
        raise ShapeError("fourier_multiply needs at least one axis")
    if mult.is_complex():
        raise ParameterError("fourier_multiply needs a real multiplier")
    if resolve_engine(x, engine) == "pyfftw":
        return _fftw.PyfftwFourierMultiply.apply(x, mult.detach().to(torch.float64), axes, _threads(),
                                                  _effort())
    s = tuple(x.shape[a] for a in axes)
    return torch.fft.irfftn(torch.fft.rfftn(x, dim=axes) * mult.to(x.dtype), s=s, dim=axes)


# ----------------------------------------------------------------------------------------------
# public transforms


def r2rn(
    x: torch.Tensor,
    kinds: Sequence[str] | str,
    axes: Sequence[int] | int | None = None,
    *,
    engine: str | None = None,
) -> torch.Tensor:
    """Unnormalised real-to-real transforms, one kind per axis (FFTW/scipy ``norm='backward'`` definitions).

    With ``N`` the length of an axis and ``n, k = 0..N-1``:

    * ``'dct2'``: ``y_k = 2 Σ_n x_n cos(π k (2n+1) / 2N)``
    * ``'dct3'``: ``y_k = x_0 + 2 Σ_{n≥1} x_n cos(π n (2k+1) / 2N)``  (``dct3(dct2(x)) = 2N x``)
    * ``'dst2'``: ``y_k = 2 Σ_n x_n sin(π (k+1)(2n+1) / 2N)``
    * ``'dst3'``: ``y_k = (-1)^k x_{N-1} + 2 Σ_{n<N-1} x_n sin(π (n+1)(2k+1) / 2N)``
      (``dst3(dst2(x)) = 2N x``)
    * ``'dct4'``: ``y_k = 2 Σ_n x_n cos(π (2k+1)(2n+1) / 4N)``  (symmetric; ``dct4(dct4(x)) = 2N x``)
    * ``'dst4'``: ``y_k = 2 Σ_n x_n sin(π (2k+1)(2n+1) / 4N)``  (symmetric; ``dst4(dst4(x)) = 2N x``)

    * ``'dct1'``: ``y_k = x_0 + (-1)^k x_{N-1} + 2 Σ_{0<n<N-1} x_n cos(π n k / (N-1))`` (``N >= 2``;
      ``dct1(dct1(x)) = 2(N-1) x``)
    * ``'dst1'``: ``y_k = 2 Σ_n x_n sin(π (n+1)(k+1) / (N+1))`` (symmetric; ``dst1(dst1(x)) = 2(N+1) x``)

    Type 4 diagonalises the cell-centred Laplacian with a Dirichlet face on one side and a Neumann
    face on the other; the torch engine computes it as a dense matrix product (O(N²) per line).
    Types 1 diagonalise the vertex-centred Laplacian (samples on the boundary: Neumann ``dct1``,
    Dirichlet values outside the transformed samples ``dst1``), e.g. a MAC velocity component along its
    own axis.

    Args:
        x: Real tensor (float32/float64), any shape; batch axes are the axes not transformed.
        kinds: One kind per axis in ``axes`` (a single string applies to all axes).
        axes: Axes to transform (default: all).
        engine: FFT engine (see :func:`resolve_engine`); None uses the default settings.

    Returns:
        Real tensor of the same shape, dtype and device.

    Raises:
        ParameterError: For a non-float tensor, an unknown kind, or a kinds/axes length mismatch.
        ShapeError: For an out-of-range or repeated axis.
    """
    _check_real(x, "r2rn")
    axes = _norm_axes(x, axes)
    if isinstance(kinds, str):
        kinds = (kinds,) * len(axes)
    kinds = tuple(kinds)
    if len(kinds) != len(axes):
        raise ParameterError(f"r2rn needs one kind per axis: got kinds={kinds} for axes={axes}")
    for k, ax in zip(kinds, axes):
        if k not in R2R_KINDS:
            raise ParameterError(f"unknown real-to-real kind {k!r}; expected one of {R2R_KINDS}")
        if k == "dct1" and x.shape[ax] < 2:
            raise ShapeError(f"dct1 needs at least 2 samples along axis {ax}, got {x.shape[ax]}")
    if not axes:
        return x
    if resolve_engine(x, engine) == "pyfftw":
        return _fftw.PyfftwR2R.apply(x, kinds, axes, _threads(), _effort())
    return _fft_torch.r2rn(x, kinds, axes)


def rfftn(
    x: torch.Tensor, axes: Sequence[int] | int | None = None, *, engine: str | None = None
) -> torch.Tensor:
    """Real-to-complex n-dimensional FFT (unnormalised forward, like ``torch.fft.rfftn``).

    Args:
        x: Real tensor (float32/float64).
        axes: Axes to transform (default: all); the last one is halved to ``n//2 + 1`` bins.
        engine: FFT engine (see :func:`resolve_engine`).

    Returns:
        Complex tensor (complex64/complex128), ``X_k = Σ_n x_n exp(-2πi k·n/N)``.

    Raises:
        ParameterError: For a non-float tensor or an unknown engine.
        ShapeError: For an out-of-range or repeated axis.
    """
    _check_real(x, "rfftn")
    axes = _norm_axes(x, axes)
    if not axes:
        raise ShapeError("rfftn needs at least one axis")
    if resolve_engine(x, engine) == "pyfftw":
        return _fftw.PyfftwRfftn.apply(x, axes, _threads(), _effort())
    return torch.fft.rfftn(x, dim=axes)


def irfftn(
    X: torch.Tensor, s: Sequence[int], axes: Sequence[int] | int | None = None, *, engine: str | None = None
) -> torch.Tensor:
    """Inverse of :func:`rfftn` (normalised by ``1/prod(s)``, like ``torch.fft.irfftn``).

    Args:
        X: Complex tensor (complex64/complex128) of half-spectrum bins.
        s: Real output sizes along ``axes`` (needed to tell even from odd last-axis lengths).
        axes: Transformed axes (default: the last ``len(s)`` axes).
        engine: FFT engine (see :func:`resolve_engine`).

    Returns:
        Real tensor; the imaginary parts of self-conjugate bins are ignored (as numpy/torch do).

    Raises:
        ParameterError: For a non-complex tensor or inconsistent sizes.
        ShapeError: For an out-of-range or repeated axis.
    """
    if not isinstance(X, torch.Tensor) or X.dtype not in (torch.complex64, torch.complex128):
        raise ParameterError(
            f"irfftn expects a complex64/complex128 tensor, got {getattr(X, 'dtype', type(X))}"
        )
    s = tuple(int(n) for n in s)
    if axes is None:
        axes = tuple(range(X.ndim - len(s), X.ndim))
    axes = _norm_axes(X, axes)
    if len(s) != len(axes):
        raise ParameterError(f"irfftn: s={s} and axes={axes} differ in length")
    if X.shape[axes[-1]] != s[-1] // 2 + 1 or any(X.shape[a] != n for a, n in zip(axes[:-1], s[:-1])):
        raise ShapeError(
            f"irfftn: input shape {tuple(X.shape)} does not match output sizes {s} on axes {axes}"
        )
    if resolve_engine(X, engine) == "pyfftw":
        return _fftw.PyfftwIrfftn.apply(X, s, axes, _threads(), _effort())
    return torch.fft.irfftn(X, s=s, dim=axes)


def _check_type_norm(type: int, norm: str | None) -> str:
    if type not in (2, 3):
        raise ParameterError(f"only DCT/DST types 2 and 3 are implemented, got type={type}")
    norm = "backward" if norm is None else norm
    if norm not in ("backward", "ortho", "forward"):
        raise ParameterError(f"norm must be 'backward', 'ortho' or 'forward', got {norm!r}")
    return norm


def _trig(x: torch.Tensor, family: str, type: int, axes, norm: str, inverse: bool, engine) -> torch.Tensor:
    _check_real(x, f"{'i' if inverse else ''}{family}n")
    norm = _check_type_norm(type, norm)
    axes = _norm_axes(x, axes)
    # the forward kind, and the kind actually applied
    applied_type = (5 - type) if inverse else type
    kind = f"{family}{applied_type}"
    # scale: forward transforms of 'forward' norm and inverses of 'backward' norm carry 1/(2N)
    if norm == "ortho":
        for ax in axes:
            n = x.shape[ax]
            if applied_type == 3:  # pre-weight h: 1/sqrt(N) at the edge entry, 1/sqrt(2N) elsewhere
                h = edge_weight(n, kind, math.sqrt(2.0), x.dtype, x.device) / math.sqrt(2.0 * n)
                x = x * axis_vector(h, x.ndim, ax)
        y = r2rn(x, kind, axes, engine=engine)
        for ax in axes:
            n = y.shape[ax]
            if applied_type == 2:  # post-weight f: sqrt(1/4N) at the edge entry, sqrt(1/2N) elsewhere
                f = edge_weight(n, kind, math.sqrt(0.5), y.dtype, y.device) / math.sqrt(2.0 * n)
                y = y * axis_vector(f, y.ndim, ax)
        return y
    y = r2rn(x, kind, axes, engine=engine)
    if (norm == "forward") != inverse:
        y = y / math.prod(2 * x.shape[a] for a in axes)
    return y


def dctn(
    x: torch.Tensor,
    type: int = 2,
    axes: Sequence[int] | int | None = None,
    norm: str | None = None,
    *,
    engine: str | None = None,
) -> torch.Tensor:
    """n-dimensional discrete cosine transform, as ``scipy.fft.dctn`` (types 2 and 3).

    Args:
        x: Real tensor (float32/float64).
        type: 2 (cell-centred, diagonalises the face-Neumann Laplacian) or 3 (its inverse up to scale).
        axes: Axes to transform (default: all).
        norm: ``'backward'`` (default, unscaled), ``'ortho'`` (orthonormal) or ``'forward'`` (1/(2N)).
        engine: FFT engine (see :func:`resolve_engine`).

    Returns:
        Real tensor of the same shape.

    Raises:
        ParameterError: For other types, an unknown norm or a non-float tensor.
    """
    return _trig(x, "dct", type, axes, norm, False, engine)


def idctn(
    x: torch.Tensor,
    type: int = 2,
    axes: Sequence[int] | int | None = None,
    norm: str | None = None,
    *,
    engine: str | None = None,
) -> torch.Tensor:
    """Inverse of :func:`dctn` with the same ``type`` and ``norm`` (as ``scipy.fft.idctn``).

    Args:
        x: Real tensor (float32/float64).
        type: 2 or 3 — the type of the forward transform being inverted.
        axes: Axes to transform (default: all).
        norm: ``'backward'`` (default), ``'ortho'`` or ``'forward'``.
        engine: FFT engine (see :func:`resolve_engine`).

    Returns:
        Real tensor of the same shape.

    Raises:
        ParameterError: For other types, an unknown norm or a non-float tensor.
    """
    return _trig(x, "dct", type, axes, norm, True, engine)


def dstn(
    x: torch.Tensor,
    type: int = 2,
    axes: Sequence[int] | int | None = None,
    norm: str | None = None,
    *,
    engine: str | None = None,
) -> torch.Tensor:
    """n-dimensional discrete sine transform, as ``scipy.fft.dstn`` (types 2 and 3).

    Args:
        x: Real tensor (float32/float64).
        type: 2 (cell-centred, diagonalises the face-Dirichlet Laplacian) or 3 (its inverse up to scale).
        axes: Axes to transform (default: all).
        norm: ``'backward'`` (default), ``'ortho'`` or ``'forward'``.
        engine: FFT engine (see :func:`resolve_engine`).

    Returns:
        Real tensor of the same shape.

    Raises:
        ParameterError: For other types, an unknown norm or a non-float tensor.
    """
    return _trig(x, "dst", type, axes, norm, False, engine)


def idstn(
    x: torch.Tensor,
    type: int = 2,
    axes: Sequence[int] | int | None = None,
    norm: str | None = None,
    *,
    engine: str | None = None,
) -> torch.Tensor:
    """Inverse of :func:`dstn` with the same ``type`` and ``norm`` (as ``scipy.fft.idstn``).

    Args:
        x: Real tensor (float32/float64).
        type: 2 or 3 — the type of the forward transform being inverted.
        axes: Axes to transform (default: all).
        norm: ``'backward'`` (default), ``'ortho'`` or ``'forward'``.
        engine: FFT engine (see :func:`resolve_engine`).

    Returns:
        Real tensor of the same shape.

    Raises:
        ParameterError: For other types, an unknown norm or a non-float tensor.
    """
    return _trig(x, "dst", type, axes, norm, True, engine)
