"""Outputs that do not surprise (issue 26, item 7): strict JSON summaries (no bare NaN / Infinity), a dataset too
small for its splits says so, training reports where its held-out samples come from, and ``phisim plot``
passes its 3-D slice options to the plotting function."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest

from inverse import cli_checks
from inverse.cli import main
from phisim.simulate import resolve_config
from phisim.simulate.dataset import plan_chunks, split_shortfall


def _strict(text: str):
    def refuse(name):
        raise ValueError(f"not JSON: {name}")

    return json.loads(text, parse_constant=refuse)


def test_json_summary_writes_null_for_non_finite_numbers_and_says_so():
    text = cli_checks.json_summary({"a": math.nan, "b": [1.0, math.inf], "c": {"d": -math.inf}, "e": 2.5, "f": None})
    data = _strict(text)
    assert data["a"] is None and data["b"] == [1.0, None] and data["c"] == {"d": None} and data["e"] == 2.5
    assert "NaN" in data[cli_checks.NULL_NOTE_KEY]
    assert cli_checks.NULL_NOTE_KEY not in _strict(cli_checks.json_summary({"x": 1.0, "f": None}))
    with pytest.raises(ValueError, match="not JSON"):
        _strict(json.dumps({"a": math.nan}))  # what the summaries printed before


def test_split_shortfall_names_the_empty_splits():
    small = resolve_config("heat", {})  # the defaults: 8 trajectories, 4 per file -> 2 files
    msg = split_shortfall(small)
    assert {c.split for c in plan_chunks(small)} == {"train"}
    assert "data/valid and data/test stay empty" in msg and "--trajectories 12" in msg
    assert "--trajectories-per-file 2" in msg  # 8 trajectories in 4 files: 2 per file
    one = split_shortfall(resolve_config("heat", {"trajectories": 1, "test_fraction": 0}))
    assert "data/valid stays empty" in one and "--trajectories-per-file" not in one
    assert split_shortfall(resolve_config("heat", {"trajectories": 12})) is None
    assert split_shortfall(resolve_config("heat", {"valid_fraction": 0, "test_fraction": 0})) is None


@pytest.fixture(scope="module")
def datasets(tmp_path_factory):
    """Two tiny heat datasets: one file (every file in train) and three files (train, valid, test)."""
    d = tmp_path_factory.mktemp("ds")
    common = ["--trajectories-per-file", "2", "--steps", "2", "--resolution", "8", "--quiet"]
    return d, common


def test_simulate_warns_when_a_split_stays_empty_and_reports_the_splits(datasets, capsys):
    d, common = datasets
    assert main(["simulate", "heat", "--trajectories", "2", *common, "--out", str(d / "small")]) == 0
    out, err = capsys.readouterr()
    summary = _strict(out)
    assert summary["files_per_split"] == {"train": 1, "valid": 0, "test": 0}
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("phisim: warning: 2 trajectories make 1 file(s)"), err
    assert main(["simulate", "heat", "--trajectories", "6", *common, "--out", str(d / "split")]) == 0
    out, err = capsys.readouterr()
    assert _strict(out)["files_per_split"] == {"train": 1, "valid": 1, "test": 1}
    assert "warning" not in err


def _train_well(d, name, capsys):
    code = main(["train", "well", "supervised", "--setting", f"data_dir={d / name}", "--setting",
                 "field=temperature", "--setting", "levels=1", "--setting", "filters=2", "--iterations", "2",
                 "--batch-size", "2", "--quiet"])
    out, err = capsys.readouterr()
    assert code == 0, err
    return _strict(out), err


def test_training_reports_where_its_heldout_samples_come_from(datasets, capsys):
    d, _ = datasets
    if not (d / "split").exists():
        pytest.skip("needs the datasets of the test before")
    summary, err = _train_well(d, "split", capsys)
    assert "2 held-out samples: all trajectories of the 'valid' split" in summary["heldout_measured_on"]
    assert "warning" not in err
    summary, err = _train_well(d, "small", capsys)
    assert ("128 held-out samples drawn from the 'train' split, the data training draws from"
            in summary["heldout_measured_on"])
    assert "phisim: warning:" in err and "does not measure generalisation" in err
    # no physics: the loss is not a number, written as null with the note
    assert summary["final_loss"] is None and summary[cli_checks.NULL_NOTE_KEY]


def test_plot_passes_the_slice_options_through(monkeypatch, tmp_path, capsys):
    import h5py

    import phisim.viz.plotfile as plotfile

    seen = {}

    def fake(path, out=None, **kw):
        seen.update(kw)
        return [tmp_path / "x.png"]

    monkeypatch.setattr(plotfile, "plot_file", fake)
    h5py.File(tmp_path / "f.h5", "w").close()
    assert main(["plot", str(tmp_path / "f.h5"), "--axis", "z", "--index", "3", "--projection", "max"]) == 0
    assert seen["axis"] == "z" and seen["index"] == 3 and seen["projection"] == "max"
    seen.clear()
    assert main(["plot", str(tmp_path / "f.h5"), "--axis", "1"]) == 0
    assert seen["axis"] == 1 and "index" not in seen and "projection" not in seen
    capsys.readouterr()
    assert main(["plot", str(tmp_path / "f.h5"), "--axis", "w"]) == 2
    assert "--axis must be x, y, z or an axis number" in capsys.readouterr().err


def test_plot_of_a_3d_dataset_file_slices_and_projects(tmp_path, capsys):
    """The flags reach the pictures: a projection and a slice of another axis, in the dataset's plots folder."""
    root = tmp_path / "d3"
    assert main(["simulate", "smoke", "--dim", "3", "--resolution", "8", "--steps", "2", "--trajectories", "1",
                 "--trajectories-per-file", "1", "--quiet", "--out", str(root)]) == 0
    capsys.readouterr()
    f = root / "data" / "train" / "smoke_00000.h5"
    assert main(["plot", str(f), "--axis", "y", "--projection", "max", "--animation", "none"]) == 0
    assert main(["plot", str(f), "--axis", "x", "--index", "2", "--animation", "none"]) == 0
    names = sorted(Path(p).name for p in capsys.readouterr().out.split())
    assert names == ["smoke_00000_density_max_y.png", "smoke_00000_density_x2.png"], names
    assert all((root / "plots" / "train" / n).is_file() for n in names)
    assert main(["plot", str(f), "--axis", "x", "--index", "20", "--animation", "none"]) == 2
    assert "index 20 out of range" in capsys.readouterr().err
