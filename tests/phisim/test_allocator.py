"""``phisim.allocator.keep_freed_memory``: freed memory is reused by the next step instead of faulted in again."""

from __future__ import annotations

import subprocess
import sys

import pytest

SCRIPT = r"""
import resource, sys, torch
from phisim.allocator import keep_freed_memory
applied = keep_freed_memory()
assert keep_freed_memory() == applied  # once per process
x = torch.ones(1 << 18)  # 1 MiB
def step():  # several blocks of 1 MiB live at once and freed together, as a time step's arrays are
    blocks = [x * float(i) for i in range(8)]
    return sum(float(b[-1]) for b in blocks)
for _ in range(3):
    step()
r0 = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
for _ in range(20):
    step()
faults = resource.getrusage(resource.RUSAGE_SELF).ru_minflt - r0
print(applied, faults)
"""


def _run(env_extra: dict) -> tuple[bool, int]:
    import os

    env = {k: v for k, v in os.environ.items() if not k.startswith("MALLOC_")}
    env.update(env_extra)
    out = subprocess.run([sys.executable, "-c", SCRIPT], capture_output=True, text=True, env=env, check=True)
    applied, faults = out.stdout.split()
    return applied == "True", int(faults)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's mallopt: Linux only")
def test_kept_memory_removes_the_page_faults_of_repeated_steps():
    """With the thresholds set, 20 steps after the first take (almost) no page fault (at most the heap
    growing by a block once). The comparison run fixes
    glibc's thresholds small through the environment (the user's choice, which ``keep_freed_memory`` leaves
    alone): each step then maps its 8 MiB afresh, about 2048 faults a step. (glibc's default thresholds adapt to
    the process's history, so whether a step re-faults with them varies from run to run; the benchmark that
    showed it is in ``docs/BENCHMARKS.md``.)"""
    applied, faults = _run({})
    off, faults_off = _run({"MALLOC_MMAP_THRESHOLD_": "131072", "MALLOC_TRIM_THRESHOLD_": "131072"})
    assert applied and not off
    assert faults_off > 20 * 1000
    assert faults < faults_off / 20  # at most a heap growth of a block or two (256 faults each), not every step


def test_switched_off_and_the_users_malloc_settings_win():
    assert not _run({"MALLOC_TRIM_THRESHOLD_": "131072"})[0]
    assert not _run({"PHISIM_KEEP_FREED_MEMORY": "0"})[0]
