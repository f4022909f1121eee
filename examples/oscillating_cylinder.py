"""A cylinder oscillating in line in a closed box: the force history of a moving body, and its smoothness.

The disc (diameter ``D = 0.2``) moves on ``x(t) = x0 + A sin(2 pi t / T)`` in ``[0, 2] x [0, 1]`` with walls, fluid
initially at rest, ``nu = 0.01``. Faces that the moving body uncovers start with the velocity the step gives them
(the body's velocity where it was, then the viscous step and projection of the fluid around them). The script
prints, per run, the largest jump of the in-line force coefficient between consecutive steps relative to its range
over the run (spikes from freshly uncovered cells show up there) and the force range.

``python examples/oscillating_cylinder.py [--n 64] [--steps 400] [--blended]``
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

from phisim import Grid, StaggeredGrid  # noqa: E402
from phisim.checks import check_device  # noqa: E402
from phisim.fluid import Body, FluidState, Sphere, body_forces, step  # noqa: E402

D, AMP, PERIOD, NU, X0 = 0.2, 0.1, 1.0, 0.01, (0.8, 0.53)


def run(n: int = 64, steps: int = 400, sharp: bool = True, dt: float = 0.005, device=None):
    """Force history ``(steps, 3)``: time, in-line and cross force coefficients (``U = 2 pi A / T``)."""
    grid = Grid((2 * n, n), bounds=[(0.0, 2.0), (0.0, 1.0)])
    body = Body(Sphere(X0, D / 2), path=lambda t: (AMP * math.sin(2 * math.pi * t / PERIOD), 0.0), sharp=sharp)
    state = FluidState(StaggeredGrid.zeros(grid, "wall", dtype=torch.float64, device=device))
    speed = 2 * math.pi * AMP / PERIOD
    hist = []
    for _ in range(steps):
        state = step(state, dt, viscosity=NU, obstacles=body, advection="semi_lagrangian")
        f = body_forces(state.velocity, state.pressure, body, dt=dt, viscosity=NU, time=state.time)
        c = f.coefficients(speed, D)[0]
        hist.append((state.time, float(c[0]), float(c[1])))
    return np.array(hist)


def spikes(hist: np.ndarray, skip: int = 20) -> dict:
    """Largest step-to-step jump of the in-line coefficient over its range, and the range (after ``skip`` steps)."""
    cd = hist[skip:, 1]
    rng = float(cd.max() - cd.min())
    jump = float(np.abs(np.diff(cd)).max())
    curv = float(np.abs(np.diff(cd, 2)).max())
    return {"range": rng, "max_jump_over_range": jump / rng, "max_second_difference_over_range": curv / rng}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--n", type=int, default=64)
    ap.add_argument("--steps", type=int, default=400)
    ap.add_argument("--blended", action="store_true")
    ap.add_argument("--out", default=None, help="CSV of the force history")
    ap.add_argument("--device", default="cpu", help="cpu, cuda or cuda:N")
    args = ap.parse_args(argv)
    device = check_device(args.device)
    torch.set_num_threads(1)
    hist = run(args.n, args.steps, sharp=not args.blended, device=device)
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        np.savetxt(args.out, hist, delimiter=",", header="t,c_inline,c_cross")
    print(json.dumps({"n": args.n, "sharp": not args.blended, "device": str(device), **spikes(hist)}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
