"""Flow past a circular cylinder in a channel: the DFG benchmark of Schäfer & Turek (1996).

Schäfer, M. & Turek, S. (1996), "Benchmark computations of laminar flow around a cylinder", in: Flow
Simulation with High-Performance Computers II, Notes on Numerical Fluid Mechanics 52, Vieweg, 547-566.

Channel ``[0, 2.2] x [0, 0.41]``, cylinder of diameter ``D = 0.1`` centred at ``(0.2, 0.2)``, kinematic
viscosity ``1e-3``, density 1; parabolic inflow ``U(y) = 4 U_m y (H - y) / H^2`` on the left, no-slip walls
above and below, an outflow on the right. ``Re = U_mean D / nu`` with ``U_mean = 2 U_m / 3``.

* case ``'2D-1'`` (steady, ``U_m = 0.3``, Re = 20): drag and lift coefficients and the pressure difference
  between the front and back points ``(0.15, 0.2)`` and ``(0.25, 0.2)``;
* case ``'2D-2'`` (periodic, ``U_m = 1.5``, Re = 100): maximum drag and lift coefficients and the Strouhal
  number ``St = D f / U_mean``; with each maximum its change over the last period (``cl_max_growth``) and the value
  the per-period maxima tend to (``cl_max_limit``): on fine grids the shedding takes longer than the default
  ``--t-end 8`` to settle.

Run ``python examples/cylinder_benchmark.py 2D-1 --ny 41 82`` (or ``2D-2``; ``--device cuda`` runs on a GPU);
results are printed as JSON, with the device they ran on.
"""

from __future__ import annotations

import argparse
import json
import math
import os
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
from phisim.fluid import (  # noqa: E402
    Body,
    FluidState,
    FluidStepper,
    Sphere,
    body_forces,
    control_volume_force,
    probe_pressure,
    wall_pressure,
)

H, L, D, CENTER, NU = 0.41, 2.2, 0.1, (0.2, 0.2), 1e-3
#: The control volume of the ``*_cv`` readings: 1.5 diameters from the cylinder's centre on each side.
CV_BOX = ((CENTER[0] - 1.5 * D, CENTER[0] + 1.5 * D), (CENTER[1] - 1.5 * D, CENTER[1] + 1.5 * D))
#: Reference values (Schäfer & Turek 1996, Table 3/4; the refined 2D-1 values of John & Matthies 2001).
REFERENCE = {
    "2D-1": {"cd": 5.57953523384, "cl": 0.010618948146, "dp": 0.11752016697,
             "ranges": {"cd": (5.57, 5.59), "cl": (0.0104, 0.0110), "dp": (0.1172, 0.1176)}},
    "2D-2": {"cd_max": 3.23, "cl_max": 1.00, "st": 0.300,
             "ranges": {"cd_max": (3.22, 3.24), "cl_max": (0.99, 1.01), "st": (0.295, 0.305)}},
}


def setup(case: str, ny: int, dtype=torch.float64, device="cpu"):
    """Grid, boundary, body and initial state (on ``device``) of a case with ``ny`` cells across the channel."""
    um = 0.3 if case == "2D-1" else 1.5
    dx = H / ny
    nx = int(round(L / dx))
    grid = Grid((nx, ny), bounds=[(0.0, nx * dx), (0.0, H)])

    def profile(x):
        y = x[..., 1]
        return torch.stack([4 * um * y * (H - y) / H**2, torch.zeros_like(y)], -1)

    boundary = {"x": (Inflow(profile), Open()), "y": "wall"}
    body = Body(Sphere(CENTER, D / 2), name="cylinder")
    v = StaggeredGrid.from_function(profile, grid, boundary, dtype=dtype, device=device)
    return grid, body, FluidState(v), um


