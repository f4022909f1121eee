"""An independent reference for the DFG cylinder benchmark: body-fitted high-order finite elements (NGSolve).

phisim's cut-cell MAC solver converges, on the 2D-2 case, to a lift maximum of about 0.987 (docs/VALIDATION.md,
"The force from a control volume"), just below the published range 0.99-1.01 of Schäfer & Turek (1996). This script
computes the same flow with a method that shares nothing with phisim: a curved, body-fitted triangular mesh,
Taylor-Hood elements of order ``k / k-1``, BDF2 in time with the convection extrapolated (``2 u^n - u^(n-1)``) and
the Stokes part implicit (one factorization per run), and the force from the discrete momentum residual of each step
(``M du/dt + N(u*) + A u``) tested with a function that is 1 on the cylinder and 0 on the other boundaries: the force
the scheme's own equations put on it, more accurate than a surface integral of the stress. Its numbers check the
reference range, not phisim.

It runs in its own virtual environment (NGSolve is not a phisim dependency), one core per run. The runs of
docs/VALIDATION.md ("An independent reference for 2D-2")::

    python -m venv /tmp/ngvenv && /tmp/ngvenv/bin/pip install ngsolve==6.2.2608
    F=data/validation/diagnostics/dfg_fem_reference.py; O=data/validation/fem_reference
    OMP_NUM_THREADS=1 /tmp/ngvenv/bin/python $F --case 2D-1 --order 4 --h-cyl 0.005 --h-max 0.02 --t-end 10 \
        --dt 0.005 --record-from 9 --out $O/dfg_2d1_k4_h005.json
    OMP_NUM_THREADS=1 /tmp/ngvenv/bin/python $F --order 3 --h-cyl 0.01 --h-max 0.04 --t-end 10 --dt 5e-4 \
        --record-from 3 --out $O/dfg_2d2_k3_h010.json
    OMP_NUM_THREADS=1 /tmp/ngvenv/bin/python $F --order 4 --h-cyl 0.01 --h-max 0.04 --t-end 6.5 --dt 3e-4 \
        --record-from 4.5 --out $O/dfg_2d2_k4_h010.json
    OMP_NUM_THREADS=1 /tmp/ngvenv/bin/python $F --order 3 --h-cyl 0.005 --h-max 0.02 --t-end 6.5 --dt 3e-4 \
        --record-from 4.5 --out $O/dfg_2d2_k3_h005.json

The convection is explicit: larger steps blow up (P3, ``h_cyl`` 0.01: 1e-3 does, 5e-4 does not).

Set-up as in examples/cylinder_benchmark.py: channel 2.2 x 0.41, cylinder of diameter 0.1 at (0.2, 0.2),
``nu = 1e-3``, parabolic inflow of peak 0.3 (2D-1) or 1.5 (2D-2), no-slip walls, do-nothing outflow
(``nu du/dn - p n = 0``, the benchmark's own), starting from the Stokes flow. Coefficients ``2 F / (U_mean^2 D)``.
"""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path

import numpy as np
from netgen.occ import Circle, OCCGeometry, Rectangle, X, Y
from ngsolve import (
    H1,
    BilinearForm,
    CoefficientFunction,
    GridFunction,
    InnerProduct,
    LinearForm,
    Mesh,
    VectorH1,
    div,
    dx,
    grad,
    y,
)

H, L, D, CENTER, NU = 0.41, 2.2, 0.1, (0.2, 0.2), 1e-3


def make_mesh(h_cyl: float, h_max: float, order: int) -> Mesh:
    """The channel minus the cylinder, boundaries named inlet / outlet / wall / cyl, curved to ``order``."""
    channel = Rectangle(L, H).Face()
    channel.edges.Min(X).name = "inlet"
    channel.edges.Max(X).name = "outlet"
    channel.edges.Min(Y).name = "wall"
    channel.edges.Max(Y).name = "wall"
    disc = Circle(CENTER, D / 2).Face()
    disc.edges.name = "cyl"
    disc.edges.maxh = h_cyl
    fluid = channel - disc
    mesh = Mesh(OCCGeometry(fluid, dim=2).GenerateMesh(maxh=h_max, grading=0.2))
    mesh.Curve(order)
    return mesh


