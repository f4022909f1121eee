"""Same seed and settings give bit-identical results in two fresh processes (default FFT planning:
measured plans shared through the machine's FFTW wisdom file; pocketfft transforms need no plans)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]

SCRIPT = r"""
import hashlib, torch
from phisim.spectral import fft
from phisim.boundary import Boundary
from phisim.field import CenteredGrid, StaggeredGrid
from phisim.fluid import FluidState, Obstacle, step
from phisim.grid import Grid

assert fft.get_fft_settings().planner_effort == "FFTW_MEASURE", fft.get_fft_settings()
torch.manual_seed(0)
grid = Grid((16, 24))
walls = Boundary.create("wall", 2)
x = grid.cell_centers(torch.float32)
source = ((((x - torch.tensor([8.0, 3.0])) ** 2).sum(-1) <= 4.0).float())[None]
marker = CenteredGrid(torch.rand(1, 16, 24) * 0.1, grid, walls.for_scalar())
velocity = StaggeredGrid.zeros(grid, walls, 1)
state = FluidState(velocity, marker)
h = hashlib.sha256()
for _ in range(8):
    state = step(state, 0.5, viscosity=0.01, buoyancy_strength=0.5, marker_source=source,
                 obstacles=Obstacle.sphere([9.0, 11.0], 2.0), advection="maccormack")
    for t in (state.marker.values, *state.velocity.values):
        h.update(t.detach().numpy().tobytes())
# float32 real-to-real transforms run on pocketfft (no plans); a float64 DCT and a real FFT use measured FFTW plans
p = torch.rand(2, 16, 24, dtype=torch.float64)
h.update(fft.dctn(p, 2, (1, 2), engine="pyfftw").numpy().tobytes())
h.update(torch.view_as_real(fft.rfftn(p.float(), (1, 2), engine="pyfftw")).numpy().tobytes())
print(h.hexdigest())
"""


def _run(wisdom: Path) -> str:
    env = {k: v for k, v in os.environ.items() if k != "PHISIM_FFT_PLANNER"}
    env["PHISIM_FFTW_WISDOM"] = str(wisdom)
    env["PYTHONPATH"] = str(ROOT) + os.pathsep + env.get("PYTHONPATH", "")
    out = subprocess.run([sys.executable, "-c", SCRIPT], capture_output=True, text=True, env=env, timeout=300,
                         cwd=ROOT)
    assert out.returncode == 0, out.stderr
    return out.stdout.strip().splitlines()[-1]


def test_plume_bit_identical_in_two_fresh_processes(tmp_path):
    wisdom = tmp_path / "wisdom.bin"  # a cold start: the first process measures, the second reuses
    a = _run(wisdom)
    assert wisdom.stat().st_size > 100
    b = _run(wisdom)
    assert len(a) == 64 and a == b


def test_unusable_wisdom_file_falls_back_to_estimate(tmp_path, monkeypatch):
    from phisim.spectral import fft
    from phisim.spectral import wisdom as _fftw_wisdom

    if not fft._HAVE_PYFFTW:
        pytest.skip("pyfftw not installed")
    blocker = tmp_path / "file"
    blocker.write_text("x")
    monkeypatch.setitem(_fftw_wisdom._STATE, "resolved", True)
    monkeypatch.setitem(_fftw_wisdom._STATE, "path", blocker / "wisdom.bin")  # its folder is a file
    monkeypatch.setitem(_fftw_wisdom._STATE, "warned", False)
    efforts = []
    with pytest.warns(RuntimeWarning, match="FFTW_ESTIMATE"):
        _fftw_wisdom.plan(fft._pyfftw, lambda e: efforts.append(e), "FFTW_MEASURE")
    assert efforts == ["FFTW_ESTIMATE"]


def test_planner_environment_variable(monkeypatch):
    from phisim.spectral import fft

    monkeypatch.setenv("PHISIM_FFT_PLANNER", "estimate")
    assert fft._settings_from_environment().planner_effort == "FFTW_ESTIMATE"
    monkeypatch.setenv("PHISIM_FFT_PLANNER", "bogus")
    with pytest.warns(UserWarning, match="PHISIM_FFT_PLANNER"):
        assert fft._settings_from_environment().planner_effort == "FFTW_MEASURE"
    monkeypatch.delenv("PHISIM_FFT_PLANNER")
    assert fft._settings_from_environment().planner_effort == "FFTW_MEASURE"
