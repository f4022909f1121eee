"""Same seed and settings give bit-identical results in fresh processes, whatever the timing: the default
planner (``FFTW_ESTIMATE``: pocketfft for DCT/DST, FFTW's cost model for real FFTs, plans built from an empty
wisdom table on 64-byte aligned buffers) needs no wisdom, times nothing, and ignores wisdom already in memory.
Measured plans stay available as an opt-in (shared per machine through a wisdom file)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from phisim.spectral import fft
from phisim.spectral import settings as fft_settings_module
from tests.phisim.spectral.conftest import fresh_env, run_fresh, run_fresh_together

needs_pyfftw = pytest.mark.skipif("pyfftw" not in fft.available_engines(), reason="pyfftw not installed")

SCRIPT = r"""
import hashlib, os, torch
from phisim.spectral import fft
from phisim.boundary import Boundary
from phisim.field import CenteredGrid, StaggeredGrid
from phisim.fluid import FluidState, Obstacle, step
from phisim.grid import Grid


def transforms(h):
    # float64 DCT/DST (pocketfft), real FFTs and a Fourier multiplier of both dtypes (FFTW plans), a fused
    # real-to-real multiply: every engine path of the default settings
    g = torch.Generator().manual_seed(5)
    p = torch.rand(2, 16, 24, dtype=torch.float64, generator=g)
    q = torch.rand(64, 96, dtype=torch.float64, generator=g)
    m = torch.rand(64, 49, dtype=torch.float64, generator=g)
    h.update(fft.dctn(p, 2, (1, 2), engine="pyfftw").numpy().tobytes())
    h.update(fft.r2rn(q, ("dst2", "dct2"), engine="pyfftw").numpy().tobytes())
    for t in (p, p.float(), q, q.float()):
        h.update(torch.view_as_real(fft.rfftn(t, engine="pyfftw")).numpy().tobytes())
    for t in (q, q.float()):
        h.update(fft.fourier_multiply(t, m, engine="pyfftw").numpy().tobytes())
        y = fft.r2r_multiply(t[None], ("dst1", "dct2"), ("dst1", "dct3"), (1, 2), torch.ones(64, 96, dtype=t.dtype),
                             engine="pyfftw")
        h.update(b"" if y is None else y.numpy().tobytes())


if os.environ.get("PRELUDE") == "measure":
    # a warm process: measured plans of the same transforms, their wisdom left in FFTW's memory
    import hashlib as _h
    with fft.fft_settings(planner_effort="FFTW_MEASURE"):
        transforms(_h.sha256())
