"""The smoke plume example runs at tiny size (2-D and 3-D) and writes a readable Well-layout file."""

from __future__ import annotations

from pathlib import Path

import h5py
import numpy as np
import pytest

from phisim.io import read_simulation


@pytest.mark.parametrize("dim, resolution", [(2, 16), (3, 8)])
def test_smoke_plume_tiny(tmp_path, dim, resolution, load_example):
    mod = load_example("smoke_plume")
    res = mod.main(
        [
            "--dim",
            str(dim),
            "--resolution",
            str(resolution),
            "--steps",
            "3",
            "--out",
            str(tmp_path),
            "--no-progress",
            "--batch-size",
            "2",
        ]
    )
    assert res["steps"] == 3 and res["time"] > 0
    assert res["max_relative_divergence"] < 1e-4  # float32 default
    # conservative smoke transport (the default): the box holds exactly what the inflow put in (float32)
    np.testing.assert_allclose(res["smoke"], res["injected"], rtol=1e-5)
    for key in ("gif", "png"):
        assert Path(res[key]).exists() and Path(res[key]).stat().st_size > 1000
    shape = (resolution, int(1.5 * resolution)) + ((resolution,) if dim == 3 else ())
    with h5py.File(res["h5"], "r") as f:
        assert f.attrs["n_spatial_dims"] == dim and f.attrs["n_trajectories"] == 2
        assert f["t0_fields"]["density"].shape == (2, 4, *shape)
        assert f["t1_fields"]["velocity"].shape == (2, 4, *shape, dim)
        assert f["dimensions"]["time"].shape == (4,)
        assert "staggered" in f and "boundary_conditions" in f
        assert all(f["boundary_conditions"][k].attrs["bc_type"] == "WALL" for k in f["boundary_conditions"])
    data = read_simulation(res["h5"])
    rho = data.fields["density"]
    assert np.isfinite(rho).all() and float(rho[:, -1].sum()) > 0 and float(np.abs(rho[:, 0]).max()) == 0
    assert np.all(np.diff(data.times) > 0)
    v = data.frame("velocity", -1)
    assert v.values[1].shape == (2, *[n + (1 if a == 1 else 0) for a, n in enumerate(shape)])
    # the walls are closed in the stored face values
    assert float(np.abs(v.values[1].numpy()[:, :, 0]).max()) == 0
    assert float(np.abs(v.values[1].numpy()[:, :, -1]).max()) == 0


def test_smoke_plume_frames_are_equally_spaced_for_the_well_loader(tmp_path, load_example):
    """Adaptive CFL sub-steps inside, frames at fixed times outside: every loader window is equally spaced."""
    from the_well.data import WellDataset

    mod = load_example("smoke_plume")
    res = mod.main(["--resolution", "12", "--steps", "5", "--interval", "2.0", "--cfl", "0.5",
                    "--out", str(tmp_path), "--no-progress"])
    assert res["substeps"] > res["steps"]  # the CFL step was shorter than the interval
    data = read_simulation(res["h5"])
    np.testing.assert_array_equal(data.times, 2.0 * np.arange(6))
    assert data.dt == 2.0
    assert data.constant_fields["obstacle_mask"].sum() > 0
    ds = WellDataset(path=str(tmp_path), n_steps_input=2, n_steps_output=2, normalize_time_grid=False)
    assert len(ds) == 3  # 6 frames, windows of 4
    for i in range(len(ds)):
        s = ds[i]
        t = np.concatenate([s["input_time_grid"].numpy(), s["output_time_grid"].numpy()]).astype(np.float64)
        np.testing.assert_allclose(np.diff(t), 2.0, rtol=1e-6)
        assert s["constant_fields"].shape[-1] == 1  # the obstacle mask travels with the window
