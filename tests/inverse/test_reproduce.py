"""examples/reproduce.py runs each experiment at tiny size and writes finite curves, figures, summaries."""

from __future__ import annotations

import copy
import importlib.util
import json
from pathlib import Path

import numpy as np
import pytest
import torch

from phisim.errors import ParameterError
from phisim.io import read_training

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def reproduce(load_example):
    return load_example("reproduce")


def test_running_average(reproduce):
    v = np.array([1.0, 3.0, np.nan, 5.0, 7.0])
    np.testing.assert_allclose(reproduce.running_average(v, 2), [1.0, 2.0, 3.0, 5.0, 6.0])
    np.testing.assert_allclose(reproduce.running_average(v, 100), [1.0, 2.0, 2.0, 3.0, 4.0])
    assert reproduce.iterations_to_reach(np.array([5.0, 3.0, 1.0]), 3.0) == 1
    assert reproduce.iterations_to_reach(np.array([5.0, 4.0]), 3.0) is None


@pytest.mark.parametrize("exp", ["e2", "e3", "e4"])
def test_network_experiment_tiny(reproduce, tmp_path, exp):
    batch = "16" if exp == "e2" else "4"
    args = ["--experiment", exp, "--iterations", "3", "--batch-size", batch, "--resolution", "16",
            "--out", str(tmp_path), "--max-iterations", "pg_lbfgsb=2"]
    result = reproduce.main(args)[exp]
    methods = reproduce.EXPERIMENTS[exp]["methods"]
    curves = read_training(tmp_path / f"{exp}.h5")
    assert set(curves) == set(methods)
    for name, c in curves.items():
        expected = 2 if name == "pg_lbfgsb" else 3
        assert len(c["metric"]) == expected, name
        if result["runs"][name]["diverged"] is None:
            assert np.all(np.isfinite(c["metric"])), name
            assert np.all(np.isfinite(c["loss"])), name
            assert (tmp_path / f"{exp}_{name}.pt").exists()
    assert (tmp_path / f"{exp}_curves.png").stat().st_size > 5_000
    summary = json.loads((tmp_path / f"{exp}_summary.json").read_text())
    finite = [m for m, r in summary["runs"].items() if r["diverged"] is None]
    assert finite, "every method diverged"
    for m in finite:
        assert np.isfinite(summary["methods"][m]["final"]), m
    if exp != "e2":
        assert summary["resolution"] == [16, 16]
        assert (tmp_path / f"{exp}_reconstruction.png").stat().st_size > 5_000
        assert all(np.isfinite(v) for v in summary["reconstruction_mae"].values())
    # --plot-only redraws from the files without training
    again = reproduce.main(args + ["--plot-only"])[exp]
    assert again["methods"]["adam"]["final"] == pytest.approx(summary["methods"]["adam"]["final"])


def test_heat_optimisation_tiny(reproduce, tmp_path):
    reproduce.main(["--experiment", "e4-opt", "--iterations", "20", "--resolution", "16", "--samples", "2",
                    "--out", str(tmp_path)])
    curves = read_training(tmp_path / "e4-opt.h5")
    assert set(curves) == {"opt_gd", "opt_inverse", "opt_inverse_floor", "opt_lbfgsb"}
    assert len(curves["opt_gd"]["metric"]) == 21
    assert len(curves["opt_inverse"]["metric"]) == 3
    assert len(curves["opt_inverse_floor"]["metric"]) == 3
    for name, c in curves.items():
        assert np.all(np.isfinite(c["metric"])), name
        # every method starts from x = 0 and improves on it
        assert c["metric"][-1] < c["metric"][0], name
    assert (tmp_path / "e4-opt_curves.png").stat().st_size > 5_000
    summary = json.loads((tmp_path / "e4-opt_summary.json").read_text())
    assert set(summary["methods"]) == {"opt_gd", "opt_inverse", "opt_inverse_floor", "opt_lbfgsb"}


