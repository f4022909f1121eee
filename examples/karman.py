"""A Kármán vortex street: flow past a cylinder in a channel (2-D), or past a sphere in a duct (``--dim 3``).

Set-up (the DFG benchmark geometry of Schäfer & Turek 1996, see ``examples/cylinder_benchmark.py``): channel
``[0, 2.2] x [0, 0.41]``, a no-slip cylinder of diameter 0.1 at ``(0.2, 0.2)`` (slightly below the centre
line, which starts the shedding), a parabolic inflow of peak speed ``--umax`` on the left
(:class:`phisim.boundary.Inflow`), an outflow on the right (:class:`phisim.boundary.Open`), no-slip walls.
The Reynolds number is ``Re = (2/3) umax D / viscosity`` (100 with the defaults). In 3-D the duct has a
square section ``0.41 x 0.41``, the body is a sphere of diameter 0.1, the inflow ``16 umax y z (H-y)(H-z)/H^4``.

The simulation sub-steps with a CFL time step shortened to land on the output times, so frames are written
at a constant interval ``--interval`` (The Well's promise).

Outputs (in ``--out``):

* ``karman.h5``: The Well layout: ``pressure`` and ``vorticity`` in ``/t0_fields``, the velocity at cell
  centres in ``/t1_fields`` (faces in ``/staggered``), the body's fluid fraction as the constant field
  ``/t0_fields/fluid_fraction``, the drag/lift history in ``/extras/forces``;
* ``karman.gif``: the vorticity with the body drawn;
* ``karman_forces.png``: drag and lift coefficients over time, the Strouhal number in the title.

Run:  python examples/karman.py                      (2-D, Re 100, about 10 min on 2 cores)
      python examples/karman.py --ny 24 --t-end 3    (a quick look)
      python examples/karman.py --dim 3 --ny 12 --t-end 0.5
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import numpy as np  # noqa: E402
import torch  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from phisim.boundary import Inflow, Open  # noqa: E402
from phisim.checks import check_device  # noqa: E402
from phisim.field import StaggeredGrid  # noqa: E402
from phisim.fluid import Body, FluidState, Sphere, body_forces, cfl_dt, solid_layout, step  # noqa: E402
from phisim.grid import Grid  # noqa: E402
from phisim.io import SimulationWriter  # noqa: E402
from phisim.ops.differential import curl  # noqa: E402
from phisim.viz.plot import new_figure, save_figure  # noqa: E402

H, LENGTH, D = 0.41, 2.2, 0.1


def parse_args(argv=None) -> argparse.Namespace:
    """Command-line options (see ``--help``)."""
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--dim", type=int, choices=(2, 3), default=2)
    p.add_argument("--ny", type=int, default=41, help="cells across the channel (dx = 0.41 / ny)")
    p.add_argument("--umax", type=float, default=1.5, help="peak inflow speed")
    p.add_argument("--viscosity", type=float, default=1e-3)
    p.add_argument("--t-end", type=float, default=8.0)
    p.add_argument("--interval", type=float, default=0.05, help="time between written frames")
    p.add_argument("--cfl", type=float, default=0.5)
    p.add_argument("--out", type=Path, default=Path("out/karman"))
    p.add_argument("--dtype", choices=("float32", "float64"), default="float64")
    p.add_argument("--device", default="cpu", help="torch device: cpu, cuda or cuda:N (default cpu)")
    p.add_argument("--threads", type=int, default=1, help="torch CPU threads (1 is fastest at these sizes)")
    args = p.parse_args(argv)
    if args.ny < 8 or args.t_end <= 0 or args.interval <= 0:
        p.error("--ny must be >= 8 and --t-end, --interval > 0")
    return args


def setup(args):
    """Grid, boundary, body, initial state and the mean inflow speed."""
    dtype, device = getattr(torch, args.dtype), check_device(args.device)
    dx = H / args.ny
    nx = int(round(LENGTH / dx))
    um = args.umax
    if args.dim == 2:
        grid = Grid((nx, args.ny), bounds=[(0, nx * dx), (0, H)])

        def profile(x):
            y = x[..., 1]
            return torch.stack([4 * um * y * (H - y) / H**2, torch.zeros_like(y)], -1)

        body = Body(Sphere((0.2, 0.2), D / 2), name="cylinder")
        umean = 2 * um / 3
        spec = {"x": (Inflow(profile), Open()), "y": "wall"}
    else:
        grid = Grid((nx, args.ny, args.ny), bounds=[(0, nx * dx), (0, H), (0, H)])

        def profile(x):
            y, z = x[..., 1], x[..., 2]
            u = 16 * um * y * z * (H - y) * (H - z) / H**4
            return torch.stack([u, torch.zeros_like(u), torch.zeros_like(u)], -1)

        body = Body(Sphere((0.2, 0.2, 0.2), D / 2), name="sphere")
        umean = 4 * um / 9
        spec = {"x": (Inflow(profile), Open()), "y": "wall", "z": "wall"}
    v = StaggeredGrid.from_function(profile, grid, spec, dtype=dtype, device=device)
    return grid, body, FluidState(v), umean


def _vorticity(v: StaggeredGrid) -> torch.Tensor:
    w = curl(v).values  # cell centres; 3-D: (B, 3, *res), keep the z component
    return w[:, 2] if v.rank == 3 else w


def strouhal(t: np.ndarray, cl: np.ndarray, umean: float) -> float:
    """``St = D f / U`` from the up-crossings of the lift about its mean (NaN with fewer than two)."""
    c = cl - cl.mean()
    up = np.nonzero((c[:-1] < 0) & (c[1:] >= 0))[0]
    tc = t[up] - c[up] * (t[up + 1] - t[up]) / (c[up + 1] - c[up])
    return D / float(np.mean(np.diff(tc))) / umean if len(tc) >= 2 else float("nan")


def main(argv=None) -> dict:
    """Run the simulation; returns a summary (paths, Strouhal number, force coefficients, timing)."""
    args = parse_args(argv)
    torch.set_num_threads(args.threads)
    grid, body, state, umean = setup(args)
    args.out.mkdir(parents=True, exist_ok=True)
    nu = args.viscosity
    lay = solid_layout(body, grid, state.velocity.boundary, 0.0, state.velocity.dtype, state.velocity.device)
    fraction = lay.cell_fraction[0]
    ref_len = D if args.dim == 2 else math.pi * D**2 / 4
    n_frames = int(round(args.t_end / args.interval))
    hist = []
    frames = []
    t0 = time.perf_counter()
    steps = 0
    h5 = args.out / "karman.h5"
    config = {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()}
    with SimulationWriter(h5, grid, state.velocity.boundary, dataset_name=f"karman_{args.dim}d",
                          fields={"pressure": "scalar", "vorticity": "scalar", "velocity": "staggered"},
                          parameters={"viscosity": nu, "umax": args.umax, "reynolds": umean * D / nu,
                                      "dt": args.interval},
                          batch_size=1, config=config) as writer:
        f = writer.file
        ds = f["t0_fields"].create_dataset("fluid_fraction", data=fraction.detach().cpu().numpy().astype(np.float32))
        ds.attrs.update({"sample_varying": False, "time_varying": False, "dim_varying": [True] * grid.rank})
        pressure = torch.zeros((1, *grid.resolution), dtype=state.velocity.dtype)
        writer.append(0.0, pressure=pressure, vorticity=_vorticity(state.velocity), velocity=state.velocity)
        for k in range(1, n_frames + 1):
            t_frame = k * args.interval
            while state.time < t_frame - 1e-12:
                dt = min(cfl_dt(state.velocity, args.cfl, max_dt=args.interval),
                         0.45 * min(grid.dx) ** 2 / (2 * grid.rank * nu))
                dt = min(dt, t_frame - state.time)
                remaining = t_frame - state.time
                if remaining - dt < 1e-3 * dt:
                    dt = remaining
                state = step(state, dt, viscosity=nu, advection="maccormack", obstacles=body)
                steps += 1
                fo = body_forces(state.velocity, state.pressure, body, dt=dt, viscosity=nu, time=state.time)
                c = fo.coefficients(umean, ref_len)[0].detach().cpu().numpy()
                hist.append((state.time, c[0], c[1]))
            state = FluidState(state.velocity, state.marker, state.pressure, t_frame)  # exact frame time
            p_phys = state.pressure.values / dt
            w = _vorticity(state.velocity)
            writer.append(t_frame, pressure=p_phys, vorticity=w, velocity=state.velocity)
            sl = w[0] if args.dim == 2 else w[0, :, :, grid.resolution[2] // 2]
            frames.append((t_frame, sl.detach().cpu().numpy()))
        hist_arr = np.array(hist)
        f.require_group("extras").create_dataset("forces", data=hist_arr)
        f["extras/forces"].attrs["columns"] = "t, drag coefficient, lift coefficient"
    wall = time.perf_counter() - t0
    second_half = hist_arr[hist_arr[:, 0] >= args.t_end / 2]
    st = strouhal(second_half[:, 0], second_half[:, 2], umean) if len(second_half) > 4 else float("nan")
    gif = _gif(frames, grid, fraction if args.dim == 2 else fraction[:, :, grid.resolution[2] // 2],
               args.out / "karman.gif")
    fig, ax = new_figure((7, 4))
    ax.plot(hist_arr[:, 0], hist_arr[:, 1], label="drag $c_D$")
    ax.plot(hist_arr[:, 0], hist_arr[:, 2], label="lift $c_L$")
    ax.set_xlabel("time")
    ax.set_ylabel("force coefficient $2F/(\\rho U^2 D)$")
    ax.legend()
    ax.set_title(f"Re = {umean * D / nu:.0f}, {'x'.join(map(str, grid.resolution))}: Strouhal number "
                 f"{st:.3f}" if st == st else f"Re = {umean * D / nu:.0f}: no full shedding period yet")
    png = save_figure(fig, args.out / "karman_forces.png")
    summary = {"h5": h5, "gif": gif, "png": png, "steps": steps, "seconds": wall, "strouhal": st,
               "cd_mean": float(second_half[:, 1].mean()) if len(second_half) else float("nan"),
               "cl_max": float(second_half[:, 2].max()) if len(second_half) else float("nan")}
    print(f"{steps} steps to t = {args.t_end} in {wall:.1f} s; St = {st:.4f}; wrote {h5}, {gif}, {png}")
    return summary


def _gif(frames, grid, fraction, path: Path) -> Path:
    """Vorticity frames with the body outline and the time in the title."""
    from matplotlib import animation

    fig, ax = new_figure((8, 2.2))
    x0, x1 = grid.bounds[0]
    y0, y1 = grid.bounds[1]
    lim = max(1e-12, float(np.percentile(np.abs(np.stack([f for _, f in frames])), 99)))
    im = ax.imshow(frames[0][1].T, origin="lower", extent=(x0, x1, y0, y1), cmap="RdBu_r", vmin=-lim, vmax=lim)
    xs = np.linspace(x0, x1, grid.resolution[0])
    ys = np.linspace(y0, y1, grid.resolution[1])
    ax.contour(xs, ys, fraction.detach().cpu().numpy().T, levels=[0.5], colors="k", linewidths=1.0)
    title = ax.set_title("")
    ax.set_xlabel("x")
    ax.set_ylabel("y")

    def draw(i):
        t, w = frames[i]
        im.set_data(w.T)
        title.set_text(f"vorticity, t = {t:.2f}")
        return im, title

    anim = animation.FuncAnimation(fig, draw, frames=len(frames), blit=False)
    anim.save(str(path), writer=animation.PillowWriter(fps=15), dpi=80)
    import matplotlib.pyplot as plt

    plt.close(fig)
    return path


if __name__ == "__main__":
    main()
