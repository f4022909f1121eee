"""A sphere in a uniform stream at Re = 100: the steady, axisymmetric wake and the drag coefficient.

A resting no-slip sphere (diameter ``D = 1``, a sharp :class:`~phisim.fluid.Body`) at the origin of the box
``[-UP, DOWN] x [-W/2, W/2]^2`` (in units of ``D``), a uniform inflow ``U = 1`` on the side ``x = -UP``
(:class:`~phisim.boundary.Inflow`), an :class:`~phisim.boundary.Open` outflow at ``x = DOWN`` and free-slip lateral
sides, ``nu = U D / Re``. Free-slip sides are the mirror planes of a square array of spheres ``W`` apart: they let
the stream pass the sides without a boundary layer and keep the flux through the box fixed (no side inflow or
outflow that an open side with pressure 0 would allow), at the price of a blockage ``pi D^2 / (4 W^2)`` (3.1 % at
``W = 5``), which speeds the stream past the sphere up and raises the drag by a few per cent.

The flow starts uniform and is advanced by the split step (MacCormack advection, explicit viscosity, projection) of
:class:`~phisim.fluid.FluidStepper` until the drag coefficient ``C_D = 2 F_x / (U^2 pi D^2 / 4)`` (pressure and
viscous parts from :func:`phisim.fluid.body_forces`) changes by less than ``--steady-tol`` (relative) over one time
unit ``D / U``, or ``--t-end`` is reached. Also recorded: the cross-stream coefficients (zero by symmetry: the grid
and the sphere are mirror-symmetric about ``y = 0`` and ``z = 0``) and the length of the recirculation behind the
sphere, from the zero of the streamwise velocity on the axis, ``L / D`` measured from the rear of the sphere. At
the end the drag is read four more ways: the pressure part at the surface and through the normal momentum equation,
the wall shear with the momentum balance at the wall, and the whole drag from the momentum balance over a box round
the sphere (``cd_cv``, :func:`phisim.fluid.control_volume_force`, box ``CV_BOX``).

Reference values: the resolved axisymmetric computations of Johnson, T. A. & Patel, V. C. (1999), "Flow past a
sphere up to a Reynolds number of 300", J. Fluid Mech. 378, 19-70, are commonly quoted as ``C_D = 1.087`` and
``L / D = 0.88`` at Re = 100 (quoted, not checked against the paper here); the drag correlations of Schiller &
Naumann (1933), ``24 / Re (1 + 0.15 Re^0.687)`` = 1.091, and of Clift, Grace & Weber (1978, "Bubbles, Drops, and
Particles", Academic Press, table 5.2, 20 < Re <= 260), ``24 / Re (1 + 0.1935 Re^0.6305)`` = 1.087, fit
measurements of spheres in unbounded fluid.

``python examples/sphere_drag.py --n 8 12 16 --out data/validation/sphere_re100.json`` runs the grids ``D / dx = n``
one after the other, prints a JSON line per grid and writes the force histories to ``<out>.n<n>.csv`` (columns ``t,
cd, cy, cz, cd_pressure, recirculation``) and the summary, with the observed order of convergence and a Richardson
estimate where three grids were run, to ``<out>``.

``--quarter`` computes the quarter ``y >= 0, z >= 0`` of the box with free-slip planes at ``y = 0`` and ``z = 0``:
the flow is mirror-symmetric about both, and a free-slip plane on the MAC grid is exactly that mirror (the normal
velocity zero, the tangential ghosts and the pressure mirrored), so the quarter box computes the whole box's flow on a
quarter of the cells (the wide box's D/8 run reproduced to 1e-15; the forces of the quarter sphere times 4). It
assumes the symmetric steady wake of Re = 100; above Re of about 210 the wake of a sphere loses the symmetry, which a
quarter box cannot show.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import pickle
import sys
import time as _time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from phisim import CenteredGrid, Grid, Open, StaggeredGrid  # noqa: E402
from phisim.boundary import Inflow  # noqa: E402
from phisim.checks import check_device  # noqa: E402
from phisim.errors import FileFormatError, ParameterError  # noqa: E402
from phisim.fluid import Body, FluidState, FluidStepper, Sphere, body_forces, control_volume_force  # noqa: E402

D, U = 1.0, 1.0
UP, DOWN, W = 2.5, 6.0, 5.0  # box [-UP, DOWN] x [-W/2, W/2]^2 in units of D
AREA = math.pi * D**2 / 4
REFERENCE = {
    "cd_johnson_patel_1999": 1.087,  # as commonly quoted (not checked against the paper here)
    "recirculation_johnson_patel_1999": 0.88,  # L / D behind the sphere, as commonly quoted
    "cd_schiller_naumann": 24 / 100 * (1 + 0.15 * 100**0.687),
    "cd_clift_grace_weber": 24 / 100 * (1 + 0.1935 * 100**0.6305),
}


def setup(n: int, re: float = 100.0, dtype=torch.float64, device="cpu", width: float = W, up: float = UP,
          down: float = DOWN, quarter: bool = False):
    """Grid, boundary, sphere and initial (uniform) state with ``n`` cells per diameter. ``quarter``: the quarter
    ``y >= 0, z >= 0`` of the box only, its planes ``y = 0`` and ``z = 0`` free-slip (the mirror planes of the
    symmetric flow; the grid's faces lie on them, as in the whole box, whose cell count across is even)."""
    dx = D / n
    nx, ny = int(round((up + down) / dx)), int(round(width / dx))
    if quarter and ny % 2:
        ny += 1  # a face plane on y = 0 and z = 0
    half = ny * dx / 2
    if quarter:
        grid = Grid((nx, ny // 2, ny // 2), bounds=[(-up, -up + nx * dx), (0.0, half), (0.0, half)])
    else:
        grid = Grid((nx, ny, ny), bounds=[(-up, -up + nx * dx), (-half, half), (-half, half)])
    boundary = {"x": (Inflow((U, 0.0, 0.0)), Open()), "y": "slip", "z": "slip"}
    body = Body(Sphere((0.0, 0.0, 0.0), D / 2), name="sphere")
    v = StaggeredGrid.from_function(lambda x: torch.stack([torch.full_like(x[..., 0], U), 0 * x[..., 0],
                                                           0 * x[..., 0]], -1), grid, boundary, dtype=dtype,
                                    device=device)
    return grid, body, FluidState(v.with_boundary_faces()), U * D / re


def stokes_velocity(x: torch.Tensor) -> torch.Tensor:
    """Stokes flow past the resting sphere in the stream ``U`` (zero inside), ``(..., 3)``: ``u = U - (3 a / 4) (U / r
    + (U . x) x / r^3) - (a^3 / 4) (U / r^3 - 3 (U . x) x / r^5)`` with ``a = D / 2``; its viscous drag is
    ``4 pi mu a U`` (two thirds of Stokes' ``6 pi mu a U``)."""
    a = D / 2
    r = x.norm(dim=-1, keepdim=True).clamp_min(1e-9)
    u_inf = torch.zeros_like(x)
    u_inf[..., 0] = U
    ux = U * x[..., :1]
    u = u_inf - 0.75 * a * (u_inf / r + ux * x / r**3) - 0.25 * a**3 * (u_inf / r**3 - 3 * ux * x / r**5)
    return torch.where(r > a, u, torch.zeros_like(u))


def stokes_viscous_check(n: int, probe_distance: float = 1.5, nu: float = 0.01, device="cpu") -> float:
    """The viscous drag coefficient that :func:`phisim.fluid.body_forces` measures on the exact Stokes flow sampled
    onto the grid with ``n`` cells per diameter, relative to the exact ``C_D,v = 16 nu / (U D)``, minus 1: the error of
    the force measurement alone, on a profile without a thin boundary layer."""
    grid, body, state, _ = setup(n, dtype=torch.float64, device=device)
    v = StaggeredGrid.from_function(stokes_velocity, grid, state.velocity.boundary, dtype=torch.float64,
                                    device=state.velocity.device)
    p = CenteredGrid.zeros(grid, "open", dtype=torch.float64, device=v.device)
    f = body_forces(v, p, body, dt=1.0, viscosity=nu, probe_distance=probe_distance)
    return float(2 * f.viscous[0, 0] / (U**2 * AREA)) / (16 * nu / (U * D)) - 1


def recirculation_length(velocity: StaggeredGrid, samples: int = 2000) -> float:
    """Length ``L / D`` of the reversed flow on the axis behind the sphere (0 without reversed flow): from the rear
    point ``x = D / 2`` to the first zero of ``u_x`` (linear interpolation between the samples)."""
    x_end = float(velocity.grid.bounds[0][1]) - velocity.grid.dx[0]
    xs = torch.linspace(D / 2 + 1e-9, x_end, samples, dtype=velocity.dtype, device=velocity.device)
    pts = torch.stack([xs, torch.zeros_like(xs), torch.zeros_like(xs)], -1)
    ux = velocity.sample(pts)[0, 0].cpu().numpy()
    xs = xs.cpu().numpy()
    if ux[1] >= 0:  # the first sample sits on the surface (u = 0); no reversed flow just behind it
        return 0.0
    up = np.nonzero((ux[1:-1] < 0) & (ux[2:] >= 0))[0]
    if len(up) == 0:
        return float("nan")
    k = up[0] + 1
    x0 = xs[k] + (xs[k + 1] - xs[k]) * (-ux[k]) / (ux[k + 1] - ux[k])
    return float(x0 - D / 2) / D


def run(n: int, re: float = 100.0, t_end: float = 40.0, cfl: float = 0.5, steady_tol: float = 1e-4,
        dtype=torch.float64, device="cpu", every: int = 5, log=None, box=(UP, DOWN, W), integrator: str = "split",
        convection: str = "central", quarter: bool = False, save_state: str | None = None,
        init_from: str | None = None):
    """Advance the flow on the grid with ``n`` cells per diameter until the drag is steady (its relative change over
    one time unit below ``steady_tol``) or ``t_end``; returns the history ``(t, cd, cy, cz, cd_pressure, L/D)`` (every
    ``every`` steps) and a summary. ``integrator`` / ``convection``: the stepper's time integrator and convection
    scheme (``docs/SCHEMES.md``; ``'imex2'`` treats the viscosity implicitly, so its time step is the CFL one).
    ``quarter``: the quarter ``y, z >= 0`` of the box with free-slip mirror planes (:func:`setup`); the forces of its
    quarter sphere are multiplied by 4 (the cross-stream coefficients are zero by the symmetry and not computed).
    ``save_state``: a file for the velocity and pressure (``torch.save``), written every time unit (a checkpoint: a
    killed run continues from it with ``init_from``) and at the end, for readings made afterwards.
    ``init_from``: such a file, of the same box, from any grid: the run starts from its state at its time, resampled
    onto this grid (grid sequencing: a fine grid starts from a coarse grid's steady wake; ``t_end`` counts from 0 as
    before, so give the saved time plus the time to settle)."""
    device = check_device(device)
    up, down, width = box
    grid, body, state, nu = setup(n, re, dtype, device, width=width, up=up, down=down, quarter=quarter)
    if init_from:
        state = load_state(init_from, grid, state.velocity.boundary, re, box, quarter, dtype, device)
        if not t_end > state.time:
            raise ParameterError(f"t_end {t_end} must lie after the saved state's time {state.time}")
    t_start = state.time
    area = AREA / 4 if quarter else AREA  # the quarter sphere's forces against a quarter of the frontal area
    dx = grid.dx[0]
    dt = cfl * dx / U
    if integrator != "imex2":
        dt = min(dt, 0.45 * dx**2 / (6 * nu))  # explicit viscosity: nu dt sum(2 / dx^2) <= 0.9
    stepper = FluidStepper(grid, state.velocity.boundary, obstacles=body, viscosity=nu, dt=dt, dtype=dtype,
                           device=device, integrator=integrator,
                           **({} if convection == "central" else {"convection": convection}))
    hist = []
    per_unit = max(1, int(round(1.0 / dt)))
    steps = int(math.ceil((t_end - t_start) / dt))
    settle = 5.0 if init_from is None else 1.0  # no steadiness verdict before (a started wake changes slowly at first)
    t0, c0 = _time.perf_counter(), _time.thread_time()
    steady = False
    k = 0
    previous = None
    for k in range(1, steps + 1):
        previous = state.velocity
        state = stepper(state)
        if k % every and k % per_unit and k != steps:
            continue
        f = body_forces(state.velocity, state.pressure, body, dt=dt, viscosity=nu, time=state.time)
        c = f.coefficients(U, area)[0]
        cy, cz = (float("nan"), float("nan")) if quarter else (float(c[1]), float(c[2]))  # zero by the mirrors
        cp = 2 * f.pressure[0, 0] / (U**2 * area)
        hist.append((state.time, float(c[0]), cy, cz, float(cp), float("nan")))
        if k % per_unit == 0:
            hist[-1] = hist[-1][:5] + (recirculation_length(state.velocity),)
            if not all(math.isfinite(v) for v in (hist[-1][1], hist[-1][4]) + (() if quarter else (cy, cz))):
                break
            prev = [h for h in hist if h[0] <= state.time - 1.0 + 0.5 * dt]
            if save_state:  # a checkpoint every time unit: a killed run continues from it with init_from
                _save(save_state, n, box, quarter, dt, state)
            if log is not None:
                log(f"n={n} t={state.time:.2f} cd={hist[-1][1]:.5f} (pressure {hist[-1][4]:.5f}) L/D={hist[-1][5]:.3f} "
                    f"wall={_time.perf_counter() - t0:.0f}s")
            if prev and state.time >= t_start + settle:
                change = abs(hist[-1][1] - prev[-1][1]) / abs(hist[-1][1])
                if change < steady_tol:
                    steady = True
                    break
    h = np.array(hist)
    last = h[-1]
    # the viscous part's dependence on the distance of the wall-shear probes (body_forces: 1.5 and 3 cells)
    probes = {}
    for d in (1.0, 1.5, 2.0, 3.0):
        f = body_forces(state.velocity, state.pressure, body, dt=dt, viscosity=nu, time=state.time, probe_distance=d)
        probes[str(d)] = float(2 * f.viscous[0, 0] / (U**2 * area))
    # the pressure part read at the surface points (quadratic extrapolation along the normal) instead of the cut cells
    surf = body_forces(state.velocity, state.pressure, body, dt=dt, viscosity=nu, time=state.time,
                       pressure_at="surface")
    cd_p_surface = float(2 * surf.pressure[0, 0] / (U**2 * area))
    # the readings through the momentum balance at the wall (docs/VALIDATION.md, "The wall shear of thin boundary
    # layers"): the pressure part through the normal momentum equation, the viscous part with the profile's curvature
    mom = body_forces(state.velocity, state.pressure, body, dt=dt, viscosity=nu, time=state.time,
                      pressure_at="momentum", shear_at="momentum")
    cd_p_mom = float(2 * mom.pressure[0, 0] / (U**2 * area))
    cd_v_mom = float(2 * mom.viscous[0, 0] / (U**2 * area))
    # the drag from the momentum balance over a box round the sphere (reads nothing next to it)
    cd_cv = control_volume_drag(state, dt, nu, quarter, previous=previous)
    if save_state:
        _save(save_state, n, box, quarter, dt, state)
    ref = REFERENCE["cd_johnson_patel_1999"]
    prev = h[h[:, 0] <= last[0] - 1.0 + 0.5 * dt]
    return h, {"n": n, "dx": dx, "cells": list(grid.resolution), "dt": dt, "steps": k, "t": float(last[0]),
               "steady": steady, "cd": float(last[1]), "cd_pressure": float(last[4]),
               "cd_viscous": float(last[1] - last[4]),
               "cd_viscous_by_probe_distance": probes, "cd_pressure_surface": cd_p_surface,
               "cd_surface": cd_p_surface + float(last[1] - last[4]), "cd_pressure_momentum": cd_p_mom,
               "cd_viscous_momentum": cd_v_mom, "cd_momentum": cd_p_mom + cd_v_mom, "cd_cv": cd_cv,
               "cv_box": list(CV_BOX),
               "cy": None if quarter else float(last[2]), "cz": None if quarter else float(last[3]),
               "recirculation": float(last[5]), "cd_change_last_unit": float(abs(last[1] - prev[-1, 1]))
               if len(prev) else None, "cd_error_vs_1.087": float(last[1] / ref - 1),
               "wall_s": _time.perf_counter() - t0, "cpu_s": _time.thread_time() - c0, "device": str(device),
               "dtype": str(dtype).replace("torch.", ""), "cfl": cfl, "box": [-up, down, width],
               "blockage": AREA / width**2, "integrator": integrator, "convection": convection, "quarter": quarter,
               **({"init_from": str(init_from), "t_start": t_start} if init_from else {})}


def _save(path, n: int, box, quarter: bool, dt: float, state: FluidState) -> None:
    """Write the state for :func:`load_state` (``torch.save``), through a temporary file: a killed run leaves the
    previous complete file."""
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(path).with_name(Path(path).name + ".tmp")
    torch.save({"n": n, "box": [float(b) for b in box], "quarter": quarter, "dt": dt, "time": state.time,
                "velocity": [c.cpu() for c in state.velocity.values], "pressure": state.pressure.values.cpu()}, tmp)
    os.replace(tmp, path)


#: The control volume of ``cd_cv``: ``x`` from ``-a`` to ``b`` diameters, ``|y|, |z|`` up to ``c`` diameters.
CV_BOX = (1.0, 1.5, 1.0)


def control_volume_drag(state: FluidState, dt: float, nu: float, quarter: bool, box=CV_BOX,
                        previous: StaggeredGrid | None = None) -> float:
    """The drag coefficient from the momentum balance over a box round the sphere
    (:func:`~phisim.fluid.control_volume_force`; with ``previous``, the momentum change included). In the quarter
    box the box's lower sides lie on the mirror planes ``y = 0`` and ``z = 0`` (it reads their mirror images), so
    the box is a quarter of the whole box round the whole sphere: the drag against a quarter of the frontal area."""
    a, b, c = box
    lo = 0.0 if quarter else -c
    cv = control_volume_force(state.velocity, state.pressure, box=((-a, b), (lo, c), (lo, c)), dt=dt, viscosity=nu,
                              previous=previous)
    return float(cv.coefficients(U, AREA / 4 if quarter else AREA)[0, 0])


def load_state(path, grid, boundary, re: float, box, quarter: bool, dtype, device) -> FluidState:
    """A state saved by :func:`run` (``save_state``), resampled onto ``grid`` (multilinear; the first step's
    projection makes the velocity divergence-free there). Raises ``FileFormatError`` for a file that is not such a
    state and ``ParameterError`` for one of another box or symmetry."""
    try:
        saved = torch.load(path, map_location="cpu", weights_only=True)
        n, time, values, pressure = saved["n"], float(saved["time"]), saved["velocity"], saved["pressure"]
    except (OSError, RuntimeError, KeyError, TypeError, EOFError, pickle.UnpicklingError) as exc:
        raise FileFormatError(f"{path}: not a state saved by sphere_drag.py ({exc})") from exc
    if [float(b) for b in saved.get("box", [])] != [float(b) for b in box] or bool(saved.get("quarter")) != quarter:
        raise ParameterError(f"{path} holds the box {saved.get('box')} (quarter {saved.get('quarter')}), not "
                             f"{list(box)} (quarter {quarter})")
    up, down, width = box
    coarse = setup(int(n), re, dtype, device, width=width, up=up, down=down, quarter=quarter)[0]
    on = boundary.on_grid(coarse, dtype, device)
    return FluidState(StaggeredGrid(tuple(v.to(device, dtype) for v in values), coarse, on),
                      pressure=CenteredGrid(pressure.to(device, dtype), coarse, on.for_pressure()),
                      time=time).resampled(grid)


def convergence(ns, values) -> dict:
    """Observed order and Richardson estimate from the last three grids (``h = 1 / n``), or from two grids with an
    assumed order 2 (then only the estimate)."""
    out = {}
    if len(ns) >= 3:
        (n1, n2, n3), (f1, f2, f3) = ns[-3:], values[-3:]
        h1, h2, h3 = 1 / n1, 1 / n2, 1 / n3
        ratio = (f1 - f2) / (f2 - f3) if f2 != f3 else float("inf")

        def g(p):  # (h1^p - h2^p) / (h2^p - h3^p) - ratio
            return (h1**p - h2**p) / (h2**p - h3**p) - ratio

        if ratio > 0 and math.isfinite(ratio):
            lo, hi = 0.05, 8.0
            if g(lo) * g(hi) < 0:
                for _ in range(200):
                    mid = 0.5 * (lo + hi)
                    lo, hi = (mid, hi) if g(lo) * g(mid) > 0 else (lo, mid)
                p = 0.5 * (lo + hi)
                out["order"] = p
                out["richardson"] = f3 + (f3 - f2) * h3**p / (h2**p - h3**p)
        else:
            out["order"] = None  # not monotone
    if len(ns) >= 2:
        (n2, n3), (f2, f3) = ns[-2:], values[-2:]
        h2, h3 = 1 / n2, 1 / n3
        out["richardson_order2_last_two"] = f3 + (f3 - f2) * h3**2 / (h2**2 - h3**2)
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--n", type=int, nargs="+", default=[8], help="cells per diameter, one run each")
    ap.add_argument("--re", type=float, default=100.0)
    ap.add_argument("--t-end", type=float, default=40.0, help="stop here if the drag is not steady before")
    ap.add_argument("--steady-tol", type=float, default=1e-4, help="relative drag change over one time unit")
    ap.add_argument("--box", type=float, nargs=3, default=[UP, DOWN, W], metavar=("UP", "DOWN", "W"),
                    help="the box [-UP, DOWN] x [-W/2, W/2]^2 in diameters")
    ap.add_argument("--cfl", type=float, default=0.5)
    ap.add_argument("--dtype", default="float64", choices=["float32", "float64"])
    ap.add_argument("--every", type=int, default=5, help="record the forces every this many steps")
    ap.add_argument("--out", default=None, help="JSON file for the results (histories beside it as CSV)")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--quiet", action="store_true", help="no progress lines")
    ap.add_argument("--device", default="cpu", help="torch device: cpu, cuda or cuda:N (default cpu)")
    ap.add_argument("--integrator", default="split", help="time integrator of the FluidStepper (default split)")
    ap.add_argument("--convection", default="central", choices=["central", "quick"],
                    help="convection scheme of the rk2 / rk3 / imex2 integrators (default central)")
    ap.add_argument("--quarter", action="store_true",
                    help="the quarter y, z >= 0 of the box with free-slip mirror planes (a quarter of the cells)")
    ap.add_argument("--save-state", default=None,
                    help="save each grid's final velocity and pressure to this file (torch.save; {n} is the grid)")
    ap.add_argument("--init-from", default=None, metavar="FILE",
                    help="start from a state saved by --save-state (same box, any grid: resampled), at its time; "
                    "--t-end is then the saved time plus the time to run")
    args = ap.parse_args(argv)
    device = check_device(args.device)
    torch.set_num_threads(args.threads)
    dtype = getattr(torch, args.dtype)
    log = None if args.quiet else (lambda s: print(s, file=sys.stderr, flush=True))
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    runs = []
    for n in args.n:
        hist, res = run(n, args.re, args.t_end, args.cfl, args.steady_tol, dtype, device, args.every, log=log,
                         box=tuple(args.box), integrator=args.integrator, convection=args.convection,
                         quarter=args.quarter,
                         save_state=None if args.save_state is None else args.save_state.format(n=n),
                         init_from=args.init_from)
        if args.out:
            np.savetxt(Path(args.out).with_suffix(f".n{n}.csv"), hist, delimiter=",",
                       header="t,cd,cy,cz,cd_pressure,recirculation")
        print(json.dumps(res), flush=True)
        runs.append(res)
        if args.out:  # written after every grid, so a long study leaves its finished grids behind
            summary = {"re": args.re, "reference": REFERENCE, "runs": runs,
                       "cd_convergence": convergence([r["n"] for r in runs], [r["cd"] for r in runs]),
                       "recirculation_convergence": convergence([r["n"] for r in runs],
                                                                [r["recirculation"] for r in runs])}
            Path(args.out).write_text(json.dumps(summary, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
