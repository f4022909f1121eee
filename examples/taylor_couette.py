"""Circular Couette flow between a rotating inner and a resting outer cylinder: the order of the no-slip bodies.

The inner cylinder (radius ``R1``, a :class:`~phisim.fluid.Body` turning at ``omega``) and the outer one (radius
``R2``, the complement of a disc, an ``SDF`` body at rest) bound an annulus of fluid in a box with walls. The steady
Stokes flow is azimuthal, ``u_theta(r) = A r + B / r`` with ``A = -omega R1^2 / (R2^2 - R1^2)`` and
``B = omega R1^2 R2^2 / (R2^2 - R1^2)``, and the pressure is constant; the torque per unit length on the inner
cylinder is ``-4 pi mu B``. The steady state is reached by the Stokes steps of the flow solver (the solids
imposed, implicit viscosity, projection), without advection.

``python examples/taylor_couette.py --n 32 64 128 [--blended]`` prints, per grid, the velocity error on the fluid
faces within two cells of either surface (max and root mean square) and over all fluid faces, the torque error,
and the observed orders between successive grids. ``--free-slip`` makes the outer cylinder free-slip: the exact
Stokes flow is then the rigid rotation ``u_theta = omega r`` (no shear stress anywhere).

``--advection maccormack`` (or ``semi_lagrangian``) solves the Navier-Stokes equations instead: the same velocity is
their steady solution (the pressure balances the centripetal term, ``dp/dr = u_theta^2 / r``), reached by split
steps of a :class:`~phisim.fluid.FluidStepper` with that self-advection and explicit viscosity ``--nu`` (default
0.02, a Reynolds number ``omega R1 (R2 - R1) / nu = 8``). This checks the no-slip bodies where the transported
velocity meets them: ``--no-extension`` transports the stored field as it is (the bodies' velocity on the faces
inside them) instead of the fluid velocity extended into them (:func:`phisim.fluid.extension.extend_into_bodies`).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from phisim import Grid, StaggeredGrid  # noqa: E402
from phisim.checks import check_device  # noqa: E402
from phisim.fluid import (  # noqa: E402
    SDF,
    Body,
    FluidState,
    FluidStepper,
    Sphere,
    diffuse_velocity,
    impose_solids,
    make_incompressible,
    solid_layout,
)
from phisim.solvers import Solve  # noqa: E402

R1, R2, OMEGA, NU = 0.4, 0.8, 1.0, 1.0
CENTER = (0.0013, -0.0021)  # off the grid's symmetry lines: no lucky cancellations


def exact(x: torch.Tensor, free_slip: bool = False) -> torch.Tensor:
    """The azimuthal velocity ``(..., 2)`` at points ``x`` (a free-slip outer cylinder: rigid rotation)."""
    a = OMEGA if free_slip else -OMEGA * R1**2 / (R2**2 - R1**2)
    b = 0.0 if free_slip else OMEGA * R1**2 * R2**2 / (R2**2 - R1**2)
    r = x - torch.tensor(CENTER, dtype=x.dtype, device=x.device)
    rad = r.norm(dim=-1)
    ut = a * rad + b / rad
    return torch.stack([-r[..., 1] / rad * ut, r[..., 0] / rad * ut], -1)


def bodies(sharp: bool = True, free_slip: bool = False):
    c = torch.tensor(CENTER, dtype=torch.float64)
    inner = Body(Sphere(CENTER, R1), angular_velocity=OMEGA, sharp=sharp, name="inner")
    outer = Body(SDF(lambda x: R2 - (x - c.to(x.dtype)).norm(dim=-1), center=CENTER, bounds=((-1, -1), (1, 1))),
                 sharp=sharp, no_slip=not free_slip, name="outer")
    return [inner, outer]


def solve_steady(n: int, sharp: bool = True, tol: float = 1e-11, max_steps: int = 400, dt_cells: float = 50.0,
                 scheme: str = "implicit", free_slip: bool = False, device=None):
    """The steady Stokes flow on an ``n x n`` grid over ``[-1, 1]^2`` by Stokes steps of ``dt = dt_cells dx^2 / nu``
    with ``scheme`` viscosity, until the largest change of a step is below ``tol * omega R1``; returns
    ``(velocity, steps)``."""
    grid = Grid((n, n), bounds=[(-1.0, 1.0), (-1.0, 1.0)])
    solids = bodies(sharp, free_slip)
    v = StaggeredGrid.zeros(grid, "wall", dtype=torch.float64, device=device)
    layout = solid_layout(solids, grid, v.boundary, 0.0, torch.float64, v.device)
    dt = dt_cells * grid.dx[0] ** 2 / NU
    tight = Solve(rtol=1e-12)
    p = None
    for k in range(max_steps):
        w = impose_solids(v, layout)
        w = diffuse_velocity(w, dt, viscosity=NU, scheme=scheme, solids=layout, solve=tight)
        new, p = make_incompressible(w, layout, solve=tight, pressure_guess=p)
        change = max(float((a - b).abs().max()) for a, b in zip(new.values, v.values))
        v = new
        if change < tol * OMEGA * R1:
            return v, k + 1
    return v, max_steps


def solve_steady_ns(n: int, advection: str = "maccormack", nu: float = 0.02, tol: float = 1e-6,
                    max_steps: int = 20000, extension: bool = True, device=None, integrator: str = "split",
                    convection: str = "central"):
    """The steady Navier-Stokes flow on an ``n x n`` grid over ``[-1, 1]^2``: split steps (``advection``, explicit
    viscosity ``nu``, ``dt = min(0.4 dx / (omega R1), 0.45 dx^2 / (4 nu))``) from rest until the largest change of a
    step is below ``tol * dt / dx`` (in units of ``omega R1``); returns ``(velocity, steps)``. ``integrator`` other
    than ``'split'``: its steps (``convection`` its scheme); ``'imex2'`` (implicit viscosity) with
    ``dt = 0.4 dx / (omega R1)``."""
    import phisim.fluid.stepper as stepper_module

    grid = Grid((n, n), bounds=[(-1.0, 1.0), (-1.0, 1.0)])
    h = grid.dx[0]
    dt = 0.4 * h / (OMEGA * R1)
    if integrator != "imex2":
        dt = min(dt, 0.45 * h * h / (4 * nu))
    stepper = FluidStepper(grid, "wall", obstacles=bodies(True), viscosity=nu, advection=advection, dt=dt,
                           dtype=torch.float64, device=device, integrator=integrator, convection=convection)
    state = FluidState(StaggeredGrid.zeros(grid, stepper.boundary, dtype=torch.float64, device=device))
    original = stepper_module.extend_into_bodies
    if not extension:  # the study's comparison: the stored field transported as it is
        stepper_module.extend_into_bodies = lambda velocity, obstacles, time=0.0: velocity
    try:
        for k in range(max_steps):
            new = stepper(state)
            change = max(float((a - b).abs().max()) for a, b in zip(new.velocity.values, state.velocity.values))
            state = new
            if change < tol * OMEGA * R1 * dt / h:
                return state.velocity, k + 1
    finally:
        stepper_module.extend_into_bodies = original
    return state.velocity, max_steps


def errors(v: StaggeredGrid, free_slip: bool = False) -> dict:
    """Velocity errors on the fluid faces (near the surfaces: within two cells of either)."""
    grid = v.grid
    h = grid.dx[0]
    near_err, all_err = [], []
    for i in range(2):
        x = grid.face_centers(i, torch.float64, v.device)
        rad = (x - torch.tensor(CENTER, dtype=torch.float64, device=v.device)).norm(dim=-1)
        fluid = (rad > R1) & (rad < R2)
        err = (v.values[i][0] - exact(x, free_slip)[..., i]).abs()
        near = fluid & ((rad - R1 < 2 * h) | (R2 - rad < 2 * h))
        near_err.append(err[near])
        all_err.append(err[fluid])
    near_err, all_err = torch.cat(near_err), torch.cat(all_err)
    scale = OMEGA * R1
    return {"near_max": float(near_err.max()) / scale, "near_rms": float(near_err.pow(2).mean().sqrt()) / scale,
            "all_max": float(all_err.max()) / scale, "all_rms": float(all_err.pow(2).mean().sqrt()) / scale}


def torque_error(v: StaggeredGrid) -> float:
    """Relative error of the viscous torque on the inner cylinder from the one-sided wall shear (probes at 1.5 and
    3 cells from the surface, as :func:`phisim.fluid.body_forces`)."""
    h = v.grid.dx[0]
    m = 256
    ang = torch.arange(m, dtype=torch.float64, device=v.device) * (2 * math.pi / m)
    nrm = torch.stack([ang.cos(), ang.sin()], -1)
    c = torch.tensor(CENTER, dtype=torch.float64, device=v.device)
    d1 = 1.5 * h
    pts = torch.cat([c + (R1 + d1) * nrm, c + (R1 + 2 * d1) * nrm])
    u = v.sample(pts)[0]  # (2, 2m)
    tang = torch.stack([-nrm[:, 1], nrm[:, 0]], -1)
    ut = (u.T[:m] * tang).sum(-1), (u.T[m:] * tang).sum(-1)
    w1, w2 = ut[0] - OMEGA * R1, ut[1] - OMEGA * R1
    dudn = (4 * w1 - w2) / (2 * d1)  # d(u_theta - u_wall)/dr at the surface
    tau = NU * (dudn - OMEGA)  # r d(u/r)/dr = du/dr - u/r
    torque = float(tau.mean()) * 2 * math.pi * R1 * R1
    b = OMEGA * R1**2 * R2**2 / (R2**2 - R1**2)
    ref = -4 * math.pi * NU * b
    return abs(torque - ref) / abs(ref)


def study(ns, sharp: bool = True, advection: str | None = None, **kw) -> list[dict]:
    """:func:`solve_steady` (or, with ``advection``, :func:`solve_steady_ns`) on each grid, its errors and the
    observed orders between successive grids."""
    rows = []
    for n in ns:
        v, steps = solve_steady(n, sharp, **kw) if advection is None else solve_steady_ns(n, advection, **kw)
        free_slip = kw.get("free_slip", False)
        row = {"n": n, "cells_across_gap": (R2 - R1) * n / 2, "steps": steps, **errors(v, free_slip)}
        if not free_slip:  # the rigid rotation of a free-slip outer cylinder exerts no torque
            row["torque"] = torque_error(v)
        rows.append(row)
    for a, b in zip(rows, rows[1:]):
        f = math.log(b["n"] / a["n"])
        b["order"] = {k: math.log(a[k] / b[k]) / f for k in ("near_max", "near_rms", "all_max", "all_rms", "torque")
                      if k in b}
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--n", type=int, nargs="+", default=[32, 64, 128])
    ap.add_argument("--blended", action="store_true", help="the blended (first-order) no-slip condition")
    ap.add_argument("--scheme", default="implicit", help="viscosity scheme of the Stokes steps")
    ap.add_argument("--dt-cells", type=float, default=50.0, help="time step in units of dx^2 / nu")
    ap.add_argument("--tol", type=float, default=1e-11, help="steady when a step changes the velocity less")
    ap.add_argument("--max-steps", type=int, default=400)
    ap.add_argument("--free-slip", action="store_true",
                    help="a free-slip outer cylinder (Stokes steps; the exact flow is a rigid rotation)")
    ap.add_argument("--advection", default=None, choices=["maccormack", "semi_lagrangian"],
                    help="solve the Navier-Stokes equations with this self-advection (default: Stokes steps)")
    ap.add_argument("--nu", type=float, default=0.02, help="viscosity of the Navier-Stokes runs")
    ap.add_argument("--no-extension", action="store_true",
                    help="Navier-Stokes runs: transport the stored field, not the velocity extended into the bodies")
    ap.add_argument("--integrator", default="split", help="Navier-Stokes runs: the time integrator")
    ap.add_argument("--convection", default="central", choices=["central", "quick"],
                    help="Navier-Stokes runs with --integrator rk2 / rk3 / imex2: the convection scheme")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--device", default="cpu", help="cpu, cuda or cuda:N")
    args = ap.parse_args(argv)
    device = check_device(args.device)
    torch.set_num_threads(args.threads)
    if args.advection is None:
        kw = dict(sharp=not args.blended, scheme=args.scheme, dt_cells=args.dt_cells, tol=args.tol,
                  max_steps=args.max_steps, free_slip=args.free_slip)
    else:
        kw = dict(advection=args.advection, nu=args.nu, extension=not args.no_extension, integrator=args.integrator,
                  convection=args.convection)
    for row in study(args.n, device=device, **kw):
        print(json.dumps({**row, "device": str(device)}), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
