"""The main job: simulate a smoke plume, train a U-net with physical gradients, write HDF5 and plots.

1. A buoyant smoke plume in a closed 2-D box with a round obstacle (MAC grid, MacCormack advection,
   pressure projection), two trajectories (inflows at two positions) run as one batch. Frames are
   written every ``dt`` (a constant output interval) in The Well's dataset layout, which its loader opens
   as it is::

       <out>/data/train/smoke.h5    trajectory 0 (the training split)
       <out>/data/valid/smoke.h5    trajectory 1 (the validation split)
       <out>/stats.yaml             normalisation statistics of the training split

   Each file stores the obstacle as the constant field ``obstacle_mask`` (1 in solid cells; the name the
   ``smoke`` scenario of ``phisim simulate`` uses too). Pictures:
   ``smoke.gif`` (every frame, titled with its time) and ``smoke_last.png``, both with the obstacle in grey.
2. The Poisson inverse problem (E3) at reduced size: a U-net learns ``y -> x`` for ``y = ∇⁻² x``,
   once with Adam through the CG solve and once with Adam + physical gradients (analytic inverse), on
   the same data stream. Curves (training batch and a fixed held-out set) go to
   ``training/training.h5`` and ``training.png``.

Load the simulation with The Well's loader::

    from the_well.data import WellDataset
    from the_well.data.normalization import ZScoreNormalization
    ds = WellDataset(path="out/demo", well_split_name="train", use_normalization=True,
                     normalization_type=ZScoreNormalization)

Run: ``python examples/demo.py [--out out/demo] [--steps 40] [--iterations 60]``.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import torch

from inverse.cli_checks import json_summary
from inverse.problems import get_problem
from inverse.train import train
from phisim import CenteredGrid, Grid, StaggeredGrid, divergence
from phisim.fluid import FluidState, Obstacle, obstacle_mask, step
from phisim.io import SimulationWriter
from phisim.io.stats import write_statistics
from phisim.viz.plot import animate, plot_field, plot_training_curves, save_figure

SPLITS = ("train", "valid")


def simulate_smoke(out: Path, resolution: int, steps: int, dt: float = 0.5) -> dict:
    """Run two plumes; write ``data/{train,valid}/smoke.h5``, ``stats.yaml``, ``smoke.gif``, ``smoke_last.png``."""
    grid = Grid((resolution, resolution), bounds=[(0, 64), (0, 64)])
    boundary = "wall"
    obstacle = Obstacle.sphere((32.0, 36.0), 6.0)
    solid = obstacle_mask([obstacle], grid)
    solid = torch.zeros(grid.resolution, dtype=torch.bool) if solid is None else solid.reshape(grid.resolution)
    centres = (27.0, 37.0)  # inflow x of trajectory 0 (train) and 1 (valid)
    x = grid.cell_centers()
    inflow = torch.stack([((x[..., 0] - c) ** 2 + (x[..., 1] - 8) ** 2 < 25).to(x.dtype) for c in centres])
    batch = len(centres)
    state = FluidState(StaggeredGrid.zeros(grid, boundary, batch), CenteredGrid.zeros(grid, "neumann", batch))
    params = {"buoyancy": 0.1, "viscosity": 0.0}
    writers = {
        split: SimulationWriter(out / "data" / split / "smoke.h5", grid, boundary, dataset_name="phisim_smoke_plume",
                                fields={"density": "scalar", "velocity": "staggered"}, parameters=params,
                                batch_size=1, output_interval=dt, constant_fields={"obstacle_mask": solid},
                                config={"resolution": resolution, "steps": steps, "split": split,
                                        "inflow_x": centres[b]})
        for b, split in enumerate(SPLITS)
    }
    frames, times = [state.marker.values[0]], [0.0]

    def write(t: float) -> None:
        for b, split in enumerate(SPLITS):
            faces = tuple(c[b:b + 1] for c in state.velocity.values)
            writers[split].append(t, density=state.marker.values[b:b + 1], velocity=faces)

    try:
        write(0.0)
        for k in range(1, steps + 1):
            # conservative smoke transport: the smoke mass is exactly what the inflow added
            state = step(state, dt, buoyancy_strength=params["buoyancy"], marker_source=inflow,
                         obstacles=[obstacle], advection="maccormack", marker_advection="conservative")
            write(k * dt)  # fixed frame times: the constant output interval dt
            frames.append(state.marker.values[0])
            times.append(k * dt)
    finally:
        for w in writers.values():
            w.close()
    stats_path = write_statistics(out)
    animate(frames, out / "smoke.gif", fps=10, grid=grid, title="smoke density (train), t = {time:g}",
            times=times, mask=solid, vmin=0.0)
    ax = plot_field(state.marker, title=f"smoke density (train), t = {steps * dt:g}", mask=solid)
    save_figure(ax.figure, out / "smoke_last.png")
    div = divergence(state.velocity).values[:, ~solid]
    return {"frames": steps + 1, "dt": dt, "final_time": steps * dt, "max_divergence": float(div.abs().max()),
            "smoke_mass": float(state.marker.values[0].sum() * grid.cell_volume),
            "smoke_added": float(inflow[0].sum() * grid.cell_volume * dt * steps),
            "files": [str(writers[s].path) for s in SPLITS], "stats": str(stats_path)}


def train_poisson(out: Path, resolution: int, iterations: int, batch_size: int, heldout: int) -> dict:
    """Adam vs physical gradients on the Poisson problem; write ``training/training.h5`` and ``training.png``."""
    problem = get_problem("poisson", resolution=(resolution, resolution), heldout_size=heldout)
    results = {}
    for method in ("adam", "pg"):
        # the demo rewrites its own output folder on every run: replace earlier runs of the same method
        results[method] = train(problem, method, iterations=iterations, batch_size=batch_size, seed=0,
                                out=out / "training" / "training.h5", overwrite=True)  # a bar in a terminal
    ax = plot_training_curves({m: r.curves for m, r in results.items()}, problem.metric_name,
                              title="Poisson inverse problem")
    save_figure(ax.figure, out / "training.png")
    return {m: {"metric": problem.metric_name,
                "train_batch_metric_last10": r.final("metric"),
                "heldout_metric": r.final_eval("metric"),
                "heldout_samples": problem.heldout_size,
                "seconds": round(r.seconds, 2)} for m, r in results.items()}


def main(argv: list[str] | None = None) -> dict:
    """Run the demo; returns a summary dict (also written to ``summary.json``)."""
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0],
                                formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("--out", type=Path, default=Path("out/demo"), help="output folder")
    p.add_argument("--resolution", type=int, default=48, help="smoke grid cells per axis")
    p.add_argument("--steps", type=int, default=40, help="smoke time steps (one frame each, dt = 0.5)")
    p.add_argument("--train-resolution", type=int, default=32, help="Poisson grid cells per axis")
    p.add_argument("--iterations", type=int, default=60, help="training iterations per method")
    p.add_argument("--batch-size", type=int, default=16, help="training samples per iteration")
    p.add_argument("--heldout", type=int, default=64, help="held-out samples of the Poisson problem")
    args = p.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    torch.set_num_threads(min(2, torch.get_num_threads()))
    t0 = time.perf_counter()
    summary = {"smoke": simulate_smoke(args.out, args.resolution, args.steps)}
    summary["training"] = train_poisson(args.out, args.train_resolution, args.iterations, args.batch_size,
                                        args.heldout)
    summary["seconds"] = round(time.perf_counter() - t0, 1)
    text = json_summary(summary, indent=2)  # strict JSON: a NaN is written as null (and the summary says so)
    (args.out / "summary.json").write_text(text + "\n")
    print(text)
    print(f"outputs in {args.out}/: data/train/smoke.h5 data/valid/smoke.h5 stats.yaml smoke.gif smoke_last.png "
          "training/training.h5 training.png summary.json")
    return summary


if __name__ == "__main__":
    main()
