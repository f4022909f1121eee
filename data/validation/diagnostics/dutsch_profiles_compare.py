"""The velocity profiles of the in-line oscillating cylinder against the experiment of Dütsch et al. (1998).

Reads the profiles that ``examples/dutsch_cylinder.py --out PREFIX`` writes (``PREFIX_profiles.csv``: ``u, v`` along
``x / D = -0.6, 0, 0.6, 1.2`` at the phase angles 180, 210 and 330 degrees) and the measured profiles, one CSV per
component, phase and station, named ``{u,v}_phi={180,210,330}_x={-0.6,0.0,0.6,1.2}.csv`` with rows ``value, y`` (in
``U_max`` and ``D``). Such a set, digitized from a figure that reproduces the paper's measurements, is public (see
docs/VALIDATION.md); it is not shipped with phisim, so ``--experiment-dir`` points at a copy.

For each profile it interpolates ours linearly to the measured ``y`` (points inside the cylinder skipped) and prints
the rms and largest difference; with ``--out`` it writes them as JSON::

    python data/validation/diagnostics/dutsch_profiles_compare.py --experiment-dir DIR \\
        data/validation/dutsch_cv_d10 data/validation/dutsch_cv_d20 data/validation/dutsch_cv_d30
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

PHASES = (180, 210, 330)
STATIONS = (-0.6, 0.0, 0.6, 1.2)


def measured(directory: Path, comp: str, phase: int, x: float) -> np.ndarray:
    """Rows ``(y, value)`` of one measured profile, sorted by ``y``."""
    data = np.loadtxt(directory / f"{comp}_phi={phase}_x={x:.1f}.csv", delimiter=",", comments="#")
    return data[np.argsort(data[:, 1])][:, ::-1]


def compare(prefix: str, directory: Path) -> dict:
    """Per profile and over all: rms and largest difference ours - measured, and the number of points."""
    ours = np.loadtxt(f"{prefix}_profiles.csv", delimiter=",", comments="#")
    out, all_diff = {}, []
    for phase in PHASES:
        for x in STATIONS:
            for j, comp in ((3, "u"), (4, "v")):
                sel = (np.abs(ours[:, 0] - phase) < 0.5) & (np.abs(ours[:, 1] - x) < 1e-9)
                y, val = ours[sel, 2], ours[sel, j]
                ok = np.isfinite(val)
                exp = measured(directory, comp, phase, x)
                inside = np.interp(exp[:, 0], y, (~ok).astype(float)) > 0  # within a cell of the cylinder
                fit = np.interp(exp[:, 0], y[ok], val[ok])
                d = (fit - exp[:, 1])[~inside]
                all_diff.append(d)
                out[f"{comp} phi={phase} x={x:+.1f}"] = {"rms": float(np.sqrt(np.mean(d**2))),
                                                         "max": float(np.abs(d).max()), "points": int(d.size)}
    d = np.concatenate(all_diff)
    out["all"] = {"rms": float(np.sqrt(np.mean(d**2))), "max": float(np.abs(d).max()), "points": int(d.size)}
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("prefixes", nargs="+", help="output prefixes of examples/dutsch_cylinder.py runs")
    ap.add_argument("--experiment-dir", required=True, type=Path)
    ap.add_argument("--out", default=None, help="JSON of the differences per run")
    args = ap.parse_args(argv)
    result = {p: compare(p, args.experiment_dir) for p in args.prefixes}
    for p, r in result.items():
        worst = max((k for k in r if k != "all"), key=lambda k: r[k]["rms"])
        print(f"{p}: rms {r['all']['rms']:.4f}, max {r['all']['max']:.4f} U_max over {r['all']['points']} points; "
              f"worst profile {worst} (rms {r[worst]['rms']:.4f})")
    if args.out:
        Path(args.out).write_text(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
