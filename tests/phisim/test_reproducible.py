"""Same seed and settings give bit-identical results in two fresh processes (default FFT planning)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]

SCRIPT = r"""
import hashlib, torch
from phisim import fft
from phisim.boundary import Boundary
from phisim.field import CenteredGrid, StaggeredGrid
from phisim.fluid import FluidState, Obstacle, step
from phisim.grid import Grid

assert fft.get_fft_settings().planner_effort == "FFTW_ESTIMATE", fft.get_fft_settings()
torch.manual_seed(0)
grid = Grid((32, 48))
walls = Boundary.create("wall", 2)
x = grid.cell_centers(torch.float32)
source = ((((x - torch.tensor([16.0, 5.0])) ** 2).sum(-1) <= 9.0).float())[None]
marker = CenteredGrid(torch.rand(1, 32, 48) * 0.1, grid, walls.for_scalar())
velocity = StaggeredGrid.zeros(grid, walls, 1)
state = FluidState(velocity, marker)
h = hashlib.sha256()
for _ in range(8):
    state = step(state, 0.5, viscosity=0.01, buoyancy_strength=0.5, marker_source=source,
                 obstacles=Obstacle.sphere([17.0, 22.0], 3.0), advection="maccormack")
    for t in (state.marker.values, *state.velocity.values):
        h.update(t.detach().numpy().tobytes())
print(h.hexdigest())
"""


def _run() -> str:
    env = {k: v for k, v in os.environ.items() if k != "PHISIM_FFT_PLANNER"}
    env["PYTHONPATH"] = str(ROOT) + os.pathsep + env.get("PYTHONPATH", "")
    out = subprocess.run([sys.executable, "-c", SCRIPT], capture_output=True, text=True, env=env, timeout=300,
                         cwd=ROOT)
    assert out.returncode == 0, out.stderr
    return out.stdout.strip().splitlines()[-1]


def test_plume_bit_identical_in_two_fresh_processes():
    a, b = _run(), _run()
    assert len(a) == 64 and a == b


def test_planner_environment_variable(monkeypatch):
    from phisim import fft

    monkeypatch.setenv("PHISIM_FFT_PLANNER", "measure")
    assert fft._settings_from_environment().planner_effort == "FFTW_MEASURE"
    monkeypatch.setenv("PHISIM_FFT_PLANNER", "bogus")

    with pytest.warns(UserWarning, match="PHISIM_FFT_PLANNER"):
        assert fft._settings_from_environment().planner_effort == "FFTW_ESTIMATE"
    monkeypatch.delenv("PHISIM_FFT_PLANNER")
    assert fft._settings_from_environment().planner_effort == "FFTW_ESTIMATE"
