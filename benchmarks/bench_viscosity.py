"""Cost of one viscosity step of a MAC velocity: explicit vs implicit (min of repeats, ms), Markdown tables.

Run: ``OMP_NUM_THREADS=1 python benchmarks/bench_viscosity.py [--dtype float32 float64] [--sizes 48 64 128 256]
[--stat min|median] [--write]``; ``--write`` saves the tables to ``benchmarks/results/viscosity.md``, which
``benchmarks/run.py`` copies into ``docs/BENCHMARKS.md`` (section "Viscosity step"). Each cell gives the wall
time and, after the slash, the CPU time of the process for the same statistic.

Cases per resolution (2-D closed box with no-slip walls, batch 1, ``ν dt / dx² = 2``, far beyond the
explicit limit; the explicit step is timed at its own stable size, the cost per call does not depend on dt):

* ``explicit``: forward Euler ``u + ν dt ∇²u`` (one stencil per component), the reference the issue sets:
  an implicit step should cost at most twice as much;
* ``implicit (spectral)``: :func:`phisim.solvers.diffusion.diffuse_staggered`, backward Euler solved exactly by
  one DST-I x DST-II transform pair per component (pocketfft one-axis transforms, in place);
* ``crank_nicolson``: the same with the explicit half folded into the multiplier;
* ``implicit, body (capacitance)``: backward Euler with the faces of a disc body fixed, solved directly
  with the cached capacitance matrix of the body surface (two box solves per component);
* ``body: one-time build``: the call that builds those matrices (|S| box solves per component; |S| the
  number of surface faces, and which call with this body and ν dt builds: the earlier ones run PCG);
* ``implicit, body (PCG)``: the same step by CG preconditioned with the exact box solve, what the first
  calls with a new body or ν dt run (timed with a tensor viscosity, which keeps the CG path).

A last table times whole Navier-Stokes steps (float32, walls, ν = 0.01, dt = 0.5 dx): the split step
with explicit and with implicit viscosity, and the second-order integrators ``rk2`` and ``imex2``.
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import sys
import time

import torch

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

from timing import synchronize  # noqa: E402

from phisim import Grid, StaggeredGrid  # noqa: E402
from phisim.checks import check_device  # noqa: E402
from phisim.fluid import FluidState, FluidStepper, navier_stokes_step  # noqa: E402
from phisim.fluid.bodies import Body  # noqa: E402
from phisim.fluid.geometry import Sphere  # noqa: E402
from phisim.solvers import mac_diffusion as _mac_diffusion  # noqa: E402
from phisim.solvers.diffusion import diffuse_staggered  # noqa: E402
from phisim.solvers.linalg import Solve  # noqa: E402
from phisim.spectral import fft  # noqa: E402

NU = 1.0  # viscosity of the single-step table
#: Statistic of the repeats: "min" (default: on a shared machine other load only adds time, so the fastest
#: repeat is the closest to the code's own cost) or "median".
STAT = "min"


NOTES = """Reading the tables:

- Goal (issue 14): an implicit step costs at most 2x the explicit one at 48²-256². Met for the box solve in
  both precisions at every size: 0.8-1.3x at 48²-128² and 1.7-1.9x at 256² (implicit and Crank-Nicolson,
  float32 and float64). Not met with fixed faces (bodies), see below.
- How the box solve got there. Per component the exact solve is one transform pair per axis. The normal
  component between two walls needs a DST-I along its own axis, which pocketfft (like FFTW) computes from a
  real FFT of twice the length: the most expensive pass (255 samples: 0.09 ms float32, 0.16-0.29 ms float64,
  against 0.05 / 0.07 ms for a real FFT of 256). From about 90² up
  (`FFTSettings.wall_solve_min_samples`) that axis is now
  solved as periodic over the faces 0..n-1, an FFT of length n, and one exact correction per transverse mode
  puts face 0 back to zero: the periodic Green's function of face 0, scaled by the value found there
  (`phisim.spectral.fft.wall_solve`; the other faces then satisfy exactly the wall problem, tests compare with the
  dense θ-scheme and with the DST-I route to round-off). Per 255x256 component: 0.33 -> 0.26 ms float32,
  0.72/0.56 -> 0.51/0.42 ms float64 (the float64 FFT along the outer axis runs on a transposed copy). The
  previous run of this script (DST-I route) measured 0.688 ms (2.17x) float32 and 1.317 ms (2.50x) float64
  at 256².
