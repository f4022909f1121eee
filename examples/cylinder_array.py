"""Stokes flow through a periodic square array of cylinders: the drag of no-slip bodies against Sangani & Acrivos.

Sangani, A. S. & Acrivos, A. (1982), "Slow flow past periodic arrays of cylinders with application to heat
transfer", Int. J. Multiphase Flow 8, 193-206 (series for the square array; Hasimoto 1959 gave its first terms):

    ``F / (mu U) = 4 pi / K``,  ``K = -ln(c) / 2 - 0.738 + c - 0.887 c^2 + 2.039 c^3 + O(c^4)``,

with ``c = pi R^2 / L^2`` the solid fraction, ``F`` the force per unit length on each cylinder and ``U`` the
superficial velocity (the volume flux per unit width). Their table (from the full multipole solution) gives 15.56 at
``c = 0.05`` and 24.83 at 0.1, where the truncated series agrees to 0.1 %; use ``c <= 0.1``.

Here a unit periodic box holds one sharp no-slip :class:`~phisim.fluid.Body` (a disc, off the grid's symmetry
lines); a uniform force density ``f = 1`` acts on the fluid, ``nu = 1``. The same velocity solves the problem driven
by a mean pressure gradient ``G = f``, for which the force on the cylinder is ``F = G L^2``, so the computed
coefficient is ``f L^2 / (nu U)`` with ``U`` the flux through the line ``x = 0``. That number measures the discrete
flow field (the momentum balance, no force formula). The force from the surface formulas
(:func:`~phisim.fluid.body_forces`: pressure in the cut cells, viscous stress from probes) balances the force
density over the fluid, ``f (L^2 - pi R^2)``, which checks those formulas.

Two ways to the steady state:

* ``--scheme incremental`` (default): steps of impose, ``u - G p`` with the previous pressure, viscosity
  (implicit, ``dt = 50 dx^2 / nu``), projection of the increment. At the steady state the increment vanishes and
  the velocity and pressure solve the discrete Stokes equations exactly, whatever ``dt``.
* ``--scheme split``: the split step of :func:`phisim.fluid.step` (impose, viscosity with the wall values moved by
  the previous tangential pressure gradient, :func:`~phisim.fluid.step.anticipate_pressure`, projection of the whole
  pressure). Its steady state depends on ``dt`` (``--dt-cells`` sets ``dt`` in units of ``dx^2 / nu``): the
  projection changes the velocity next to a body by ``G p`` after the viscous step has imposed the wall value; the
  anticipated gradient removes most of its tangential part (``docs/VALIDATION.md``).

``python examples/cylinder_array.py --n 32 64 128`` prints the coefficient, its error and the observed orders.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time as _time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from phisim import Grid, StaggeredGrid  # noqa: E402
from phisim.checks import check_device  # noqa: E402
from phisim.errors import ParameterError  # noqa: E402
from phisim.fluid import (  # noqa: E402
    Body,
    Sphere,
    anticipate_pressure,
    body_forces,
    diffuse_velocity,
    impose_solids,
    make_incompressible,
    solid_layout,
)
from phisim.ops.stencil import face_gradient, normalize_kinds  # noqa: E402
from phisim.solvers import Solve  # noqa: E402

NU, FORCE = 1.0, 1.0
OFFSET = (0.013, -0.021)  # the disc's centre off the grid's symmetry lines: no lucky cancellations


def sangani_acrivos(c: float) -> float:
    """``F / (mu U)`` of the square array at solid fraction ``c`` (the series above)."""
    k = -0.5 * math.log(c) - 0.738 + c - 0.887 * c**2 + 2.039 * c**3
    return 4 * math.pi / k


def solve_steady(n: int, c: float = 0.05, scheme: str = "incremental", dt_cells: float | None = None,
                 tol: float = 1e-7, max_steps: int = 100000, device=None) -> dict:
    """The steady flow on an ``n x n`` grid; returns the coefficient, the surface force and the run's numbers.

    Steps until the largest change of a step is below ``tol`` times the largest velocity. The surface force of the
    incremental iteration is not a result: the pressure of cut cells reached only through faces centred inside the
    body settles far more slowly than the velocity (the command line prints it for the split step alone)."""
    if scheme not in ("incremental", "split"):
        raise ParameterError(f"scheme must be 'incremental' or 'split', got {scheme!r}")
    dt_cells = (50.0 if scheme == "incremental" else 1.0) if dt_cells is None else dt_cells
    radius = math.sqrt(c / math.pi)
    grid = Grid((n, n), bounds=[(0.0, 1.0), (0.0, 1.0)])
    body = Body(Sphere((0.5 + OFFSET[0], 0.5 + OFFSET[1]), radius))
    v = StaggeredGrid.zeros(grid, "periodic", dtype=torch.float64, device=device)
    layout = solid_layout([body], grid, v.boundary, 0.0, torch.float64, v.device)
    dt = dt_cells * grid.dx[0] ** 2 / NU
    tight = Solve(rtol=1e-12)
    p = None
    t0 = _time.perf_counter()
    periodic = normalize_kinds("periodic", 2)
    kick = (FORCE * dt, 0.0)
    steps = 0
    while steps < max_steps:
        steps += 1
        grad = (0.0, 0.0) if (scheme == "split" or p is None) else face_gradient(p.values, grid.dx, periodic)
        w = impose_solids(v.with_values(tuple(u + kk - g for u, kk, g in zip(v.values, kick, grad))), layout)
        walls = layout if scheme == "incremental" else anticipate_pressure(layout, p, w)
        w = diffuse_velocity(w, dt, viscosity=NU, scheme="implicit", solids=walls, solve=tight)
        new, q = make_incompressible(w, layout, solve=tight, pressure_guess=None if scheme == "incremental" else p)
        p = q if (scheme == "split" or p is None) else p.with_values(p.values + q.values)
        change = max(float((a - b).abs().max()) for a, b in zip(new.values, v.values))
        v = new
        if change < tol * float(v.values[0].abs().max()):
            break
    flux = float(v.values[0][0, 0, :].sum()) * grid.dx[1]  # faces on x = 0, all in the fluid
    coefficient = FORCE / (NU * flux)
    surface = body_forces(v, p, body, dt=dt, viscosity=NU)
    balance = FORCE * (1.0 - c)
    ref = sangani_acrivos(c)
    return {"n": n, "cells_per_diameter": 2 * radius * n, "scheme": scheme, "dt_cells": dt_cells, "steps": steps,
            "coefficient": coefficient, "reference": ref, "error": coefficient / ref - 1,
            "surface_force": float(surface.total[0, 0]), "surface_pressure": float(surface.pressure[0, 0]),
            "surface_viscous": float(surface.viscous[0, 0]), "surface_error": float(surface.total[0, 0]) / balance - 1,
            "wall_s": _time.perf_counter() - t0}


def orders(rows: list[dict], key: str) -> list[float]:
    """Observed orders of ``|row[key]|`` between successive rows (grids doubling)."""
    return [math.log(abs(a[key]) / abs(b[key])) / math.log(b["n"] / a["n"]) for a, b in zip(rows, rows[1:])]


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--n", type=int, nargs="+", default=[32, 64, 128], help="grid sizes (default 32 64 128)")
    parser.add_argument("--c", type=float, default=0.05, help="solid fraction (default 0.05)")
    parser.add_argument("--scheme", choices=["incremental", "split"], default="incremental",
                        help="steady iteration (default incremental)")
    parser.add_argument("--dt-cells", type=float, default=None,
                        help="time step in units of dx^2 / nu (default 50 incremental, 1 split)")
    parser.add_argument("--tol", type=float, default=1e-7, help="steady when a step changes the velocity less "
                        "than this times its maximum (default 1e-7)")
    parser.add_argument("--max-steps", type=int, default=100000, help="most steps per grid (default 100000)")
    parser.add_argument("--threads", type=int, default=1, help="torch threads (default 1)")
    parser.add_argument("--device", default="cpu", help="cpu, cuda or cuda:N (default cpu)")
    parser.add_argument("--out", default=None, help="JSON file for the results")
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    device = check_device(args.device)
    rows = []
    for n in args.n:
        row = solve_steady(n, args.c, args.scheme, args.dt_cells, args.tol, args.max_steps, device=device)
        rows.append(row)
        surface = f"  surface force {100 * row['surface_error']:+.3f} %" if args.scheme == "split" else ""
        print(f"n={n:4d} D/dx={row['cells_per_diameter']:5.1f} steps={row['steps']:6d}  "
              f"F/(mu U)={row['coefficient']:.5f} (reference {row['reference']:.5f}, {100 * row['error']:+.3f} %)"
              f"{surface}  ({row['wall_s']:.1f} s)", flush=True)
    if len(rows) > 1:
        print("orders, coefficient:", [round(o, 2) for o in orders(rows, "error")],
              *([" surface force:", [round(o, 2) for o in orders(rows, "surface_error")]] if args.scheme == "split"
                else []))
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(json.dumps({"rows": rows, "argv": list(sys.argv[1:] if argv is None else argv)},
                                              indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
