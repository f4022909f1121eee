"""E5: a U-net infers the initial fluid velocity from two marker frames; Adam vs Adam + physical gradients.

Both methods (``adam``: Adam through the 8-step simulation on the frequency loss; ``pg``: Adam on the proxy
loss ``1/2 |v0 - v~|^2`` with the reverse-simulation local inverse of :class:`inverse.FluidMarkerOperator`)
start from the same network and see the same stream of batches (:func:`inverse.train.train`).

Outputs (in ``--out``):

* ``fluid_inverse.h5``: ``/training/<method>/{iteration, loss, metric, objective, time}`` (the metric is the
  per-sample ``sum_cells |v0 - v0*|``, batch mean) and ``/validation/<method>/metric`` on a held-out batch;
* ``fluid_inverse.png``: learning curves (running mean) of the metric and the marker loss, and one validation
  example: ``m0``, ``m_t``, the markers simulated from each prediction, the true and predicted ``v0``;
* ``fluid_inverse.json``: the summary (settings, final metrics, crossing iteration, ratios).

Run:  python examples/fluid_inverse.py --resolution 32 --batch-size 16 --iterations 200 --out out/fluid
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import h5py
import numpy as np
import torch

from inverse.fluid_inverse import FluidProblem
from inverse.train import batch_generator, train
from phisim.checks import check_device
from phisim.viz.plot import new_figure, plot_curves, plot_field, plot_vector_field, save_figure

METHODS = ("adam", "pg")
LABELS = {"adam": "Adam", "pg": "Adam + PG"}


def running_mean(values: np.ndarray, window: int) -> np.ndarray:
    """Trailing running mean (the first entries average what is there).

    Args:
        values: 1-D array.
        window: Window length (>= 1).

    Returns:
        Array of the same length.
    """
    v = np.asarray(values, dtype=np.float64)
    c = np.cumsum(np.insert(v, 0, 0.0))
    idx = np.arange(1, len(v) + 1)
    lo = np.maximum(0, idx - window)
    return (c[idx] - c[lo]) / (idx - lo)


def summarize(curves: dict[str, dict[str, np.ndarray]], window: int) -> dict:
    """Crossing iteration and ratios of the smoothed metric curves (PG relative to Adam).

    Args:
        curves: Method -> curves with ``iteration`` and ``metric``.
        window: Running-mean window.

    Returns:
        ``{'final': {method: value}, 'pg_iterations_to_match_adam_final': int | None,
        'ratio_adam_over_pg': {iteration: ratio}}``.
    """
    smooth = {m: running_mean(c["metric"], window) for m, c in curves.items()}
    out: dict = {"window": window, "final": {m: float(s[-1]) for m, s in smooth.items()}}
    if "adam" in smooth and "pg" in smooth:
        target = smooth["adam"][-1]
        below = np.nonzero(smooth["pg"] <= target)[0]
        out["pg_iterations_to_match_adam_final"] = int(below[0]) + 1 if len(below) else None
        n = min(len(smooth["adam"]), len(smooth["pg"]))
        marks = sorted({i for i in (50, 100, 200, 500, 1000, 2000, n) if i <= n})
        out["ratio_adam_over_pg"] = {
            str(i): float(smooth["adam"][i - 1] / smooth["pg"][i - 1]) for i in marks
        }
    return out


def plot(problem: FluidProblem, results: dict, curves: dict, batch, window: int, path: Path) -> Path:
    """Learning curves and one validation example.

    Args:
        problem: The problem.
        results: Method -> :class:`inverse.train.TrainResult`.
        curves: Method -> curves.
        batch: A validation batch.
        window: Running-mean window.
        path: PNG to write.

    Returns:
        The path written.
    """
    ncol = max(3, 1 + len(results))
    fig, _ = new_figure(figsize=(4.6 * ncol, 12.0))
    fig.clear()
    ax = fig.add_subplot(3, ncol, 1)
    plot_curves(
        {LABELS[m]: (c["iteration"] + 1, running_mean(c["metric"], window)) for m, c in curves.items()},
        ax,
        ylabel="sum over cells |v0 - v0*|",
        title=f"metric (running mean {window})",
    )
    ax = fig.add_subplot(3, ncol, 2)
    plot_curves(
        {LABELS[m]: (c["iteration"] + 1, running_mean(c["loss"], window)) for m, c in curves.items()},
        ax,
        ylabel="frequency loss",
        title="marker loss",
    )
    grid = problem.grid
    stride = max(1, grid.resolution[0] // 16)
    plot_field(batch.inputs[0, 0], fig.add_subplot(3, ncol, 3), grid=grid, title="m0 (validation sample)")
    plot_vector_field(
        batch.x_true[0], fig.add_subplot(3, ncol, ncol + 1), grid=grid, title="v0 ground truth", stride=stride
    )
    plot_field(batch.y_target[0], fig.add_subplot(3, ncol, 2 * ncol + 1), grid=grid, title="m_t target")
    for j, (m, r) in enumerate(results.items()):
        r.model.eval()
        with torch.no_grad():
            x = problem.predict(r.model, batch)
            y = batch.operator.forward(x)
            err = float(problem.metric(x, batch)[0])
        plot_vector_field(
            x[0],
            fig.add_subplot(3, ncol, ncol + 2 + j),
            grid=grid,
            title=f"v0 {LABELS[m]} (error {err:.0f})",
            stride=stride,
        )
        plot_field(
            y[0], fig.add_subplot(3, ncol, 2 * ncol + 2 + j), grid=grid, title=f"m_t from {LABELS[m]} v0"
        )
    return save_figure(fig, path)


def main(argv: list[str] | None = None) -> dict:
    """Train, evaluate, write HDF5/PNG/JSON; returns the summary.

    Args:
        argv: Command-line arguments (default ``sys.argv``).

    Returns:
        The summary dictionary written to ``fluid_inverse.json``.
    """
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--resolution", type=int, default=32, help="cells per axis (E5: 64), multiple of 16")
    ap.add_argument("--batch-size", type=int, default=16, help="samples per batch (E5: 64)")
    ap.add_argument("--iterations", type=int, default=200)
    ap.add_argument("--out", type=Path, default=Path("out/fluid"))
    ap.add_argument("--methods", nargs="+", choices=METHODS, default=list(METHODS))
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--window", type=int, default=20, help="running-mean window of the reported curves")
    ap.add_argument("--validation-size", type=int, default=32)
    ap.add_argument("--checkpoint-every", type=int, default=25)
    ap.add_argument("--resume", action="store_true", help="continue from the checkpoints in --out")
    ap.add_argument("--device", default="cpu", help="torch device: cpu, cuda or cuda:N (default cpu)")
    ap.add_argument("--lr", type=float, default=0.005, help="Adam learning rate of both methods (E5: 0.005)")
    ap.add_argument("--delta-factor", type=float, default=1.0,
                    help="factor on the local inverse's vortex-strength update (1: the reference's)")
    args = ap.parse_args(argv)
    check_device(args.device)  # a bad device fails before anything is written

    problem = FluidProblem(resolution=(args.resolution, args.resolution), batch_size=args.batch_size,
                           lr=args.lr, delta_factor=args.delta_factor)
    args.out.mkdir(parents=True, exist_ok=True)
    h5 = args.out / "fluid_inverse.h5"
    results = {}
    for m in args.methods:
        t0 = time.perf_counter()

        def report(it: int, rec: dict, m=m, t0=t0) -> None:
            if (it + 1) % 10 == 0 or it == 0:
                print(
                    f"{m} it {it + 1}: loss {rec['loss']:.4g} metric {rec['metric']:.4g} "
                    f"({time.perf_counter() - t0:.0f} s)",
                    flush=True,
                )

        results[m] = train(
            problem,
            m,
            iterations=args.iterations,
            seed=args.seed,
            device=args.device,
            out=h5,
            checkpoint_every=args.checkpoint_every,
            resume=args.resume,
            callback=report,
        )
    curves = {m: r.curves for m, r in results.items()}

    # held-out batch: an iteration index the training stream never reaches
    val = problem.sample(args.validation_size, batch_generator(args.seed + 7919, 10**9), device=args.device)
    validation = {}
    for m, r in results.items():
        r.model.eval()
        with torch.no_grad():
            x = problem.predict(r.model, val)
            validation[m] = {
                "metric": float(problem.metric(x, val).mean()),
                "loss": float(problem.loss(val.operator.forward(x), val.y_target).mean()),
            }
    with h5py.File(h5, "a") as f:
        for m, v in validation.items():
            grp = f.require_group(f"validation/{m}")
            for k, val_k in v.items():
                if k in grp:
                    del grp[k]
                grp[k] = val_k
    summary = {
        "settings": {
            "resolution": args.resolution,
            "batch_size": args.batch_size,
            "iterations": args.iterations,
            "seed": args.seed,
            "lr": args.lr,
            "delta_factor": args.delta_factor,
            "window": args.window,
            "device": args.device,
            "torch_threads": torch.get_num_threads(),
        },
        "train": summarize(curves, args.window),
        "validation": validation,
        "seconds": {m: float(c["time"][-1]) if len(c["time"]) else 0.0 for m, c in curves.items()},
    }
    png = plot(problem, results, curves, val, args.window, args.out / "fluid_inverse.png")
    (args.out / "fluid_inverse.json").write_text(json.dumps(summary, indent=2))
    print(json.dumps(summary, indent=2))
    print(f"wrote {h5}, {png}")
    return summary


if __name__ == "__main__":
    main()