def run(case: str, order: int, h_cyl: float, h_max: float, dt: float, t_end: float,
        record_from: float) -> tuple[dict, np.ndarray]:
    """One run: its summary and the history ``(t, c_D, c_L, dp)`` from ``record_from`` on."""
    um = 0.3 if case == "2D-1" else 1.5
    umean = 2 * um / 3
    mesh = make_mesh(h_cyl, h_max, order)
    V = VectorH1(mesh, order=order, dirichlet="inlet|wall|cyl")
    Q = H1(mesh, order=order - 1)
    X_ = V * Q
    (u, p), (v, q) = X_.TnT()

    stokes = NU * InnerProduct(grad(u), grad(v)) * dx - div(u) * q * dx - div(v) * p * dx
    mass = u * v * dx
    a_stokes = BilinearForm(stokes).Assemble()
    a_step = BilinearForm(1.5 / dt * mass + stokes).Assemble()
    m_mat = BilinearForm(mass).Assemble()

    state = GridFunction(X_)
    inflow = CoefficientFunction((4 * um * y * (H - y) / H**2, 0))
    state.components[0].Set(inflow, definedon=mesh.Boundaries("inlet"))
    # Serial on purpose: on one shared core NGSolve's task manager costs more than it gives.
    inv_stokes = a_stokes.mat.Inverse(X_.FreeDofs(), inverse="umfpack")
    res = state.vec.CreateVector()
    res.data = -a_stokes.mat * state.vec
    state.vec.data += inv_stokes * res
    inv_step = a_step.mat.Inverse(X_.FreeDofs(), inverse="umfpack")


    # The test function of the force: 1 (in the chosen direction) on the cylinder, 0 on the other boundaries.
    tests = []
    for e in ((1, 0), (0, 1)):
        g = GridFunction(X_)
        g.components[0].Set(CoefficientFunction(e), definedon=mesh.Boundaries("cyl"))
        tests.append(g)

    old = state.vec.CreateVector()
    old.data = state.vec
    older = state.vec.CreateVector()
    older.data = state.vec
    extrap = GridFunction(X_)
    conv = LinearForm(InnerProduct(grad(extrap.components[0]) * extrap.components[0], v) * dx)
    rhs = state.vec.CreateVector()
    tmp = state.vec.CreateVector()

    def force(dudt_vec) -> tuple[float, float]:
        """The discrete momentum residual of the step just taken, tested with each ``g``: ``-(M du/dt + N(u*) +
        A u)(g)``, the force the scheme's own equations put on the cylinder (the convection ``N`` of the velocity
        ``u*`` the step extrapolated)."""
        tmp.data = a_stokes.mat * state.vec
        tmp.data += m_mat.mat * dudt_vec
        tmp.data += conv.vec
        return tuple(-InnerProduct(tmp, g.vec) for g in tests)

    n_steps = int(round(t_end / dt))
    hist = []
    t = 0.0
    dudt = state.vec.CreateVector()
    p_front = (CENTER[0] - D / 2 - 1e-5, CENTER[1])  # 1e-5 inside the fluid: the curved mesh's edge is not the
    p_back = (CENTER[0] + D / 2 + 1e-5, CENTER[1])   # exact circle (stagnation points: dp/dx = 0)
    front, back = mesh(*p_front), mesh(*p_back)
    t0 = time.time()
    for k in range(1, n_steps + 1):
        first = k == 1
        # extrapolated convection velocity 2 u^n - u^(n-1) (u^n itself on the first step)
        extrap.vec.data = (1.0 if first else 2.0) * old - (0.0 if first else 1.0) * older
        conv.Assemble()
        # BDF2: (3 u^(n+1) - 4 u^n + u^(n-1)) / (2 dt) + Stokes(u^(n+1)) = -conv
        tmp.data = (2.0 / dt) * old - (0.5 / dt) * older
        rhs.data = m_mat.mat * tmp
        rhs.data -= conv.vec
        rhs.data -= a_step.mat * state.vec
        state.vec.data += inv_step * rhs
        t = k * dt
        dudt.data = (1.5 / dt) * state.vec - (2.0 / dt) * old + (0.5 / dt) * older
        older.data = old
        old.data = state.vec
        if t >= record_from - 1e-12:
            fx, fy = force(dudt)
            pr = state.components[1]
            dp = pr(front) - pr(back)
            hist.append((t, 2 * fx / (umean**2 * D), 2 * fy / (umean**2 * D), dp))
    h = np.array(hist)
    out = {"case": case, "order": order, "h_cyl": h_cyl, "h_max": h_max, "dt": dt, "t_end": t_end,
           "record_from": record_from, "ndof": X_.ndof, "elements": mesh.ne, "wall_s": time.time() - t0}
    if case == "2D-1":
        out.update(cd=float(h[-1, 1]), cl=float(h[-1, 2]), dp=float(h[-1, 3]),
                   cd_change_last_unit=float(abs(h[-1, 1] - h[h[:, 0] <= h[-1, 0] - 1 + 1e-9][-1, 1])))
    else:
        cl = h[:, 2]
        xm = cl - 0.5 * (cl.max() + cl.min())
        up = np.nonzero((xm[:-1] < 0) & (xm[1:] >= 0))[0]
        periods = [(float(h[a, 0]), float(h[b, 0])) for a, b in zip(up[:-1], up[1:])]
        out.update(cl_max_per_period=[float(cl[a:b + 1].max()) for a, b in zip(up[:-1], up[1:])],
                   cd_max_per_period=[float(h[a:b + 1, 1].max()) for a, b in zip(up[:-1], up[1:])],
                   cl_min_per_period=[float(cl[a:b + 1].min()) for a, b in zip(up[:-1], up[1:])],
                   periods=periods,
                   st=float(D / umean / np.mean([b - a for a, b in periods])) if periods else math.nan)
    return out, h


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--case", default="2D-2", choices=["2D-1", "2D-2"])
    ap.add_argument("--order", type=int, default=3)
    ap.add_argument("--h-cyl", type=float, default=0.01, help="mesh size on the cylinder")
    ap.add_argument("--h-max", type=float, default=0.04, help="largest mesh size")
    ap.add_argument("--dt", type=float, default=5e-4)
    ap.add_argument("--t-end", type=float, default=8.0)
    ap.add_argument("--record-from", type=float, default=None)
    ap.add_argument("--out", default=None, help="JSON summary; the history beside it as CSV")
    args = ap.parse_args(argv)
    rec = args.record_from if args.record_from is not None else max(args.t_end - 2.0, 0.0)
    out, h = run(args.case, args.order, args.h_cyl, args.h_max, args.dt, args.t_end, rec)
    if args.out:
        path = Path(args.out)
        path.parent.mkdir(parents=True, exist_ok=True)
        np.savetxt(path.with_suffix(".csv"), h, delimiter=",", fmt="%.10g", header="t,cd,cl,dp")
        path.write_text(json.dumps(out, indent=1))
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