def test_sine_phase_inverse_is_the_papers_rounding_rule():
    """E2 inverse: ``n = round(a/(2π x0) − 3/4)``, ``x* = a/(3π/2 + 2πn)``, outermost minima kept."""
    import math

    import torch

    from inverse.operators import Sine

    gen = torch.Generator().manual_seed(0)
    a = 0.1 + 10 * torch.rand(2000, generator=gen, dtype=torch.float64)
    x0 = torch.empty(2000, dtype=torch.float64).uniform_(-3, 3, generator=gen)
    n = torch.round(a / (2 * math.pi * x0) - 0.75)
    n = torch.where((x0 > 0) & (n < 0), 0.0, n)
    n = torch.where((x0 < 0) & (n >= 0), -1.0, n)
    expected = a / (1.5 * math.pi + 2 * math.pi * n)
    got = Sine(a, closest="phase").local_inverse(-torch.ones(2000, 1, dtype=torch.float64), x0[:, None])[:, 0]
    torch.testing.assert_close(got, expected, rtol=1e-12, atol=0)
    closest_x = Sine(a).local_inverse(-torch.ones(2000, 1, dtype=torch.float64), x0[:, None])[:, 0]
    assert (closest_x != got).any(), "the two selection rules should differ somewhere"
    assert torch.all(torch.sin(a / got) + 1 < 1e-9)
    assert Sine(a, closest="phase").select(slice(0, 3)).closest == "phase"


# ---------------------------------------------------------------------------------------------------------
# Headline regressions: short, seeded float64 runs whose Adam / PG ratios are pinned, so that a change in a
# method that loses (or halves) its advantage fails here. The pins were measured with these exact settings.
# Tolerances: for E3, switching the network from float64 to float32 (a far larger perturbation than
# cross-machine float64 round-off) moved the ratio by 0.4%, and replacing the training CG (rtol 1e-5) by the
# exact spectral solve by < 0.1%. So 3% for E3 is many times the round-off spread, while halving PG's
# advantage (1.37 -> 1.18) or losing it (-> 1) fails. E4's advantage is small at this size (4%), so its band
# is 1%; E2's ratio is 260 and its band 10%. Each check also asserts the direction (ratio > 1).

HEADLINES = {
    # (problem, settings, iterations, batch, first averaged iteration): pinned Adam / PG ratio, rel. tol.
    "e3_poisson": (("poisson", {"resolution": (16, 16)}, 30, 4, 20), 1.368218, 0.03),
    "e4_heat": (("heat", {"resolution": (16, 16)}, 60, 4, 40), 1.041527, 0.01),
    "e2_sine": (("sine", {}, 300, 100, 250), 260.331592, 0.1),
}


def _ratio_adam_over_pg(name: str, settings: dict, iterations: int, batch: int, lo: int) -> float:
    import torch

    from inverse.problems import get_problem
    from inverse.train import train

    problem = get_problem(name, dtype=torch.float64, **settings)
    pg = "pg_analytic" if name == "sine" else "pg"
    # eval_every=0: the held-out set only after the last iteration (the pinned ratios use training batches)
    curves = {m: train(problem, m, iterations=iterations, batch_size=batch, seed=0, eval_every=0).curves["metric"]
              for m in ("adam", pg)}
    return float(curves["adam"][lo:].mean() / curves[pg][lo:].mean())


@pytest.mark.parametrize("case", sorted(HEADLINES))
def test_headline_pg_ahead_of_adam(case):
    """Adam / PG of the metric averaged over the last iterations of a short seeded run (float64)."""
    (name, settings, iterations, batch, lo), pinned, rel = HEADLINES[case]
    ratio = _ratio_adam_over_pg(name, settings, iterations, batch, lo)
    assert ratio > 1.0, f"{case}: PG is no longer ahead of Adam (Adam / PG = {ratio:.4f})"
    assert ratio == pytest.approx(pinned, rel=rel), f"{case}: Adam / PG = {ratio:.6f}, pinned {pinned}"


