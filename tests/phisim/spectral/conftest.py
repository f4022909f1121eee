"""Shared helpers of the spectral-layer tests: settings restored after every test, fresh Python processes with a
chosen FFTW wisdom location, and a busy background process."""

from __future__ import annotations

import os
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

from phisim.spectral import fft

ROOT = Path(__file__).resolve().parents[3]

# Spins all CPUs it is given until killed: FFTW timings (and so measured plans) change under such load.
BUSY = "import os, time\nwhile True:\n    sum(i * i for i in range(10000))\n"


@pytest.fixture(autouse=True)
def _default_fft_settings() -> Iterator[None]:
    """Every test starts from, and leaves behind, the process-wide FFT settings it found."""
    with fft.fft_settings():
        yield


def fresh_env(wisdom: Path | str | None = None, **extra: str) -> dict[str, str]:
    """The environment of a fresh process: phisim importable, the default planner (``PHISIM_FFT_PLANNER``
    unset unless given in ``extra``), FFTW wisdom at ``wisdom`` (``PHISIM_FFTW_WISDOM``), one thread."""
    env = {k: v for k, v in os.environ.items() if k not in ("PHISIM_FFT_PLANNER", "PHISIM_FFTW_WISDOM")}
    if wisdom is not None:
        env["PHISIM_FFTW_WISDOM"] = str(wisdom)
    env["PYTHONPATH"] = str(ROOT) + os.pathsep + env.get("PYTHONPATH", "")
    env.setdefault("OMP_NUM_THREADS", "1")
    env.update(extra)
    return env


def run_fresh(script: str, env: dict[str, str], timeout: float = 300) -> str:
    """Run ``script`` in a fresh interpreter; return the last line it printed (fails the test on an error)."""
    return run_fresh_together([(script, env)], timeout)[0]


def run_fresh_together(jobs: list[tuple[str, dict[str, str]]], timeout: float = 300) -> list[str]:
    """Run several ``(script, env)`` jobs at once, each in a fresh interpreter; the last line each printed."""
    procs = [subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                              text=True, env=env, cwd=ROOT) for script, env in jobs]
    outs = []
    try:
        for p in procs:
            stdout, stderr = p.communicate(timeout=timeout)
            assert p.returncode == 0, stderr
            outs.append(stdout.strip().splitlines()[-1])
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
                p.wait()
    return outs


@pytest.fixture
def busy_background() -> Iterator[list[subprocess.Popen]]:
    """One CPU-bound process per core this process may use (at most 8), running for the duration of the test."""
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    procs = [subprocess.Popen([sys.executable, "-c", BUSY], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
             for _ in range(min(cores, 8))]
    try:
        yield procs
    finally:
        for p in procs:
            p.kill()
        for p in procs:
            p.wait(timeout=30)