- Earlier history: before `diffuse_staggered`, implicit viscosity was unpreconditioned CG (about 12
  iterations per component), 12.5 / 13.5 / 16.3 / 36.8 ms at 48² / 64² / 128² / 256², 83-112x the explicit
  step; the issue's own figure was 9.3 ms of an 11 ms step at 48².
- Crank-Nicolson in a box costs the same as backward Euler: `2 (I - αL/2)⁻¹ f - f`, one solve and a
  subtraction.
- Per unit of simulated time the comparison favours the implicit solve at every size: at the dt of this
  table the explicit step would need 8 sub-steps (ν dt Σ 2/dx² = 8).
- With fixed faces (a disc body) the solve is direct: a capacitance matrix on the body surface (|S| faces per
  component), LU-factored once per body and ν dt, then two exact box solves and one |S|-sized triangular solve
  per component: 2.3-2.6x explicit at 48²-64², 2.9-3.4x at 128², 4.2-4.5x at 256² (both precisions), i.e.
  about twice the box solve, the floor of this method (the second solve's source is sparse, but its answer
  is not). The build (|S| box solves) runs at the first call of an owner that keeps the body (a stepper's static
  bodies pass their solver cache as `capacitance=`). PCG with the exact box solve as preconditioner (pure
  function calls, a tensor ν, per-sample bodies) costs 30-58x explicit. Only `imex2` pays the body solve: the
  split step imposes bodies before and after a box solve, so its viscosity costs the box column.
- In whole steps with a body the viscosity solves no longer dominate (last table): 5-7 % of a split step and
  12-19 % of an `imex2` step at 48²-256² (ν dt / dx² = 0.3-1.3 per solve); the masked pressure projection
  takes most of the rest (PCG: the closed box is singular, which the direct pressure solve of static bodies
  declines).
- Whole steps: the split step with implicit viscosity costs 0.5-1.2 ms at 48²-128² and 3.1 ms at 256²;
  `imex2` (two Crank-Nicolson solves, two projections, two convection terms) 1.2-1.8x that; it buys second
  order in time (docs/SCHEMES.md).
