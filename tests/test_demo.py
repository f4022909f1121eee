"""The README's main job runs at tiny size and writes every promised output, as a dataset The Well opens."""

import importlib.util
import json
from pathlib import Path

import h5py
import numpy as np
import torch

from phisim.io import read_simulation

ROOT = Path(__file__).resolve().parents[1]


def _equally_spaced_windows(ds, dt):
    """Every window of the loader has frame times k*dt apart (input and output together)."""
    assert len(ds) > 0
    for i in range(len(ds)):
        s = ds[i]
        t = torch.cat([s["input_time_grid"], s["output_time_grid"]]).double().numpy()
        np.testing.assert_allclose(np.diff(t), dt, rtol=1e-6)


def test_demo_tiny(tmp_path):
    from the_well.data import WellDataset
    from the_well.data.normalization import ZScoreNormalization

    spec = importlib.util.spec_from_file_location("demo", ROOT / "examples" / "demo.py")
    demo = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(demo)
    summary = demo.main(["--out", str(tmp_path), "--resolution", "16", "--steps", "3",
                         "--train-resolution", "16", "--iterations", "2", "--batch-size", "2", "--heldout", "4"])
    for name in ("data/train/smoke.h5", "data/valid/smoke.h5", "stats.yaml", "smoke.gif", "smoke_last.png",
                 "training/training.h5", "training.png", "summary.json"):
        assert (tmp_path / name).stat().st_size > 0, name
    assert not list(tmp_path.glob("*.h5"))  # nothing beside the dataset that a loader would pick up
    def refuse(constant):  # NaN / Infinity are not JSON: the summary writes null
        raise AssertionError(f"summary.json holds {constant}")

    assert json.loads((tmp_path / "summary.json").read_text(), parse_constant=refuse) == summary
    assert summary["smoke"]["max_divergence"] < 1e-4
    # conservative smoke transport: the smoke mass is exactly what the inflow put in
    smoke = summary["smoke"]
    assert abs(smoke["smoke_mass"] - smoke["smoke_added"]) < 1e-6 * smoke["smoke_added"]
    train = read_simulation(tmp_path / "data" / "train" / "smoke.h5")
    valid = read_simulation(tmp_path / "data" / "valid" / "smoke.h5")
    assert train.n_frames == 4 and train.fields["density"].shape == (1, 4, 16, 16)
    assert train.dt == 0.5 and np.allclose(np.diff(train.times), 0.5)
    assert np.isfinite(train.fields["density"]).all() and train.fields["density"][0, -1].sum() > 0
    assert not np.array_equal(train.fields["density"][0, -1], valid.fields["density"][0, -1])  # other inflow
    solid = train.constant_fields["obstacle_mask"]  # the one name of the obstacle field (scenarios too)
    assert solid.shape == (16, 16) and 0 < solid.sum() < 256
    assert np.abs(train.fields["density"][0, :, solid > 0.5]).max() < np.abs(train.fields["density"]).max()
    # The README's three lines: the loader opens the folder as it is, with normalisation
    ds = WellDataset(path=str(tmp_path), well_split_name="train", use_normalization=True,
                     normalization_type=ZScoreNormalization)
    assert ds.norm is not None and len(ds) == 3  # one trajectory, windows of 1 + 1 frames
    s = ds[0]
    assert s["constant_fields"].shape == (16, 16, 1)
    _equally_spaced_windows(WellDataset(path=str(tmp_path), well_split_name="valid", n_steps_input=2,
                                        n_steps_output=2, normalize_time_grid=False), 0.5)
    with h5py.File(tmp_path / "training" / "training.h5") as f:
        for m in ("adam", "pg"):
            g = f[f"training/{m}"]
            assert g["metric"].shape == (2,) and np.isfinite(g["metric"][()]).all()
            assert np.isfinite(g["eval_metric"][()]).tolist() == [False, True]  # the final model
            assert "sum over cells" in g.attrs["metric_name"] and g.attrs["heldout_size"] == 4
    assert summary["training"]["adam"]["heldout_metric"] > 0
