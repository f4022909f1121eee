"""Order of the no-slip condition of MOVING sharp bodies in 3-D: spherical Couette flow carried at a constant velocity.

The spherical Couette flow of ``examples/spherical_couette.py`` (inner sphere of radius ``R1`` turning at ``Omega``
about a tilted axis ``e``, outer sphere of radius ``R2`` at rest, ``nu = 1``) seen from a frame in which both spheres
translate at ``W``: the exact velocity is ``u(x, t) = W + u_c(x - c(t))``, ``c(t) = c0 + W t``, with
``u_c(r) = (A + B / |r|^3) omega x r``. Both surfaces sweep across the grid obliquely, so faces are covered and
uncovered at every step. The Stokes steps of the solver (:func:`phisim.fluid.step.finish_step`: the solids imposed at
the new time with the freshly uncovered faces treated, implicit viscosity, projection) get the forcing
``f = du/dt = -(W . grad) u_c(x - c(t))``, which makes ``u`` an exact solution with a constant pressure; the run starts
from the exact field and measures the error at ``t_end``. Time steps ``dt = dx^2 / nu``.

Measured, as in the 2-D study (``test_moving_bodies_order.py``): velocity errors on the fluid faces within two cells of
either surface (max, rms) and on all fluid faces (rms), relative to the wall speed ``Omega R1``; the torque on the
inner sphere about the axis from the wall shear of ``u - W`` (probes 1.5 and 3 cells out, as ``body_forces``), against
the exact ``-8 pi mu Omega B`` (``torque``) and against the same probes applied to the exact field (``torque_flow``,
which removes the truncation error of the one-sided difference on the steep profile next to a small sphere); the net
force on it (exactly 0) from ``body_forces``, relative to ``torque / R1``.

``python tests/phisim/fluid/test_moving_bodies_order_3d.py 16 24 32`` prints the study.
"""

from __future__ import annotations

import importlib.util
import json
import math
import sys
import time
from pathlib import Path

import pytest
import torch

ROOT = Path(__file__).resolve().parents[3]
if __name__ == "__main__":
    sys.path.insert(0, str(ROOT))

from phisim import Grid, StaggeredGrid  # noqa: E402
from phisim.boundary import Inflow, Open  # noqa: E402
from phisim.fluid import SDF, Body, Sphere, body_forces, navier_stokes_step  # noqa: E402
from phisim.fluid.bodies import uncovered_stencil  # noqa: E402
from phisim.fluid.step import finish_step  # noqa: E402
from phisim.solvers import Solve  # noqa: E402


