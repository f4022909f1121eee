"""The README's main job runs at tiny size and writes every promised output."""

import importlib.util
import json
from pathlib import Path

import h5py
import numpy as np

from phisim.io import read_simulation

ROOT = Path(__file__).resolve().parents[1]


def test_demo_tiny(tmp_path):
    spec = importlib.util.spec_from_file_location("demo", ROOT / "examples" / "demo.py")
    demo = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(demo)
    summary = demo.main(["--out", str(tmp_path), "--resolution", "16", "--steps", "3",
                         "--train-resolution", "16", "--iterations", "2", "--batch-size", "2"])
    for name in ("smoke.h5", "smoke.gif", "smoke_last.png", "training.h5", "training.png", "summary.json"):
        assert (tmp_path / name).stat().st_size > 0, name
    assert json.loads((tmp_path / "summary.json").read_text()) == summary
    assert summary["smoke"]["max_divergence"] < 1e-4
    # conservative smoke transport: 3 steps of dt 0.5 from an inflow of 4 cells of volume 16 put in exactly 96
    assert abs(summary["smoke"]["smoke_mass"] - 96.0) < 1e-3
    sim = read_simulation(tmp_path / "smoke.h5")
    assert sim.n_frames == 4 and sim.fields["density"].shape == (1, 4, 16, 16)
    assert np.isfinite(sim.fields["density"]).all() and sim.fields["density"][0, -1].sum() > 0
    with h5py.File(tmp_path / "training.h5") as f:
        for m in ("adam", "pg"):
            assert f[f"training/{m}/metric"].shape == (2,)
            assert np.isfinite(f[f"training/{m}/metric"][()]).all()
