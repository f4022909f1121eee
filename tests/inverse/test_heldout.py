"""Held-out evaluation: a fixed set per problem, measured in eval mode, logged beside the training-batch curves."""

import copy
import json

import h5py
import numpy as np
import pytest
import torch

from inverse.cli import main as cli_main
from inverse.problems import HELDOUT_SEED, get_problem
from inverse.train import batch_generator, evaluate, train
from phisim.errors import ParameterError
from phisim.viz.plot import plot_training_curves


def _poisson(**kw):
    return get_problem("poisson", **{"resolution": (16, 16), "heldout_size": 6, **kw})


def test_heldout_set_is_fixed_and_not_a_training_batch():
    p = _poisson()
    a = p.heldout()
    assert a is p.heldout()  # built once
    b = _poisson().heldout()  # another instance, same numbers
    torch.testing.assert_close(a.x_true, b.x_true, rtol=0, atol=0)
    assert a.x_true.shape == (6, 16, 16) and p.heldout_seed == HELDOUT_SEED
    for seed in (0, 1):
        train_batch = p.sample(6, batch_generator(seed, 0))
        assert not torch.allclose(train_batch.x_true, a.x_true)
    other = _poisson(heldout_seed=7).heldout()
    assert not torch.allclose(other.x_true, a.x_true)
    with pytest.raises(ParameterError):
        _poisson(heldout_size=0).heldout()
    for name in ("sine", "poisson", "heat"):
        q = get_problem(name)
        assert q.heldout_size == 128 and q.metric_name and q.loss_name


def test_heldout_curves_are_eval_mode_numbers_of_the_model(tmp_path):
    p = _poisson()
    r = train(p, "adam", iterations=4, batch_size=3, seed=0, eval_every=2, out=tmp_path / "t.h5")
    ev = r.curves["eval_metric"]
    assert np.isnan(ev[[0, 2]]).all() and np.isfinite(ev[[1, 3]]).all()
    assert r.model.training  # the loop's evaluation restored train mode
    # the last entry is the final model in eval mode (BatchNorm running statistics) ...
    held = evaluate(p, r.model)
    assert r.final_eval("metric") == pytest.approx(held["metric"], rel=1e-12)
    assert r.final_eval("loss") == pytest.approx(held["loss"], rel=1e-12)
    # ... which is not what train mode (batch statistics) gives on the same samples
    batch = p.heldout()
    with torch.no_grad():  # on a copy: a train-mode forward pass updates the running statistics
        train_mode = float(p.metric(p.predict(copy.deepcopy(r.model), batch), batch).mean())
    assert abs(train_mode - held["metric"]) > 1e-3 * held["metric"]
    # in eval mode samples do not interact: chunking does not change the result
    assert evaluate(p, r.model, chunk_size=1)["metric"] == pytest.approx(held["metric"], rel=1e-5)
    with h5py.File(tmp_path / "t.h5") as f:
        g = f["training/adam"]
        np.testing.assert_array_equal(np.isfinite(g["eval_metric"][()]), [False, True, False, True])
        assert "held-out" in g.attrs["eval_measured_on"] and "training batch" in g.attrs["loss_measured_on"]
        assert g.attrs["metric_name"] == p.metric_name and g.attrs["heldout_size"] == 6
    ax = plot_training_curves({"adam": r.curves}, p.metric_name)
    labels = [t.get_text() for t in ax.get_legend().get_texts()]
    assert labels == ["adam (train batch)", "adam (held-out)"] and ax.get_ylabel() == p.metric_name
    with pytest.raises(ParameterError):
        train(p, "adam", iterations=1, eval_every=-1)


def test_default_schedule_evaluates_about_20_times_and_at_the_end():
    p = get_problem("sine", batch_size=20, heldout_size=50)
    r = train(p, "adam", iterations=45, seed=0)
    assert np.flatnonzero(np.isfinite(r.curves["eval_metric"])).tolist() == [1, 3, 5, 7, 9, 11, 13, 15, 17, 19, 21,
                                                                             23, 25, 27, 29, 31, 33, 35, 37, 39,
                                                                             41, 43, 44]
    r0 = train(p, "adam", iterations=3, seed=0, eval_every=0)
    assert np.isfinite(r0.curves["eval_metric"]).tolist() == [False, False, True]


def test_cli_reports_named_train_and_heldout_numbers(tmp_path, capsys):
    assert cli_main(["train", "poisson", "pg", "--iterations", "2", "--batch-size", "2", "--resolution", "16", "16",
                     "--heldout-size", "3", "--quiet", "--out", str(tmp_path / "p.h5")]) == 0
    rep = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert rep["metric_name"] == "x L1 per sample (sum over cells of |x−x*|)"
    assert np.isfinite(rep["heldout_metric"]) and "3 held-out samples" in rep["heldout_measured_on"]
    assert "training batches" in rep["final_measured_on"]
    assert cli_main(["compare", "poisson", "adam", "pg", "--iterations", "2", "--batch-size", "2",
                     "--resolution", "16", "16", "--heldout-size", "3", "--quiet",
                     "--plot", str(tmp_path / "c.png")]) == 0
    assert (tmp_path / "c.png").stat().st_size > 1000
