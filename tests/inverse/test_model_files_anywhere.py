"""Model files rebuild their problem from any working directory (issue 26, item 2).

A factory named ``file.py:function`` is stored by its absolute path; ``module:function`` as it is, with the
module's file as the fallback when the module is not importable from the other folder; model files of earlier
versions (a relative ``file.py``) are found beside the model file or in a folder above it. A model of a problem
built with ``make_problem`` in Python loads with ``network=problem.make_network()``; one built through its
factory (``get_problem('file.py:function')``) loads by itself.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest
import torch

from inverse import get_problem, load_model, model_path, train
from inverse.models import read_model_file, save_model
from phisim.errors import ParameterError

ROOT = Path(__file__).resolve().parents[2]
SMALL = {"resolution": 8, "steps": 2}


def test_cli_model_of_a_relative_factory_file_loads_and_predicts_from_another_folder(tmp_path, monkeypatch, capsys):
    from inverse.cli import main

    monkeypatch.chdir(ROOT)  # as the tutorial: `phisim train examples/burgers_inverse.py:burgers_problem ...`
    out = tmp_path / "run" / "b.h5"
    assert main(["train", "examples/burgers_inverse.py:burgers_problem", "pg_inverse_gradient", "--iterations", "2",
                 "--batch-size", "2", "--setting", "resolution=8", "--setting", "steps=2", "--out", str(out),
                 "--quiet"]) == 0
    model = model_path(out, "pg_inverse_gradient")
    state = read_model_file(model)
    assert state["factory"] == f"{ROOT / 'examples' / 'burgers_inverse.py'}:burgers_problem"
    assert Path(state["factory_file"]) == ROOT / "examples" / "burgers_inverse.py"
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    net = load_model(model)
    with h5py.File("later.h5", "w") as f:
        f["inputs"] = np.random.default_rng(0).normal(size=(5, 8))
    capsys.readouterr()
    assert main(["predict", str(model), "later.h5", "--key", "inputs", "--out", "pred.h5"]) == 0
    with h5py.File("pred.h5", "r") as f:
        pred = np.asarray(f["predictions"])
    with h5py.File("later.h5", "r") as f, torch.no_grad():
        assert np.allclose(pred, net(torch.as_tensor(np.asarray(f["inputs"]))).numpy())
    # a fresh process in yet another folder (nothing cached from the training run)
    code = (f"from inverse import load_model; n = load_model({str(model)!r}); "
            "print(type(n).__name__, n.phisim_model['method'])")
    r = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    assert r.stdout.split() == ["ResidualMLP", "pg_inverse_gradient"]


def test_module_factory_found_only_from_its_folder_falls_back_to_its_file(tmp_path, monkeypatch):
    a = tmp_path / "a"
    a.mkdir()
    shutil.copy(ROOT / "examples" / "burgers_inverse.py", a / "my_burgers_xyz.py")
    monkeypatch.setattr(sys, "path", list(sys.path))
    monkeypatch.chdir(a)
    p = get_problem("my_burgers_xyz:burgers_problem", **SMALL)  # importable because the working folder is on the path
    assert p.spec["factory"] == "my_burgers_xyz:burgers_problem"
    r = train(p, "adam", iterations=2, batch_size=2, out=a / "m.h5")
    model = model_path(a / "m.h5", "adam")
    assert read_model_file(model)["factory_file"] == str((a / "my_burgers_xyz.py").resolve())
    b = tmp_path / "b"
    b.mkdir()
    monkeypatch.chdir(b)
    monkeypatch.setattr(sys, "path", [s for s in sys.path if s not in ("", str(a))])
    monkeypatch.delitem(sys.modules, "my_burgers_xyz")
    net = load_model(model)
    x = torch.randn(3, 8, dtype=torch.float64)
    with torch.no_grad():
        assert torch.equal(net(x), r.model.eval()(x))


def test_model_file_of_an_earlier_version_with_a_relative_path_is_found_above_the_model(tmp_path, monkeypatch):
    proj = tmp_path / "proj"
    (proj / "examples").mkdir(parents=True)
    shutil.copy(ROOT / "examples" / "burgers_inverse.py", proj / "examples" / "burgers_inverse.py")
    monkeypatch.chdir(proj)
    p = get_problem("examples/burgers_inverse.py:burgers_problem", **SMALL)
    net0 = p.make_network()
    model = save_model(proj / "out" / "old.model.pt", net0, p, method="adam")
    state = torch.load(model, weights_only=True)
    state["factory"] = "examples/burgers_inverse.py:burgers_problem"  # as written before factories were anchored
    del state["factory_file"]
    torch.save(state, model)
    monkeypatch.chdir(tmp_path)  # not the project folder: the relative path alone does not resolve here
    assert type(load_model(model)).__name__ == "ResidualMLP"
    state["factory"] = "nowhere/missing_factory.py:burgers_problem"
    torch.save(state, model)
    with pytest.raises(ParameterError, match="cannot be found.*network="):
        load_model(model)


def test_python_trained_models_load_as_the_tutorial_shows(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(sys, "path", [str(ROOT / "examples"), *sys.path])
    monkeypatch.setitem(sys.modules, "burgers_inverse", None)  # restored (removed) after the test
    del sys.modules["burgers_inverse"]
    from burgers_inverse import burgers_problem
    # built in Python from functions: the weights load into the network the problem makes
    problem = burgers_problem(**SMALL)
    train(problem, "adam", iterations=2, batch_size=2, out="out/direct.h5")
    with pytest.raises(ParameterError, match="network=problem.make_network"):
        load_model("out/direct.h5.adam.model.pt")
    net = load_model("out/direct.h5.adam.model.pt", network=problem.make_network())
    assert not net.training
    # built through its factory by name: the model file rebuilds the network by itself
    factory = f"{ROOT / 'examples' / 'burgers_inverse.py'}:burgers_problem"
    problem = get_problem(factory, **SMALL)
    r = train(problem, "pg_inverse_gradient", iterations=2, batch_size=2, out="out/named.h5")
    net = load_model("out/named.h5.pg_inverse_gradient.model.pt")
    assert json.loads(json.dumps(net.phisim_model["settings"])) == SMALL
    x = torch.randn(2, 8, dtype=torch.float64)
    with torch.no_grad():
        assert torch.equal(net(x), r.model.eval()(x))