assert fft.get_fft_settings().planner_effort == "FFTW_ESTIMATE", fft.get_fft_settings()
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
transforms(h)
print(h.hexdigest())
"""


@needs_pyfftw
def test_plume_bit_identical_in_fresh_processes_without_wisdom_under_load(tmp_path, busy_background):
    # Fresh processes running at the same time while every core is busy: two with their own empty wisdom
    # location, a third that first makes measured plans of the same transforms (their wisdom in memory and in
    # its file, as on a warm machine).
    locations = [tmp_path / name / "wisdom.bin" for name in ("a", "b", "c")]
    hashes = run_fresh_together([(SCRIPT, fresh_env(locations[0])), (SCRIPT, fresh_env(locations[1])),
                                 (SCRIPT, fresh_env(locations[2], PRELUDE="measure"))])
    assert all(p.poll() is None for p in busy_background)  # the load lasted through the runs
    assert len(hashes[0]) == 64 and hashes[0] == hashes[1] == hashes[2]
    assert not locations[0].exists() and not locations[1].exists()  # the default plans need no wisdom file
    assert locations[2].stat().st_size > 100  # the measured plans of the warm process did use theirs


@needs_pyfftw
def test_measured_plans_are_an_opt_in_shared_through_the_wisdom_file(tmp_path):
    wisdom = tmp_path / "wisdom.bin"  # a cold start: the first process measures, the second reuses its wisdom
    script = SCRIPT.replace('== "FFTW_ESTIMATE"', '== "FFTW_MEASURE"')
    a = run_fresh(script, fresh_env(wisdom, PHISIM_FFT_PLANNER="measure"))
    assert wisdom.stat().st_size > 100
    b = run_fresh(script, fresh_env(wisdom, PHISIM_FFT_PLANNER="measure"))
    assert len(a) == 64 and a == b  # same warm machine; not promised across machines


@needs_pyfftw
@pytest.mark.parametrize("shape,dtype", [((256, 256), np.float32), ((64, 64, 64), np.float64)])
def test_estimated_plan_ignores_wisdom_in_memory(shape, dtype):
    # FFTW lets measured wisdom in memory change an estimated plan (both sizes here did); phisim builds its
    # estimated plans from an empty table and restores the wisdom it found.
    import pyfftw

    from phisim.spectral import fftw as fft_fftw

    x = torch.from_numpy(np.random.default_rng(3).standard_normal(shape).astype(dtype))
    fft_fftw.clear_plans()
    pyfftw.forget_wisdom()
    fresh = fft.rfftn(x, engine="pyfftw")
    a = pyfftw.empty_aligned(shape, dtype=dtype)
    hshape = (*shape[:-1], shape[-1] // 2 + 1)
    b = pyfftw.empty_aligned(hshape, dtype=np.result_type(dtype, np.complex64))
    pyfftw.FFTW(a, b, axes=tuple(range(len(shape))), flags=("FFTW_MEASURE", "FFTW_DESTROY_INPUT"))
    def entries():
        return [sorted(w.splitlines()) for w in pyfftw.export_wisdom()]

    held = entries()
    fft_fftw.clear_plans()
    again = fft.rfftn(x, engine="pyfftw")
    assert entries() == held  # the measured wisdom is still there, nothing added
    pyfftw.forget_wisdom()
    assert torch.equal(torch.view_as_real(fresh), torch.view_as_real(again))


@needs_pyfftw
@pytest.mark.parametrize("offset", [1, 2, 3])
def test_results_do_not_depend_on_the_input_alignment(offset):
    # FFTW picks SIMD codelets by the buffers' alignment; plans own 64-byte aligned buffers, inputs are copied in
    shape = (64, 96)
    src = torch.from_numpy(np.random.default_rng(4).standard_normal(shape).astype(np.float32))
    base = torch.empty(src.numel() + offset, dtype=torch.float32)
    view = base[offset:].view(shape)
    view.copy_(src)
    assert view.data_ptr() % 16 != 0 or offset == 0
    assert torch.equal(torch.view_as_real(fft.rfftn(view, engine="pyfftw")),
                       torch.view_as_real(fft.rfftn(src.clone(), engine="pyfftw")))
    m = torch.rand(64, 49, dtype=torch.float64)
    assert torch.equal(fft.fourier_multiply(view, m, engine="pyfftw"), fft.fourier_multiply(src, m, engine="pyfftw"))


@needs_pyfftw
def test_unusable_wisdom_file_falls_back_to_estimate(tmp_path, monkeypatch):
    from phisim.spectral import wisdom as fft_wisdom

    blocker = tmp_path / "file"
    blocker.write_text("x")
    monkeypatch.setitem(fft_wisdom._STATE, "resolved", True)
    monkeypatch.setitem(fft_wisdom._STATE, "path", blocker / "wisdom.bin")  # its folder is a file
    monkeypatch.setitem(fft_wisdom._STATE, "warned", False)
    efforts = []
    with pytest.warns(RuntimeWarning, match="FFTW_ESTIMATE"):
        fft_wisdom.plan(fft._pyfftw, lambda e: efforts.append(e), "FFTW_MEASURE")
    assert efforts == ["FFTW_ESTIMATE"]


def test_planner_environment_variable(monkeypatch):
    read = fft_settings_module.settings_from_environment
    monkeypatch.delenv("PHISIM_FFT_PLANNER", raising=False)
    assert read().planner_effort == "FFTW_ESTIMATE" and read().deterministic
    monkeypatch.setenv("PHISIM_FFT_PLANNER", "measure")
    assert read().planner_effort == "FFTW_MEASURE" and not read().deterministic
    monkeypatch.setenv("PHISIM_FFT_PLANNER", "FFTW_ESTIMATE")
    assert read().planner_effort == "FFTW_ESTIMATE"
    monkeypatch.setenv("PHISIM_FFT_PLANNER", "bogus")
    with pytest.warns(UserWarning, match="PHISIM_FFT_PLANNER"):
        assert read().planner_effort == "FFTW_ESTIMATE"
