"""The main job: simulate a smoke plume, train a U-net with physical gradients, write HDF5 and plots.

1. A buoyant smoke plume in a closed 2-D box with a round obstacle (MAC grid, MacCormack advection,
   pressure projection), written frame by frame to ``smoke.h5`` (The Well layout), plus ``smoke.gif``
   and ``smoke_last.png``.
2. The Poisson inverse problem (E3) at reduced size: a U-net learns ``y -> x`` for ``y = ∇⁻² x``,
   once with Adam through the CG solve and once with Adam + physical gradients (analytic inverse), on
   the same data stream. Curves go to ``training.h5`` and ``training.png``.

Run: ``python examples/demo.py [--out out/demo] [--steps 40] [--iterations 60]``.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import torch

from inverse.problems import get_problem
from inverse.train import train
from phisim import CenteredGrid, Grid, StaggeredGrid
from phisim.fluid import FluidState, Obstacle, obstacle_mask, step
from phisim.io import SimulationWriter
from phisim.plot import animate, plot_curves, plot_field, save_figure


def simulate_smoke(out: Path, resolution: int, steps: int, dt: float = 0.5) -> dict:
    """Run the plume and write ``smoke.h5``, ``smoke.gif``, ``smoke_last.png``; return a summary."""
    grid = Grid((resolution, resolution), bounds=[(0, 64), (0, 64)])
    boundary = "wall"
    obstacle = Obstacle.sphere((32.0, 36.0), 6.0)
    solid = obstacle_mask([obstacle], grid)
    inflow = CenteredGrid.from_function(
        lambda x: ((x[..., 0] - 32) ** 2 + (x[..., 1] - 8) ** 2 < 25).to(x.dtype), grid, "neumann")
    state = FluidState(StaggeredGrid.zeros(grid, boundary), CenteredGrid.zeros(grid, "neumann"))
    frames = []
    params = {"dt": dt, "buoyancy": 0.1, "viscosity": 0.0}
    with SimulationWriter(out / "smoke.h5", grid, boundary, dataset_name="phisim_smoke_plume",
                          fields={"density": "scalar", "velocity": "staggered"}, parameters=params,
                          batch_size=1, config={"resolution": resolution, "steps": steps}) as writer:
        writer.append(0.0, density=state.marker, velocity=state.velocity)
        for _ in range(steps):
            # conservative smoke transport: the smoke mass is exactly what the inflow added
            state = step(state, dt, buoyancy_strength=params["buoyancy"], marker_source=inflow,
                         obstacles=[obstacle], advection="maccormack", marker_advection="conservative")
            writer.append(state.time, density=state.marker, velocity=state.velocity)
            frames.append(state.marker)
    animate(frames, out / "smoke.gif", fps=10)
    ax = plot_field(state.marker, title=f"smoke density, t = {state.time:g}")
    save_figure(ax.figure, out / "smoke_last.png")
    from phisim import divergence

    div = divergence(state.velocity).values[0][~solid[0] if solid.ndim == 3 else ~solid]
    return {"frames": steps + 1, "final_time": state.time, "max_divergence": float(div.abs().max()),
            "smoke_mass": float(state.marker.values.sum() * grid.cell_volume)}


def train_poisson(out: Path, resolution: int, iterations: int, batch_size: int) -> dict:
    """Adam vs physical gradients on the Poisson problem; write ``training.h5`` and ``training.png``."""
    problem = get_problem("poisson", resolution=(resolution, resolution))
    results = {}
    for method in ("adam", "pg"):
        r = train(problem, method, iterations=iterations, batch_size=batch_size, seed=0,
                  out=out / "training.h5", progress=True)
        results[method] = r
    ax = plot_curves({m: (r.curves["iteration"], r.curves["metric"]) for m, r in results.items()},
                     logy=True, title="Poisson inverse problem: x MAE per sample", ylabel="x MAE")
    save_figure(ax.figure, out / "training.png")
    return {m: {"final_x_mae": r.final("metric"), "seconds": round(r.seconds, 2)} for m, r in results.items()}


def main(argv: list[str] | None = None) -> dict:
    """Run the demo; returns a summary dict (also written to ``summary.json``)."""
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--out", type=Path, default=Path("out/demo"))
    p.add_argument("--resolution", type=int, default=48, help="smoke grid cells per axis")
    p.add_argument("--steps", type=int, default=40, help="smoke time steps")
    p.add_argument("--train-resolution", type=int, default=32)
    p.add_argument("--iterations", type=int, default=60, help="training iterations per method")
    p.add_argument("--batch-size", type=int, default=16)
    args = p.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    torch.set_num_threads(min(2, torch.get_num_threads()))
    t0 = time.perf_counter()
    summary = {"smoke": simulate_smoke(args.out, args.resolution, args.steps)}
    summary["training"] = train_poisson(args.out, args.train_resolution, args.iterations, args.batch_size)
    summary["seconds"] = round(time.perf_counter() - t0, 1)
    (args.out / "summary.json").write_text(json.dumps(summary, indent=2))
    print(json.dumps(summary, indent=2))
    print(f"outputs in {args.out}/: smoke.h5 smoke.gif smoke_last.png training.h5 training.png summary.json")
    return summary


if __name__ == "__main__":
    main()
