"""The pressure of DFG 2D-1 on the stagnation line at fixed points, on several grids (docs/VALIDATION.md).

    python data/validation/diagnostics/dfg_pressure_field.py NY [NY ...] [--out FILE.json]

Runs examples/cylinder_benchmark.py's 2D-1 case (split step, CFL 0.5, to t = 10) on each grid and samples the final
pressure bilinearly from the cell centres on the line y = 0.2 at points in front of (x < 0.15) and behind (x > 0.25)
the cylinder, relative to the point (1.5, 0.2). Prints one JSON object: per grid the values, and the observed orders
of the differences between successive grids (grids doubling).
"""
import argparse
import json
import math
import os
import sys

ROOT = os.environ.get("REPO", os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "..", ".."))
sys.path.insert(0, ROOT)
sys.path.insert(0, os.path.join(ROOT, "examples"))
import cylinder_benchmark as cb  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402

XS = (0.02, 0.05, 0.08, 0.10, 0.12, 0.13, 0.14, 0.26, 0.27, 0.28, 0.30, 0.35, 0.40, 0.50)
REF = (1.5, 0.2)


def sample(p: np.ndarray, dx: float, x: float, y: float) -> float:
    """Bilinear interpolation of cell-centred values ``p`` (spacing ``dx``, origin 0) at ``(x, y)``."""
    fx, fy = x / dx - 0.5, y / dx - 0.5
    i, j = int(math.floor(fx)), int(math.floor(fy))
    a, b = fx - i, fy - j
    return float((1 - a) * (1 - b) * p[i, j] + a * (1 - b) * p[i + 1, j] + (1 - a) * b * p[i, j + 1]
                 + a * b * p[i + 1, j + 1])


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("ny", type=int, nargs="+")
    ap.add_argument("--out", default=None)
    args = ap.parse_args()
    torch.set_num_threads(1)
    rows = []
    for ny in args.ny:
        hist, state, meta = cb.run("2D-1", ny, 10.0, record_from=9.99)
        p = state.pressure.values[0].numpy() / meta["dt"]  # the step stores dt * p
        dx = cb.H / ny
        ref = sample(p, dx, *REF)
        rows.append({"ny": ny, "D_over_dx": cb.D / dx, "wall_s": meta["wall_s"],
                     "p_minus_ref": [sample(p, dx, x, 0.2) - ref for x in XS], "dp": float(hist[-1, 3])})
        print(json.dumps(rows[-1]), file=sys.stderr, flush=True)
    orders = []
    for a, b, c in zip(rows, rows[1:], rows[2:]):
        o = []
        for k in range(len(XS)):
            d1 = b["p_minus_ref"][k] - a["p_minus_ref"][k]
            d2 = c["p_minus_ref"][k] - b["p_minus_ref"][k]
            o.append(math.log(abs(d1 / d2)) / math.log(2) if d1 and d2 else None)
        orders.append({"grids": [a["ny"], b["ny"], c["ny"]], "orders": o})
    out = {"x": list(XS), "y": 0.2, "reference_point": list(REF), "rows": rows, "observed_orders": orders}
    text = json.dumps(out, indent=1)
    print(text)
    if args.out:
        with open(args.out, "w") as f:
            f.write(text + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
