"""The FFT settings of the spectral layer: engine, planner, threads, plan-cache size and layout thresholds.

One process-wide :class:`FFTSettings` object (:func:`get_fft_settings`, :func:`set_fft_settings`, the context
manager :func:`fft_settings`); every engine module reads it at call time, so a behaviour is chosen by changing
the settings, never by patching a module constant. :mod:`phisim.spectral.fft` re-exports these names.
"""

from __future__ import annotations

import contextlib
import os
import warnings
from collections.abc import Iterator
from dataclasses import dataclass, fields, replace

from phisim.checks import check_choice, check_int
from phisim.errors import ParameterError

__all__ = ["FFTSettings", "get_fft_settings", "set_fft_settings", "fft_settings", "EFFORTS", "ENGINES"]

ENGINES = ("auto", "torch", "pyfftw")
EFFORTS = ("FFTW_ESTIMATE", "FFTW_MEASURE", "FFTW_PATIENT", "FFTW_EXHAUSTIVE")
#: Default of :attr:`FFTSettings.plan_cache_size`.
PLAN_CACHE_SIZE = 32
#: Default of :attr:`FFTSettings.transpose_bytes` and :attr:`FFTSettings.wall_transpose_bytes` (384 KiB).
TRANSPOSE_BYTES = 384 * 1024
#: Default of :attr:`FFTSettings.wall_solve_min_samples`: below about 90² the periodic wall solve's extra calls
#: cost more than the shorter transform saves (64², float32: 40 vs 36 µs per component; 96²: 61 vs 61; 128²: 86
#: vs 92; 256²: 0.27 vs 0.33 ms; development CPU, 1 thread).
WALL_SOLVE_MIN_SAMPLES = 8192


@dataclass(frozen=True)
class FFTSettings:
    """Which FFT engine to use and how to plan it.

    Attributes:
        engine: ``'auto'`` (torch on accelerators, pyfftw on the CPU when installed), ``'torch'``
            or ``'pyfftw'`` (CPU tensors only).
        threads: FFTW / pocketfft threads per transform (pyfftw engine). Default 1: two threads measured no
            faster on the 2-core development machine. Bits are reproducible for a fixed thread count.
        planner_effort: ``'FFTW_ESTIMATE'`` (default): bit-reproducible plans. Real-to-real kinds (DCT/DST) run
            on pocketfft (no plans at all) and real FFTs on FFTW plans chosen by FFTW's fixed cost model, each
            built from an empty wisdom table on 64-byte aligned buffers; the same seed and settings give the
            same bits in every process on the machine, fresh or warm, loaded or idle, whatever else was
            planned before. ``'FFTW_MEASURE'`` / ``'FFTW_PATIENT'`` / ``'FFTW_EXHAUSTIVE'`` (opt-in, also via
            the environment variable ``PHISIM_FFT_PLANNER=measure``): FFTW times candidate algorithms (10 ms
            to a few s per new size) and shares its choice through a per-machine wisdom file
            (:mod:`phisim.spectral.wisdom`); float64 DCT/DST of power-of-two sizes then run on FFTW's plans.
            Faster for some transforms (``docs/BENCHMARKS.md``, "Deterministic plans") but **not
            bit-reproducible** across machines, between a machine without wisdom and one with it, or under
            load (the timing decides the plan, and the plan the round-off).
        plan_cache_size: How many FFTW plans each plan cache keeps (least recently used evicted first). There
            are two caches, single transforms and fused transform-multiply-transform pairs; a plan owns
            aligned buffers of its input and output (twice the array, three times for a pair). Default 32.
        transpose_bytes: Planes of at least this many bytes take a type-1 (DCT-I/DST-I) strided axis of a fused
            2-D real-to-real multiply in a transposed copy (:func:`phisim.spectral.pocket.pocket_multiply`).
            Default 384 KiB; 0 always transposes.
        wall_transpose_bytes: float64 arrays of at least this many bytes take the periodic FFT of
            :func:`phisim.spectral.pocket.wall_solve` along a strided axis in a transposed copy. Default
            384 KiB; 0 always transposes (where the axis allows it).
        wall_solve_min_samples: Fewest samples (batch included) of a MAC component for which a box viscosity
            solve with walls on both sides of its own axis runs as a periodic FFT plus a one-face correction
            (:func:`phisim.spectral.fft.wall_solve`) instead of a DST-I; the same answer to round-off. Default
            8192 (about 90²); 0 always takes the periodic route.
    """

    engine: str = "auto"
    threads: int = 1
    planner_effort: str = "FFTW_ESTIMATE"
    plan_cache_size: int = PLAN_CACHE_SIZE
    transpose_bytes: int = TRANSPOSE_BYTES
    wall_transpose_bytes: int = TRANSPOSE_BYTES
    wall_solve_min_samples: int = WALL_SOLVE_MIN_SAMPLES

    def __post_init__(self) -> None:
        # the checks.py helpers: a list, None, a string or NaN where an int/choice is expected, or an int beyond
        # int64, is a ParameterError naming the field
        check_choice(self.engine, "FFT engine", ENGINES)
        check_int(self.threads, "threads", minimum=1)
        check_choice(self.planner_effort, "planner_effort", EFFORTS)
        check_int(self.plan_cache_size, "plan_cache_size", minimum=1)
        for name in ("transpose_bytes", "wall_transpose_bytes", "wall_solve_min_samples"):
            object.__setattr__(self, name, check_int(getattr(self, name), name, minimum=0))
        object.__setattr__(self, "threads", int(self.threads))
        object.__setattr__(self, "plan_cache_size", int(self.plan_cache_size))

    @property
    def deterministic(self) -> bool:
        """Whether these settings give bit-identical results in every process (``FFTW_ESTIMATE``)."""
        return self.planner_effort == "FFTW_ESTIMATE"


