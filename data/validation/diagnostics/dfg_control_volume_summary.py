"""The table of "The force from a control volume" (docs/VALIDATION.md) from the runs of dfg_control_volume.py in
data/validation/control_volume/: per grid, the cut cells' reading beside the control volumes' readings, the
spread of the control volumes (their own error), the gap between the readings and its observed order.

    python data/validation/diagnostics/dfg_control_volume_summary.py
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parents[1] / "control_volume"


def _order(h, gaps):
    """Observed order of a gap that should vanish, between consecutive grids."""
    return [math.log(abs(g0 / g1)) / math.log(h0 / h1) if g0 * g1 > 0 else float("nan")
            for h0, h1, g0, g1 in zip(h, h[1:], gaps, gaps[1:])]


def table(case: str, variant: str = ""):
    """Per grid and reading: ``(c_D, c_L)`` at the end (2D-1) or the maxima of the last full period (2D-2), as
    dfg_control_volume.py wrote them; ``variant`` ``"central_"`` for the runs with central fluxes."""
    rows = []
    for f in sorted(HERE.glob(f"dfg_{case}_{variant}ny*.json")):
        r = json.loads(f.read_text())
        row = {"ny": r["ny"], "D/h": round(r["ny"] * 0.1 / 0.41)}
        for nm, v in r["readings"].items():
            row[nm] = (v["cd_last"], v["cl_last"]) if case == "2d1" else (v["cd_max"], v["cl_max_per_period"][-1])
        rows.append(row)
    rows.sort(key=lambda r: r["ny"])
    return rows


def main() -> int:
    for case, variant, labels in (("2d1", "", ("c_D", "c_L")), ("2d2", "", ("c_D,max", "c_L,max")),
                                  ("2d2", "central_", ("c_D,max", "c_L,max"))):
        rows = table(case, variant)
        if not rows:
            continue
        print(f"DFG {case.upper()}" + (" (central fluxes)" if variant else ""))
        cvs = [k for k in rows[0] if k.startswith("cv_")]
        for r in rows:
            cv = np.array([r[k] for k in cvs])
            print(f"  D/{r['D/h']:<3d} cells {labels[0]} {r['cells'][0]:.5f} {labels[1]} {r['cells'][1]:.5f} | "
                  f"control volumes {labels[0]} {cv[:, 0].min():.5f}-{cv[:, 0].max():.5f} "
                  f"{labels[1]} {cv[:, 1].min():.5f}-{cv[:, 1].max():.5f}")
        h = [1 / r["D/h"] for r in rows]
        for i, lab in enumerate(labels):
            gaps = [float(np.mean([r[k][i] for k in cvs]) - r["cells"][i]) for r in rows]
            spread = [float(np.ptp([r[k][i] for k in cvs])) for r in rows]
            print(f"  {lab}: gap control volumes - cells {[round(g, 5) for g in gaps]}, orders "
                  f"{[round(o, 2) for o in _order(h, gaps)]}; spread of the boxes {[round(s, 5) for s in spread]}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
