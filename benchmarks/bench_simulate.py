"""Throughput of ``phisim simulate`` (trajectories per second with 1 and N worker processes), and the
fixed cost of one smoke step (``--step-cost``).

Run: ``python benchmarks/bench_simulate.py [--scenario smoke] [--workers 2] [--trajectories 8]``.
Each configuration writes a fresh dataset folder in a temporary directory (simulation, HDF5 writing and
the statistics file included) and reports the wall time; the JSON line goes to stdout and, with
``--out``, to a file. The speed-up is bounded by the free cores of the machine (each worker gets
``cpu_count // workers`` torch threads).

``--step-cost`` times :func:`phisim.fluid.step` on small grids, where the per-step cost is almost all
fixed (Python, dispatch, validation): MacCormack marker and velocity, buoyancy, the spectral projection
of a closed box, batch 1, one thread. Per size it reports the CPU time of the process
(``time.process_time``) and the wall time per step (lowest of ``--rounds`` rounds of ``--calls``
steps), the same for each phase called on its own through its public function (marker advection,
velocity self-advection, buoyancy, projection), and over the 2-D sizes the least-squares intercept of
time against cell count (the fixed cost). ``--markdown`` prints the table for ``docs/BENCHMARKS.md``.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import tempfile
import time
from pathlib import Path

from phisim.checks import check_device
from phisim.simulate import resolve_config, simulate_dataset


def measure(scenario: str, workers: int, trajectories: int, resolution: int, steps: int, device: str = "cpu"
            ) -> float:
    """Wall seconds of one dataset with ``trajectories`` trajectories, one per file."""
    cfg = resolve_config(scenario, trajectories=trajectories, trajectories_per_file=1, resolution=resolution,
                         steps=steps, device=device)
    with tempfile.TemporaryDirectory() as tmp:
        t = time.perf_counter()
        simulate_dataset(Path(tmp) / "ds", cfg, workers=workers, progress=False)
        return time.perf_counter() - t


def _smoke_state(resolution: tuple[int, ...], dtype, device):
    """The smoke case of ``benchmarks/inputs.py`` (blob of smoke, random divergence-free-ish velocity, walls)."""
    import numpy as np
    import torch

    from phisim.field import CenteredGrid, StaggeredGrid
    from phisim.fluid import FluidState
    from phisim.grid import Grid

    sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
    import inputs

    init = inputs.smoke_initial(resolution, 1, dtype="float64")
    grid = Grid(resolution)
    v = StaggeredGrid([torch.as_tensor(np.asarray(c), dtype=dtype, device=device) for c in init["velocity"]], grid,
                      "wall")
    smoke = CenteredGrid(torch.as_tensor(init["smoke"], dtype=dtype, device=device), grid, v.boundary.for_scalar())
    return FluidState(v, smoke)


def _per_call(fn, steps: int, rounds: int, sync) -> tuple[float, float]:
    """Lowest (CPU, wall) seconds per call of ``fn`` over ``rounds`` rounds of ``steps`` calls (2 warm-up calls)."""
    fn()
    fn()
    sync()
    best_cpu = best_wall = math.inf
    for _ in range(rounds):
        c0, w0 = time.process_time(), time.perf_counter()
        for _ in range(steps):
            fn()
        sync()
        best_cpu = min(best_cpu, (time.process_time() - c0) / steps)
        best_wall = min(best_wall, (time.perf_counter() - w0) / steps)
    return best_cpu, best_wall


def _size_row(res: tuple[int, ...], steps: int, rounds: int, dtype: str, device: str) -> dict:
    """One row of :func:`step_cost`."""
    import torch

    from phisim.fluid import buoyancy, make_incompressible, step
    from phisim.ops.advection import advect

    state = _smoke_state(res, {"float32": torch.float32, "float64": torch.float64}[dtype], device)
    sync = torch.cuda.synchronize if str(device).startswith("cuda") else (lambda: None)
    box = [state]

    def run_step():
        box[0] = step(box[0], 0.5, buoyancy_strength=0.5, advection="maccormack")

    v, m = state.velocity, state.marker
    phases = {
        "step": run_step,
        "marker": lambda: advect(m, v, 0.5, scheme="maccormack"),
        "velocity": lambda: advect(v, v, 0.5, scheme="maccormack"),
        "buoyancy": lambda: buoyancy(v, m, 0.5, strength=0.5),
        "projection": lambda: make_incompressible(v),
    }
    row = {"resolution": "x".join(map(str, res)), "cells": math.prod(res), "dtype": dtype, "device": device,
           "steps": steps, "rounds": rounds}
    for name, fn in phases.items():
        cpu, wall = _per_call(fn, steps, rounds, sync)
        row[f"{name}_cpu_ms"] = round(cpu * 1e3, 4)
        row[f"{name}_wall_ms"] = round(wall * 1e3, 4)
    return row


def step_cost(sizes: list[tuple[int, ...]], steps: int, rounds: int, dtype: str, device: str) -> list[dict]:
    """Per-step CPU and wall time of ``phisim.fluid.step`` and of its phases, per grid size (see module doc)."""
    import torch

    torch.set_num_threads(1)
    rows = []
    for res in sizes:
        rows.append(_size_row(res, steps, rounds, dtype, device))
        print(json.dumps(rows[-1]), flush=True)
    return rows


def _intercept(rows: list[dict], key: str, rank: int = 2) -> float | None:
    """Least-squares intercept of ``key`` against the cell count over the ``rank``-D rows (the fixed cost)."""
    pts = [(r["cells"], r[key]) for r in rows if r["resolution"].count("x") == rank - 1]
    if len(pts) < 2:
        return None
    n = len(pts)
    mx = sum(p[0] for p in pts) / n
    my = sum(p[1] for p in pts) / n
    sxx = sum((p[0] - mx) ** 2 for p in pts)
    slope = sum((p[0] - mx) * (p[1] - my) for p in pts) / sxx
    return my - slope * mx


def _markdown(rows: list[dict]) -> str:
    head = ("| grid | step CPU | step wall | marker | velocity | buoyancy | projection | rest of the step |\n"
            "|---|---|---|---|---|---|---|---|\n")
    lines = []
    for r in rows:
        rest = r["step_cpu_ms"] - sum(r[f"{k}_cpu_ms"] for k in ("marker", "velocity", "buoyancy", "projection"))
        lines.append(f"| {r['resolution']} | {r['step_cpu_ms']:.3f} | {r['step_wall_ms']:.3f} | "
                     f"{r['marker_cpu_ms']:.3f} | {r['velocity_cpu_ms']:.3f} | {r['buoyancy_cpu_ms']:.3f} | "
                     f"{r['projection_cpu_ms']:.3f} | {rest:.3f} |")
    out = head + "\n".join(lines) + "\n"
    for rank in (2, 3):
        a, b = _intercept(rows, "step_cpu_ms", rank), _intercept(rows, "step_wall_ms", rank)
        if a is not None:
            out += f"\nFixed cost (intercept over the {rank}-D sizes): {a:.3f} ms CPU, {b:.3f} ms wall per step.\n"
    return out


def main(argv: list[str] | None = None) -> None:
    """Measure and print one JSON line per worker count (or per grid size with ``--step-cost``)."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--step-cost", action="store_true", help="time one smoke step on small grids instead")
    ap.add_argument("--sizes", type=int, nargs="+", default=[16, 32, 48, 64], help="2-D sizes (--step-cost)")
    ap.add_argument("--sizes3d", type=int, nargs="*", default=[16, 24], help="3-D sizes (--step-cost)")
    ap.add_argument("--rounds", type=int, default=5, help="rounds per size (--step-cost)")
    ap.add_argument("--calls", type=int, default=100, help="calls per round (--step-cost)")
    ap.add_argument("--dtype", default="float32", choices=("float32", "float64"))
    ap.add_argument("--device", default="cpu", help="torch device, e.g. cpu or cuda")
    ap.add_argument("--markdown", action="store_true", help="print a markdown table (--step-cost)")
    ap.add_argument("--scenario", default="smoke")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--trajectories", type=int, default=8)
    ap.add_argument("--resolution", type=int, default=32)
    ap.add_argument("--steps", type=int, default=40)
    ap.add_argument("--out", type=Path, default=None)
    a = ap.parse_args(argv)
    a.device = str(check_device(a.device))  # before any work or output
    if a.step_cost:
        sizes = [(n, n) for n in a.sizes] + [(n, n, n) for n in a.sizes3d]
        rows = step_cost(sizes, a.calls, a.rounds, a.dtype, a.device)
        if a.markdown:
            print(_markdown(rows))
        if a.out is not None:
            a.out.parent.mkdir(parents=True, exist_ok=True)
            a.out.write_text(json.dumps(rows, indent=1) + "\n")
        return
    rows = []
    for w in sorted({1, a.workers}):
        s = measure(a.scenario, w, a.trajectories, a.resolution, a.steps, a.device)
        rows.append({"scenario": a.scenario, "workers": w, "device": a.device, "trajectories": a.trajectories,
                     "resolution": a.resolution, "steps": a.steps, "seconds": round(s, 3),
                     "trajectories_per_s": round(a.trajectories / s, 3), "cpu_count": os.cpu_count()})
        print(json.dumps(rows[-1]), flush=True)
    if a.out is not None:
        a.out.write_text(json.dumps(rows, indent=1) + "\n")


if __name__ == "__main__":
    main()
