"""Keep freed memory for the next time step (glibc's malloc on Linux).

A time step allocates and frees the same few arrays every call. With glibc's default, adaptive thresholds,
arrays of a few MiB are served by ``mmap`` or, when freed at the top of the heap, handed back to the system at
once (the trim threshold follows the largest freed block); the next step then takes a page fault for every 4 KiB
it writes. Measured on a 2-D periodic step at 64² x 32 (float32, one thread): 3.8 ms per step with freed memory
kept, 6.8 ms without, and several hundred page faults per step (``benchmarks/bench_jaxcfd.py``).

:func:`keep_freed_memory` sets the trim and mmap thresholds once per process, so that memory freed by one step is
reused by the next. Steppers call it when they are built on the CPU. It changes nothing where the C library is
not glibc, where the environment already sets ``MALLOC_TRIM_THRESHOLD_``, ``MALLOC_MMAP_THRESHOLD_`` or
``MALLOC_TOP_PAD_`` (the user's choice wins), or where ``PHISIM_KEEP_FREED_MEMORY=0``. The cost is that a
process keeps up to the peak of its heap (up to ``trim_bytes`` above what it uses) instead of returning it early.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os
import sys

__all__ = ["keep_freed_memory"]

# mallopt parameters (malloc.h)
_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3

_done: list[bool] = []


def keep_freed_memory(trim_bytes: int = 256 << 20, mmap_bytes: int = 32 << 20) -> bool:
    """Let glibc keep up to ``trim_bytes`` of freed heap memory and serve blocks below ``mmap_bytes`` from the heap.

    Args:
        trim_bytes: Freed memory at the top of the heap kept before it is returned to the system.
        mmap_bytes: Blocks at least this large are mapped (and unmapped on free) individually.

    Returns:
        Whether the thresholds are set (now or by an earlier call); False where it does not apply (see the
        module docstring).
    """
    if _done:
        return _done[0]
    applied = False
    env = os.environ
    if (sys.platform.startswith("linux") and env.get("PHISIM_KEEP_FREED_MEMORY", "1") != "0"
            and not any(k in env for k in ("MALLOC_TRIM_THRESHOLD_", "MALLOC_MMAP_THRESHOLD_", "MALLOC_TOP_PAD_"))):
        try:
            libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
            mallopt = libc.mallopt
        except (OSError, AttributeError):  # not glibc
            mallopt = None
        if mallopt is not None:
            mallopt.argtypes = (ctypes.c_int, ctypes.c_int)
            mallopt.restype = ctypes.c_int
            applied = bool(mallopt(_M_MMAP_THRESHOLD, int(mmap_bytes))) and bool(
                mallopt(_M_TRIM_THRESHOLD, int(trim_bytes)))
    _done.append(applied)
    return applied