def settings_from_environment() -> FFTSettings:
    """The default settings, with ``PHISIM_FFT_PLANNER`` (``estimate``, ``measure``, ``patient``, ``exhaustive``;
    case-insensitive, the ``FFTW_`` prefix optional) applied; an unknown value warns and keeps the default."""
    raw = os.environ.get("PHISIM_FFT_PLANNER", "")
    effort = raw.strip().upper()
    if not effort:
        return FFTSettings()
    if not effort.startswith("FFTW_"):
        effort = "FFTW_" + effort
    if effort not in EFFORTS:
        warnings.warn(f"PHISIM_FFT_PLANNER={raw!r} is not one of {EFFORTS}; using FFTW_ESTIMATE "
                      "(bit-reproducible plans)", stacklevel=2)
        return FFTSettings()
    return FFTSettings(planner_effort=effort)


_SETTINGS = settings_from_environment()


def get_fft_settings() -> FFTSettings:
    """Return the process-wide default :class:`FFTSettings`."""
    return _SETTINGS


def set_fft_settings(settings: FFTSettings | None = None, **changes) -> FFTSettings:
    """Replace the process-wide default FFT settings.

    Args:
        settings: A complete settings object, or None to modify the current one.
        **changes: Fields of :class:`FFTSettings` to change (``engine``, ``threads``, ``planner_effort``,
            ``plan_cache_size``, ``transpose_bytes``, ``wall_transpose_bytes``,
            ``wall_solve_min_samples``).

    Returns:
        The previous settings (pass them back to restore).

    Raises:
        ParameterError: For an unknown engine, thread count, planner flag, a bad size or an unknown setting.
    """
    global _SETTINGS
    previous = _SETTINGS
    base = settings if settings is not None else _SETTINGS
    if not isinstance(base, FFTSettings):
        raise ParameterError(f"set_fft_settings expects an FFTSettings, got {type(base).__name__}")
    unknown = sorted(set(changes) - {f.name for f in fields(FFTSettings)})
    if unknown:
        raise ParameterError(f"unknown FFT setting(s) {unknown}; known: {[f.name for f in fields(FFTSettings)]}")
    _SETTINGS = replace(base, **changes) if changes else base
    return previous


@contextlib.contextmanager
def fft_settings(**changes) -> Iterator[FFTSettings]:
    """Context manager that changes the default FFT settings temporarily.

    Args:
        **changes: Fields of :class:`FFTSettings` to change inside the block.

    Yields:
        The settings in effect inside the block.
    """
    previous = set_fft_settings(**changes)
    try:
        yield _SETTINGS
    finally:
        set_fft_settings(previous)