def _spherical_couette():
    path = ROOT / "examples" / "spherical_couette.py"
    spec = importlib.util.spec_from_file_location("spherical_couette_carried", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


SC = _spherical_couette()  # R1, R2, OMEGA, NU, AXIS, HALF, coefficients, the sphere quadrature
F64 = torch.float64
C0 = SC.CENTER
W = (0.6, 0.35, -0.25)  # carries the surfaces across the grid, obliquely
A, B = SC.coefficients()
#: The box of the free-slip variant: the free-slip ghost values need about two cells inside the outer sphere, which
#: the box of the no-slip study (0.1 beyond the resting sphere) does not leave once the sphere has moved.
HALF_FREE_SLIP = 1.05
OMEGA_VEC = torch.tensor([SC.OMEGA * e for e in SC.AXIS], dtype=F64)


def centre(t: float) -> torch.Tensor:
    return torch.tensor([c + w * t for c, w in zip(C0, W)], dtype=F64)


def couette(r: torch.Tensor, free_slip: bool = False) -> torch.Tensor:
    """``u_c`` at offsets ``r`` (``(..., 3)``) from the centre (a free-slip outer sphere: the rigid rotation)."""
    a, b = SC.coefficients(free_slip)
    g = a + b / r.norm(dim=-1, keepdim=True) ** 3
    return g * torch.linalg.cross(OMEGA_VEC.expand(r.shape), r, dim=-1)


def forcing(r: torch.Tensor, free_slip: bool = False) -> torch.Tensor:
    """``-(W . grad) u_c`` at offsets ``r``: ``g`` varies as ``-3 B r_k / |r|^5`` and ``omega x r`` by ``omega x W``."""
    a, b = SC.coefficients(free_slip)
    w = torch.tensor(W, dtype=F64).expand(r.shape)
    rad = r.norm(dim=-1, keepdim=True)
    g = a + b / rad**3
    wr = (w * r).sum(-1, keepdim=True)
    om = OMEGA_VEC.expand(r.shape)
    return 3 * b * wr / rad**5 * torch.linalg.cross(om, r, dim=-1) - g * torch.linalg.cross(om, w, dim=-1)


def bodies(free_slip: bool = False):
    inner = Body(Sphere(C0, SC.R1), velocity=W, angular_velocity=tuple(OMEGA_VEC.tolist()), name="inner")
    c = torch.tensor(C0, dtype=F64)
    outer = Body(SDF(lambda x: SC.R2 - (x - c.to(x.dtype)).norm(dim=-1), center=C0,
                     bounds=((-SC.HALF,) * 3, (SC.HALF,) * 3)), velocity=W, no_slip=not free_slip, name="outer")
    return [inner, outer]


def exact_field(grid: Grid, t: float, free_slip: bool = False) -> StaggeredGrid:
    comps = tuple((W[i] + couette(grid.face_centers(i, F64) - centre(t), free_slip)[..., i])[None] for i in range(3))
    return StaggeredGrid(comps, grid, "wall")


def torque(v: StaggeredGrid, t: float) -> float:
    """The viscous torque on the inner sphere about the axis from the wall shear of ``u - W`` (the resting study's
    probes and quadrature, at the centre of time ``t``)."""
    return SC.torque(v, center=centre(t), frame=W)


def run(n: int, t_end: float = 0.05, dt_cells: float = 1.0, rtol: float = 1e-6, free_slip: bool = False) -> dict:
    """The carried spherical Couette flow on ``n^3`` over ``[-HALF, HALF]^3`` up to ``t_end``; errors at ``t_end`` (a
    free-slip outer sphere: the carried rigid rotation, velocity errors alone).

    ``rtol`` of the pressure and viscous solves: 1e-6 is far below the no-slip study's velocity errors (1e-4 and more
    of the wall speed; at 16^3 and 24^3 the errors agree with 1e-10 solves to three digits); the free-slip errors from
    40^3 on (near rms 2e-5 and less) need 1e-9 (with 1e-6 the solves' error is of their size: 1.1e-5 against 1.9e-5
    at 40^3)."""
    half = HALF_FREE_SLIP if free_slip else SC.HALF
    grid = Grid((n, n, n), bounds=[(-half, half)] * 3)
    h = grid.dx[0]
    steps = int(math.ceil(t_end / (dt_cells * h * h / SC.NU)))
    dt = t_end / steps
    solids = bodies(free_slip)
    v = exact_field(grid, 0.0, free_slip)
    p = None
    tight = Solve(rtol=rtol)
    t = 0.0
    cpu = time.thread_time()
    for _ in range(steps):
        t_new = t + dt
        f = tuple(forcing(grid.face_centers(i, F64) - centre(t_new), free_slip)[..., i][None] for i in range(3))
        v = v.with_values(tuple(c + dt * fi for c, fi in zip(v.values, f)))
        v, p = finish_step(v, dt, None, SC.NU, "implicit", solids, tight, p, t_new)
        t = t_new
    cpu = time.thread_time() - cpu
    changing = 0
    err_near, err_all, err_outer = [], [], []
    for i in range(3):
        x = grid.face_centers(i, F64)
        changing += int(sum(((b.sdf(x, t - dt) <= 0) != (b.sdf(x, t) <= 0)).sum() for b in solids))
        rad = (x - centre(t)).norm(dim=-1)
        fluid = (rad > SC.R1) & (rad < SC.R2)
        err = (v.values[i][0] - W[i] - couette(x - centre(t), free_slip)[..., i]).abs()
        err_near.append(err[fluid & ((rad - SC.R1 < 2 * h) | (SC.R2 - rad < 2 * h))])
        err_all.append(err[fluid])
        err_outer.append(err[fluid & (SC.R2 - rad < 2 * h)])
    err_near, err_all, err_outer = torch.cat(err_near), torch.cat(err_all), torch.cat(err_outer)
    scale = SC.OMEGA * SC.R1
    row = {"n": n, "steps": steps, "dt": dt, "faces_changing_side_in_the_last_step": changing,
           "near_max": float(err_near.max()) / scale, "near_rms": float(err_near.pow(2).mean().sqrt()) / scale,
           "all_rms": float(err_all.pow(2).mean().sqrt()) / scale,
           "outer_max": float(err_outer.max()) / scale, "outer_rms": float(err_outer.pow(2).mean().sqrt()) / scale,
           "cpu_s": cpu}
    if free_slip:  # the rigid rotation exerts no stress: no torque or force to compare
        return row
    ref = SC.exact_torque()
    force = body_forces(v, p, solids[0], dt=dt, viscosity=SC.NU, time=t)
    return {**row, "torque": abs(torque(v, t) - ref) / abs(ref),
            "torque_flow": abs(torque(v, t) - torque(exact_field(grid, t), t)) / abs(ref),
            "force": float(force.total[0].norm()) / (abs(ref) / SC.R1)}


def study(ns, on_row=None, **kw) -> list[dict]:
    """:func:`run` on each grid with the observed orders between successive grids (``on_row(row)`` as each is done)."""
    rows = []
    for n in ns:
        rows.append(run(n, **kw))
        if len(rows) > 1:
            a, b = rows[-2:]
            f = math.log(b["n"] / a["n"])
            keys = ("near_max", "near_rms", "all_rms", "outer_max", "outer_rms", "torque", "torque_flow", "force")
            b["order"] = {k: math.log(a[k] / b[k]) / f for k in keys if k in b}
        if on_row is not None:
            on_row(rows[-1])
    return rows


def test_forcing_is_the_time_derivative_of_the_carried_flow():
    r = torch.tensor([[0.5, 0.1, -0.2], [-0.3, 0.55, 0.1], [0.2, -0.6, 0.35]], dtype=F64)
    w = torch.tensor(W, dtype=F64)
    h = 1e-6
    fd = (couette(r - w * h) - couette(r + w * h)) / (2 * h)
    assert torch.allclose(forcing(r), fd, atol=1e-7)


def test_carried_field_fits_both_moving_walls():
    """The exact field equals each body's rigid velocity on its surface, at a time when both have moved."""
    t = 0.37
    gen = torch.Generator().manual_seed(1)
    dirs = torch.nn.functional.normalize(torch.randn(40, 3, dtype=F64, generator=gen), dim=-1)
    c = centre(t)
    inner, outer = c + SC.R1 * dirs, c + SC.R2 * dirs
    w = torch.tensor(W, dtype=F64)
    rigid = torch.linalg.cross(OMEGA_VEC.expand(40, 3), inner - c, dim=-1)
    torch.testing.assert_close(w + couette(inner - c), w + rigid)
    torch.testing.assert_close(w + couette(outer - c), w.expand(40, 3))


def test_carried_spherical_couette_converges_at_second_order():
    """16^3 -> 24^3, both surfaces carried 0.3 / 0.5 cells over the run with about 90 / 150 faces changing side in a
    step: the rms errors near the surfaces and over the shell at order at least 1.5 (measured 1.85 / 1.92; the errors
    equal those of the resting spheres, 2.1e-3 / 2.1e-3 at 24^3), the largest error near the surfaces falling (order
    1.25 here, 1.65 and 1.94 on the next pairs: the maximum over the cut faces of two spheres jumps with how they cut
    the grid), the torque error falling at the rate of the resting study (1.30; the probes' truncation error), the net
    force below 4e-3 of torque / R1 (measured 2.4e-3, 3.6e-4)."""
    rows = study([16, 24])
    order = rows[1]["order"]
    assert all(r["faces_changing_side_in_the_last_step"] > 50 for r in rows), rows
    assert order["near_rms"] > 1.5 and order["all_rms"] > 1.5, rows
    assert order["near_max"] > 1.0 and order["torque"] > 1.0, rows
    assert rows[1]["near_max"] < 2e-2 and rows[1]["near_rms"] < 3e-3, rows
    assert all(r["force"] < 4e-3 for r in rows), rows


@pytest.mark.slow  # about 60 s
def test_carried_spherical_couette_orders_24_32():
    """24^3 -> 32^3: every velocity error at order at least 1.5 (measured 1.65 / 1.87 / 1.98), the torque 1.49."""
    rows = study([24, 32])
    order = rows[1]["order"]
    assert order["near_max"] > 1.5 and order["near_rms"] > 1.5 and order["all_rms"] > 1.5, rows
    assert order["torque"] > 1.3, rows


def test_carried_free_slip_sphere():
    """The outer sphere free-slip, both carried (the exact flow: the carried rigid rotation), 24^3, in a box that
    leaves the free-slip ghost values room: measured largest error 2.3e-4 of Omega R1 and rms near the surfaces 4.8e-5,
    with the fractions and the flux correction's centroids from the curvature-corrected sub-cuts (``curved_cut``;
    the planar sub-cuts: 8.6e-4 / 7.4e-5; the sub-cuts' fractions with one planar cut's centroid: 4.3e-3 / 2.6e-4; one
    planar cut for both: 8.7e-3 / 8.9e-4; all fail the bounds)."""
    row = study([24], free_slip=True)[0]
    assert row["faces_changing_side_in_the_last_step"] > 50, row
    assert row["near_max"] < 4e-4 and row["near_rms"] < 6.5e-5, row


@pytest.mark.parametrize(("integrator", "convection"), [
    ("split", "central"), pytest.param("imex2", "quick", marks=pytest.mark.slow)])
def test_gradcheck_3d_step_past_a_moving_sphere(integrator, convection):
    """A step past a sharp sphere that translates (uncovering faces) and turns is differentiable w.r.t. its radius,
    centre, velocity and angular velocity, with the force read from it (in 3-D as the 2-D tests of the disc)."""
    grid = Grid((7, 6, 6), bounds=[(0, 1.4), (0, 1.2), (0, 1.2)])
    dt = 0.05
    boundary = {"x": (Inflow(0.4), Open()), "y": "wall", "z": "wall"}
    settings = {} if convection == "central" else {"convection": convection}

    def run(radius, center, velocity, omega):
        body = Body(Sphere(center, radius), velocity=velocity, angular_velocity=omega)
        v0 = StaggeredGrid.zeros(grid, boundary, dtype=F64)
        v0 = v0.with_values((v0.values[0] + 0.4, *v0.values[1:]))  # a stream: QUICK's upwind side stays put
        out, p = navier_stokes_step(v0, dt, viscosity=0.05, obstacles=body, solve=Solve(rtol=1e-12),
                                    integrator=integrator, **settings)
        f = body_forces(out, p, body, dt=dt, viscosity=0.05, time=dt)
        return f.total[0], out.values[0].sum() + (out.values[1] ** 2).sum() + (out.values[2] ** 3).sum()

    # A generic configuration: with radius 0.37 a face centre lies on the surface at t = 0 (the face set switches
    # there), and with x = 0.66 the centre reaches a plane of cell centres at t = dt, where the multilinear
    # interpolation of the probes has a kink (one-sided derivatives 1 % apart).
    radius = torch.tensor(0.355, dtype=F64, requires_grad=True)
    center = torch.tensor([0.663, 0.58, 0.63], dtype=F64, requires_grad=True)
    velocity = torch.tensor([0.8, 0.3, -0.2], dtype=F64, requires_grad=True)
    omega = torch.tensor([0.3, -0.5, 0.7], dtype=F64, requires_grad=True)
    probe = Body(Sphere(center.detach(), radius.detach()), velocity=velocity.detach())
    assert any(uncovered_stencil([probe], grid, i, 0.0, dt, F64, None) is not None for i in range(3))
    assert torch.autograd.gradcheck(run, (radius, center, velocity, omega), eps=1e-6, atol=1e-6, rtol=1e-5)


if __name__ == "__main__":
    import argparse

    ap = argparse.ArgumentParser(description="the carried spherical Couette study; one JSON line per grid")
    ap.add_argument("n", type=int, nargs="*", default=[16, 24, 32])
    ap.add_argument("--free-slip", action="store_true", help="a free-slip outer sphere (the carried rigid rotation)")
    ap.add_argument("--rtol", type=float, default=1e-6, help="tolerance of the pressure and viscous solves")
    ap.add_argument("--dt-cells", type=float, default=1.0, help="time step in units of dx^2 / nu")
    ap.add_argument("--resting", action="store_true", help="W = 0: the same run with the spheres at rest")
    args = ap.parse_args()
    torch.set_num_threads(1)
    if args.resting:
        W = (0.0, 0.0, 0.0)
    extra = {"rtol": args.rtol, "dt_cells": args.dt_cells, "W": list(W)}
    study(args.n, free_slip=args.free_slip, rtol=args.rtol, dt_cells=args.dt_cells,
          on_row=lambda row: print(json.dumps({**row, **extra}), flush=True))
