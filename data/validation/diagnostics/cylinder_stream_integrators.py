"""Drag of a cylinder started in a uniform stream (Re = 100) by time integrator and grid: how far apart the
integrators' body treatments are on coarse grids.

The 2-D analogue of ``examples/sphere_drag.py``: a resting sharp no-slip cylinder of diameter 1 at the origin, a
uniform ``Inflow`` U = 1 upstream, an ``Open`` outflow, free-slip sides (box ``[-4, 10] x [-4, 4]``), ``nu = 0.01``,
from a uniform start to ``t_end`` (the symmetric wake is still growing at t = 10: the figures compare integrators at
one time, they are not a steady drag). ``dt = 0.5 dx / U`` (the split step also at most ``0.45 dx^2 / (4 nu)``).

``python data/validation/diagnostics/cylinder_stream_integrators.py --n 8 16 32 --variants split imex2 imex2+quick
--out data/validation/diagnostics/cylinder_stream_integrators.jsonl`` (and ``--n 8 --variants rk2 split2
imex2+convext``, ``--n 64 --variants split imex2``).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[3]))

from phisim import Grid, StaggeredGrid  # noqa: E402
from phisim.boundary import Inflow, Open  # noqa: E402
from phisim.fluid import Body, FluidState, FluidStepper, Sphere, body_forces  # noqa: E402

NU, U = 0.01, 1.0
body = Body(Sphere((0.0, 0.0), 0.5))


def simulate(n: int, integrator: str, convection: str = "", t_end: float = 10.0):
    """The cylinder started in the stream on the grid of ``n`` cells per diameter, stepped to ``t_end``: returns the
    final ``FluidState``, the step ``dt`` and the seconds it took. ``convection`` '' is the integrator's default."""
    dx = 1.0 / n
    nx, ny = int(round(14 / dx)), int(round(8 / dx))
    half = ny * dx / 2
    grid = Grid((nx, ny), bounds=[(-4, -4 + nx * dx), (-half, half)])
    boundary = {"x": (Inflow((U, 0.0)), Open()), "y": "slip"}
    v = StaggeredGrid.from_function(lambda x: torch.stack([torch.full_like(x[..., 0], U), 0 * x[..., 0]], -1),
                                    grid, boundary, dtype=torch.float64).with_boundary_faces()
    dt = 0.5 * dx / U
    if integrator != "imex2":
        dt = min(dt, 0.45 * dx**2 / (4 * NU))
    stepper = FluidStepper(grid, v.boundary, obstacles=body, viscosity=NU, dt=dt, dtype=torch.float64,
                           integrator=integrator, **({"convection": convection} if convection else {}))
    state = FluidState(v)
    t0 = time.perf_counter()
    while state.time < t_end - 1e-9:
        state = stepper(state)
    return state, dt, time.perf_counter() - t0


def run(n: int, variant: str, t_end: float = 10.0) -> dict:
    """One run; ``variant`` is an integrator, ``integrator+quick`` (QUICK convection) or ``integrator+convext``
    (central convection reading the velocity extended into the body, as the split steps' transport reads it)."""
    integrator, _, convection = variant.partition("+")
    if convection == "convext":
        import phisim.fluid.integrators as integrators
        from phisim.fluid.extension import extend_into_bodies

        plain = integrators.convection
        integrators.convection = lambda v, scheme="central": plain(extend_into_bodies(v, body), scheme)
        try:
            return {**run(n, integrator, t_end), "variant": variant}
        finally:
            integrators.convection = plain
    state, dt, seconds = simulate(n, integrator, convection, t_end)
    f = body_forces(state.velocity, state.pressure, body, dt=dt, viscosity=NU, time=state.time)
    fs = body_forces(state.velocity, state.pressure, body, dt=dt, viscosity=NU, time=state.time, pressure_at="surface")
    q = 0.5 * U**2 * 1.0
    return {"n": n, "variant": variant, "t": state.time, "dt": dt, "cd": float(f.total[0, 0]) / q,
            "cd_pressure": float(f.pressure[0, 0]) / q, "cd_viscous": float(f.viscous[0, 0]) / q,
            "cd_surface": float(fs.total[0, 0]) / q, "wall_s": seconds}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--n", type=int, nargs="+", default=[8, 16])
    ap.add_argument("--variants", nargs="+", default=["split", "imex2", "imex2+quick"])
    ap.add_argument("--t-end", type=float, default=10.0)
    ap.add_argument("--out", default=None, help="JSON lines file to append to")
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    for n in args.n:
        for variant in args.variants:
            row = run(n, variant, args.t_end)
            print(json.dumps(row), flush=True)
            if args.out:
                with open(args.out, "a") as fh:
                    fh.write(json.dumps(row) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
