"""Reproduce E2-E4 of the physical-gradient paper (EXPERIMENTS.md) and the plain optimisation of E4.

Experiments:

* ``e2``: ``sin(a/x) = −1`` (:class:`inverse.problems.SineProblem`), MLP with 461 parameters, batch 1000;
  methods ``supervised``, ``adam``, ``pg_newton``, ``pg_inverse_gradient``, ``pg_analytic``, ``hig`` (lr 0.002
  on the linear loss, as the other methods) and ``hig_squared`` (lr 1 on ``½(y − y*)²``, as HIG is usually run).
  Metric ``sin(a/x) + 1``; curves are shown as running averages over 1000 mini-batches.
* ``e3``: Poisson's equation (:class:`inverse.problems.PoissonProblem`), U-net with 37,697 parameters;
  methods ``pg``, ``adam``, ``sgd``, ``pg_lbfgsb``. Metric: x L1 per sample (sum over cells), training
  batch; running average over 16 mini-batches (the published analysis), with the 64-batch average beside it
  in the summary.
* ``e4``: heat equation (:class:`inverse.problems.HeatProblem`), the same U-net; methods ``pg``, ``adam``,
  ``pg_lbfgsb``, ``sgd``. Metric: x L1 per sample (sum over cells), training batch; running average over 16
  mini-batches (64 beside it).
* ``e4-opt``: plain optimisation of a few heat problems without a network, from ``x = 0``: gradient descent
  (step 1, 1000 iterations), the Bayes-damped inverse iterated (100 iterations), L-BFGS-B (scipy).

Every method of an experiment is trained by :func:`inverse.train.train` on the same data stream (same seed).
Outputs in ``--out``: ``<exp>.h5`` (the curves, ``/training/<method>``), ``<exp>_curves.png`` (running
averages), ``<exp>_reconstruction.png`` (E3/E4: one test example, ``y*``, ``x*`` and each method's
prediction), ``<exp>_summary.json`` (final values, seconds per iteration, the comparisons of
EXPERIMENTS.md), ``<exp>_<method>.pt`` (trained weights, used by ``--plot-only``) and ``<exp>.log``.

With several ``--seeds`` the curves are stored as ``<method>_s<seed>``. A method that diverges (NaN/Inf) is
reported in the summary with the iteration it reached; the other methods still run.

Run (full settings of the paper; expensive)::

    python examples/reproduce.py --experiment e2 --iterations 10000 --out out/reproduce
    python examples/reproduce.py --experiment e3 --resolution 32 --batch-size 32 --iterations 2500 \\
        --max-iterations pg_lbfgsb=30 --out out/reproduce
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import math
import os
import sys
import time
from collections.abc import Sequence
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import numpy as np  # noqa: E402
import scipy.optimize  # noqa: E402
import torch  # noqa: E402

from inverse.cli_checks import json_summary  # noqa: E402
from inverse.local_solvers import GradientStepSolver  # noqa: E402
from inverse.operators import Heat  # noqa: E402
from inverse.problems import Problem, get_problem  # noqa: E402
from inverse.train import batch_generator, train  # noqa: E402
from phisim.checks import check_device  # noqa: E402
from phisim.errors import ParameterError, PhisimError  # noqa: E402
from phisim.io import TrainingLog, read_training  # noqa: E402
from phisim.io.interrupts import interruptible
from phisim.viz.plot import new_figure, plot_curves, plot_field, save_figure  # noqa: E402

X_L1 = "x L1 per sample (sum over cells), training batch"
EXPERIMENTS: dict[str, dict] = {
    "e2": {"problem": "sine", "window": 1000, "iterations": 10000,
           "methods": ["supervised", "adam", "pg_newton", "pg_inverse_gradient", "pg_analytic", "hig",
                       "hig_squared"],
           "metric": "sin(a/x) + 1 per sample, training batch", "reference": "adam"},
    "e3": {"problem": "poisson", "window": 16, "alt_window": 64, "iterations": 5000,
           "methods": ["pg", "adam", "sgd", "pg_lbfgsb"], "metric": X_L1, "reference": "adam"},
    "e4": {"problem": "heat", "window": 16, "alt_window": 64, "iterations": 10000,
           "methods": ["pg", "adam", "pg_lbfgsb", "sgd"], "metric": X_L1, "reference": "adam"},
}
#: E3/E4: ``window`` is the published analysis' running mean (16 mini-batches); the summaries also give the
#: values for ``alt_window`` (64, the window of this project's earlier tables) beside it.
#: Iterations at which EXPERIMENTS.md states a published ratio ``reference / method`` (E3: 60, E4: 100).
CHECKPOINTS = {"e2": (), "e3": (60,), "e4": (100,)}
#: Seed of the held-out example drawn for the reconstruction figures (not part of any training stream).
TEST_SEED = 987_654

log = logging.getLogger("reproduce")


# ----------------------------------------------------------------------------------------- curve helpers


def running_average(values: np.ndarray, window: int) -> np.ndarray:
    """Trailing running mean over ``window`` entries (the first entries average what exists so far).

    Args:
        values: 1-D array; NaNs are ignored inside a window.
        window: Window length ``>= 1``.

    Returns:
        Array of the same length; entry ``i`` is the mean of ``values[max(0, i − window + 1) : i + 1]``.
    """
    v = np.asarray(values, dtype=np.float64)
    assert v.ndim == 1, f"running_average needs a 1-D array, got shape {v.shape}"
    assert window >= 1, f"window must be >= 1, got {window}"
    ok = np.isfinite(v)
    csum = np.concatenate([[0.0], np.cumsum(np.where(ok, v, 0.0))])
    ccnt = np.concatenate([[0], np.cumsum(ok)])
    hi = np.arange(1, len(v) + 1)
    lo = np.maximum(0, hi - window)
    count = ccnt[hi] - ccnt[lo]
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(count > 0, (csum[hi] - csum[lo]) / np.maximum(count, 1), np.nan)


def iterations_to_reach(smoothed: np.ndarray, target: float) -> int | None:
    """First iteration (0-based index) at which a smoothed curve is ``<= target``; None if never."""
    hit = np.nonzero(np.asarray(smoothed) <= target)[0]
    return int(hit[0]) if hit.size else None


def _method_key(method: str, seed: int, seeds: Sequence[int]) -> str:
    return method if len(seeds) == 1 else f"{method}_s{seed}"


# ----------------------------------------------------------------------------------------- training


def _problem(exp: str, resolution: int | Sequence[int] | None, sgd_lr: float | None = None, solver: str | None = None,
             data_solver: str | None = None, boundary: str | None = None, reduction: str | None = None,
             normalize: bool | None = None) -> Problem:
    spec = EXPERIMENTS[exp]
    settings = {}
    if reduction is not None and spec["problem"] != "sine":
        settings["reduction"] = reduction
    if normalize is not None and spec["problem"] == "poisson":
        settings["normalize"] = normalize
    if boundary is not None and spec["problem"] == "poisson":
        settings["boundary"] = boundary
    if solver is not None and spec["problem"] == "poisson":
        settings["solver"] = solver
    if data_solver is not None and spec["problem"] == "poisson":
        settings["data_solver"] = data_solver
    if resolution is not None and spec["problem"] != "sine":
        settings["resolution"] = (resolution, resolution) if isinstance(resolution, int) else tuple(resolution)
    if sgd_lr is not None and spec["problem"] != "sine":
        settings["sgd_lr"] = sgd_lr
    return get_problem(spec["problem"], **settings)


def train_experiment(exp: str, *, iterations: int, batch_size: int | None, resolution: int | tuple | None,
                     seeds: Sequence[int], out: Path, methods: Sequence[str] | None = None,
                     max_iterations: dict[str, int] | None = None, sgd_lr: float | None = None,
                     solver: str | None = None, device: str = "cpu", checkpoint_every: int = 0,
                     resume: bool = False, data_solver: str | None = None, boundary: str | None = None,
                     reduction: str | None = None, normalize: bool | None = None) -> dict:
    """Train every method of a network experiment on the same data stream and save curves and weights.

    Args:
        exp: ``'e2'``, ``'e3'`` or ``'e4'``.
        iterations: Training iterations per method.
        batch_size: Mini-batch size (None: the problem's default, the paper's value).
        resolution: Grid cells for E3/E4: one count for every axis or one per axis (None: the default, 64²).
        seeds: Network-initialisation / data-stream seeds; each method runs once per seed.
        out: Output folder (``<exp>.h5`` and ``<exp>_<key>.pt`` are written there).
        methods: Subset of the experiment's methods (default: all).
        max_iterations: Per-method cap on the iterations (for expensive methods such as L-BFGS-B).
        sgd_lr: Learning rate of the ``sgd`` method of E3/E4 (None: the problem's default).
        solver: E3's training-path solve (``'cg'``, the default, or ``'spectral'``; see
            :class:`inverse.problems.PoissonProblem`).
        device: Torch device.
        checkpoint_every: Checkpoint interval (next to ``<exp>.h5``; 0: none).
        resume: Continue each run from its checkpoint when there is one.
        data_solver: E3's data solve (``'spectral'``, the default, or ``'cg'``, which the runs before the
            spectral default used; needed to reproduce their curves bit for bit).
        boundary: E3's Dirichlet convention, ``'face'`` (default) or ``'ghost'`` (the reference code's).
        reduction: E3/E4: ``'sum'`` (default) or ``'mean'`` over the batch for the backpropagated objective.
        normalize: E3: False leaves out the per-sample normalisation of ``x*`` (default: the recipe's).

    Returns:
        ``{key: {'method', 'seed', 'iterations', 'seconds', 'diverged'}}`` per run; ``diverged`` holds the
        error message of a run stopped by NaN/Inf (None otherwise).
    """
    spec = EXPERIMENTS[exp]
    methods = list(spec["methods"] if methods is None else methods)
    problem = _problem(exp, resolution, sgd_lr, solver, data_solver, boundary, reduction, normalize)
    unknown = [m for m in methods if m not in problem.methods]
    assert not unknown, f"{exp}: unknown methods {unknown}; choose from {sorted(problem.methods)}"
    caps = dict(max_iterations or {})
    h5 = out / f"{exp}.h5"
    runs = {}
    for seed in seeds:
        for name in methods:
            key = _method_key(name, seed, seeds)
            n = min(iterations, caps.get(name, iterations))
            method = dataclasses.replace(problem.method(name), name=key)
            log.info("%s: training %s (seed %d) for %d iterations", exp, key, seed, n)
            t0 = time.perf_counter()
            info = {"method": name, "seed": seed, "iterations": n, "diverged": None}
            try:
                res = train(problem, method, iterations=n, batch_size=batch_size, seed=seed, out=h5,
                            device=device, checkpoint_every=checkpoint_every, resume=resume)
                torch.save(res.model.state_dict(), out / f"{exp}_{key}.pt")
            except PhisimError as exc:  # NaN/Inf: keep the curve up to the failure, go on with the others
                info["diverged"] = str(exc)
                log.warning("%s: %s stopped: %s", exp, key, exc)
            info["seconds"] = time.perf_counter() - t0
            runs[key] = info
            log.info("%s: %s done in %.1f s", exp, key, info["seconds"])
    return runs


# ----------------------------------------------------------------------------------------- summaries, plots


def summarize(exp: str, curves: dict[str, dict[str, np.ndarray]], window: int) -> dict:
    """Final running averages, seconds per iteration and the comparisons stated in EXPERIMENTS.md.

    For every method: ``final`` (running average of the training-batch metric at the last iteration),
    ``heldout_final`` (the last held-out evaluation, when logged), ``iterations``,
    ``sec_per_it`` (median), ``at`` (running average at the checkpoints of :data:`CHECKPOINTS`). Against the
    reference method (Adam) of the same seed: ``ratio_final`` and ``ratio_at`` (reference / method, >1 means
    the method is more accurate) and ``iters_to_reference_final`` (first iteration at which the method's
    running average reaches the reference's final running average).
    """
    spec = EXPERIMENTS[exp]
    summary: dict[str, dict] = {}
    smooth = {k: running_average(c["metric"], window) for k, c in curves.items()}
    for key, c in curves.items():
        s = smooth[key]
        t = np.diff(np.asarray(c["time"], dtype=np.float64))
        entry = {"iterations": int(len(s)), "final": float(s[-1]) if len(s) else math.nan,
                 "sec_per_it": float(np.median(t)) if t.size else math.nan,
                 "at": {str(i): float(s[i]) for i in CHECKPOINTS[exp] if i < len(s)}}
        held = np.asarray(c.get("eval_metric", []), dtype=np.float64)
        if np.isfinite(held).any():  # the final network in eval mode on the problem's held-out set
            entry["heldout_final"] = float(held[np.isfinite(held)][-1])
        summary[key] = entry
    for key, entry in summary.items():
        _, seed = _split_key(key)
        ref_key = spec["reference"] + ("" if seed is None else f"_s{seed}")  # compare within a seed
        if ref_key not in smooth or ref_key == key:
            continue
        ref = smooth[ref_key]
        s = smooth[key]
        if len(s) and len(ref) and len(s) >= len(ref):
            entry["ratio_final"] = float(ref[-1] / s[len(ref) - 1])
        common = min(len(s), len(ref))
        entry["ratio_at"] = {str(i): float(ref[i] / s[i]) for i in CHECKPOINTS[exp] if i < common}
        if len(ref):
            entry["reference_final"] = float(ref[-1])
            entry["iters_to_reference_final"] = iterations_to_reach(s, float(ref[-1]))
    return summary


def plot_learning_curves(curves: dict[str, dict[str, np.ndarray]], window: int, title: str, ylabel: str,
                         path: Path) -> Path:
    """PNG of the running averages (over ``window`` mini-batches) of each method's metric, log scale."""
    fig, ax = new_figure(figsize=(6.4, 4.2), dpi=90)
    data = {k: (c["iteration"], running_average(c["metric"], window)) for k, c in curves.items()}
    split = {k: _split_key(k) for k in data}
    if all(seed is None for _, seed in split.values()):
        plot_curves(data, ax, logy=True, title=f"{title} (running average over {window})", ylabel=ylabel)
        return save_figure(fig, path)
    # several seeds: one colour per method, one line style per seed
    methods = list(dict.fromkeys(m for m, _ in split.values()))
    seeds = sorted({seed for _, seed in split.values()})
    styles = ["-", "--", ":", "-."]
    for key, (it, val) in data.items():
        method, seed = split[key]
        keep = np.isfinite(val) & (val > 0)
        ax.plot(it[keep], val[keep], color=f"C{methods.index(method) % 10}",
                linestyle=styles[seeds.index(seed) % len(styles)], linewidth=1.0,
                label=method if seed == seeds[0] else None)
    ax.set_yscale("log")
    ax.set_xlabel("iteration")
    ax.set_ylabel(ylabel)
    ax.grid(True, which="both", alpha=0.3)
    legend_title = f"seeds {', '.join(map(str, seeds))} ({' '.join(styles[: len(seeds)])})"
    ax.legend(fontsize=8, title=legend_title, title_fontsize=7)
    ax.set_title(f"{title} (running average over {window})")
    return save_figure(fig, path)


def _split_key(key: str) -> tuple[str, int | None]:
    """``'adam_s3'`` -> ``('adam', 3)``; ``'adam'`` -> ``('adam', None)``."""
    head, sep, tail = key.rpartition("_s")
    return (head, int(tail)) if sep and tail.isdigit() else (key, None)


def _load_models(exp: str, problem: Problem, out: Path, keys: Sequence[str]) -> dict[str, torch.nn.Module]:
    models = {}
    for key in keys:
        p = out / f"{exp}_{key}.pt"
        if p.exists():
            model = problem.make_network().to(dtype=problem.dtype)
            model.load_state_dict(torch.load(p, map_location="cpu", weights_only=True))
            models[key] = model
    return models


def plot_reconstruction(exp: str, problem: Problem, models: dict[str, torch.nn.Module], batch_size: int,
                        path: Path, index: int = 0) -> dict[str, float]:
    """Figure of one held-out example: ``y*``, ``x*``, each method's prediction ``x`` (E3/E4).

    The networks run in evaluation mode (BatchNorm with its running statistics) on a batch of
    ``batch_size`` problems drawn with :data:`TEST_SEED`; sample ``index`` is shown.

    Returns:
        ``{method: x L1 error (sum over cells) of the shown sample}``.
    """
    batch = problem.sample(batch_size, batch_generator(TEST_SEED, 0))
    n = 2 + len(models)
    fig, axes = new_figure(figsize=(2.6 * n, 2.6), dpi=70)
    fig.clear()
    axes = [fig.add_subplot(1, n, i + 1) for i in range(n)]
    x_true = batch.x_true[index].detach().double()
    lo, hi = float(x_true.min()), float(x_true.max())
    plot_field(batch.y_target[index].detach().double(), axes[0], title="y*", colorbar=False)
    plot_field(x_true, axes[1], title="x*", colorbar=False, vmin=lo, vmax=hi)
    maes = {}
    for ax, (key, model) in zip(axes[2:], models.items(), strict=True):
        model.eval()
        with torch.no_grad():
            x = problem.predict(model, batch)
        mae = float(problem.metric(x, batch)[index])
        maes[key] = mae
        plot_field(x[index].double(), ax, title=f"{key}\nx L1 (sum) {mae:.4g}", colorbar=False, vmin=lo, vmax=hi)
    for ax in axes:
        ax.set_xticks([])
        ax.set_yticks([])
        ax.set_xlabel("")
        ax.set_ylabel("")
    fig.tight_layout()
    save_figure(fig, path)
    return maes


# ----------------------------------------------------------------------------------------- E4 optimisation


def _x_mae(x: torch.Tensor, x_true: torch.Tensor) -> np.ndarray:
    return (x - x_true).abs().reshape(x.shape[0], -1).sum(dim=1).detach().cpu().numpy()


def optimise_heat(*, samples: int, resolution: int | tuple | None, gd_iterations: int, inverse_iterations: int,
                  lbfgsb_iterations: int, seed: int, out: Path) -> dict:
    """E4 without a network: optimise ``x`` for a few heat problems from ``x = 0`` and record x L1 curves.

    Methods: ``opt_gd`` (gradient descent on ``½‖P(x) − y*‖²`` with step 1, via
    :class:`~inverse.local_solvers.GradientStepSolver`), ``opt_inverse`` (``x ← P⁻¹(y*; x)``, the Bayes-damped
    inverse of :class:`inverse.operators.Heat` iterated), ``opt_inverse_floor`` (the same with the operator's
    ``noise_floor=1e-6``), ``opt_lbfgsb`` (scipy's L-BFGS-B per sample on the
    same loss, x L1 recorded at every iteration; a sample that stops early keeps its last value).
    Curves (mean over the samples) go to ``/training/<method>`` of ``out/e4-opt.h5``; iteration 0 is
    ``x = 0``.

    Returns:
        ``{method: {'final', 'iterations', 'seconds', 'min', 'argmin'}}``.
    """
    problem = _problem("e4", resolution)
    batch = problem.sample(samples, batch_generator(seed, 0))
    op = batch.operator
    y = batch.y_target.to(torch.float64)
    x_true = batch.x_true.to(torch.float64)
    x0 = torch.zeros_like(x_true)
    curves: dict[str, np.ndarray] = {}
    seconds: dict[str, float] = {}

    t0 = time.perf_counter()
    gd = GradientStepSolver(step_size=1.0)
    x, rows = x0, [_x_mae(x0, x_true)]
    for _ in range(gd_iterations):
        x = gd(op, y, x)
        rows.append(_x_mae(x, x_true))
    curves["opt_gd"], seconds["opt_gd"] = np.stack(rows), time.perf_counter() - t0

    t0 = time.perf_counter()
    x, rows = x0, [_x_mae(x0, x_true)]
    for _ in range(inverse_iterations):
        x = op.local_inverse(y, x)
        rows.append(_x_mae(x, x_true))
    curves["opt_inverse"], seconds["opt_inverse"] = np.stack(rows), time.perf_counter() - t0

    # The same inverse with a floor on the noise scale (1e-6 ‖y*‖): E4's σ_n = 1e-6 ‖r‖ shrinks with the
    # residual, so once the residual reaches round-off the plain iteration amplifies round-off.
    t0 = time.perf_counter()
    floored = Heat(nu_t=op.nu_t, noise_scale=op.noise_scale, signal_scale=op.signal_scale,
                   threshold=op.threshold, noise_floor=1e-6)
    x, rows = x0, [_x_mae(x0, x_true)]
    for _ in range(inverse_iterations):
        x = floored.local_inverse(y, x)
        rows.append(_x_mae(x, x_true))
    curves["opt_inverse_floor"], seconds["opt_inverse_floor"] = np.stack(rows), time.perf_counter() - t0

    t0 = time.perf_counter()
    per_sample = []
    for i in range(samples):
        yi, xi_true = y[i : i + 1], x_true[i : i + 1]
        shape = xi_true.shape

        def fun(v: np.ndarray, yi=yi, shape=shape) -> tuple[float, np.ndarray]:
            xt = torch.from_numpy(v.reshape(shape)).requires_grad_(True)
            loss = 0.5 * ((op(xt) - yi) ** 2).sum()
            (g,) = torch.autograd.grad(loss, xt)
            return float(loss.detach()), g.numpy().ravel()

        trace = [float(_x_mae(x0[i : i + 1], xi_true)[0])]

        def record(v: np.ndarray, xi_true=xi_true, shape=shape, trace=trace) -> None:
            trace.append(float(_x_mae(torch.from_numpy(v.reshape(shape)), xi_true)[0]))

        scipy.optimize.minimize(fun, x0[i].numpy().ravel(), jac=True, method="L-BFGS-B", callback=record,
                                options={"maxiter": lbfgsb_iterations, "ftol": 1e-15, "gtol": 1e-12})
        per_sample.append(trace)
    length = max(len(t) for t in per_sample)
    padded = [np.pad(t, (0, length - len(t)), mode="edge") for t in per_sample]
    curves["opt_lbfgsb"] = np.stack(padded, axis=1)
    seconds["opt_lbfgsb"] = time.perf_counter() - t0

    h5 = out / "e4-opt.h5"
    if h5.exists():
        h5.unlink()
    summary = {}
    for name, rows in curves.items():
        mean = rows.mean(axis=1)
        assert np.all(np.isfinite(mean)), f"{name}: non-finite x L1"
        with TrainingLog(h5, name, attrs={"problem": "heat", "samples": samples, "seed": seed,
                                          "x0": "zeros"}) as tl:
            for it, v in enumerate(mean):
                tl.append(it, metric=float(v))
        summary[name] = {"final": float(mean[-1]), "iterations": int(len(mean) - 1),
                         "seconds": seconds[name], "min": float(mean.min()), "argmin": int(mean.argmin())}
    return summary


# ----------------------------------------------------------------------------------------- driver


def _parse_caps(items: Sequence[str]) -> dict[str, int]:
    caps = {}
    for item in items:
        name, _, value = item.partition("=")
        if not value.isdigit():
            raise SystemExit(f"--max-iterations expects METHOD=N, got {item!r}")
        caps[name] = int(value)
    return caps


def run_network_experiment(exp: str, args: argparse.Namespace) -> dict:
    """Train (unless ``--plot-only``), then write the curves PNG, the reconstruction PNG and the summary."""
    spec = EXPERIMENTS[exp]
    out: Path = args.out
    iterations = spec["iterations"] if args.iterations is None else args.iterations
    runs = {}
    if not args.plot_only:
        runs = train_experiment(exp, iterations=iterations, batch_size=args.batch_size,
                                resolution=args.resolution, seeds=args.seeds, out=out, methods=args.methods,
                                max_iterations=_parse_caps(args.max_iterations), sgd_lr=args.sgd_lr,
                                solver=args.poisson_solver, device=args.device,
                                checkpoint_every=args.checkpoint_every, resume=args.resume,
                                data_solver=args.poisson_data_solver, boundary=args.poisson_boundary,
                                reduction=args.reduction, normalize=False if args.no_normalize else None)
    curves = read_training(out / f"{exp}.h5")
    assert curves, f"{out / f'{exp}.h5'} holds no training curves"
    longest = max(len(c["metric"]) for c in curves.values())
    window = min(spec["window"] if args.window is None else args.window, longest)
    problem = _problem(exp, args.resolution, data_solver=args.poisson_data_solver, boundary=args.poisson_boundary,
                       normalize=False if args.no_normalize else None)
    size = "" if spec["problem"] == "sine" else f", {problem.resolution[0]}x{problem.resolution[1]}"
    batch_size = problem.batch_size if args.batch_size is None else args.batch_size
    title = f"{exp.upper()} {spec['problem']}{size}, batch {batch_size}"
    plot_learning_curves(curves, window, title, spec["metric"], out / f"{exp}_curves.png")
    summary = {"experiment": exp, "problem": spec["problem"], "batch_size": batch_size, "window": window,
               "resolution": None if spec["problem"] == "sine" else list(problem.resolution),
               "methods": summarize(exp, curves, window), "runs": runs}
    if "alt_window" in spec and spec["alt_window"] != window:
        summary["alt_window"] = min(spec["alt_window"], longest)
        summary["methods_alt_window"] = summarize(exp, curves, summary["alt_window"])
    if spec["problem"] != "sine":
        models = _load_models(exp, problem, out, list(curves))
        if models:
            summary["reconstruction_mae"] = plot_reconstruction(exp, problem, models, min(batch_size, 16),
                                                                out / f"{exp}_reconstruction.png")
    (out / f"{exp}_summary.json").write_text(json_summary(summary, indent=1))  # strict JSON: NaN -> null
    return summary


def run_opt_experiment(args: argparse.Namespace) -> dict:
    """E4-opt: plain optimisation; writes ``e4-opt.h5``, ``e4-opt_curves.png`` and ``e4-opt_summary.json``."""
    out: Path = args.out
    if args.iterations is None:
        gd_it, inv_it, lb_it = 1000, 100, 1000
    else:
        gd_it, inv_it, lb_it = args.iterations, max(1, args.iterations // 10), args.iterations
    if not args.plot_only:
        summary = optimise_heat(samples=args.samples, resolution=args.resolution, gd_iterations=gd_it,
                                inverse_iterations=inv_it, lbfgsb_iterations=lb_it, seed=args.seeds[0],
                                out=out)
    else:  # keep the numbers of the run that made the curves
        old = out / "e4-opt_summary.json"
        summary = json.loads(old.read_text())["methods"] if old.exists() else {}
    curves = read_training(out / "e4-opt.h5")
    fig, ax = new_figure(figsize=(6.4, 4.2), dpi=90)
    res = _problem("e4", args.resolution).resolution
    plot_curves({k: (c["iteration"], c["metric"]) for k, c in curves.items()}, ax, logy=True,
                title=f"E4 optimisation from x = 0 ({args.samples} samples, {res[0]}x{res[1]})",
                ylabel="x L1 per sample (sum over cells), mean over samples")
    ax.set_xscale("symlog", linthresh=1.0)
    ax.set_xlim(left=0)
    save_figure(fig, out / "e4-opt_curves.png")
    (out / "e4-opt_summary.json").write_text(json_summary(
        {"experiment": "e4-opt", "samples": args.samples, "resolution": list(res), "methods": summary}, indent=1))
    return summary


def build_parser() -> argparse.ArgumentParser:
    """The command-line parser of this script."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--experiment", choices=["e2", "e3", "e4", "e4-opt", "all"], default="all")
    p.add_argument("--iterations", type=int, default=None,
                   help="training iterations (default: E2 10000, E3 5000, E4 10000; e4-opt: GD and L-BFGS-B "
                        "iterations, the damped inverse gets a tenth)")
    p.add_argument("--batch-size", type=int, default=None, help="mini-batch size (default: the paper's)")
    p.add_argument("--resolution", type=int, nargs="+", default=None,
                   help="E3/E4 cells: one number per axis, or one for all (default 64; the E3 paper text's "
                        "grid is --resolution 80 60)")
    p.add_argument("--seeds", type=int, nargs="+", default=[0])
    p.add_argument("--methods", nargs="+", default=None, help="subset of the experiment's methods")
    p.add_argument("--max-iterations", nargs="*", default=[], metavar="METHOD=N",
                   help="per-method iteration caps, e.g. pg_lbfgsb=30")
    p.add_argument("--sgd-lr", type=float, default=None, help="E3/E4: learning rate of the sgd method")
    p.add_argument("--samples", type=int, default=4, help="e4-opt: number of problems optimised")
    p.add_argument("--window", type=int, default=None,
                   help="running-mean window of the curves and summary (default: E2 1000, E3/E4 16, the "
                        "published analysis'; E3/E4 summaries also give the 64-batch window)")
    p.add_argument("--poisson-solver", choices=["cg", "spectral"], default=None,
                   help="E3 training-path solve: plain CG (default, as specified) or spectral-preconditioned CG")
    p.add_argument("--poisson-data-solver", choices=["cg", "spectral"], default=None,
                   help="E3 data solve: exact spectral (default) or CG (as the runs made before that default)")
    p.add_argument("--reduction", choices=["sum", "mean"], default=None,
                   help="E3/E4: batch reduction of the backpropagated objective (default: sum, as specified)")
    p.add_argument("--no-normalize", action="store_true",
                   help="E3: skip the per-sample zero-mean / unit-std normalisation of x* (an experiment)")
    p.add_argument("--poisson-boundary", choices=["face", "ghost"], default=None,
                   help="E3: zero Dirichlet value on the cell faces (phisim's convention, default) or in the ghost "
                        "cells (the reference code's)")
    p.add_argument("--device", default="cpu", help="torch device, e.g. cuda")
    p.add_argument("--checkpoint-every", type=int, default=0,
                   help="write a checkpoint next to <exp>.h5 every N iterations (0: none)")
    p.add_argument("--resume", action="store_true", help="continue each run from its checkpoint")
    p.add_argument("--plot-only", action="store_true", help="redraw figures and summary from existing files")
    p.add_argument("--out", type=Path, default=Path("out/reproduce"))
    return p


def main(argv: Sequence[str] | None = None) -> dict:
    """Command-line entry point; returns ``{experiment: summary}``."""
    args = build_parser().parse_args(argv)
    check_device(args.device)  # a bad device fails before anything is written
    if args.resolution is not None:
        if len(args.resolution) > 2 or min(args.resolution) < 1:
            raise ParameterError(f"--resolution takes one or two positive cell counts, got {args.resolution}")
        args.resolution = args.resolution[0] if len(args.resolution) == 1 else tuple(args.resolution)
    args.out.mkdir(parents=True, exist_ok=True)
    exps = ["e2", "e3", "e4", "e4-opt"] if args.experiment == "all" else [args.experiment]
    results = {}
    for exp in exps:
        handler = logging.FileHandler(args.out / f"{exp}.log")
        handler.setFormatter(logging.Formatter("%(asctime)s %(message)s"))
        log.addHandler(handler)
        log.setLevel(logging.INFO)
        try:
            results[exp] = run_opt_experiment(args) if exp == "e4-opt" else run_network_experiment(exp, args)
            log.info("%s summary: %s", exp, json.dumps(results[exp].get("methods", results[exp]))[:2000])
        finally:
            log.removeHandler(handler)
            handler.close()
    return results


if __name__ == "__main__":
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    try:
        with interruptible():  # SIGTERM stops it like Ctrl-C
            main()
    except KeyboardInterrupt:  # Ctrl-C or SIGTERM: the files are closed by now; leave without the slow shutdown
        print("interrupted: finished runs are complete; rerun with the same arguments to continue", file=sys.stderr)
        sys.stderr.flush()
        os._exit(130)
