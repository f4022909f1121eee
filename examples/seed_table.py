"""Adam / method ratios of several seeds at given iterations, from the training logs that reproduce.py writes.

Each ``--runs`` entry is a training log (``<out>/<exp>.h5``) of one seed holding a reference method (Adam)
and the compared methods (PG by default; ``--method pg sgd pg_lbfgsb`` for several). For every method, every
iteration asked for and every window, the script prints the running mean (trailing, over ``window``
mini-batches; iteration ``n`` is the ``n``-th update, entry ``n - 1``) of both methods per seed, the ratio
(reference / method: above 1 means the method is more accurate), and the mean and range of the ratio over the
seeds, as a Markdown table; with ``--json`` it also writes them (``ratios``: the first method, ``methods``:
every method).

Run:  python examples/seed_table.py --runs data/results/e3_64x128/e3.h5 data/results/e3_64x128_s1/e3.h5 \\
          data/results/e3_64x128_s2/e3.h5 --at 60 100 --windows 16 64 --method pg sgd pg_lbfgsb
"""

from __future__ import annotations

import argparse
import json
import sys
from functools import cache
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from reproduce import running_average  # noqa: E402

from phisim.errors import ParameterError  # noqa: E402
from phisim.io import read_training  # noqa: E402


@cache
def _logs(run: Path) -> dict:
    """The training curves of one log, read once per process (every table reads the same few files)."""
    return read_training(run)


def centred_average(values: np.ndarray, window: int) -> np.ndarray:
    """Centred running mean, NaN where the window does not fit: entry ``i`` averages the entries
    ``i - window//2 + 1 .. i + window//2`` (a 'valid' moving average placed at its centre, as a common curve
    plotting helper, and the published analysis, place it)."""
    v = np.asarray(values, dtype=np.float64)
    out = np.full(v.shape, np.nan)
    if len(v) >= window:
        valid = np.convolve(v, np.ones(window) / window, mode="valid")
        start = window // 2 - 1
        out[start:start + len(valid)] = valid
    return out


def first_crossing(runs: list[Path], level: float, window: int, reference: str = "adam", method: str = "pg",
                   centred: bool = False) -> list[int | None]:
    """Per run: the first iteration (1-based) at which the smoothed reference / method ratio reaches ``level``
    (None if never)."""
    smooth = centred_average if centred else running_average
    out = []
    for run in runs:
        logs = _logs(Path(run))
        a, b = smooth(logs[reference]["metric"], window), smooth(logs[method]["metric"], window)
        n = min(len(a), len(b))
        with np.errstate(invalid="ignore"):
            hit = np.flatnonzero(a[:n] / b[:n] >= level)
        out.append(int(hit[0]) + 1 if hit.size else None)
    return out


def iterations_to_reach(runs: list[Path], at: int, window: int, reference: str = "adam", method: str = "pg",
                        centred: bool = False) -> list[int | None]:
    """Per run: the first iteration (1-based) at which the method's smoothed curve is at or below the
    reference's smoothed value at iteration ``at`` (the published "iterations to reach Adam's accuracy after
    N iterations"); None if never."""
    smooth = centred_average if centred else running_average
    out = []
    for run in runs:
        logs = _logs(Path(run))
        ref, m = smooth(logs[reference]["metric"], window), smooth(logs[method]["metric"], window)
        if len(ref) < at:
            raise ParameterError(f"{run} holds {len(ref)} iterations of '{reference}', fewer than {at}")
        with np.errstate(invalid="ignore"):
            hit = np.flatnonzero(m <= ref[at - 1])
        out.append(int(hit[0]) + 1 if hit.size else None)
    return out


def ratios(runs: list[Path], at: list[int], windows: list[int], reference: str = "adam",
           method: str = "pg", centred: bool = False) -> dict:
    """``{window: {iteration: {"per_seed": [(ref, method, ratio)], "mean", "min", "max"}}}`` (see the module doc).

    ``centred`` uses :func:`centred_average` instead of the trailing running mean.

    Raises:
        ParameterError: A log lacks one of the methods or is shorter than an iteration asked for.
    """
    smooth = centred_average if centred else running_average
    curves = []
    for run in runs:
        logs = _logs(Path(run))
        for name in (reference, method):
            if name not in logs:
                raise ParameterError(f"{run} has no curve '{name}' (it has {sorted(logs)})")
        curves.append((logs[reference]["metric"], logs[method]["metric"]))
    out: dict = {}
    for w in windows:
        out[w] = {}
        for n in at:
            rows = []
            for run, (ref, m) in zip(runs, curves):
                if min(len(ref), len(m)) < n:
                    raise ParameterError(f"{run} holds {min(len(ref), len(m))} iterations, fewer than {n}")
                a, b = smooth(ref, w)[n - 1], smooth(m, w)[n - 1]
                rows.append((float(a), float(b), float(a / b)))
            r = np.array([x[2] for x in rows])
            out[w][n] = {"per_seed": rows, "mean": float(r.mean()), "min": float(r.min()), "max": float(r.max())}
    return out


def markdown(result: dict, runs: list[Path], reference: str = "adam", method: str = "pg") -> str:
    """The table of :func:`ratios` in Markdown."""
    names = {"adam": "Adam", "pg": "PG", "sgd": "SGD", "pg_lbfgsb": "PG+L-BFGS-B"}
    pair = f"{names.get(reference, reference)} / {names.get(method, method)}"
    lines = ["| window | iteration | " + " | ".join(f"seed log {i}: {pair}" for i in range(len(runs)))
             + " | mean ratio (min-max) |", "|---|---:|" + "---|" * len(runs) + "---|"]
    for w, by_it in result.items():
        for n, v in by_it.items():
            cells = [f"{a:,.0f} / {b:,.0f} = {r:.2f}" for a, b, r in v["per_seed"]]
            spread = f"**{v['mean']:.2f}** ({v['min']:.2f}-{v['max']:.2f})"
            lines.append(f"| {w} | {n} | " + " | ".join(cells) + f" | {spread} |")
    return "\n".join(lines)


