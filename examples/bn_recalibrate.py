"""Held-out error of trained networks with BatchNorm statistics as trained, recomputed, and per batch.

The held-out evaluation of ``inverse.train`` puts the network in eval mode: BatchNorm then normalises with its
running statistics, an exponential average (momentum 0.1) of the training batches' statistics. While the
weights still move fast those averages lag the weights, and the held-out error can exceed the training-batch
error although nothing is overfitted (the data are drawn fresh every batch). This script separates that lag
from generalisation. For the final network of each run (read from its checkpoint) it reports the mean
per-sample metric on the problem's held-out set:

* ``as trained``: eval mode with the running statistics as the run left them (the held-out figure the
  reproductions log);
* ``recalibrated``: eval mode after the statistics are recomputed as exact averages over ``--batches`` fresh
  training batches (forward passes only; the weights do not change), the usual BatchNorm recalibration;
* ``batch statistics``: each held-out batch of ``batch_size`` samples normalised by its own statistics
  (train-mode normalisation; the network is a copy, nothing is kept);
* ``training stream``: the mean training-batch metric of the last ``--window`` iterations of the run.

Run:  python examples/bn_recalibrate.py --experiment e4 --resolution 64 --methods adam pg \\
          --runs data/results/e4_64x128_s0 data/results/e4_64x128_s1 data/results/e4_64x128_s2 \\
          --json data/results/e4_64x128_bn.json
"""

from __future__ import annotations

import argparse
import copy
import json
import sys
from pathlib import Path

import numpy as np
import torch
from torch import nn

sys.path.insert(0, str(Path(__file__).resolve().parent))

from reproduce import _problem  # noqa: E402

from inverse.train import _slice_batch, evaluate  # noqa: E402
from phisim.checks import check_device  # noqa: E402
from phisim.errors import ParameterError  # noqa: E402
from phisim.io import read_training  # noqa: E402

#: Seed of the recalibration batches (independent of the training streams and of the held-out set).
RECALIBRATION_SEED = 20_261_124


def recalibrate(problem, model: nn.Module, batches: int, device) -> nn.Module:
    """A copy of ``model`` whose BatchNorm statistics are exact averages over ``batches`` fresh batches."""
    net = copy.deepcopy(model)
    norms = [m for m in net.modules() if isinstance(m, nn.modules.batchnorm._BatchNorm)]
    if not norms:
        raise ParameterError("the network has no BatchNorm layer to recalibrate")
    for m in norms:
        m.reset_running_stats()
        m.momentum = None  # cumulative average over the batches seen
    gen = torch.Generator().manual_seed(RECALIBRATION_SEED)
    net.train()
    with torch.no_grad():
        for _ in range(batches):
            problem.predict(net, problem.sample(problem.batch_size, gen, device=device))
    return net


def batch_statistics(problem, model: nn.Module, device) -> float:
    """Mean held-out metric with every chunk of ``batch_size`` samples normalised by its own statistics."""
    net = copy.deepcopy(model)
    net.train()
    held = problem.heldout(device)
    n = int(held.inputs.shape[0])
    total = 0.0
    with torch.no_grad():
        for start in range(0, n, problem.batch_size):
            part = _slice_batch(held, slice(start, start + problem.batch_size))
            total += float(problem.metric(problem.predict(net, part), part).double().sum())
    return total / n


def diagnose(exp: str, resolution: int | None, runs: list[Path], methods: list[str], batches: int, window: int,
             batch_size: int | None, device) -> dict:
    """``{run: {method: {'as_trained', 'recalibrated', 'batch_statistics', 'training_stream', 'iteration'}}}``."""
    problem = _problem(exp, resolution)
    if batch_size is not None:
        problem.batch_size = batch_size
    out: dict = {}
    for run in runs:
        h5 = run / f"{exp}.h5"
        logs = read_training(h5)
        out[str(run)] = {}
        for method in methods:
            ckpt = run / f"{exp}.h5.{method}.ckpt"
            if not ckpt.exists() or method not in logs:
                raise ParameterError(f"{run}: no checkpoint or curve of '{method}' ({ckpt.name})")
            state = torch.load(ckpt, map_location="cpu", weights_only=False)
            model = problem.make_network().to(device=device, dtype=problem.dtype)
            model.load_state_dict(state["model"])
            metric = np.asarray(logs[method]["metric"], dtype=np.float64)
            entry = {
                "iteration": int(state["iteration"]),
                "as_trained": evaluate(problem, model, device=device)["metric"],
                "recalibrated": evaluate(problem, recalibrate(problem, model, batches, device),
                                         device=device)["metric"],
                "batch_statistics": batch_statistics(problem, model, device),
                "training_stream": float(metric[-window:].mean()),
            }
            out[str(run)][method] = entry
            print(f"{run} {method} it {entry['iteration']}: as trained {entry['as_trained']:.1f}, recalibrated "
                  f"{entry['recalibrated']:.1f}, batch statistics {entry['batch_statistics']:.1f}, training "
                  f"stream {entry['training_stream']:.1f}", flush=True)
    return out


def main(argv: list[str] | None = None) -> dict:
    """Command-line entry point."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--experiment", choices=["e3", "e4"], required=True)
    ap.add_argument("--resolution", type=int, default=None, help="cells per axis (default 64)")
    ap.add_argument("--batch-size", type=int, default=None, help="the runs' batch size (default: the paper's)")
    ap.add_argument("--runs", type=Path, nargs="+", required=True, help="output folders of reproduce.py")
    ap.add_argument("--methods", nargs="+", default=["adam", "pg"])
    ap.add_argument("--batches", type=int, default=20, help="fresh batches for the recalibration")
    ap.add_argument("--window", type=int, default=16, help="iterations of the training-stream mean")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)
    result = diagnose(args.experiment, args.resolution, args.runs, args.methods, args.batches, args.window,
                      args.batch_size, check_device(args.device))
    if args.json is not None:
        args.json.write_text(json.dumps({"experiment": args.experiment, "batches": args.batches,
                                         "window": args.window, "seed": RECALIBRATION_SEED,
                                         "runs": result}, indent=1))
    return result


if __name__ == "__main__":
    main()
