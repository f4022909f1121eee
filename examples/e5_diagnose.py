"""E5 diagnosis: how well trained networks recover the prior's two parameters (uniform velocity, vortex strength).

For each ``DIR:METHOD`` given, loads the network from the training checkpoint that
``examples/fluid_inverse.py`` writes (``DIR/fluid_inverse.h5.METHOD.ckpt``), predicts ``v0`` for a held-out
batch, and reports: the metric (``sum_cells |v0 - v0*|``, batch mean); the relative error of the uniform
part (the domain mean of ``v0`` against ``u = (c - com(m0)) / t``); the correlation of the predicted vortex
strength (:func:`inverse.fluid_inverse.vortex_strength`) with the true one, and the slope of the
least-squares fit ``s_pred ~ a s_true``. Also the running means of the training metric at a few iterations.

The grid comes from the checkpoints (all runs given must share it); ``--resolution``, when given, must agree.

Run:  python examples/e5_diagnose.py out/e5_delta5:pg out/e5_lr1e-3_pg:pg --out e5_diag.json [--device cuda]
(the held-out batch is drawn on the CPU and moved, so every device diagnoses the same samples).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch

from inverse.fluid_inverse import FluidProblem, vortex_strength
from inverse.train import batch_generator
from phisim.checks import check_device
from phisim.errors import ParameterError
from phisim.io import read_training


def _checkpoint(run: str) -> Path:
    folder, _, method = run.partition(":")
    return Path(folder) / f"fluid_inverse.h5.{method}.ckpt"


def run_resolution(runs: list[str], requested: int | None) -> int:
    """The cells per axis the runs were trained on (read from their checkpoints); all must agree."""
    found = {}
    for run in runs:
        settings = torch.load(_checkpoint(run), map_location="cpu", weights_only=False).get("settings") or {}
        res = settings.get("resolution")
        if res is not None:
            found[run] = int(res[0])
    sizes = set(found.values()) | ({requested} if requested is not None else set())
    if len(sizes) > 1:
        raise ParameterError(f"the runs were trained on different grids ({found}, --resolution {requested}); "
                             "diagnose runs of one resolution at a time")
    if not sizes:
        raise ParameterError("the checkpoints do not record their resolution; pass --resolution")
    return sizes.pop()


def diagnose(problem: FluidProblem, ckpt: Path, batch) -> dict[str, float]:
    """Prior-parameter recovery of the network stored in ``ckpt`` on ``batch`` (on ``batch``'s device)."""
    state = torch.load(ckpt, map_location="cpu", weights_only=False)
    net = problem.make_network().to(device=batch.inputs.device, dtype=problem.dtype)
    net.load_state_dict(state["model"])
    net.eval()
    with torch.no_grad():
        v = problem.predict(net, batch)
        u = batch.operator.uniform_velocity(v.dtype)
        u_pred = v.mean(dim=(2, 3))
        s_true = vortex_strength(batch.x_true.to(v.dtype), problem.grid, problem.sigma)
        s_pred = vortex_strength(v, problem.grid, problem.sigma)
        metric = float(problem.metric(v, batch).mean())
    s_t, s_p = s_true.double().cpu().numpy(), s_pred.double().cpu().numpy()
    return {
        "iteration": int(state["iteration"]),
        "metric": metric,
        "uniform_rel_error": float((u_pred - u).norm(dim=1).mean() / u.norm(dim=1).mean()),
        "strength_corr": float(np.corrcoef(s_t, s_p)[0, 1]),
        "strength_slope": float((s_t @ s_p) / (s_t @ s_t)),
    }


def main(argv: list[str] | None = None) -> dict:
    """Command-line entry point; prints and optionally writes the diagnosis as JSON."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", nargs="+", help="DIR:METHOD")
    ap.add_argument("--resolution", type=int, default=None, help="cells per axis (default: from the checkpoints)")
    ap.add_argument("--samples", type=int, default=64)
    ap.add_argument("--window", type=int, default=64)
    ap.add_argument("--out", type=Path, default=None)
    ap.add_argument("--device", default="cpu", help="torch device: cpu, cuda or cuda:N (default cpu)")
    args = ap.parse_args(argv)
    device = check_device(args.device)
    torch.manual_seed(0)
    args.resolution = run_resolution(args.runs, args.resolution)
    problem = FluidProblem(resolution=(args.resolution, args.resolution))
    batch = problem.sample(args.samples, batch_generator(7919, 10**9), device=device)
    result = {}
    for run in args.runs:
        folder, _, method = run.partition(":")
        entry = diagnose(problem, _checkpoint(run), batch)
        curve = read_training(Path(folder) / "fluid_inverse.h5")[method]["metric"]
        csum = np.cumsum(np.insert(curve, 0, 0.0))
        entry["train_running_mean"] = {
            str(i): float((csum[i] - csum[max(0, i - args.window)]) / min(i, args.window))
            for i in (50, 100, 200, 300, 400, 500, 1000) if i <= len(curve)
        }
        result[run] = entry
        print(run, json.dumps(entry), flush=True)
    if args.out is not None:
        args.out.write_text(json.dumps({"settings": vars(args) | {"out": str(args.out)}, "runs": result}, indent=1))
    return result


if __name__ == "__main__":
    main()