def run(case: str, ny: int, t_end: float, cfl: float = 0.5, advection: str = "maccormack",
        record_from: float = 0.0, dtype=torch.float64, viscosity_scheme: str = "explicit", dt: float | None = None,
        integrator: str = "split", device="cpu", convection: str = "central", init: dict | None = None):
    """Simulate a case on ``device``; returns the force history, the final state and the run's settings.

    ``init`` (from :func:`load_state`) starts the run from a saved state at its time instead of the inflow profile
    at ``t = 0``, resampled onto this grid when it was saved on another (grid sequencing: a fine grid starts from a
    coarse grid's developed shedding and needs a shorter run to settle).

    The history's columns: ``t, cd, cl, dp, cd_pressure, cl_pressure`` with the pressure of the cut cells
    (:func:`~phisim.fluid.body_forces`, ``pressure_at='cells'``) and ``dp`` from the linear extrapolation to the front
    and back points; then ``cd_surface, cl_surface, dp_quadratic``: the pressure read at the surface
    (``pressure_at='surface'``) and ``dp`` from the quadratic extrapolation (``probe_pressure(..., order=2)``); then
    ``cd_momentum, cl_momentum, dp_momentum``: the pressure read through the momentum equation along the normal
    (``pressure_at='momentum'``, :func:`~phisim.fluid.wall_pressure`, with the previous step's velocity); then
    ``cd_cv, cl_cv``: the force from the momentum balance over the box ``CV_BOX`` around the cylinder
    (:func:`~phisim.fluid.control_volume_force`, at the half step), which reads nothing next to it."""
    device = check_device(device)
    grid, body, state, um = setup(case, ny, dtype, device)
    t0 = 0.0
    if init is not None:
        state = initial_state(init, case, grid, state.velocity.boundary, dtype, device)
        t0 = state.time
        if not t_end > t0:
            raise ParameterError(f"--t-end {t_end} must lie after the saved state's time {t0}")
    umean = 2 * um / 3
    dx = grid.dx[0]
    if dt is None:
        dt = cfl * dx / (1.5 * um)
        if viscosity_scheme == "explicit":
            dt = min(dt, 0.45 * dx**2 / (4 * NU))
    n = int(math.ceil((t_end - t0) / dt))
    dt = (t_end - t0) / n
    # a stepper holds the resting cylinder's layout and its direct pressure solve (the pure step() rasterises the
    # body and solves by PCG at every call; the two agree to the solver's tolerance)
    stepper = FluidStepper(grid, state.velocity.boundary, obstacles=body, viscosity=NU, advection=advection,
                           viscosity_scheme=viscosity_scheme, integrator=integrator, dtype=dtype, device=device, dt=dt,
                           convection=convection)
    hist = []
    clock = _time.perf_counter()
    front_back = torch.tensor([[0.15, 0.2], [0.25, 0.2]], dtype=dtype, device=device)
    for _ in range(n):
        previous = state.velocity
        state = stepper(state)
        if state.time >= record_from - 1e-12:
            f = body_forces(state.velocity, state.pressure, body, dt=dt, viscosity=NU, time=state.time)
            c = f.coefficients(umean, D)[0]
            pfb = probe_pressure(state.pressure, front_back, dt=dt, bodies=body)[0]
            cp = 2 * f.pressure[0] / (umean**2 * D)
            fs = body_forces(state.velocity, state.pressure, body, dt=dt, viscosity=0.0, time=state.time,
                             pressure_at="surface")  # its pressure part; the viscous part is f's
            cs = 2 * (fs.pressure[0] + f.viscous[0]) / (umean**2 * D)
            pq = probe_pressure(state.pressure, front_back, dt=dt, bodies=body, order=2)[0]
            fm = body_forces(state.velocity, state.pressure, body, dt=dt, viscosity=NU, time=state.time,
                             pressure_at="momentum", previous_velocity=previous)
            cm = fm.coefficients(umean, D)[0]
            pm = wall_pressure(state.velocity, state.pressure, body, front_back, dt=dt, viscosity=NU, time=state.time,
                               previous_velocity=previous)[0]
            fc = control_volume_force(state.velocity, state.pressure, box=CV_BOX, dt=dt, viscosity=NU,
                                      previous=previous)  # stands at the half step
            cc = fc.coefficients(umean, D)[0]
            hist.append((state.time, float(c[0]), float(c[1]), float(pfb[0] - pfb[1]), float(cp[0]), float(cp[1]),
                         float(cs[0]), float(cs[1]), float(pq[0] - pq[1]), float(cm[0]), float(cm[1]),
                         float(pm[0] - pm[1]), float(cc[0]), float(cc[1])))
    if device.type == "cuda":
        torch.cuda.synchronize(device)
    wall = _time.perf_counter() - clock
    return np.array(hist), state, {"steps": n, "dt": dt, "wall_s": wall, "nx": grid.resolution[0], "ny": ny,
                                   **({"t_start": t0} if init is not None else {}),
                                   "integrator": integrator, "device": str(device),
                                   **({"convection": convection} if convection != "central" else {})}


def save_state(path, case: str, state: FluidState, meta: dict) -> None:
    """Write a run's final state (velocity, pressure, time, grid) to ``path`` (``.npz``), atomically: a killed
    run leaves the previous file or none, never a partial one."""
    path = Path(path)
    grid = state.velocity.grid
    arrays = {f"velocity_{i}": c.detach().cpu().numpy() for i, c in enumerate(state.velocity.values)}
    if state.pressure is not None:
        arrays["pressure"] = state.pressure.values.detach().cpu().numpy()
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "wb") as fh:
        np.savez(fh, case=case, time=state.time, resolution=np.array(grid.resolution),
                 bounds=np.array(grid.bounds), settings=json.dumps(meta), **arrays)
    os.replace(tmp, path)


