"""DFG 2D-1 / 2D-2: the force on the cylinder read from a momentum balance over a control volume away from it.

The body readings of ``body_forces`` (cut cells, surface, momentum) all read the pressure and the wall shear within a
few cells of the cylinder. This script reads the same force a fourth way, from the flow only where it is smooth: for
a rectangle ``V`` of cell faces around the cylinder with outer boundary ``S`` (outward normal ``n``), the momentum
balance of the fluid in ``V`` gives the force of the fluid on the body

    F = -d/dt int_V u dV + oint_S ( -u (u . n) - p n + nu (grad u + grad u^T) n ) dS,

(density 1). On the MAC grid: the momentum integral by the trapezoid rule across the rectangle's face lines and the
midpoint rule along them (the body's interior holds zero velocity), the side integrals by the midpoint rule with
second-order central differences and averages at the sides; the time derivative ``(M^(n+1) - M^n) / dt`` centred at
the half step with the pressure of the step (``imex2``'s incremental pressure stands at the half step) and the mean of
the two time levels' fluxes (:func:`phisim.fluid.control_volume_force`). Its error is the flow's own truncation error
away from the body, plus ``O(h^2)`` quadrature, so where it agrees with the body readings the lift is the flow's, not
the readings'.

Run from a state saved by ``examples/cylinder_benchmark.py --save-state`` (``--init-from``), for example::

    python data/validation/diagnostics/dfg_control_volume.py --ny 164 --t-end 5.0 --record-from 4.3 \\
        --init-from data/validation/sequenced/dfg_2d2_imex2_quick_ny82_t4.npz --out cv_ny164.json

It prints and writes the per-period lift maxima of each reading, with the control volumes ``--boxes`` (half-widths
in diameters about the cylinder's centre; several give a check of the quadrature: their readings agree to its error).
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import math
import sys
import time as _time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[3]
sys.path.insert(0, str(ROOT))
_spec = importlib.util.spec_from_file_location("cylinder_benchmark", ROOT / "examples" / "cylinder_benchmark.py")
cb = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(cb)

from phisim.fluid import FluidStepper, body_forces, control_volume_box, control_volume_force  # noqa: E402


def box_of(half: tuple[float, float]) -> tuple[tuple[float, float], tuple[float, float]]:
    """The rectangle ``centre +- half * D`` (rounded to faces by :func:`phisim.fluid.control_volume_box`)."""
    cx, cy = cb.CENTER
    return ((cx - half[0] * cb.D, cx + half[0] * cb.D), (cy - half[1] * cb.D, cy + half[1] * cb.D))


def period_maxima(t: np.ndarray, cl: np.ndarray) -> list[float]:
    """The lift's maximum in each full period between its upward zero crossings of the mean."""
    x = cl - 0.5 * (cl.max() + cl.min())
    up = np.nonzero((x[:-1] < 0) & (x[1:] >= 0))[0]
    return [float(cl[a:b + 1].max()) for a, b in zip(up[:-1], up[1:])]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--case", default="2D-2", choices=["2D-1", "2D-2"])
    ap.add_argument("--ny", type=int, required=True)
    ap.add_argument("--t-end", type=float, required=True)
    ap.add_argument("--record-from", type=float, required=True)
    ap.add_argument("--init-from", default=None, help="a state saved by examples/cylinder_benchmark.py (default: "
                    "from the inflow profile at t = 0)")
    ap.add_argument("--integrator", default="imex2")
    ap.add_argument("--convection", default="quick", choices=["central", "quick"])
    ap.add_argument("--cfl", type=float, default=0.5)
    ap.add_argument("--boxes", type=float, nargs="+", default=[1.0, 1.0, 1.5, 1.0, 1.5, 1.5],
                    help="pairs of half-widths (x, y) in diameters")
    ap.add_argument("--out", default=None, help="JSON summary; the history beside it as CSV")
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    dtype = torch.float64
    grid, body, state, um = cb.setup(args.case, args.ny, dtype, "cpu")
    if args.init_from:
        state = cb.initial_state(cb.load_state(args.init_from), args.case, grid, state.velocity.boundary, dtype, "cpu")
    h = grid.dx[0]
    dt = args.cfl * h / (1.5 * um)
    n = int(math.ceil((args.t_end - state.time) / dt))
    dt = (args.t_end - state.time) / n
    stepper = FluidStepper(grid, state.velocity.boundary, obstacles=body, viscosity=cb.NU, integrator=args.integrator,
                           dtype=dtype, device="cpu", dt=dt, convection=args.convection)
    halves = list(zip(args.boxes[0::2], args.boxes[1::2]))
    boxes = [box_of(hw) for hw in halves]
    umean = 2 * um / 3
    scale = 2.0 / (umean**2 * cb.D)
    rows = []
    clock = _time.perf_counter()
    for _ in range(n):
        prev = state.velocity
        state = stepper(state)
        if state.time < args.record_from - 1e-12:
            continue
        f = body_forces(state.velocity, state.pressure, body, dt=dt, viscosity=cb.NU, time=state.time)
        row = [state.time - 0.5 * dt, state.time, float(f.total[0, 0]) * scale, float(f.total[0, 1]) * scale]
        for box in boxes:
            force = control_volume_force(state.velocity, state.pressure, box=box, dt=dt, viscosity=cb.NU,
                                         previous=prev).total
            row += [float(force[0, 0]) * scale, float(force[0, 1]) * scale]
        rows.append(row)
    hist = np.array(rows)
    names = ["cells"] + [f"cv_{a:g}x{b:g}" for a, b in halves]
    summary = {"case": args.case, "ny": args.ny, "dt": dt, "steps": n, "t": [float(hist[0, 1]), float(hist[-1, 1])],
               "integrator": args.integrator, "convection": args.convection, "init_from": args.init_from,
               "boxes": {nm: [list(r) for r in control_volume_box(grid, b)] for nm, b in zip(names[1:], boxes)},
               "wall_s": _time.perf_counter() - clock, "readings": {}}
    for k, nm in enumerate(names):
        cd, cl = hist[:, 2 + 2 * k], hist[:, 3 + 2 * k]
        summary["readings"][nm] = {"cl_max_per_period": period_maxima(hist[:, 1], cl),
                                   "cl_min": float(cl.min()), "cd_max": float(cd.max()), "cd_mean": float(cd.mean()),
                                   "cd_last": float(cd[-1]), "cl_last": float(cl[-1])}
    print(json.dumps(summary, indent=1))
    if args.out:
        Path(args.out).write_text(json.dumps(summary, indent=1))
        header = "t_half,t," + ",".join(f"cd_{nm},cl_{nm}" for nm in names)
        np.savetxt(Path(args.out).with_suffix(".csv"), hist, delimiter=",", header=header)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
