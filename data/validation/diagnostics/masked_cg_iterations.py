"""Iterations of the masked pressure PCG (``phisim.solvers.masked.MaskedPoisson``) on the layouts that tell its
preconditioner apart: warm-started 2-D wake and plume steps (``benchmarks/bench_bodies.py`` scenes, PCG only), the
resting spherical Couette layout in 3-D (a random compatible right-hand side, ``rtol = 1e-10``, cold) and the carried
3-D spherical Couette study (``tests/phisim/fluid/test_moving_bodies_order_3d.py``, 24^3, ``rtol = 1e-6``, warm).

``python data/validation/diagnostics/masked_cg_iterations.py [--root TREE]`` prints one JSON line per case: solves,
iterations per solve, status of the cold solves. ``--root`` imports phisim (and the scenes) from another tree, e.g.
an older commit exported with ``git archive``, to compare the preconditioners on the same machine.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import sys
from pathlib import Path


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--root", default=str(Path(__file__).resolve().parents[3]))
    ap.add_argument("--cases", nargs="*", default=["wake", "plume", "spheres", "carried"])
    args = ap.parse_args()
    root = Path(args.root).resolve()
    for p in (root / "tests" / "phisim" / "fluid", root / "benchmarks", root):
        sys.path.insert(0, str(p))
    import torch

    torch.set_num_threads(1)
    import phisim.solvers.masked as masked

    count = {"solves": 0, "iterations": 0}
    solve = masked.MaskedPoisson.solve

    def counting(self, rhs, **kw):
        p, info = solve(self, rhs, **kw)
        count["solves"] += 1
        count["iterations"] += int(info.iterations.sum())
        return p, info

    masked.MaskedPoisson.solve = counting

    def report(case, **extra):
        print(json.dumps({"case": case, **count, "per_solve": round(count["iterations"] / count["solves"], 2),
                          **extra}), flush=True)
        count.update(solves=0, iterations=0)

    if "wake" in args.cases or "plume" in args.cases:
        import bench_bodies

        for case in ("wake", "plume"):
            if case in args.cases:
                for n in (128, 256):
                    step = bench_bodies.wake_step_ms if case == "wake" else bench_bodies.plume_step_ms
                    step(n, torch.float64, False, steps=80)
                    report(f"{case} {n}^2, 80 steps")
    if "spheres" in args.cases:
        from phisim import Grid
        from phisim.boundary import Boundary
        from phisim.fluid import solid_layout
        from phisim.solvers import Solve
        from phisim.solvers.poisson import field_kinds_and_values

        spec = importlib.util.spec_from_file_location("sc", root / "examples" / "spherical_couette.py")
        sc = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(sc)
        boundary = Boundary.create("wall", 3)
        kinds = field_kinds_and_values(boundary.for_pressure())[0]
        for n in (32, 48):
            grid = Grid((n, n, n), bounds=[(-sc.HALF, sc.HALF)] * 3)
            layout = solid_layout(sc.bodies(), grid, boundary, 0.0, torch.float64)
            op = masked.MaskedPoisson(layout.theta, grid.dx, kinds, direct=False)
            gen = torch.Generator().manual_seed(0)
            b = op.project(torch.randn(1, n, n, n, dtype=torch.float64, generator=gen) * op.active)
            _, info = op.solve(b, solve=Solve(rtol=1e-10, raise_on_failure=False, max_iter=4000))
            report(f"resting spherical Couette layout {n}^3, cold, rtol 1e-10", status=info.status[0])
    if "carried" in args.cases:
        import test_moving_bodies_order_3d as carried

        row = carried.run(24)
        report("carried spherical Couette 24^3, rtol 1e-6", near_rms=row["near_rms"])


if __name__ == "__main__":
    main()