def load_state(path) -> dict:
    """A state written by :func:`save_state`, as plain arrays; raises ``FileFormatError`` for a file that is not
    one."""
    try:
        with np.load(path, allow_pickle=False) as f:
            out = {k: f[k] for k in f.files}
    except (OSError, ValueError, EOFError) as exc:
        raise FileFormatError(f"{path}: not a readable state file ({exc})") from exc
    need = {"case", "time", "resolution", "bounds", "velocity_0", "velocity_1"}
    if not need <= set(out):
        raise FileFormatError(f"{path}: not a state file of this script (missing {sorted(need - set(out))})")
    return out


def initial_state(init: dict, case: str, grid: Grid, boundary, dtype, device) -> FluidState:
    """The saved state ``init`` on ``grid`` (resampled multilinearly where it was saved on another resolution; the
    first step's projection makes the velocity divergence-free on the new grid)."""
    if str(init["case"]) != case:
        raise ParameterError(f"the saved state is of case {init['case']}, not {case}")
    saved = Grid(tuple(int(n) for n in init["resolution"]), bounds=[tuple(b) for b in init["bounds"].tolist()])
    on_saved = boundary.on_grid(saved, dtype, device)
    values = tuple(torch.as_tensor(init[f"velocity_{i}"], dtype=dtype, device=device) for i in range(2))
    pressure = None
    if "pressure" in init:
        pressure = CenteredGrid(torch.as_tensor(init["pressure"], dtype=dtype, device=device), saved,
                                on_saved.for_pressure())
    return FluidState(StaggeredGrid(values, saved, on_saved), pressure=pressure,
                      time=float(init["time"])).resampled(grid)


def summarize(case: str, hist: np.ndarray) -> dict:
    """Benchmark quantities from a force history (the columns of :func:`run`; the ``*_surface`` / ``dp_quadratic``
    entries where the history has them)."""
    surface = hist.shape[1] > 6
    if case == "2D-1":
        t, cd, cl, dp = hist[-1, :4]
        out = {"cd": float(cd), "cl": float(cl), "dp": float(dp), "cd_pressure": float(hist[-1, 4]),
               "drift_cd_last_unit": float(abs(hist[-1, 1] - hist[0, 1]))}
        if surface:
            out.update({"cd_surface": float(hist[-1, 6]), "cl_surface": float(hist[-1, 7]),
                        "dp_quadratic": float(hist[-1, 8])})
        if hist.shape[1] > 9:
            out.update({"cd_momentum": float(hist[-1, 9]), "cl_momentum": float(hist[-1, 10]),
                        "dp_momentum": float(hist[-1, 11])})
        if hist.shape[1] > 12:
            out.update({"cd_cv": float(hist[-1, 12]), "cl_cv": float(hist[-1, 13])})
        return out
    out = _periodic(hist[:, 0], hist[:, 1], hist[:, 2])
    if surface:
        out.update({f"{k}_surface": v for k, v in _periodic(hist[:, 0], hist[:, 6], hist[:, 7]).items()
                    if k in ("cd_max", "cl_max")})
    if hist.shape[1] > 9:
        out.update({f"{k}_momentum": v for k, v in _periodic(hist[:, 0], hist[:, 9], hist[:, 10]).items()
                    if k in ("cd_max", "cl_max")})
    if hist.shape[1] > 12:
        out.update({f"{k}_cv": v for k, v in _periodic(hist[:, 0], hist[:, 12], hist[:, 13]).items()
                    if k in ("cd_max", "cl_max", "cd_max_limit", "cl_max_limit")})
    return out


def _periodic(t: np.ndarray, cd: np.ndarray, cl: np.ndarray) -> dict:
    """Maximum drag and lift and the Strouhal number of a periodic force history, and how far the oscillation is
    from its periodic state: ``*_growth`` the change of the per-period maximum over the last period, ``*_limit``
    its limit where the last maxima still grow geometrically (:func:`saturated_maximum`)."""
    # Strouhal number from the zero up-crossings of the lift
    s = np.sign(cl - cl.mean())
    up = np.nonzero((s[:-1] < 0) & (s[1:] >= 0))[0]
    tc = [t[i] + (t[i + 1] - t[i]) * (-(cl[i] - cl.mean())) / (cl[i + 1] - cl[i]) for i in up]
    period = float(np.mean(np.diff(tc))) if len(tc) >= 2 else float("nan")
    out = {"cd_max": float(cd.max()), "cl_max": float(cl.max()), "st": D / period / 1.0 if period == period else None,
           "periods": len(tc) - 1}
    for name, y in (("cd_max", cd), ("cl_max", cl)):
        maxima = [float(y[sel].max()) for a, b in zip(tc[:-1], tc[1:]) if (sel := (t >= a) & (t < b)).any()]
        if len(maxima) >= 2:
            out[f"{name}_growth"] = maxima[-1] - maxima[-2]
            out[f"{name}_limit"] = saturated_maximum(maxima)
    return out