NAMES = {"adam": "Adam", "pg": "PG", "sgd": "SGD", "pg_lbfgsb": "PG+L-BFGS-B"}


def overview(runs: list[Path], at: list[int], window: int, methods: list[str], reach: int,
             reference: str = "adam", bn: dict | None = None) -> str:
    """One Markdown table for several methods: the reference / method ratio at each iteration of ``at`` (mean and
    range over the seeds), the method's mean running average at the last of them, and the iterations each seed
    needs to reach the reference's level at ``reach``. With ``bn`` (the JSON of ``bn_recalibrate.py``), a second
    table of held-out errors: as trained, with recalibrated BatchNorm statistics, and the training stream."""
    logs = [_logs(Path(r)) for r in runs]
    last = at[-1]
    lines = ["| " + f"{NAMES.get(reference, reference)} / method (window {window}) | "
             + " | ".join(f"it. {n}" for n in at) + f" | x L1 at {last} (mean of seeds) | iterations to reach "
             f"{NAMES.get(reference, reference)}'s level at {reach}, per seed |", "|---|" + "---:|" * (len(at) + 1)
             + "---|"]
    ref_level = np.mean([running_average(g[reference]["metric"], window)[last - 1] for g in logs])
    lines.append(f"| {NAMES.get(reference, reference)} | " + " | ".join("1" for _ in at) + f" | {ref_level:,.0f} | |")
    for m in methods:
        res = ratios(runs, at, [window], reference, m)[window]
        cells = [f"**{res[n]['mean']:.2f}** ({res[n]['min']:.2f}-{res[n]['max']:.2f})" for n in at]
        level = np.mean([running_average(g[m]["metric"], window)[last - 1] for g in logs])
        hits = iterations_to_reach(runs, reach, window, reference, m)
        lines.append(f"| {NAMES.get(m, m)} | " + " | ".join(cells) + f" | {level:,.0f} | "
                     + " / ".join("not reached" if h is None else str(h) for h in hits) + " |")
    if bn is not None:
        lines += ["", "| held-out set, final networks (mean of seeds) | as trained (eval mode) | BatchNorm "
                  "recalibrated | batch statistics | training stream (last iterations) |", "|---|---:|---:|---:|---:|"]
        for m in [reference] + list(methods):
            vals = [bn["runs"][str(r.parent)][m] for r in runs if m in bn["runs"].get(str(r.parent), {})]
            if len(vals) == len(runs):
                def mean(k, vals=vals):
                    return np.mean([v[k] for v in vals])
                lines.append(f"| {NAMES.get(m, m)} | {mean('as_trained'):,.0f} | {mean('recalibrated'):,.0f} | "
                             f"{mean('batch_statistics'):,.0f} | {mean('training_stream'):,.0f} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> dict:
    """Command-line entry point."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=Path, nargs="+", required=True)
    ap.add_argument("--at", type=int, nargs="+", required=True)
    ap.add_argument("--windows", type=int, nargs="+", default=[16, 64])
    ap.add_argument("--reference", default="adam")
    ap.add_argument("--method", "--methods", nargs="+", default=["pg"], help="compared method(s)")
    ap.add_argument("--centred", action="store_true", help="centred instead of trailing running means")
    ap.add_argument("--first-ratio", type=float, default=None, metavar="R",
                    help="also print the first iteration at which the ratio reaches R (first window)")
    ap.add_argument("--reach", type=int, default=None, metavar="N",
                    help="also print the iterations each method needs to reach the reference's level at N")
    ap.add_argument("--overview", action="store_true",
                    help="one table for all methods (first window; --reach defaults to the last --at)")
    ap.add_argument("--bn", type=Path, default=None, help="with --overview: bn_recalibrate.py's JSON")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)
    if args.overview:
        bn = None if args.bn is None else json.loads(args.bn.read_text())
        print(overview(args.runs, args.at, args.windows[0], args.method, args.reach or args.at[-1], args.reference,
                       bn))
    results = {m: ratios(args.runs, args.at, args.windows, args.reference, m, args.centred) for m in args.method}
    print("runs: " + ", ".join(str(r) for r in args.runs) + (" (centred windows)" if args.centred else ""))
    for m, result in results.items():
        print(markdown(result, args.runs, args.reference, m) + "\n")
        if args.first_ratio is not None:
            hits = first_crossing(args.runs, args.first_ratio, args.windows[0], args.reference, m, args.centred)
            print(f"first iteration with {args.reference} / {m} >= {args.first_ratio}: {hits}\n")
        if args.reach is not None:
            hits = iterations_to_reach(args.runs, args.reach, args.windows[0], args.reference, m, args.centred)
            print(f"iterations of {m} to reach {args.reference}'s level at {args.reach}: {hits}\n")
    if args.json is not None:
        first = results[args.method[0]]
        args.json.write_text(json.dumps({"runs": [str(r) for r in args.runs], "reference": args.reference,
                                         "ratios": first, "methods": results}, indent=1))
    return results[args.method[0]] if len(results) == 1 else results


if __name__ == "__main__":
    main()
