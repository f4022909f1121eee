"""Bad input to the workflow commands (simulate, plot, predict, export, custom problems, offline data):
exit status 2 and one line on stderr starting with ``phisim: error:``, never a traceback."""

from __future__ import annotations

import re

import h5py
import pytest

from inverse.cli import main


@pytest.fixture()
def files(tmp_path):
    (tmp_path / "bad.json").write_text("{not json")
    (tmp_path / "list.json").write_text("[1, 2]")
    (tmp_path / "factory.py").write_text("def wrong():\n    return 'a string'\n")
    (tmp_path / "model.pt").write_bytes(b"not a model")
    with h5py.File(tmp_path / "empty.h5", "w") as f:
        f.attrs["x"] = 1
    (tmp_path / "ds" / "data" / "train").mkdir(parents=True)
    return tmp_path


CASES = [
    ("simulate-unknown", ["simulate", "smok"], r"did you mean 'smoke'"),
    ("simulate-no-scenario", ["simulate"], r"scenario"),
    ("simulate-unknown-key", ["simulate", "heat", "--set", "difusivity=1"], r"did you mean 'diffusivity'"),
    ("simulate-bad-flag-value", ["simulate", "heat", "--set", "steps=0"], r"steps"),
    ("simulate-bad-dim", ["simulate", "cavity", "--dim", "3"], r"2-D"),
    ("simulate-config-missing", ["simulate", "heat", "--config", "{d}/nope.yaml"], r"does not exist"),
    ("simulate-config-broken", ["simulate", "heat", "--config", "{d}/bad.json"], r"cannot parse"),
    ("simulate-config-not-mapping", ["simulate", "heat", "--config", "{d}/list.json"], r"mapping"),
    ("simulate-workers", ["simulate", "heat", "--workers", "0", "--out", "{d}/w"], r"workers"),
    ("simulate-foreign-folder", ["simulate", "heat", "--out", "{d}/ds"], r"not a phisim dataset"),
    ("plot-missing", ["plot", "{d}/missing.h5"], r"not a readable HDF5|does not exist"),
    ("plot-empty", ["plot", "{d}/empty.h5"], r"neither simulation fields nor training"),
    ("predict-not-a-model", ["predict", "{d}/model.pt", "{d}/empty.h5", "--out", "{d}/p.h5"], r"model file"),
    ("export-no-curves", ["export", "{d}/empty.h5", "--csv", "{d}/csv"], r"no training curves"),
    ("train-factory-wrong-type", ["train", "{d}/factory.py:wrong", "adam", "--iterations", "1"],
     r"expected an inverse.Problem"),
    ("train-factory-typo", ["train", "{d}/factory.py:wrnog", "adam", "--iterations", "1"], r"did you mean 'wrong'"),
    ("train-well-bad-dir", ["train", "well", "supervised", "--setting", "data_dir={d}/ds", "--setting",
                            "field=u", "--iterations", "1"], r"Well's layout"),
    ("train-bad-setting", ["train", "poisson", "adam", "--setting", "resolutoin=8", "--iterations", "1"],
     r"bad settings"),
]


@pytest.mark.parametrize("name, argv, match", CASES, ids=[c[0] for c in CASES])
def test_workflow_errors_are_one_line(name, argv, match, files, capsys, monkeypatch):
    monkeypatch.chdir(files)
    code = main([a.format(d=files) for a in argv])
    err = capsys.readouterr().err
    assert code == 2, err
    assert "Traceback" not in err and err.startswith("phisim: error:")
    assert len(err.strip().splitlines()) == 1, err
    assert re.search(match, err), err
