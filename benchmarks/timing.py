"""Timing helpers shared by the phisim side and the PhiFlow side of the benchmarks.

Imports in both virtual environments (torch is optional here).
"""

from __future__ import annotations

import os
import statistics
import time
from collections.abc import Callable
from typing import Any

#: Threads used by both sides unless told otherwise (see docs/BENCHMARKS.md: 2 shared cores).
DEFAULT_THREADS = 1


def set_threads(n: int) -> None:
    """Fix the intra-op thread count of torch (and the BLAS/OpenMP pools started after this call).

    Args:
        n: number of threads.
    """
    for var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
        os.environ[var] = str(n)
    try:
        import torch

        torch.set_num_threads(n)
    except ImportError:
        pass


#: XLA on one CPU thread (the JAX peers' setting beside a one-thread torch side).
XLA_ONE_THREAD = "--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1"


def jax_peer_environment(device_type: str) -> dict:
    """The environment of a JAX peer's child process: on the CPU one XLA thread; for a GPU run JAX on the GPU,
    without taking most of its memory up front (the phisim side shares the card).

    Args:
        device_type: ``'cpu'`` or ``'cuda'`` (the phisim side's device type).
    """
    if device_type == "cpu":
        return dict(os.environ, XLA_FLAGS=XLA_ONE_THREAD, JAX_PLATFORMS="cpu", OMP_NUM_THREADS="1")
    return dict(os.environ, JAX_PLATFORMS="cuda", XLA_PYTHON_CLIENT_PREALLOCATE="false", OMP_NUM_THREADS="1")


def _sync_fn(device: Any) -> Callable[[], None]:
    if device is not None and str(device).startswith("cuda"):
        import torch

        return lambda: torch.cuda.synchronize(device)
    return lambda: None


def synchronize(device: Any) -> None:
    """Wait until the work queued on ``device`` has finished (CUDA); a no-op for the CPU and ``None``.

    Call it before reading a clock around GPU work: kernels run asynchronously, so without it a timer
    measures only the launches.

    Args:
        device: a torch device or its name.
    """
    _sync_fn(device)()


def time_fn(
    fn: Callable[[], Any],
    *,
    repeats: int = 5,
    warmup: int = 1,
    device: Any = None,
    min_total_s: float = 0.0,
    max_total_s: float = 60.0,
) -> dict:
    """Median wall time of ``fn()`` after warm-up.

    Each repeat is one call; on CUDA the device is synchronised before and after. More repeats
    are added (up to ``max_total_s``) while their total is below ``min_total_s``, which makes
    short cases less noisy.

    Args:
        fn: the work to time; its result is discarded.
        repeats: minimum number of timed calls.
        warmup: untimed calls first (compilation, plan building, caches).
        device: a torch device or string; ``cuda...`` synchronises around each call.
        min_total_s: keep repeating until the timed calls add up to this many seconds.
        max_total_s: stop adding repeats after this many seconds.

    Returns:
        dict with ``median_s``, ``min_s``, ``repeats`` and ``times_s`` (all timed calls).
    """
    sync = _sync_fn(device)
    for _ in range(warmup):
        fn()
    sync()
    times: list[float] = []
    total = 0.0
    while len(times) < repeats or (total < min_total_s and total < max_total_s):
        sync()
        t0 = time.perf_counter()
        fn()
        sync()
        dt = time.perf_counter() - t0
        times.append(dt)
        total += dt
    return {
        "median_s": statistics.median(times),
        "min_s": min(times),
        "repeats": len(times),
        "times_s": times,
    }


def time_steps(
    step: Callable[[Any], Any],
    state: Any,
    *,
    repeats: int = 5,
    warmup: int = 1,
    device: Any = None,
    min_total_s: float = 0.0,
    max_total_s: float = 60.0,
) -> tuple[dict, Any]:
    """Median wall time of one step of a running simulation: ``state = step(state)`` repeatedly.

    The state evolves (the next step starts from the previous result), as in a real run.

    Returns:
        ``(timing dict as in time_fn, final state)``.
    """
    box = [state]

    def once():
        box[0] = step(box[0])

    timing = time_fn(
        once, repeats=repeats, warmup=warmup, device=device, min_total_s=min_total_s, max_total_s=max_total_s
    )
    return timing, box[0]
