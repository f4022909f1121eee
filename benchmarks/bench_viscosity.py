"""Cost of one viscosity step of a MAC velocity: explicit vs implicit (median of repeats, ms), Markdown table.

Run: ``OMP_NUM_THREADS=1 python benchmarks/bench_viscosity.py [--dtype float32] [--sizes 48 64 128 256]``.

Cases per resolution (2-D closed box with no-slip walls, batch 1, ``ν dt / dx² = 2``, far beyond the
explicit limit; the explicit step is timed at its own stable size, the cost per call does not depend on dt):

* ``explicit``: forward Euler ``u + ν dt ∇²u`` (one stencil per component), the reference the issue sets:
  an implicit step should cost at most twice as much;
* ``implicit (spectral)``: :func:`phisim.diffusion.diffuse_staggered`, backward Euler solved exactly by
  one DST-I/DST-II transform pair per component;
* ``crank_nicolson``: the same with the explicit half step (one extra stencil);
* ``implicit, body (PCG)``: backward Euler with the faces of a disc body fixed, CG preconditioned by the
  exact box solve;
* ``implicit, old CG``: the unpreconditioned CG of the fluid module before this change (for the record).
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch

from phisim import Grid, StaggeredGrid, fft
from phisim.diffusion import diffuse_staggered
from phisim.linalg import Solve


def bench(fn, repeat: int = 30, min_total: float = 0.3) -> float:
    fn()
    fn()
    times = []
    total = 0.0
    while len(times) < repeat or total < min_total:
        t = time.perf_counter()
        fn()
        dt = time.perf_counter() - t
        times.append(dt)
        total += dt
        if len(times) > 2000:
            break
    return 1e3 * statistics.median(times)


def _old_cg(v, alpha, solve):
    try:
        from phisim.fluid import _implicit_diffusion
    except ImportError:  # the fluid package may have moved it
        return None
    return lambda: _implicit_diffusion(v, alpha, solve)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--sizes", type=int, nargs="+", default=[48, 64, 128, 256])
    ap.add_argument("--dtype", default="float32", choices=["float32", "float64"])
    args = ap.parse_args()
    torch.set_num_threads(1)
    dtype = getattr(torch, args.dtype)
    rows = []
    with fft.fft_settings(planner_effort="FFTW_MEASURE"):
        for n in args.sizes:
            grid = Grid((n, n), bounds=[(0, 1), (0, 1)])
            g = torch.Generator().manual_seed(0)
            v = StaggeredGrid(tuple(torch.randn(1, *grid.face_shape(i), generator=g, dtype=torch.float64).to(dtype)
                                    for i in range(2)), grid, "wall").with_boundary_faces()
            dx = grid.dx[0]
            nu = 1.0
            dt = 2 * dx**2
            dt_explicit = 0.2 * dx**2
            x = grid.cell_centers(torch.float64)
            solid = ((x - 0.5) ** 2).sum(-1) <= 0.2**2
            masks = []
            for i in range(2):
                f = torch.nn.functional.pad(solid.to(torch.float64)[None, None], (1, 1, 1, 1) if i else (1, 1, 1, 1),
                                            mode="replicate")[0, 0]
                m = f.narrow(i, 0, n + 1).narrow(1 - i, 1, n) + f.narrow(i, 1, n + 1).narrow(1 - i, 1, n)
                masks.append(m > 0)
            solve = Solve(rtol=1e-6 if dtype == torch.float32 else 1e-8)
            explicit = bench(lambda: diffuse_staggered(v, dt_explicit, viscosity=nu, method="explicit"))
            implicit = bench(lambda: diffuse_staggered(v, dt, viscosity=nu, method="implicit"))
            cn = bench(lambda: diffuse_staggered(v, dt, viscosity=nu, method="crank_nicolson"))
            body = bench(lambda: diffuse_staggered(v, dt, viscosity=nu, method="implicit", fixed=masks,
                                                   solve=solve), repeat=10)
            old = _old_cg(v, nu * dt, solve)
            old_ms = bench(old, repeat=5) if old is not None else float("nan")
            rows.append((n, explicit, implicit, cn, body, old_ms))
    print(f"dtype {args.dtype}, batch 1, walls, ν dt/dx² = 2, 1 thread; times in ms (ratio to explicit)\n")
    print("| n² | explicit | implicit (spectral) | crank_nicolson | implicit, body (PCG) | implicit, old CG |")
    print("|---|---|---|---|---|---|")
    for n, e, i, c, b, o in rows:
        print(f"| {n}² | {e:.3f} | {i:.3f} ({i / e:.2f}x) | {c:.3f} ({c / e:.2f}x) | {b:.2f} ({b / e:.1f}x) | "
              f"{o:.2f} ({o / e:.1f}x) |")


if __name__ == "__main__":
    main()
