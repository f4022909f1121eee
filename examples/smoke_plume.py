"""A buoyant smoke plume rising around an obstacle in a closed box (2-D, or 3-D with ``--dim 3``).

Physics (:func:`phisim.fluid.step`, one call per frame):

* smoke density ``rho`` is transported by the MAC velocity with the conservative finite-volume scheme
  (``--marker-advection``, default ``conservative``: the smoke in the box is exactly what the inflow disc
  near the floor has put in, and never negative; MacCormack, the former default, lost 3 % in 50 steps)
  and fed by that inflow;
* the velocity is self-advected (MacCormack), accelerated upwards by Boussinesq buoyancy
  ``dt * buoyancy * rho`` on the vertical faces, diffused (``--viscosity-scheme``, default implicit: an
  exact spectral solve, as cheap as the explicit step and stable at any dt) and projected to be
  divergence-free with no flow through the walls (no-slip box) or the obstacle (a sphere above the inflow);
  this operator-split step is first order in time. ``--integrator imex2`` selects the second-order
  integrator (central convection): accurate where the flow is resolved (cell Reynolds number
  ``|u| dx / viscosity`` of a few), but a smoke plume at ``viscosity = 0.01`` and ``dx = 1`` is far from
  that, and the split step's MacCormack advection is the robust choice there;
* frames are written at fixed times ``k * --interval`` (The Well's constant output interval); between two
  frames the simulation sub-steps with the CFL time step of the current velocity (``--cfl``, at most
  ``--dt``), each interval split into equal sub-steps so the last one lands exactly on the frame time.

Outputs (in ``--out``):

* ``smoke_plume.h5``: the run in The Well layout (:class:`phisim.io.SimulationWriter`): ``density`` in
  ``/t0_fields`` ``(B, T, *res)``, the velocity at cell centres in ``/t1_fields`` and its exact face values
  in ``/staggered``, one frame per output interval (stored as the scalar ``dt``), written as the
  simulation goes; the obstacle as the constant field ``obstacle_mask`` (1 in solid cells);
* ``smoke_plume.gif``: an animation of the density with the time of each frame and the obstacle in grey
  (the middle ``z`` slice in 3-D);
* ``smoke_plume.png``: the last frame (density and velocity magnitude, obstacle in grey).

Run:  python examples/smoke_plume.py --resolution 64 --steps 100 --out out/smoke
      python examples/smoke_plume.py --dim 3 --resolution 24 --steps 30 --out out/smoke3d
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import time
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import torch  # noqa: E402
from tqdm import tqdm  # noqa: E402

from phisim.boundary import Boundary  # noqa: E402
from phisim.checks import check_device  # noqa: E402
from phisim.field import CenteredGrid, StaggeredGrid  # noqa: E402
from phisim.fluid import (  # noqa: E402
    INTEGRATORS,
    VISCOSITY_SCHEMES,
    FluidState,
    Obstacle,
    cfl_dt,
    obstacle_mask,
    relative_divergence,
    step,
)
from phisim.grid import Grid  # noqa: E402
from phisim.io import SimulationWriter  # noqa: E402
from phisim.ops.advection import SCALAR_SCHEMES  # noqa: E402
from phisim.viz.plot import animate, new_figure, plot_field, save_figure  # noqa: E402

DTYPES = {"float32": torch.float32, "float64": torch.float64}


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    """Command-line options (see ``--help``)."""
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--dim", type=int, choices=(2, 3), default=2, help="2-D or 3-D")
    p.add_argument("--resolution", type=int, default=64, help="cells along x (and z); y gets 1.5x as many")
    p.add_argument("--steps", type=int, default=100, help="number of output intervals (frames after t = 0)")
    p.add_argument("--interval", type=float, default=1.0, help="time between written frames")
    p.add_argument("--dt", type=float, default=None,
                   help="largest sub-step (default: the interval; the CFL step may be smaller)")
    p.add_argument("--cfl", type=float, default=1.0, help="Courant number of the adaptive time step")
    p.add_argument("--buoyancy", type=float, default=0.5, help="buoyancy per unit density")
    p.add_argument("--viscosity", type=float, default=0.01, help="kinematic viscosity")
    p.add_argument("--viscosity-scheme", choices=VISCOSITY_SCHEMES, default="implicit",
                   help="viscosity of the split step")
    p.add_argument("--integrator", choices=tuple(INTEGRATORS), default="split", help="time integrator")
    p.add_argument("--marker-advection", choices=SCALAR_SCHEMES, default="conservative",
                   help="transport of the smoke density")
    p.add_argument(
        "--batch-size", type=int, default=1, help="independent plumes (inflows at shifted positions)"
    )
    p.add_argument("--out", type=Path, default=Path("out/smoke_plume"), help="output folder")
    p.add_argument("--dtype", choices=sorted(DTYPES), default="float32")
    p.add_argument("--device", default="cpu", help="torch device, e.g. cpu or cuda")
    p.add_argument("--fps", type=int, default=10, help="frames per second of the animation")
    p.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    args = p.parse_args(argv)
    if args.resolution < 8:
        p.error("--resolution must be >= 8")
    if args.steps < 1:
        p.error("--steps must be >= 1")
    if not args.interval > 0:
        p.error("--interval must be > 0")
    if args.dt is None:
        args.dt = args.interval
    if not args.dt > 0:
        p.error("--dt must be > 0")
    return args


def advance(state: FluidState, t_end: float, max_dt: float, cfl: float, **step_kwargs) -> tuple[FluidState, int]:
    """Sub-step ``state`` to exactly ``t_end`` with CFL-limited steps; returns the state and the sub-step count.

    The remaining time is split into ``ceil(remaining / cfl_dt)`` equal sub-steps, re-evaluated after every
    sub-step from the current velocity, so no sub-step exceeds the CFL limit and the last one ends on
    ``t_end`` (the state's time is then set to ``t_end`` exactly, removing round-off of the sum).
    """
    n = 0
    while t_end - state.time > 1e-12 * max(1.0, abs(t_end)):
        remaining = t_end - state.time
        limit = cfl_dt(state.velocity, cfl, max_dt=max_dt)
        dt = remaining / math.ceil(remaining / limit * (1 - 1e-12))
        state = step(state, dt, **step_kwargs)
        n += 1
    return dataclasses.replace(state, time=t_end), n


def setup(args: argparse.Namespace):
    """Grid, boundary, obstacle, inflow and initial state of the plume.

    The box is ``resolution`` units wide (``dx = 1``) and 1.5x as tall along ``y`` (the up axis in 2-D and
    3-D). The inflow is a disc of radius ``0.08 * width`` at height ``0.1 * height``; the obstacle a sphere
    of radius ``0.1 * width`` at height ``0.45 * height``, shifted sideways so the plume splits unevenly.
    """
    n = args.resolution
    dtype, device = DTYPES[args.dtype], check_device(args.device)
    if args.dim == 2:
        res = (n, int(1.5 * n))
    else:
        res = (n, int(1.5 * n), n)
    grid = Grid(res)
    walls = Boundary.create("wall", args.dim)
    width, height = grid.size[0], grid.size[1]
    centre = [0.5 * s for s in grid.size]
    obstacle_centre = list(centre)
    obstacle_centre[0] += 0.05 * width
    obstacle_centre[1] = 0.45 * height
    obstacle = Obstacle.sphere(obstacle_centre, 0.1 * width)
    x = grid.cell_centers(dtype, device)
    sources = []
    for b in range(args.batch_size):
        c = torch.tensor(centre, dtype=dtype, device=device)
        c[1] = 0.1 * height
        c[0] += (b - (args.batch_size - 1) / 2) * 0.1 * width
        sources.append((((x - c) ** 2).sum(-1) <= (0.08 * width) ** 2).to(dtype))
    source = torch.stack(sources)
    marker = CenteredGrid.zeros(grid, walls.for_scalar(), args.batch_size, dtype=dtype, device=device)
    velocity = StaggeredGrid.zeros(grid, walls, args.batch_size, dtype=dtype, device=device)
    return grid, walls, obstacle, source, FluidState(velocity, marker)


def _display_slice(values: torch.Tensor) -> torch.Tensor:
    """The first sample of a ``(B, *res)`` array; the middle ``z`` slice in 3-D."""
    v = values[0]
    return v[..., v.shape[-1] // 2] if v.ndim == 3 else v


def main(argv: list[str] | None = None) -> dict:
    """Run the plume; returns a summary (paths, steps, simulated time, timings, divergence).

    Args:
        argv: Command-line arguments (default ``sys.argv[1:]``).

    Returns:
        ``{'h5': Path, 'gif': Path, 'png': Path, 'steps': int (frames after t = 0), 'substeps': int,
        'interval': float, 'time': float, 'seconds_per_step': float (per sub-step),
        'max_relative_divergence': float, 'smoke': [float], 'injected': [float]}`` (per sample, total
        smoke in the box and the amount the inflow has put in, in cell units).
    """
    args = parse_args(argv)
    torch.set_num_threads(max(1, torch.get_num_threads()))
    grid, walls, obstacle, source, state = setup(args)
    solid = obstacle_mask([obstacle], grid)
    solid = torch.zeros(grid.resolution, dtype=torch.bool) if solid is None else solid.reshape(grid.resolution)
    args.out.mkdir(parents=True, exist_ok=True)
    h5_path = args.out / "smoke_plume.h5"
    config = {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()}
    frames = [_display_slice(state.marker.values).cpu()]
    times = [0.0]
    worst_div = 0.0
    substeps = 0
    injected = torch.zeros(args.batch_size, dtype=torch.float64, device=source.device)
    t_start = time.perf_counter()
    with SimulationWriter(
        h5_path,
        grid,
        walls,
        dataset_name="smoke_plume",
        fields={"density": "scalar", "velocity": "staggered"},
        parameters={
            "buoyancy": args.buoyancy,
            "viscosity": args.viscosity,
            "cfl": args.cfl,
            "max_dt": args.dt,
        },
        batch_size=args.batch_size,
        config=config,
        output_interval=args.interval,
        constant_fields={"obstacle_mask": solid.cpu().to(torch.float32)},
    ) as writer:
        writer.append(0.0, density=state.marker, velocity=state.velocity)
        bar = tqdm(
            range(1, args.steps + 1),
            desc=f"smoke {args.dim}-D {'x'.join(map(str, grid.resolution))}",
            disable=args.no_progress,
            unit="frame",
        )
        for k in bar:
            t_frame = k * args.interval
            state, n = advance(
                state,
                t_frame,
                args.dt,
                args.cfl,
                viscosity=args.viscosity,
                buoyancy_strength=args.buoyancy,
                marker_source=source,
                obstacles=obstacle,
                advection="maccormack",
                viscosity_scheme=args.viscosity_scheme,
                integrator=args.integrator,
                marker_advection=args.marker_advection,
            )
            substeps += n
            injected = injected + args.interval * source.sum(tuple(range(1, source.ndim))).double()
            div = float(relative_divergence(state.velocity).max())
            if not math.isfinite(div) or not bool(torch.isfinite(state.marker.values).all()):
                raise FloatingPointError(f"the simulation became non-finite at t = {state.time:.3g}")
            worst_div = max(worst_div, div)
            writer.append(t_frame, density=state.marker, velocity=state.velocity)
            frames.append(_display_slice(state.marker.values).cpu())
            times.append(t_frame)
            bar.set_postfix(t=f"{state.time:.2f}", substeps=n, div=f"{div:.1e}")
    seconds = (time.perf_counter() - t_start) / max(substeps, 1)
    display_solid = _display_slice(solid[None])

    display_grid = Grid(grid.resolution[:2], bounds=grid.bounds[:2])
    gif_path = animate(
        [f.float().numpy() for f in frames],
        args.out / "smoke_plume.gif",
        fps=args.fps,
        grid=display_grid,
        title="smoke density, t = {time:.2f}",
        vmin=0.0,
        times=times,
        mask=display_solid,
    )
    fig, axes = new_figure((9.0, 4.5))
    fig.clf()
    ax_density, ax_speed = fig.subplots(1, 2)
    plot_field(
        frames[-1].float().numpy(),
        ax_density,
        grid=display_grid,
        title=f"density, t = {state.time:.2f}",
        vmin=0.0,
        mask=display_solid,
    )
    speed = state.velocity.at_centers().values.norm(dim=1)
    plot_field(
        _display_slice(speed).detach().cpu().float().numpy(),
        ax_speed,
        grid=display_grid,
        title="|velocity|",
        cmap="magma",
        mask=display_solid,
    )
    png_path = save_figure(fig, args.out / "smoke_plume.png")
    print(
        f"{args.steps} frames ({substeps} sub-steps) to t = {state.time:.3f}: {1e3 * seconds:.1f} ms/sub-step, "
        f"max relative divergence {worst_div:.2e}; wrote {h5_path}, {gif_path}, {png_path}"
    )
    return {
        "h5": h5_path,
        "gif": gif_path,
        "png": png_path,
        "steps": args.steps,
        "substeps": substeps,
        "interval": args.interval,
        "time": state.time,
        "seconds_per_step": seconds,
        "max_relative_divergence": worst_div,
        "smoke": state.marker.values.double().sum(tuple(range(1, grid.rank + 1))).tolist(),
        "injected": injected.tolist(),
    }


if __name__ == "__main__":
    main()