def test_seed_table_ratios_of_running_means(tmp_path):
    import sys

    from phisim.io.traininglog import TrainingLog

    sys.path.insert(0, str(ROOT / "examples"))
    spec = importlib.util.spec_from_file_location("seed_table", ROOT / "examples" / "seed_table.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    runs = []
    for seed, scale in ((0, 2.0), (1, 4.0)):
        path = tmp_path / f"s{seed}.h5"
        for name, factor in (("adam", scale), ("pg", 1.0)):
            with TrainingLog(path, name) as log:
                for it in range(10):
                    log.append(it, metric=factor * (10.0 + it))
        runs.append(path)
    out = mod.ratios(runs, at=[4, 10], windows=[1, 4])
    # window 1 at iteration 4: entry 3 -> 2*13/13 and 4*13/13; window 4 at 10: mean of entries 6..9
    assert out[1][4]["per_seed"][0][2] == pytest.approx(2.0) and out[1][4]["mean"] == pytest.approx(3.0)
    assert out[4][10]["per_seed"][1][:2] == pytest.approx((4 * 17.5, 17.5))
    assert out[4][10]["min"] == pytest.approx(2.0) and out[4][10]["max"] == pytest.approx(4.0)
    assert "| 4 | 10 |" in mod.markdown(out, runs) and "Adam / PG" in mod.markdown(out, runs)
    assert "Adam / SGD" in mod.markdown(out, runs, method="sgd")
    # centred windows: entry i averages entries i-1 .. i+2 for window 4 ('valid' average placed at its centre)
    c = mod.centred_average(np.arange(10.0), 4)
    assert np.isnan(c[0]) and c[1] == pytest.approx(1.5) and c[7] == pytest.approx(7.5) and np.isnan(c[8])
    cen = mod.ratios(runs, at=[5], windows=[4], centred=True)
    assert cen[4][5]["per_seed"][0][:2] == pytest.approx((2 * 14.5, 14.5))
    # seed 0's ratio is 2 throughout, seed 1's is 4: the first iteration reaching 3
    assert mod.first_crossing(runs, 3.0, window=1) == [None, 1]
    # pg (10..19) lies below adam's level at iteration 10 (2*19, 4*19) from its first iteration on; adam (20..)
    # never gets down to pg's level at iteration 1 (10)
    assert mod.iterations_to_reach(runs, at=10, window=1) == [1, 1]
    assert mod.iterations_to_reach(runs, at=1, window=1, reference="pg", method="adam") == [None, None]
    bn = {"runs": {str(r.parent): {m: {"as_trained": 3.0, "recalibrated": 2.0, "batch_statistics": 2.5,
                                        "training_stream": 1.0} for m in ("adam", "pg")} for r in runs}}
    text = mod.overview(runs, at=[4, 10], window=1, methods=["pg"], reach=10, bn=bn)
    assert "| PG | **3.00** (2.00-4.00) | **3.00** (2.00-4.00) | 19 | 1 / 1 |" in text
    assert "| PG | 3 | 2 | 2 | 1 |" in text
    with pytest.raises(ParameterError, match="fewer than 11"):
        mod.ratios(runs, at=[11], windows=[1])
    with pytest.raises(ParameterError, match="no curve 'hig'"):
        mod.ratios(runs, at=[1], windows=[1], method="hig")


def test_bn_recalibration_is_the_exact_average_of_the_batches():
    """``recalibrate`` resets BatchNorm and averages the statistics of the fresh batches exactly; the weights
    and the original network stay as they were."""
    import sys
    from types import SimpleNamespace

    sys.path.insert(0, str(ROOT / "examples"))
    spec = importlib.util.spec_from_file_location("bn_recalibrate", ROOT / "examples" / "bn_recalibrate.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    torch.manual_seed(0)
    net = torch.nn.Sequential(torch.nn.Conv2d(1, 3, 3, padding=1), torch.nn.BatchNorm2d(3))
    seen = []

    def sample(batch_size, gen, device=None):
        x = torch.randn(batch_size, 1, 6, 5, generator=gen, dtype=torch.float64) * 2 + 1
        seen.append(x)
        return x

    problem = SimpleNamespace(batch_size=4, sample=sample, predict=lambda model, x: model(x))
    net = net.double()
    before = copy.deepcopy(net.state_dict())
    out = mod.recalibrate(problem, net, batches=3, device="cpu")
    conv = net[0]
    with torch.no_grad():
        acts = [conv(x) for x in seen]
    mean = torch.stack([a.mean(dim=(0, 2, 3)) for a in acts]).mean(0)
    var = torch.stack([a.var(dim=(0, 2, 3), unbiased=True) for a in acts]).mean(0)
    torch.testing.assert_close(out[1].running_mean, mean, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(out[1].running_var, var, rtol=1e-12, atol=1e-12)
    for k, v in net.state_dict().items():  # the original is untouched
        torch.testing.assert_close(v, before[k], rtol=0, atol=0)
    assert all(torch.equal(out.state_dict()[k], v) for k, v in before.items() if "running" not in k
               and "num_batches" not in k)
    with pytest.raises(ParameterError, match="no BatchNorm"):
        mod.recalibrate(problem, torch.nn.Conv2d(1, 1, 1).double(), batches=1, device="cpu")


def test_bn_recalibrate_tiny_run(reproduce, tmp_path):
    """On a tiny E4 run with checkpoints: 'as trained' is the run's own last held-out figure, and the other
    measures are finite."""
    reproduce.main(["--experiment", "e4", "--iterations", "2", "--batch-size", "2", "--resolution", "16",
                    "--methods", "adam", "pg", "--checkpoint-every", "1", "--out", str(tmp_path)])
    spec = importlib.util.spec_from_file_location("bn_recalibrate", ROOT / "examples" / "bn_recalibrate.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    out = mod.main(["--experiment", "e4", "--resolution", "16", "--batch-size", "2", "--runs", str(tmp_path),
                    "--batches", "2", "--window", "2", "--json", str(tmp_path / "bn.json")])
    logs = read_training(tmp_path / "e4.h5")
    for method in ("adam", "pg"):
        entry = out[str(tmp_path)][method]
        assert entry["iteration"] == 2
        held = np.asarray(logs[method]["eval_metric"], dtype=np.float64)
        assert entry["as_trained"] == pytest.approx(held[np.isfinite(held)][-1], rel=1e-9)
        assert all(np.isfinite(entry[k]) for k in ("recalibrated", "batch_statistics", "training_stream"))
    assert json.loads((tmp_path / "bn.json").read_text())["runs"][str(tmp_path)]["pg"]["iteration"] == 2


def test_non_square_grid_as_in_the_papers_text(reproduce, tmp_path):
    """``--resolution NX NY`` (the E3 text's 80x60): the U-net handles sizes that do not halve evenly."""
    out = reproduce.main(["--experiment", "e3", "--resolution", "20", "12", "--batch-size", "2", "--iterations",
                          "2", "--methods", "adam", "pg", "--out", str(tmp_path)])["e3"]
    assert out["resolution"] == [20, 12]
    assert all(np.isfinite(m["final"]) for m in out["methods"].values())
    for bad in (["1", "2", "3"], ["0"]):
        with pytest.raises(ParameterError, match="--resolution"):
            reproduce.main(["--experiment", "e3", "--resolution", *bad, "--out", str(tmp_path / "bad")])


def test_loss_reduction_cannot_change_adam_driven_runs(reproduce, tmp_path):
    """Adam is invariant to a constant scale of its gradient (up to eps), so a batch mean instead of the batch
    sum gives the same E3 curves for Adam and PG to round-off: the reduction cannot explain a gap."""
    common = ["--experiment", "e3", "--resolution", "16", "--batch-size", "4", "--iterations", "4",
              "--methods", "adam", "pg"]
    reproduce.main(common + ["--out", str(tmp_path / "sum")])
    reproduce.main(common + ["--reduction", "mean", "--out", str(tmp_path / "mean")])
    a, b = read_training(tmp_path / "sum" / "e3.h5"), read_training(tmp_path / "mean" / "e3.h5")
    for m in ("adam", "pg"):
        np.testing.assert_allclose(a[m]["metric"], b[m]["metric"], rtol=1e-6)  # float32 round-off: 1e-7


def test_poisson_data_without_normalisation():
    from inverse.problems import get_problem

    gen = torch.Generator().manual_seed(0)
    x = get_problem("poisson", resolution=(16, 16)).sample(3, gen).x_true
    gen = torch.Generator().manual_seed(0)
    raw = get_problem("poisson", resolution=(16, 16), normalize=False).sample(3, gen).x_true
    std = x.double().flatten(1).std(1, unbiased=False)
    np.testing.assert_allclose(std.numpy(), 1.0, rtol=1e-5)
    np.testing.assert_allclose(x.double().flatten(1).mean(1).numpy(), 0.0, atol=1e-6)
    assert not np.allclose(raw.double().flatten(1).std(1, unbiased=False).numpy(), 1.0, rtol=1e-2)
    # the same noise, only shifted and scaled per sample
    for i in range(3):
        r, n = raw[i].double().flatten(), x[i].double().flatten()
        np.testing.assert_allclose(((r - r.mean()) / r.std(unbiased=False)).numpy(), n.numpy(), atol=1e-5)
