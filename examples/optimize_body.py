"""Shape optimisation through the unsteady solver: turn a plate in a stream to lower its drag.

A flat plate (a :class:`~phisim.fluid.geometry.RotatedBox`, 0.4 x 0.08) sits in a channel with a uniform
inflow on the left (:class:`~phisim.boundary.Inflow`), an outflow on the right and free-slip walls. Its angle
of attack is a torch tensor that requires grad. Each optimisation iteration simulates the flow from rest
for ``--steps`` steps (MacCormack advection, viscosity, projection with the plate's fractional face
weights), averages the drag over the second half (:func:`phisim.fluid.body_forces`) and takes a gradient
step on the angle; the gradient flows through every step: the advection, the viscous term, the pressure
solve (implicit adjoint of the weighted CG, whose operator depends on the angle through the face
fractions) and the force evaluation. The plate turns towards the flow direction, where its drag is least.

Outputs (in ``--out``): ``optimize_body.png`` (drag and angle per iteration, the plate before and after)
and ``optimize_body.json`` (the history).

Run:  python examples/optimize_body.py                      (about a minute)
      python examples/optimize_body.py --iterations 2 --nx 32 --steps 6     (a smoke test)
      python examples/optimize_body.py --device cuda                 (on a GPU)
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import torch  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from phisim.boundary import Inflow, Open  # noqa: E402
from phisim.checks import check_device  # noqa: E402
from phisim.field import StaggeredGrid  # noqa: E402
from phisim.fluid import Body, FluidState, RotatedBox, body_forces, step  # noqa: E402
from phisim.grid import Grid  # noqa: E402
from phisim.viz.plot import new_figure, save_figure  # noqa: E402


def parse_args(argv=None) -> argparse.Namespace:
    """Command-line options (see ``--help``)."""
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--nx", type=int, default=64, help="cells along the 2 units of channel length")
    p.add_argument("--steps", type=int, default=30, help="simulation steps per evaluation")
    p.add_argument("--dt", type=float, default=0.02)
    p.add_argument("--viscosity", type=float, default=0.02)
    p.add_argument("--angle", type=float, default=0.6, help="initial angle of attack (radians)")
    p.add_argument("--iterations", type=int, default=8)
    p.add_argument("--lr", type=float, default=0.5, help="gradient step (radians per unit drag gradient)")
    p.add_argument("--out", type=Path, default=Path("out/optimize_body"))
    p.add_argument("--device", default="cpu", help="torch device: cpu, cuda or cuda:N (default cpu)")
    return p.parse_args(argv)


def mean_drag(angle: torch.Tensor, args) -> torch.Tensor:
    """Drag on the plate averaged over the second half of a run from rest (differentiable in ``angle``).

    The flow lives on ``angle``'s device.
    """
    grid = Grid((args.nx, args.nx // 2), bounds=[(0, 2), (0, 1)])
    boundary = {"x": (Inflow(1.0), Open()), "y": "free_slip"}
    body = Body(RotatedBox((0.6, 0.5), (0.4, 0.08), angle))
    state = FluidState(StaggeredGrid.zeros(grid, boundary, dtype=torch.float64, device=angle.device))
    drags = []
    for k in range(args.steps):
        state = step(state, args.dt, viscosity=args.viscosity, advection="maccormack", obstacles=body)
        if k >= args.steps // 2:
            f = body_forces(state.velocity, state.pressure, body, dt=args.dt, viscosity=args.viscosity)
            drags.append(f.total[0, 0])
    return torch.stack(drags).mean()


def main(argv=None) -> dict:
    """Optimise the angle; returns the history (angles, drags), the device and the output paths.

    Raises:
        ParameterError: For an unknown device or one this machine does not have.
    """
    args = parse_args(argv)
    device = check_device(args.device)
    torch.set_num_threads(1)
    args.out.mkdir(parents=True, exist_ok=True)
    angle = torch.tensor(args.angle, dtype=torch.float64, device=device, requires_grad=True)
    history = []
    t0 = time.perf_counter()
    for it in range(args.iterations):
        drag = mean_drag(angle, args)
        (grad,) = torch.autograd.grad(drag, angle)
        history.append({"iteration": it, "angle": float(angle.detach()), "drag": float(drag.detach()),
                        "gradient": float(grad)})
        print(f"iteration {it}: angle {history[-1]['angle']:+.4f} rad, drag {history[-1]['drag']:.5f}, d drag/d angle "
              f"{float(grad):+.4f}", flush=True)
        with torch.no_grad():
            angle -= args.lr * grad
    final = float(mean_drag(angle.detach(), args))  # float() waits for the device: the time below is complete
    history.append({"iteration": args.iterations, "angle": float(angle.detach()), "drag": final, "gradient": None})
    seconds = time.perf_counter() - t0
    fig, ax = new_figure((10, 3.6))
    fig.clf()
    a1, a2 = fig.subplots(1, 2)
    its = [h["iteration"] for h in history]
    a1.plot(its, [h["drag"] for h in history], "o-", label="mean drag")
    a1.set_xlabel("optimisation iteration")
    a1.set_ylabel("drag force (per unit depth)")
    b1 = a1.twinx()
    b1.plot(its, [math.degrees(h["angle"]) for h in history], "s--", color="C1", label="angle")
    b1.set_ylabel("angle of attack (degrees)")
    a1.set_title("gradient descent through the unsteady solver")
    for h, style in ((history[0], "C0--"), (history[-1], "C3-")):
        c, s = torch.tensor([0.6, 0.5]), torch.tensor([0.2, 0.04])
        corners = torch.tensor([[-1, -1], [1, -1], [1, 1], [-1, 1], [-1, -1]], dtype=torch.float64) * s
        r = torch.tensor([[math.cos(h["angle"]), -math.sin(h["angle"])], [math.sin(h["angle"]), math.cos(h["angle"])]])
        pts = corners.float() @ r.T.float() + c
        a2.plot(pts[:, 0], pts[:, 1], style, label=f"iteration {h['iteration']}: drag {h['drag']:.4f}")
    a2.set_xlim(0, 2)
    a2.set_ylim(0, 1)
    a2.set_aspect("equal")
    a2.legend(fontsize=8)
    a2.set_title("plate (flow from the left)")
    png = save_figure(fig, args.out / "optimize_body.png")
    js = args.out / "optimize_body.json"
    js.write_text(json.dumps({"args": {k: str(v) for k, v in vars(args).items()}, "device": str(device),
                              "history": history, "seconds": seconds}, indent=1))
    print(f"angle {history[0]['angle']:.3f} -> {history[-1]['angle']:.3f} rad, drag {history[0]['drag']:.4f} -> "
          f"{history[-1]['drag']:.4f} in {seconds:.1f} s on {device}; wrote {png}, {js}")
    return {"history": history, "device": str(device), "png": png, "json": js}


if __name__ == "__main__":
    main()
