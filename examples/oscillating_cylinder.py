"""A cylinder oscillating in line in a closed box: the force history of a moving body, and its smoothness.

The disc (diameter ``D = 0.2``) moves on ``x(t) = x0 + A sin(2 pi t / T)`` in ``[0, 2] x [0, 1]`` with walls, fluid
initially at rest, ``nu = 0.01``. Faces that the moving (sharp) body uncovers take the linear wall profile between the
body's velocity at the surface and the fluid's at a probe two cells out
(:func:`~phisim.fluid.projection.uncover_faces`); ``--keep-uncovered`` switches that off for comparison (the faces
then keep the velocity they were given inside the body, as before the treatment existed). The script prints, per
run, the largest jump and the largest second difference of the in-line force coefficient between consecutive steps
relative to its range over the run (spikes from freshly uncovered cells show up there), for the total force and for
its pressure and viscous parts (relative to the range of the total).

``python examples/oscillating_cylinder.py [--n 64] [--steps 400] [--dt 0.005] [--blended] [--keep-uncovered]``
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import phisim.fluid.projection as projection  # noqa: E402
from phisim import Grid, StaggeredGrid  # noqa: E402
from phisim.checks import check_device  # noqa: E402
from phisim.fluid import Body, FluidState, Sphere, body_forces, step  # noqa: E402

D, AMP, PERIOD, NU, X0 = 0.2, 0.1, 1.0, 0.01, (0.8, 0.53)


def run(n: int = 64, steps: int = 400, sharp: bool = True, dt: float = 0.005, device=None):
    """Force history ``(steps, 5)``: time, in-line and cross force coefficients (``U = 2 pi A / T``), pressure and
    viscous parts of the in-line coefficient."""
    grid = Grid((2 * n, n), bounds=[(0.0, 2.0), (0.0, 1.0)])
    body = Body(Sphere(X0, D / 2), path=lambda t: (AMP * math.sin(2 * math.pi * t / PERIOD), 0.0), sharp=sharp)
    state = FluidState(StaggeredGrid.zeros(grid, "wall", dtype=torch.float64, device=device))
    speed = 2 * math.pi * AMP / PERIOD
    hist = []
    for _ in range(steps):
        state = step(state, dt, viscosity=NU, obstacles=body, advection="semi_lagrangian")
        f = body_forces(state.velocity, state.pressure, body, dt=dt, viscosity=NU, time=state.time)
        c = f.coefficients(speed, D)[0]
        q = 0.5 * speed**2 * D
        hist.append((state.time, float(c[0]), float(c[1]), float(f.pressure[0, 0]) / q, float(f.viscous[0, 0]) / q))
    return np.array(hist)


def spikes(hist: np.ndarray, skip: int = 20) -> dict:
    """Largest step-to-step jump and second difference of the in-line coefficient over its range, and the range
    (after ``skip`` steps); the same for its pressure and viscous parts (over the range of the total)."""
    cd = hist[skip:, 1]
    rng = float(cd.max() - cd.min())
    out = {"range": rng}
    for name, col in (("", 1), ("pressure_", 3), ("viscous_", 4)):
        if hist.shape[1] <= col:
            continue
        c = hist[skip:, col]
        out[f"{name}max_jump_over_range"] = float(np.abs(np.diff(c)).max()) / rng
        out[f"{name}max_second_difference_over_range"] = float(np.abs(np.diff(c, 2)).max()) / rng
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--n", type=int, default=64)
    ap.add_argument("--steps", type=int, default=400)
    ap.add_argument("--dt", type=float, default=0.005, help="time step (explicit viscosity: below dx^2 / (4 nu))")
    ap.add_argument("--blended", action="store_true")
    ap.add_argument("--keep-uncovered", action="store_true",
                    help="no treatment of freshly uncovered faces (they keep the velocity they had in the body)")
    ap.add_argument("--out", default=None, help="CSV of the force history")
    ap.add_argument("--device", default="cpu", help="cpu, cuda or cuda:N")
    args = ap.parse_args(argv)
    device = check_device(args.device)
    torch.set_num_threads(1)
    if args.keep_uncovered:
        projection.uncover_faces = lambda values, *rest: values
    hist = run(args.n, args.steps, sharp=not args.blended, dt=args.dt, device=device)
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        np.savetxt(args.out, hist, delimiter=",", header="t,c_inline,c_cross,c_inline_pressure,c_inline_viscous")
    print(json.dumps({"n": args.n, "sharp": not args.blended, "uncovered_treatment": not args.keep_uncovered,
                      "device": str(device), **spikes(hist, skip=int(round(0.1 / args.dt)))}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
