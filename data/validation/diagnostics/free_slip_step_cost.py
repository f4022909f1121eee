"""CPU cost of a step of the carried free-slip spherical Couette flow (``test_moving_bodies_order_3d.py --free-slip``:
both spheres move, so each step builds their layout) with the fine sub-cuts on the faces nearly
parallel to the surface (``FREE_SLIP_PARALLEL`` as set) and without them (``FREE_SLIP_PARALLEL = 2``: the coarse
count on every face), alternating in one process: ``python data/validation/diagnostics/free_slip_step_cost.py [n]
[steps] [rounds]`` prints one JSON line per round and setting (thread time per step, one thread)."""
import json
import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[3]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests" / "phisim" / "fluid"))
import test_moving_bodies_order_3d as M  # noqa: E402

import phisim.fluid.bodies as fb  # noqa: E402
from phisim import Grid  # noqa: E402
from phisim.fluid.step import finish_step  # noqa: E402
from phisim.solvers import Solve  # noqa: E402


def step_cost(n: int, steps: int) -> float:
    grid = Grid((n, n, n), bounds=[(-M.HALF_FREE_SLIP, M.HALF_FREE_SLIP)] * 3)
    h = grid.dx[0]
    dt = h * h / M.SC.NU
    solids = M.bodies(True)
    v = M.exact_field(grid, 0.0, True)
    p, t = None, 0.0
    cpu = time.thread_time()
    for _ in range(steps):
        t += dt
        v, p = finish_step(v, dt, None, M.SC.NU, "implicit", solids, Solve(rtol=1e-9), p, t)
    return (time.thread_time() - cpu) / steps


if __name__ == "__main__":
    torch.set_num_threads(1)
    n, steps, rounds = (int(a) for a in (sys.argv[1:] + ["48", "5", "2"][len(sys.argv) - 1:]))
    default = getattr(fb, "FREE_SLIP_PARALLEL", None)
    for r in range(rounds):
        for parallel in (default, 2.0):
            if parallel is None:
                continue
            fb.FREE_SLIP_PARALLEL = parallel
            print(json.dumps({"n": n, "round": r, "FREE_SLIP_PARALLEL": parallel,
                              "step_cpu_s": step_cost(n, steps)}), flush=True)
