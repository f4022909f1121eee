"""The in-line oscillating cylinder of Dütsch, Durst, Becker & Lienhart (1998), J. Fluid Mech. 360, 249-271.

A circular cylinder of diameter ``D`` moves on ``x(t) = -A sin(2 pi f t)`` through fluid at rest, with
``Re = U_max D / nu = 100`` and ``KC = U_max / (f D) = 5`` (so ``A = KC D / (2 pi)``, ``U(t) = -U_max cos(2 pi f t)``).
Units: ``D = U_max = 1``, ``nu = 0.01``, ``T = 1 / f = 5``.

Domain: a closed square box ``[-L, L]^2`` (walls; default ``L = 8 D``, 16 diameters across). The cylinder moves by
``A = 0.8 D`` about the centre: the walls stand 7 diameters beyond its farthest position; the fluid it displaces
returns round it, and the blockage ``D / 2L = 6 %`` changes the potential added mass by about ``(D / 2L)^2``, well
below the differences discussed here (larger boxes cost as their area on a uniform grid).

Records per step: time, body position and velocity, in-line force (pressure and viscous parts from
:func:`~phisim.fluid.body_forces`) and cross force, as coefficients ``c = F / (0.5 rho U_max^2 D)``. After the run:

* **Morison fit** over the recorded periods (``--record-from``, default from the start of period 3):
  ``F = -0.5 rho C_d D |U| U - rho C_i (pi D^2 / 4) dU/dt`` (``U`` the cylinder velocity, the in-line force on a
  cylinder moving through fluid at rest) by linear least squares for ``C_d, C_i``; the rms difference between the
  force and the fitted Morison force relative to the force amplitude.
* **Control-volume readings** ``c_inline_cv`` (one per box of ``CV_HALF_WIDTHS`` that fits in the domain): the
  momentum balance over a box fixed in the laboratory that holds the cylinder's whole path
  (:func:`~phisim.fluid.control_volume_force`, at the half step ``t - dt / 2``), plus the cylinder's own momentum
  change ``rho (pi D^2 / 4) dU/dt`` (its interior holds its velocity): a reading that looks nowhere near the
  cylinder. Each gets its Morison fit (``morison_cv``).
* **Velocity profiles** ``u, v`` along the vertical lines ``x / D = -0.6, 0, 0.6, 1.2`` (the laboratory frame; at
  phase 180 deg the cylinder is centred at ``x = 0``), ``-2 <= y / D <= 2``, at the phase angles ``2 pi f t`` =
  180, 210, 330 degrees of the last recorded period (points inside the cylinder are NaN).

``python examples/dutsch_cylinder.py --res 20 --periods 5 --out data/validation/dutsch_d20``
writes ``<out>_forces.csv``, ``<out>_profiles.csv`` and ``<out>.json``.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time as wall
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from phisim import Grid, StaggeredGrid  # noqa: E402
from phisim.checks import check_device  # noqa: E402
from phisim.fluid import Body, FluidState, Sphere, body_forces, control_volume_force, step  # noqa: E402

D, U_MAX, RE, KC = 1.0, 1.0, 100.0, 5.0
NU = U_MAX * D / RE
FREQ = U_MAX / (KC * D)
PERIOD = 1.0 / FREQ
AMP = KC * D / (2 * math.pi)
OMEGA = 2 * math.pi * FREQ
LINES = (-0.6, 0.0, 0.6, 1.2)
#: Half-widths (in diameters, about the origin) of the control volumes of the ``c_inline_cv`` readings: each holds
#: the cylinder's whole path (``|x| <= A + D / 2 = 1.3 D``) with at least 1.2 diameters to spare.
CV_HALF_WIDTHS = ((2.5, 1.5), (3.0, 2.0))
PHASES = (180.0, 210.0, 330.0)
#: The columns of the force history; one ``c_inline_cv<j>`` per control volume follows them.
COLUMNS = ("t", "x_body", "u_body", "c_inline", "c_inline_pressure", "c_inline_viscous", "c_cross")


def position(t: float) -> float:
    return -AMP * math.sin(OMEGA * t)


def body_velocity(t: float) -> float:
    return -U_MAX * math.cos(OMEGA * t)


def body_acceleration(t: float) -> float:
    return U_MAX * OMEGA * math.sin(OMEGA * t)


def morison_fit(t: np.ndarray, c: np.ndarray) -> dict:
    """Least-squares ``C_d, C_i`` of ``c = -C_d |U| U / U_max^2 - C_i (pi D / 2) (dU/dt) / U_max^2`` and the rms
    difference of the fit relative to the amplitude ``(max c - min c) / 2``."""
    u = np.array([body_velocity(x) for x in t])
    a = np.array([body_acceleration(x) for x in t])
    basis = np.stack([-np.abs(u) * u / U_MAX**2, -(math.pi * D / 2) * a / U_MAX**2], 1)
    (cd, ci), *_ = np.linalg.lstsq(basis, c, rcond=None)
    fit = basis @ np.array([cd, ci])
    amp = 0.5 * float(c.max() - c.min())
    return {"C_d": float(cd), "C_i": float(ci), "rms_difference_over_amplitude": float(np.sqrt(np.mean((c - fit) ** 2))
                                                                                      / amp),
            "max_difference_over_amplitude": float(np.abs(c - fit).max() / amp), "amplitude": amp}


def profiles(velocity: StaggeredGrid, body: Body, t: float, ys: np.ndarray) -> list:
    """Rows ``(phase, x, y, u, v)`` along the vertical lines (NaN inside the cylinder)."""
    dtype = velocity.dtype
    rows = []
    pts = torch.tensor([[x, y] for x in LINES for y in ys], dtype=dtype, device=velocity.device)
    vals = velocity.sample(pts)[0].cpu().numpy()
    inside = (body.sdf(pts, t) <= 0).cpu().numpy()
    phase = (math.degrees(OMEGA * t) + 1e-6) % 360.0
    for k, (x, y) in enumerate(pts.cpu().numpy()):
        u, v = (math.nan, math.nan) if inside[k] else (float(vals[0, k]), float(vals[1, k]))
        rows.append((round(phase, 3), float(x), float(y), u, v))
    return rows


def run(res: int = 20, periods: float = 5.0, half_width: float = 8.0, cfl: float = 0.4, record_from: float = 2.0,
        advection: str = "maccormack", device=None, dtype=torch.float64, progress: bool = False,
        pressure_at: str = "cells", shear_at: str = "probes", integrator: str = "split",
        convection: str = "central") -> dict:
    """Run the case with ``res`` cells per diameter; returns the force history, the profiles and the fit.

    ``pressure_at`` / ``shear_at``: how the force reads the pressure and the wall shear
    (:func:`~phisim.fluid.body_forces`); ``integrator`` / ``convection``: the time integrator and the convection
    scheme of :func:`~phisim.fluid.step` (``docs/SCHEMES.md``)."""
    n = int(round(2 * half_width * res))
    grid = Grid((n, n), bounds=[(-half_width, half_width), (-half_width, half_width)])
    dx = grid.dx[0]
    steps_per_period = int(math.ceil(PERIOD * U_MAX / (cfl * dx)))
    steps_per_period += (-steps_per_period) % 12  # the phases 180, 210 and 330 deg fall on steps
    dt = PERIOD / steps_per_period
    total = int(round(periods * steps_per_period))
    body = Body(Sphere((0.0, 0.0), D / 2), path=lambda t: (position(t), 0.0), name="cylinder")
    state = FluidState(StaggeredGrid.zeros(grid, "wall", dtype=dtype, device=device))
    ys = np.round(np.arange(-2.0, 2.0 + 1e-9, 0.05), 6)
    last = int(math.floor(periods - 1e-9))  # the last period that is completely recorded starts at last - 1
    wanted = {int(round((last - 1 + ph / 360.0) * steps_per_period)): ph for ph in PHASES}
    hist, rows = [], []
    q = 0.5 * U_MAX**2 * D
    area = math.pi * D**2 / 4
    cv_boxes = [((-hx * D, hx * D), (-hy * D, hy * D)) for hx, hy in CV_HALF_WIDTHS
                if hx * D <= half_width and hy * D <= half_width]
    t0 = wall.thread_time()
    for k in range(1, total + 1):
        previous = state.velocity
        state = step(state, dt, viscosity=NU, obstacles=body, advection=advection, integrator=integrator,
                     **({} if convection == "central" else {"convection": convection}))
        t = state.time
        f = body_forces(state.velocity, state.pressure, body, dt=dt, viscosity=NU, time=t, pressure_at=pressure_at,
                        previous_velocity=previous if pressure_at == "momentum" else None, shear_at=shear_at)
        cv = [float(control_volume_force(state.velocity, state.pressure, box=b, dt=dt, viscosity=NU,
                                         previous=previous).total[0, 0]) + area * body_acceleration(t - 0.5 * dt)
              for b in cv_boxes]
        hist.append((t, position(t), body_velocity(t), float(f.total[0, 0]) / q, float(f.pressure[0, 0]) / q,
                     float(f.viscous[0, 0]) / q, float(f.total[0, 1]) / q, *(c / q for c in cv)))
        if k in wanted:
            rows += profiles(state.velocity, body, t, ys)
        if progress and k % 100 == 0:
            print(f"step {k}/{total} t={t:.3f} c_x={hist[-1][3]:+.4f} cpu {wall.thread_time() - t0:.0f} s", flush=True)
    h = np.array(hist)
    rec = h[:, 0] >= record_from * PERIOD - 1e-9
    fit = morison_fit(h[rec, 0], h[rec, 3])
    fit_cv = [morison_fit(h[rec, 0] - 0.5 * dt, h[rec, len(COLUMNS) + j]) for j in range(len(cv_boxes))]
    per_period = []
    for p in range(int(record_from), int(math.floor(periods + 1e-9))):
        sel = (h[:, 0] > p * PERIOD + 1e-9) & (h[:, 0] <= (p + 1) * PERIOD + 1e-9)
        if sel.sum() > 10:
            one = morison_fit(h[sel, 0], h[sel, 3])
            per_period.append({"period": p + 1, "C_d": one["C_d"], "C_i": one["C_i"],
                               "max_c": float(h[sel, 3].max()), "min_c": float(h[sel, 3].min())})
    cd = h[min(int(0.1 * steps_per_period), max(len(h) - 3, 0)):, 3]
    rng = max(float(cd.max() - cd.min()), 1e-300)
    return {"res": res, "grid": [n, n], "half_width": half_width, "dx": dx, "dt": dt, "steps": total,
            "steps_per_period": steps_per_period, "periods": periods, "record_from_period": record_from,
            "advection": advection, "pressure_at": pressure_at, "shear_at": shear_at, "integrator": integrator,
            "convection": convection,
            "cpu_seconds": wall.thread_time() - t0, "morison": fit,
            "cv_boxes": cv_boxes, "morison_cv": fit_cv,
            "morison_per_period": per_period,
            "smoothness": {"max_jump_over_range": float(np.abs(np.diff(cd)).max() / rng),
                           "max_second_difference_over_range": float(np.abs(np.diff(cd, 2)).max() / rng)},
            "history": h, "profiles": rows}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--res", type=int, default=20, help="cells per diameter")
    ap.add_argument("--periods", type=float, default=5.0)
    ap.add_argument("--half-width", type=float, default=8.0, help="the box is [-L, L]^2 in diameters")
    ap.add_argument("--cfl", type=float, default=0.4, help="U_max dt / dx")
    ap.add_argument("--record-from", type=float, default=2.0, help="fit over the periods after this many")
    ap.add_argument("--advection", default="maccormack", choices=["maccormack", "semi_lagrangian"])
    ap.add_argument("--out", default=None, help="prefix of the output files (CSV of forces and profiles, JSON)")
    ap.add_argument("--device", default="cpu", help="cpu, cuda or cuda:N")
    ap.add_argument("--progress", action="store_true")
    ap.add_argument("--pressure-at", default="cells", choices=["cells", "surface", "momentum"],
                    help="where the force reads the pressure (phisim.fluid.body_forces; default cells)")
    ap.add_argument("--shear-at", default="probes", choices=["probes", "momentum"],
                    help="how the force reads the wall shear (phisim.fluid.body_forces; default probes)")
    ap.add_argument("--integrator", default="split", help="time integrator of phisim.fluid.step (default split)")
    ap.add_argument("--convection", default="central", choices=["central", "quick"],
                    help="convection scheme of the rk2 / rk3 / imex2 integrators (default central)")
    args = ap.parse_args(argv)
    device = check_device(args.device)
    torch.set_num_threads(1)
    out = run(args.res, args.periods, args.half_width, args.cfl, min(args.record_from, max(args.periods - 1, 0)),
              args.advection, device, progress=args.progress, pressure_at=args.pressure_at, shear_at=args.shear_at,
              integrator=args.integrator, convection=args.convection)
    hist, rows = out.pop("history"), out.pop("profiles")
    if args.out:
        prefix = Path(args.out)
        prefix.parent.mkdir(parents=True, exist_ok=True)
        np.savetxt(f"{prefix}_forces.csv", hist, delimiter=",", fmt="%.8g",
                   header=",".join([*COLUMNS, *(f"c_inline_cv{j}" for j in range(len(out["cv_boxes"])))]))
        np.savetxt(f"{prefix}_profiles.csv", np.array(rows, dtype=float).reshape(-1, 5), delimiter=",", fmt="%.8g",
                   header="phase_deg,x,y,u,v")
        Path(f"{prefix}.json").write_text(json.dumps({**out, "device": str(device)}, indent=1))
    print(json.dumps({k: out[k] for k in ("res", "grid", "dt", "steps", "cpu_seconds", "morison", "morison_cv",
                                          "smoothness")}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
