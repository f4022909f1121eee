"""Recover an earlier state of Kuramoto–Sivashinsky from a later one: Adam vs physical gradients vs HIG, several seeds.

The problem is :class:`inverse.pde_inverse.PDEProblem` (registered as ``"pde"``): 1-D Kuramoto–Sivashinsky on the
chaotic box ``L = 22`` with 64 points (ETDRK4, ``dt = 0.25``, float64 physics); ``x*`` is a state of the attractor
(a band-limited random field advanced 200 steps), ``y* = P(x*)`` the state ``steps`` steps later; a small
convolutional ResNet (identity at initialisation, float32) maps ``y*`` to ``x``. Methods (one data stream per
seed, shared by all methods; :func:`inverse.train.train`):

* ``adam``: Adam through the ETDRK solver;
* ``pg``: physical gradients, the local inverse being one Wiener-damped step with the inverse of the linear part
  (``eps``) followed by one inverse-gradient iteration (Gauss-Newton with the autograd Jacobian, cut-off ``rcond``)
  for the nonlinear part, then Adam on the proxy loss;
* ``hig``: half-inverse gradients (SGD, ``hig_lr``, truncation ``hig_rcond``);
* ``pg_linear`` (the Wiener step alone) and ``pg_inverse_gradient`` (the generic step alone): the two stages of
  ``pg`` separately.

Every run is evaluated on the problem's fixed held-out set (128 samples) every ``--eval-every`` iterations. The
reference lines without a network on the same held-out set: ``x = y*`` (what the untrained network predicts),
``x = W y*`` (the damped inverse of the linear part alone), and the operator's local inverse iterated from
``x = y*`` (optimisation of each sample separately, ``--reference-iterations`` times).

Outputs in ``--out``: ``pde_inverse.h5`` (the curves, ``/training/<method>_s<seed>``, and ``/summary`` with the
table as attributes), ``pde_inverse.png`` (held-out curves, mean and spread over the seeds; one reconstruction),
``pde_inverse_modes.png`` (held-out error per Fourier mode), ``pde_inverse_summary.json`` and the trained networks
(``pde_inverse.h5.<run>.model.pt``). ``--plot-only`` remakes the table and figures from the runs in ``--out``.

Run (the documented experiment, ``docs/RESULTS_PDE.md``)::

    nice -n 10 python examples/pde_inverse.py --out out/pde_inverse > /tmp/pde_inverse.log 2>&1 &

Small run (a minute)::

    python examples/pde_inverse.py --iterations 20 --max-iterations hig=5 --seeds 0 --heldout-size 16 --out out/t
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import time
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import h5py  # noqa: E402
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402

from inverse.models import load_model, model_path  # noqa: E402
from inverse.problems import get_problem  # noqa: E402
from inverse.train import train  # noqa: E402
from phisim.checks import check_device  # noqa: E402
from phisim.errors import ParameterError, PhisimError  # noqa: E402
from phisim.io import read_training  # noqa: E402

DEFAULT_METHODS = ("adam", "pg", "pg_linear", "pg_inverse_gradient", "hig")


def _caps(items: list[str]) -> dict[str, int]:
    out = {}
    for item in items:
        name, sep, value = item.partition("=")
        if not sep:
            raise ParameterError(f"--max-iterations takes METHOD=N, got {item!r}")
        out[name] = int(value)
    return out


def references(problem, iterations: int) -> dict[str, float]:
    """Held-out x L1 per sample (mean) of the predictions without a network.

    Args:
        problem: The :class:`~inverse.pde_inverse.PDEProblem`.
        iterations: Applications of the operator's local inverse, started from ``x = y*``.

    Returns:
        ``{'identity', 'linear_inverse', 'local_inverse_1', 'local_inverse_<iterations>'}`` and the y-space losses
        ``*_loss`` of the same predictions.
    """
    held = problem.heldout()
    op = problem.operator()
    y = held.y_target.double()
    xs = held.x_true.double()

    def scores(x):
        with torch.no_grad():
            return (float((x - xs).abs().reshape(len(x), -1).sum(1).mean()),
                    float(problem.loss(op.forward(x), y).mean()))

    out = {}
    for name, x in (("identity", y), ("linear_inverse", op.linear_inverse(y))):
        out[name], out[name + "_loss"] = scores(x)
    x = y
    for i in range(1, iterations + 1):
        x = op.local_inverse(y, x)
        if i in (1, iterations):
            out[f"local_inverse_{i}"], out[f"local_inverse_{i}_loss"] = scores(x)
    return out


def _value_at(curve: dict, iteration: int, name: str = "eval_metric") -> float:
    """The held-out value recorded after ``iteration`` updates (NaN when not evaluated then)."""
    its = np.asarray(curve["iteration"]) + 1
    vals = np.asarray(curve[name], dtype=np.float64)
    hit = np.nonzero(its == iteration)[0]
    return float(vals[hit[0]]) if hit.size else math.nan


def summarize(curves: dict, methods: list[str], seeds: list[int], common: int) -> dict:
    """Mean and standard deviation over the seeds of the final held-out metric and loss, the metric after ``common``
    updates, and the median seconds per iteration.

    Args:
        curves: ``{run: curve}`` as :func:`phisim.io.read_training` returns them.
        methods: Method names.
        seeds: Seeds.
        common: The iteration every method reached (the comparison at equal iterations).

    Returns:
        ``{method: {...}}``.
    """
    table = {}
    for m in methods:
        runs = [curves[f"{m}_s{s}"] for s in seeds if f"{m}_s{s}" in curves]
        if not runs:
            continue
        final = [float(np.asarray(c["eval_metric"], dtype=np.float64)[-1]) for c in runs]
        final_loss = [float(np.asarray(c["eval_loss"], dtype=np.float64)[-1]) for c in runs]
        at = [_value_at(c, common) for c in runs]
        # seconds per iteration: the median step (the first record's time is that of the first iteration)
        sec = [float(np.median(np.diff(np.asarray(c["time"], dtype=np.float64), prepend=0.0))) for c in runs]
        table[m] = {
            "seeds": len(runs), "iterations": int(len(runs[0]["iteration"])),
            "heldout_metric_final": final, "heldout_loss_final": final_loss, f"heldout_metric_at_{common}": at,
            "mean_final": float(np.mean(final)), "std_final": float(np.std(final)),
            "mean_loss_final": float(np.mean(final_loss)), "std_loss_final": float(np.std(final_loss)),
            "mean_at_common": float(np.mean(at)), "std_at_common": float(np.std(at)),
            "sec_per_it": float(np.median(sec)),
        }
    return table


def plot(path: Path, problem, curves: dict, methods: list[str], seeds: list[int], refs: dict, out: Path) -> None:
    """Held-out curves (mean over seeds, band min..max) and one held-out reconstruction per method (first seed)."""
    fig, (ax, ax2) = plt.subplots(1, 2, figsize=(13, 4.5))
    colors = dict(zip(methods, plt.rcParams["axes.prop_cycle"].by_key()["color"]))
    for m in methods:
        runs = [curves[f"{m}_s{s}"] for s in seeds if f"{m}_s{s}" in curves]
        if not runs:
            continue
        n = min(len(c["iteration"]) for c in runs)
        it = np.asarray(runs[0]["iteration"][:n]) + 1
        vals = np.stack([np.asarray(c["eval_metric"][:n], dtype=np.float64) for c in runs])
        keep = np.isfinite(vals).all(0)
        ax.plot(it[keep], vals[:, keep].mean(0), color=colors[m], label=f"{m} ({len(runs)} seeds)")
        ax.fill_between(it[keep], vals[:, keep].min(0), vals[:, keep].max(0), color=colors[m], alpha=0.2)
    for name, style in (("identity", ":"), ("linear_inverse", "--"), ("local_inverse_1", "-.")):
        ax.axhline(refs[name], color="gray", ls=style, lw=1, label=f"no network: {name}")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("iteration")
    ax.set_ylabel("held-out x L1 per sample (sum over 64 cells)")
    ax.legend(fontsize=8)
    ax.set_title("Kuramoto-Sivashinsky L=22: recover u(t0) from u(t0+T)")
    held = problem.heldout()
    xgrid = np.arange(held.x_true.shape[-1]) * (problem.operator().grid.domain[0] / held.x_true.shape[-1])
    k = 0
    ax2.plot(xgrid, held.x_true[k, 0].numpy(), "k-", lw=2, label="x* (earlier state)")
    ax2.plot(xgrid, held.y_target[k, 0].numpy(), "k:", label="y* (later state, network input)")
    for m in methods:
        model_file = model_path(path, f"{m}_s{seeds[0]}")
        if not Path(model_file).exists():
            continue
        net = load_model(model_file)
        net.eval()
        with torch.no_grad():
            x = problem.predict(net, held)[k, 0].numpy()
        ax2.plot(xgrid, x, color=colors[m], label=m)
    ax2.set_xlabel("x")
    ax2.legend(fontsize=8)
    ax2.set_title(f"held-out sample {k}, seed {seeds[0]}")
    fig.tight_layout()
    fig.savefig(out, dpi=110)
    plt.close(fig)


def mode_errors(problem, path: Path, methods: list[str], seeds: list[int]) -> dict:
    """Held-out error per Fourier mode: the mean over samples (and seeds) of ``|x̂_m − x̂*_m|`` (amplitudes, ``rfft``
    scaled by ``2/N``), for each trained method, for ``x = y*`` and for one application of the local inverse from
    ``x = y*``; with the amplitude ``|x̂*_m|`` of the states and the linear part's factor ``|g_m|``.

    Args:
        problem: The problem.
        path: The HDF5 results file (the model files lie beside it).
        methods: Method names.
        seeds: Seeds.

    Returns:
        ``{name: [value per mode]}``.
    """
    held = problem.heldout()
    op = problem.operator()
    xs = held.x_true.double()
    y = held.y_target.double()
    n = xs.shape[-1]

    def spectrum(x):
        return ((torch.fft.rfft(x.double() - xs, dim=-1).abs() * (2.0 / n)).mean(dim=(0, 1))).tolist()

    out = {"signal": (torch.fft.rfft(xs, dim=-1).abs() * (2.0 / n)).mean(dim=(0, 1)).tolist(),
           "transfer": op.transfer.abs()[0].tolist(), "identity": spectrum(y),
           "local_inverse_1": spectrum(op.local_inverse(y, y))}
    for m in methods:
        per_seed = []
        for seed in seeds:
            f = model_path(path, f"{m}_s{seed}")
            if Path(f).exists():
                net = load_model(f)
                with torch.no_grad():
                    per_seed.append(spectrum(problem.predict(net, held)))
        if per_seed:
            out[m] = np.mean(np.asarray(per_seed), axis=0).tolist()
    return out


def plot_modes(modes: dict, methods: list[str], out: Path) -> None:
    """The per-mode held-out errors of :func:`mode_errors` against the mode number, with ``|g|`` beside them."""
    fig, ax = plt.subplots(figsize=(7.5, 4.5))
    m = np.arange(len(modes["signal"]))
    ax.semilogy(m, modes["signal"], "k-", lw=2, label="|x*| (the states)")
    ax.semilogy(m, modes["identity"], "k:", label="error of x = y*")
    ax.semilogy(m, modes["local_inverse_1"], "k-.", label="error of one local inverse from y* (no network)")
    for name in methods:
        if name in modes:
            ax.semilogy(m, modes[name], label=f"error of {name}")
    ax.semilogy(m, modes["transfer"], color="gray", lw=3, alpha=0.4, label="|g| (linear part over the horizon)")
    ax.set_xlabel("mode m (wavenumber 2πm/L)")
    ax.set_ylabel("mean amplitude")
    ax.set_ylim(1e-6, 10)
    ax.legend(fontsize=7)
    ax.set_title("held-out error per Fourier mode (mean over samples and seeds)")
    fig.tight_layout()
    fig.savefig(out, dpi=110)
    plt.close(fig)


def main(argv: list[str] | None = None) -> dict:
    """Train every method for every seed, evaluate, write the HDF5 file, the summary and the figure.

    Args:
        argv: Command-line arguments (see ``--help``).

    Returns:
        The summary (``{'settings', 'references', 'table', 'runs'}``).
    """
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--methods", nargs="+", default=list(DEFAULT_METHODS))
    p.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    p.add_argument("--iterations", type=int, default=1000)
    p.add_argument("--max-iterations", nargs="*", default=["hig=250"], metavar="METHOD=N",
                   help="per-method caps (default: hig=250)")
    p.add_argument("--batch-size", type=int, default=8)
    p.add_argument("--eval-every", type=int, default=50)
    p.add_argument("--heldout-size", type=int, default=128)
    p.add_argument("--steps", type=int, default=2, help="time steps of dt = 0.25 between x* and y*")
    p.add_argument("--eps", type=float, default=1e-2)
    p.add_argument("--rcond", type=float, default=1e-2)
    p.add_argument("--lr", type=float, default=1e-3)
    p.add_argument("--hig-lr", type=float, default=1.0)
    p.add_argument("--hig-rcond", type=float, default=1e-4)
    p.add_argument("--width", type=int, default=12)
    p.add_argument("--blocks", type=int, default=3)
    p.add_argument("--reference-iterations", type=int, default=10)
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--device", default="cpu", help="torch device of the networks: cpu, cuda or cuda:N (the ETDRK "
                   "physics runs on the CPU in float64)")
    p.add_argument("--out", type=Path, default=Path("out/pde_inverse"))
    p.add_argument("--plot-only", action="store_true",
                   help="no training: the table and figures from the runs already in --out")
    args = p.parse_args(argv)
    device = check_device(args.device)  # before anything is written
    torch.set_num_threads(args.threads)
    caps = _caps(args.max_iterations)
    settings = dict(steps=args.steps, eps=args.eps, rcond=args.rcond, lr=args.lr, hig_lr=args.hig_lr,
                    hig_rcond=args.hig_rcond, width=args.width, blocks=args.blocks, heldout_size=args.heldout_size,
                    batch_size=args.batch_size)
    problem = get_problem("pde", **settings)
    unknown = [m for m in args.methods if m not in problem.methods]
    if unknown:
        raise ParameterError(f"unknown methods {unknown}; choose from {sorted(problem.methods)}")
    args.out.mkdir(parents=True, exist_ok=True)
    h5 = args.out / "pde_inverse.h5"
    t0 = time.perf_counter()
    refs = references(problem, args.reference_iterations)
    print(f"references (no network, held-out x L1 per sample): {json.dumps(refs)}", flush=True)
    summary_file = args.out / "pde_inverse_summary.json"
    earlier = json.loads(summary_file.read_text()) if args.plot_only and summary_file.exists() else {}
    runs = dict(earlier.get("runs", {}))
    for seed in [] if args.plot_only else args.seeds:
        for name in args.methods:
            key = f"{name}_s{seed}"
            n = min(args.iterations, caps.get(name, args.iterations))
            method = dataclasses.replace(problem.method(name), name=key)
            start = time.perf_counter()
            info = {"method": name, "seed": seed, "iterations": n, "diverged": None}
            try:
                r = train(problem, method, iterations=n, seed=seed, out=h5, eval_every=args.eval_every,
                          overwrite=True, device=device)
                info["heldout_metric"] = r.final_eval("metric")
            except PhisimError as exc:  # NaN/Inf: the curve up to the failure stays in the file
                info["diverged"] = str(exc)
            info["seconds"] = time.perf_counter() - start
            runs[key] = info
            print(f"{key}: {json.dumps(info)}", flush=True)
    curves = read_training(h5)
    common = min(min(args.iterations, caps.get(m, args.iterations)) for m in args.methods)
    table = summarize(curves, args.methods, args.seeds, common)
    summary = {"settings": {**settings, "equation": problem.equation, "domain": problem.domain,
                            "resolution": problem.resolution, "dt": problem.dt, "warmup_steps": problem.warmup_steps,
                            "iterations": args.iterations, "caps": caps, "seeds": args.seeds,
                            "eval_every": args.eval_every, "threads": args.threads, "common_iteration": common,
                            "device": str(device),
                            "torch": torch.__version__},
               "references": refs, "table": table, "runs": runs,
               "seconds_total": earlier.get("seconds_total", time.perf_counter() - t0)}
    summary["mode_errors"] = mode_errors(problem, h5, args.methods, args.seeds)
    with h5py.File(h5, "a") as f:
        if "summary" in f:
            del f["summary"]
        g = f.create_group("summary")
        g.attrs["json"] = json.dumps(summary)
        for m, row in table.items():
            for k in ("mean_final", "std_final", "mean_at_common", "std_at_common", "sec_per_it"):
                g.attrs[f"{m}/{k}"] = row[k]
    summary_file.write_text(json.dumps(summary, indent=1))
    plot(h5, problem, curves, args.methods, args.seeds, refs, args.out / "pde_inverse.png")
    plot_modes(summary["mode_errors"], args.methods, args.out / "pde_inverse_modes.png")
    print("method | iterations | held-out x L1 at the end | at iteration", common, "| s/it")
    for m, row in table.items():
        print(f"{m} | {row['iterations']} | {row['mean_final']:.3f} ± {row['std_final']:.3f} | "
              f"{row['mean_at_common']:.3f} ± {row['std_at_common']:.3f} | {row['sec_per_it']:.3f}")
    return summary


if __name__ == "__main__":
    main()
