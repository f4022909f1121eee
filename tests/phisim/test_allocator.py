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
    applied, faults = _run({})
    off, faults_off = _run({"PHISIM_KEEP_FREED_MEMORY": "0"})
    assert applied and not off
    # glibc's default returns the 8 MiB freed by each step to the system: 20 steps fault ~ 20 x 2048 pages in
    assert faults_off > 1000
    assert faults < faults_off / 20


def test_the_users_malloc_settings_win():
    applied, _ = _run({"MALLOC_TRIM_THRESHOLD_": "131072"})
    assert not applied
