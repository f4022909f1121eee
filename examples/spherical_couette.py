"""Spherical Couette flow between a rotating inner and a resting outer sphere: the order of the no-slip bodies in 3-D.

The inner sphere (radius ``R1``, a :class:`~phisim.fluid.Body` turning at the angular velocity ``omega = Omega e``
about a tilted axis ``e``) and the outer one (radius ``R2``, the complement of a ball, an ``SDF`` body at rest) bound
a spherical shell of fluid in a box with walls. The steady Stokes flow is azimuthal about the axis,

    ``u = (A + B / r^3) omega x (x - c)``, i.e. ``u_phi = (A r + B / r^2) sin(theta)``,

with ``A = -R1^3 / (R2^3 - R1^3)`` and ``B = R1^3 R2^3 / (R2^3 - R1^3)`` (``theta`` measured from the axis): the
Stokes operator on ``f(r) sin(theta) e_phi`` is ``f'' + 2 f' / r - 2 f / r^2``, whose solutions are ``r`` and
``r^-2``; ``A R1 + B / R1^2 = R1`` and ``A R2 + B / R2^2 = 0`` fit the walls. The pressure is constant. The shear
stress on the inner sphere is ``tau_r_phi = mu r d(u_phi / r)/dr = -3 mu Omega B sin(theta) / R1^3``, and the torque
of the fluid on it is ``-8 pi mu Omega B`` about ``e``. The steady state is reached by the Stokes steps of the flow
solver (the solids imposed, implicit viscosity, projection), without advection, as in
``examples/taylor_couette.py`` (the 2-D analogue).

``python examples/spherical_couette.py --n 16 24 32`` prints, per grid, the velocity error on the fluid faces within
two cells of either surface (max and root mean square) and over all fluid faces, the torque error (``torque``: against
the exact torque; ``torque_flow``: against the same probes applied to the exact velocity, which removes the error of
the one-sided difference itself, ``torque_probe_of_exact``; ``torque_mid``: the torque transmitted through the sphere
halfway between the walls, by central differences, which equals the torque on the inner sphere in this flow;
``torque_mid_flow``: the same against the exact velocity through the same differences), and the observed orders between
successive grids (``--out FILE`` writes them as JSON).

``--free-slip`` makes the outer sphere free-slip: the exact Stokes flow is then the rigid rotation ``u = omega x (x -
c)`` (no stress anywhere, so no torque), and the errors measure the free-slip condition on a curved surface in 3-D.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from phisim import Grid, StaggeredGrid  # noqa: E402
from phisim.checks import check_device  # noqa: E402
from phisim.fluid import SDF, Body, Sphere, diffuse_velocity, impose_solids, make_incompressible, solid_layout  # noqa: E402
from phisim.solvers import Solve  # noqa: E402

R1, R2, OMEGA, NU = 0.4, 0.8, 1.0, 1.0
HALF = 0.9  # the box [-HALF, HALF]^3: the outer sphere with a margin of half a cell or more on the grids used
AXIS = (1.0 / 3.0, 2.0 / 3.0, 2.0 / 3.0)  # a tilted axis of rotation (unit vector)
CENTER = (0.0013, -0.0021, 0.0017)  # off the grid's symmetry planes: no lucky cancellations
KEYS = ("near_max", "near_rms", "all_max", "all_rms", "torque", "torque_flow", "torque_mid", "torque_mid_flow")


def coefficients(free_slip: bool = False) -> tuple[float, float]:
    """``(A, B)`` of ``u_phi = Omega (A r + B / r^2) sin(theta)`` (a free-slip outer sphere: ``(1, 0)``)."""
    if free_slip:
        return 1.0, 0.0
    d = R2**3 - R1**3
    return -(R1**3) / d, R1**3 * R2**3 / d


def exact(x: torch.Tensor, free_slip: bool = False) -> torch.Tensor:
    """The exact velocity ``(..., 3)`` at points ``x``."""
    a, b = coefficients(free_slip)
    r = x - torch.tensor(CENTER, dtype=x.dtype, device=x.device)
    rad = r.norm(dim=-1, keepdim=True)
    w = OMEGA * torch.tensor(AXIS, dtype=x.dtype, device=x.device).expand(r.shape)
    return (a + b / rad**3) * torch.linalg.cross(w, r, dim=-1)


def bodies(sharp: bool = True, free_slip: bool = False):
    """The inner (turning) and outer (resting, the complement of a ball; no-slip or free-slip) spheres."""
    c = torch.tensor(CENTER, dtype=torch.float64)
    inner = Body(Sphere(CENTER, R1), angular_velocity=tuple(OMEGA * e for e in AXIS), sharp=sharp, name="inner")
    outer = Body(SDF(lambda x: R2 - (x - c.to(x.dtype)).norm(dim=-1), center=CENTER,
                     bounds=((-HALF,) * 3, (HALF,) * 3)), sharp=sharp, no_slip=not free_slip, name="outer")
    return [inner, outer]


def solve_steady(n: int, sharp: bool = True, tol: float = 1e-9, max_steps: int = 200, dt_cells: float = 50.0,
                 scheme: str = "implicit", rtol: float = 1e-10, device=None, free_slip: bool = False,
                 start_exact: bool = False):
    """The steady Stokes flow on an ``n^3`` grid over ``[-HALF, HALF]^3`` by Stokes steps of ``dt = dt_cells dx^2 /
    nu`` with ``scheme`` viscosity, until the largest change of a step is below ``tol * Omega R1``; returns
    ``(velocity, steps)``. From rest, or with ``start_exact`` from the exact flow sampled on the faces (the same
    discrete steady state, the fixed point of the linear step, reached in fewer steps: the free-slip flow spins up
    the whole ball, a slow mode from rest)."""
    grid = Grid((n, n, n), bounds=[(-HALF, HALF)] * 3)
    v = StaggeredGrid.zeros(grid, "wall", dtype=torch.float64, device=device)
    if start_exact:
        v = StaggeredGrid.from_function(lambda x: exact(x, free_slip), grid, "wall", dtype=torch.float64,
                                        device=device)
    layout = solid_layout(bodies(sharp, free_slip), grid, v.boundary, 0.0, torch.float64, v.device)
    dt = dt_cells * grid.dx[0] ** 2 / NU
    tight = Solve(rtol=rtol)
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


def errors(v: StaggeredGrid, free_slip: bool = False) -> dict:
    """Velocity errors on the fluid faces relative to the wall speed ``Omega R1`` (near the surfaces: within two
    cells of either)."""
    grid = v.grid
    h = grid.dx[0]
    c = torch.tensor(CENTER, dtype=torch.float64, device=v.device)
    near_err, all_err = [], []
    for i in range(3):
        x = grid.face_centers(i, torch.float64, v.device)
        rad = (x - c).norm(dim=-1)
        fluid = (rad > R1) & (rad < R2)
        err = (v.values[i][0] - exact(x, free_slip)[..., i]).abs()
        near = fluid & ((rad - R1 < 2 * h) | (R2 - rad < 2 * h))
        near_err.append(err[near])
        all_err.append(err[fluid])
    near_err, all_err = torch.cat(near_err), torch.cat(all_err)
    scale = OMEGA * R1
    return {"near_max": float(near_err.max()) / scale, "near_rms": float(near_err.pow(2).mean().sqrt()) / scale,
            "all_max": float(all_err.max()) / scale, "all_rms": float(all_err.pow(2).mean().sqrt()) / scale}


def _sphere_quadrature(m: int, device):
    """Unit normals ``(P, 3)``, ``e_phi sin(theta)`` about the axis ``(P, 3)`` and weights ``d(cos theta) d(phi)``
    ``(P,)`` of a product rule on the unit sphere: Gauss-Legendre in ``cos(theta)`` (``m`` nodes), trapezoidal in
    ``phi`` (``2 m`` nodes)."""
    import numpy as np

    f64 = torch.float64
    e = torch.tensor(AXIS, dtype=f64, device=device)
    e1 = torch.linalg.cross(e, torch.tensor([1.0, 0.0, 0.0], dtype=f64, device=device))
    e1 = e1 / e1.norm()
    e2 = torch.linalg.cross(e, e1)  # (e1, e2, e) orthonormal
    nodes, weights = np.polynomial.legendre.leggauss(m)
    ct = torch.tensor(nodes, dtype=f64, device=device)[:, None]
    st = (1 - ct**2).sqrt()
    ph = (torch.arange(2 * m, dtype=f64, device=device) * (math.pi / m))[None, :]
    nrm = (st[..., None] * (ph.cos()[..., None] * e1 + ph.sin()[..., None] * e2) + ct[..., None] * e).reshape(-1, 3)
    tang = torch.linalg.cross(e.expand(nrm.shape), nrm, dim=-1)
    w = (torch.tensor(weights, dtype=f64, device=device)[:, None] * (math.pi / m)).expand(m, 2 * m).reshape(-1)
    return nrm, tang, w


def _g(v: StaggeredGrid, nrm, tang, radius: float, center=CENTER, frame=(0.0, 0.0, 0.0)) -> torch.Tensor:
    """``u_phi sin(theta)`` of the velocity relative to ``frame`` at the points ``center + radius n``."""
    c = torch.as_tensor(center, dtype=torch.float64, device=v.device)
    rel = v.sample(c + radius * nrm)[0].T - torch.as_tensor(frame, dtype=torch.float64, device=v.device)
    return (rel * tang).sum(-1)


def torque(v: StaggeredGrid, m: int = 24, center=CENTER, frame=(0.0, 0.0, 0.0)) -> float:
    """The viscous torque of the fluid on the inner sphere about the axis, from the one-sided wall shear (probes at
    1.5 and 3 cells from the surface, as :func:`phisim.fluid.body_forces`); ``center``: where the spheres are,
    ``frame``: their common translation velocity (the shear of the velocity relative to it)."""
    h = v.grid.dx[0]
    nrm, tang, w = _sphere_quadrature(m, v.device)
    d1 = 1.5 * h
    s2 = (tang * tang).sum(-1)  # sin(theta)^2
    wall = OMEGA * R1 * s2  # the wall's u_phi sin(theta), constant along the normal
    g1 = _g(v, nrm, tang, R1 + d1, center, frame) - wall
    g2 = _g(v, nrm, tang, R1 + 2 * d1, center, frame) - wall
    dudr = (4 * g1 - g2) / (2 * d1)  # d(u_phi)/dr sin(theta) at the surface
    tau = NU * (dudr - OMEGA * s2)  # tau_r_phi sin(theta) = mu (du_phi/dr - u_phi / r) sin(theta)
    return float((tau * w).sum()) * R1**3  # oint R1 sin(theta) tau_r_phi dS, dS = R1^2 d(cos theta) d(phi)


def torque_through(v: StaggeredGrid, radius: float, m: int = 24) -> float:
    """The torque transmitted through the sphere of ``radius`` between the walls, ``mu r^4 oint d(u_phi / r)/dr
    sin(theta) dOmega`` by the fourth-order central difference over two cells on either side; in the steady Stokes
    flow it equals the torque on the inner sphere at every radius."""
    h = v.grid.dx[0]
    nrm, tang, w = _sphere_quadrature(m, v.device)

    def f(r):
        return _g(v, nrm, tang, r) / r

    ddr = (8 * (f(radius + h) - f(radius - h)) - (f(radius + 2 * h) - f(radius - 2 * h))) / (12 * h)
    return NU * radius**4 * float((ddr * w).sum())


def exact_torque() -> float:
    """``-8 pi mu Omega B``: the torque of the fluid on the inner sphere about the axis."""
    return -8 * math.pi * NU * OMEGA * coefficients()[1]


def study(ns, sharp: bool = True, on_row=None, free_slip: bool = False, **kw) -> list[dict]:
    """:func:`solve_steady` on each grid, its errors and the observed orders between successive grids (``on_row(row)``
    is called as each grid is done; a free-slip outer sphere: the velocity errors alone, its flow exerts no torque)."""
    rows = []
    ref = exact_torque()
    for n in ns:
        t0 = time.thread_time()
        v, steps = solve_steady(n, sharp, free_slip=free_slip, **kw)
        cpu = time.thread_time() - t0
        row = {"n": n, "cells_across_gap": (R2 - R1) * n / (2 * HALF), "steps": steps, **errors(v, free_slip)}
        if not free_slip:
            tq = torque(v)
            ex = StaggeredGrid.from_function(exact, v.grid, v.boundary, dtype=torch.float64, device=v.device)
            tq_probe = torque(ex)
            rm = 0.5 * (R1 + R2)
            tq_mid = torque_through(v, rm)
            row.update({"torque": abs(tq - ref) / abs(ref), "torque_flow": abs(tq - tq_probe) / abs(ref),
                        "torque_probe_of_exact": abs(tq_probe - ref) / abs(ref),
                        "torque_mid": abs(tq_mid - ref) / abs(ref),
                        "torque_mid_flow": abs(tq_mid - torque_through(ex, rm)) / abs(ref), "torque_value": tq,
                        "torque_exact": ref})
        rows.append({**row, "cpu_s": cpu})
        if len(rows) > 1:
            a, b = rows[-2:]
            f = math.log(b["n"] / a["n"])
            b["order"] = {k: math.log(a[k] / b[k]) / f for k in KEYS if k in b}
        if on_row is not None:
            on_row(rows[-1])
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--n", type=int, nargs="+", default=[16, 24, 32])
    ap.add_argument("--blended", action="store_true", help="the blended (first-order) no-slip condition")
    ap.add_argument("--free-slip", action="store_true",
                    help="a free-slip outer sphere (the exact flow is the rigid rotation)")
    ap.add_argument("--start-exact", action="store_true",
                    help="start the Stokes steps from the exact flow instead of rest (the same steady state)")
    ap.add_argument("--scheme", default="implicit", help="viscosity scheme of the Stokes steps")
    ap.add_argument("--dt-cells", type=float, default=50.0, help="time step in units of dx^2 / nu")
    ap.add_argument("--tol", type=float, default=1e-9, help="steady when a step changes the velocity less")
    ap.add_argument("--max-steps", type=int, default=200)
    ap.add_argument("--rtol", type=float, default=1e-10, help="relative tolerance of the pressure and viscous solves")
    ap.add_argument("--out", default=None, help="JSON file for the rows")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--device", default="cpu", help="cpu, cuda or cuda:N")
    args = ap.parse_args(argv)
    device = check_device(args.device)
    torch.set_num_threads(args.threads)
    rows = study(args.n, sharp=not args.blended, scheme=args.scheme, dt_cells=args.dt_cells, tol=args.tol,
                 max_steps=args.max_steps, rtol=args.rtol, device=device, free_slip=args.free_slip,
                 start_exact=args.start_exact,
                 on_row=lambda row: print(json.dumps({**row, "device": str(device)}), flush=True))
    rows = [{**row, "device": str(device)} for row in rows]
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        meta = {"sharp": not args.blended, "free_slip": args.free_slip, "R1": R1, "R2": R2, "axis": AXIS}
        Path(args.out).write_text(json.dumps({**meta, "rows": rows}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