- Wall and CPU times agree for the min of the repeats (the machine was otherwise idle)."""


DEVICE = torch.device("cpu")


def bench(fn, repeat: int = 30, min_total: float = 0.3) -> tuple[float, float]:
    """(wall, CPU) ms of one call: the chosen statistic of the repeats (CPU time of this process; on a GPU the
    device is synchronised around each call, and the CPU time is that of the host)."""
    fn()
    fn()
    walls, cpus = [], []
    total = 0.0
    while len(walls) < repeat or total < min_total:
        synchronize(DEVICE)
        t, c = time.perf_counter(), time.process_time()
        fn()
        synchronize(DEVICE)
        dt = time.perf_counter() - t
        cpus.append(time.process_time() - c)
        walls.append(dt)
        total += dt
        if len(walls) > 2000:
            break
    pick = min if STAT == "min" else statistics.median
    return 1e3 * pick(walls), 1e3 * pick(cpus)


def _disc_masks(grid, n):
    x = grid.cell_centers(torch.float64, DEVICE)
    solid = ((x - 0.5) ** 2).sum(-1) <= 0.2**2
    masks = []
    for i in range(2):
        f = torch.nn.functional.pad(solid.to(torch.float64)[None, None], (1, 1, 1, 1), mode="replicate")[0, 0]
        m = f.narrow(i, 0, n + 1).narrow(1 - i, 1, n) + f.narrow(i, 1, n + 1).narrow(1 - i, 1, n)
        masks.append(m > 0)
    return masks


def table(sizes, dtype) -> list[str]:
    """One viscosity step per method and size (a Markdown table)."""
    rows = []
    for n in sizes:
        grid = Grid((n, n), bounds=[(0, 1), (0, 1)])
        g = torch.Generator().manual_seed(0)
        v = StaggeredGrid(tuple(torch.randn(1, *grid.face_shape(i), generator=g, dtype=torch.float64).to(
            dtype=dtype, device=DEVICE) for i in range(2)), grid, "wall").with_boundary_faces()
        dx = grid.dx[0]
        dt = 2 * dx**2
        dt_explicit = 0.2 * dx**2
        masks = _disc_masks(grid, n)
        solve = Solve(rtol=1e-6 if dtype == torch.float32 else 1e-8)
        explicit = bench(lambda v=v, h=dt_explicit: diffuse_staggered(v, h, viscosity=NU, method="explicit"))
        implicit = bench(lambda v=v, h=dt: diffuse_staggered(v, h, viscosity=NU, method="implicit"))
        cn = bench(lambda v=v, h=dt: diffuse_staggered(v, h, viscosity=NU, method="crank_nicolson"))
        cache: dict = {}  # the body's solver cache, as a stepper keeps it for its static bodies
        t0, c0 = time.perf_counter(), time.process_time()  # the first call with the cache builds the matrices
        diffuse_staggered(v, dt, viscosity=NU, method="implicit", fixed=masks, solve=solve, capacitance=cache)
        build = (1e3 * (time.perf_counter() - t0), 1e3 * (time.process_time() - c0))
        calls = 1
        surface = max(s.surface.numel() for k, (_, s) in cache.items() if k[0] == "capacitance" and s)
        body = bench(lambda v=v, h=dt, m=masks, s=solve, c=cache: diffuse_staggered(
            v, h, viscosity=NU, method="implicit", fixed=m, solve=s, capacitance=c))
        # a tensor viscosity keeps the PCG path (what the first call with a new body or ν dt runs)
        nu_t = torch.tensor(NU, dtype=dtype, device=DEVICE)
        pcg = bench(lambda v=v, h=dt, m=masks, s=solve, nu=nu_t: diffuse_staggered(
            v, h, viscosity=nu, method="implicit", fixed=m, solve=s), repeat=10)
        rows.append((n, explicit, implicit, cn, body, build, (surface, calls), pcg))
    lines = [f"One viscosity step of a MAC velocity, {str(dtype).split('.')[-1]}, batch 1, walls, ν dt/dx² = 2, "
             f"1 thread; {STAT} of the repeats, wall ms (ratio to explicit) / CPU ms of the process:", "",
             "| n² | explicit | implicit (spectral) | crank_nicolson | implicit, body (capacitance) | "
             "body: one-time build (surface faces; which call) | implicit, body (PCG) |",
             "|---|---|---|---|---|---|---|"]
    for n, e, i, c, b, bu, k, p in rows:
        def cell(x, e=e):
            return f"{x[0]:.3f} ({x[0] / e[0]:.2f}x) / {x[1]:.3f}"
        lines.append(f"| {n}² | {e[0]:.3f} / {e[1]:.3f} | {cell(i)} | {cell(c)} | {cell(b)} | "
                     f"{bu[0]:.0f} / {bu[1]:.0f} ({k[0]}; call {k[1]}) | {p[0]:.2f} ({p[0] / e[0]:.1f}x) / "
                     f"{p[1]:.2f} |")
    return lines


def main(argv: list[str] | None = None) -> str:
    """Command-line entry point; returns the Markdown text."""
    ap = argparse.ArgumentParser()
    ap.add_argument("--sizes", type=int, nargs="+", default=[48, 64, 128, 256])
    ap.add_argument("--dtype", nargs="+", default=["float32", "float64"], choices=["float32", "float64"])
    ap.add_argument("--write", action="store_true", help="save the tables to benchmarks/results/viscosity.md")
    ap.add_argument("--stat", choices=["min", "median"], default="min", help="statistic of the repeats")
    ap.add_argument("--device", default="cpu", help="torch device, e.g. cuda (timings synchronise it)")
    args = ap.parse_args(argv)
    global STAT, DEVICE
    STAT = args.stat
    DEVICE = check_device(args.device)
    torch.set_num_threads(1)
    lines = []
    with fft.fft_settings(planner_effort="FFTW_MEASURE"):
        for name in args.dtype:
            lines += table(args.sizes, getattr(torch, name)) + [""]
        lines += bench_steps(args.sizes, torch.float32)
        lines += bench_body_steps(args.sizes, torch.float32)
    text = "\n".join(lines) + "\n\n" + NOTES + "\n"
    if DEVICE.type != "cpu":
        text = f"Device: {DEVICE}.\n\n" + text
    print(text)
    if args.write:
        path = os.path.join(os.path.dirname(os.path.abspath(__file__)), "results", "viscosity.md")
        os.makedirs(os.path.dirname(path), exist_ok=True)
        stamp = time.strftime("%Y-%m-%dT%H:%M:%S")
        with open(path, "w") as fh:
            fh.write(f"Made by `OMP_NUM_THREADS=1 python benchmarks/bench_viscosity.py --write` ({stamp}, "
                     f"{platform.machine()}, {os.cpu_count()} cores).\n\n" + text)
    return text


def bench_steps(sizes, dtype) -> list[str]:
    """Whole steps: split (explicit / implicit viscosity), rk2, imex2 (a Markdown table, one line per size)."""
    lines = ["", "Whole Navier-Stokes steps (walls, ν = 0.01, dt = 0.5 dx), ms per step; `nan`: the explicit "
             "viscosity of that scheme is unstable at this dt:", "",
             "| n² | split, explicit visc. | split, implicit visc. | rk2 | imex2 |", "|---|---|---|---|---|"]
    for n in sizes:
        grid = Grid((n, n), bounds=[(0, 1), (0, 1)])
        g = torch.Generator().manual_seed(0)
        v = StaggeredGrid(tuple(0.1 * torch.randn(1, *grid.face_shape(i), generator=g, dtype=torch.float64).to(
            dtype=dtype, device=DEVICE) for i in range(2)), grid, "wall").with_boundary_faces()
        dt = 0.5 / n
        row = []
        for kw in ({"viscosity_scheme": "explicit"}, {"viscosity_scheme": "implicit"}, {"integrator": "rk2"},
                   {"integrator": "imex2"}):
            try:
                row.append(bench(lambda kw=kw, v=v, dt=dt: navier_stokes_step(
                    v, dt, viscosity=0.01, advection="maccormack", **kw), repeat=10)[0])
            except Exception:  # noqa: BLE001 - e.g. an explicit scheme beyond its limit
                row.append(float("nan"))
        lines.append(f"| {n}² | " + " | ".join(f"{t:.2f}" for t in row) + " |")
    return lines


def bench_body_steps(sizes, dtype, repeat: int = 10) -> list[str]:
    """Whole steps with a disc body (split with implicit viscosity, imex2): ms per step and the part spent in
    the viscosity solves (a Markdown table). The first calls build the body's capacitance matrices and
    projection operators; the timed calls repeat the same step."""
    lines = ["", "Whole Navier-Stokes steps with a disc body (radius 0.2, walls, ν = 0.01, dt = 0.5 dx, MacCormack), "
             f"ms per step, {STAT} of {repeat} after 12 warm-up steps; in brackets the viscosity solves' part:", "",
             "| n² | split, implicit visc. | imex2 |", "|---|---|---|"]
    real = _mac_diffusion.diffuse_staggered
    spent = [0.0]

    def timed(*args, **kwargs):
        t = time.perf_counter()
        try:
            return real(*args, **kwargs)
        finally:
            spent[0] += time.perf_counter() - t

    body = Body(Sphere((0.5, 0.5), 0.2))
    _mac_diffusion.diffuse_staggered = timed
    try:
        for n in sizes:
            grid = Grid((n, n), bounds=[(0, 1), (0, 1)])
            g = torch.Generator().manual_seed(0)
            v = StaggeredGrid(tuple(0.1 * torch.randn(1, *grid.face_shape(i), generator=g, dtype=torch.float64).to(
                dtype=dtype, device=DEVICE) for i in range(2)), grid, "wall").with_boundary_faces()
            row = []
            for kw in ({"viscosity_scheme": "implicit"}, {"integrator": "imex2"}):
                stepper = FluidStepper(grid, v.boundary, obstacles=[body], viscosity=0.01, advection="maccormack",
                                       dt=0.5 / n, dtype=dtype, device=DEVICE, **kw)

                def step(stepper=stepper, v=v):
                    return stepper(FluidState(v))
                for _ in range(12):
                    step()
                samples = []
                for _ in range(repeat):
                    spent[0] = 0.0
                    synchronize(DEVICE)
                    t = time.perf_counter()
                    step()
                    synchronize(DEVICE)
                    samples.append((time.perf_counter() - t, spent[0]))
                total, visc = min(samples) if STAT == "min" else sorted(samples)[len(samples) // 2]
                row.append(f"{1e3 * total:.2f} ({1e3 * visc:.2f}, {100 * visc / total:.0f} %)")
            lines.append(f"| {n}² | " + " | ".join(row) + " |")
    finally:
        _mac_diffusion.diffuse_staggered = real
    return lines


if __name__ == "__main__":
    main()