def saturated_maximum(maxima) -> float | None:
    """The limit of per-period maxima that approach it geometrically, ``m_k = m - c r^k`` (the amplitude of vortex
    shedding saturating): from the last three, ``m_3 + d_3 r / (1 - r)`` with ``d_k = m_k - m_(k-1)`` and
    ``r = d_3 / d_2``. The last maximum where they have stopped changing (``|d_3| <= 1e-4 |m_3|``); None where the
    last three do not change geometrically (``r`` outside ``(0, 0.9)``)."""
    if len(maxima) < 3:
        return None
    m1, m2, m3 = (float(m) for m in maxima[-3:])
    d2, d3 = m2 - m1, m3 - m2
    if abs(d3) <= 1e-4 * abs(m3):
        return m3
    r = d3 / d2 if d2 != 0 else float("nan")
    if not 0 < r < 0.9:
        return None
    return m3 + d3 * r / (1 - r)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("case", choices=["2D-1", "2D-2"])
    ap.add_argument("--ny", type=int, nargs="+", default=[41])
    ap.add_argument("--t-end", type=float, default=None)
    ap.add_argument("--record-from", type=float, default=None)
    ap.add_argument("--out", default=None, help="JSON file for the results")
    ap.add_argument("--threads", type=int, default=1, help="torch threads (1 is fastest on small grids)")
    ap.add_argument("--integrator", default="split", help="time integrator of phisim.fluid.step")
    ap.add_argument("--convection", default="central", choices=["central", "quick"],
                    help="convection scheme of the rk2 / rk3 / imex2 integrators (default central)")
    ap.add_argument("--device", default="cpu", help="torch device: cpu, cuda or cuda:N (default cpu)")
    ap.add_argument("--cfl", type=float, default=0.5,
                    help="1.5 U_m dt / dx (default 0.5; explicit viscosity may lower dt)")
    ap.add_argument("--dt", type=float, default=None, help="time step (instead of --cfl; rounded to divide --t-end)")
    ap.add_argument("--save-state", default=None, metavar="FILE",
                    help="write the final state to FILE (.npz; with several --ny, FILE gets .nyN before its suffix)")
    ap.add_argument("--init-from", default=None, metavar="FILE",
                    help="start from a state written by --save-state (any resolution: it is resampled), at its time")
    args = ap.parse_args(argv)
    device = check_device(args.device)
    torch.set_num_threads(args.threads)
    t_end = args.t_end or (6.0 if args.case == "2D-1" else 8.0)
    rec = args.record_from if args.record_from is not None else (t_end - 1.0 if args.case == "2D-1" else t_end - 4.0)
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    init = load_state(args.init_from) if args.init_from else None
    results = []
    for ny in args.ny:
        hist, state, meta = run(args.case, ny, t_end, cfl=args.cfl, dt=args.dt, record_from=rec,
                                integrator=args.integrator, device=device, convection=args.convection, init=init)
        if init is not None:
            meta["init_from"] = str(args.init_from)
        if args.save_state:
            target = Path(args.save_state)
            if len(args.ny) > 1:
                target = target.with_name(f"{target.stem}.ny{ny}{target.suffix}")
            save_state(target, args.case, state, meta)
        if args.out:
            np.savetxt(Path(args.out).with_suffix(f".ny{ny}.csv"), hist, delimiter=",",
                       header="t,cd,cl,dp,cd_pressure,cl_pressure,cd_surface,cl_surface,dp_quadratic,"
                       "cd_momentum,cl_momentum,dp_momentum,cd_cv,cl_cv")
        tail = hist[hist[:, 0] >= t_end - (1.0 if args.case == "2D-1" else 2.0)]
        res = {**meta, **summarize(args.case, tail)}
        growth = res.get("cl_max_growth")
        if growth is not None and abs(growth) > 1e-3 * abs(res["cl_max"]):
            print(f"ny {ny}: the lift maximum still changes by {growth:+.2e} per period (not yet periodic); "
                  f"cl_max_limit {res.get('cl_max_limit')} is where it tends to, or run longer (--t-end)",
                  file=sys.stderr, flush=True)
        print(json.dumps(res), flush=True)
        results.append(res)
    if args.out:
        Path(args.out).write_text(json.dumps({"case": args.case, "reference": REFERENCE[args.case], "runs": results},
                                             indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
