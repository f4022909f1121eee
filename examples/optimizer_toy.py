"""Optimizer toy of the physgrad chapter (EXPERIMENTS.md, E1, second part).

Minimise ``L = y1² + y2²`` with ``y = P(x) = (x1, x2²)`` from ``x = (3, 3)`` in 10 iterations with

* ``gd``: gradient descent on ``L``, ``η = 0.01``;
* ``newton``: Newton's method with the full 2×2 Hessian of ``L``, ``η = 1/3``;
* ``pg``: physical gradient with the analytic local inverse: the Newton step in y space
  ``y ← (1 − η) y`` then ``x ← (y1, sqrt(y2))`` (sign of ``x2`` kept), ``η = 0.3``;
* ``ig``: inverse gradient ``Δx = J⁻¹ Δy`` with the same y step ``Δy = −η y``, ``η = 0.3``;
* ``pg_lbfgsb``: the physical gradient with scipy's L-BFGS-B (started at the current x) as local inverse.

The three PG-type methods run through :func:`inverse.physgrad.physical_gradient_loss` with
``torch.optim.SGD(lr=1)`` on ``x`` (so ``x ← x − (x − x̃) = x̃``); they differ only in the local inverse.

Prints the final ``x`` and its distance to the optimum ``(0, 0)`` per method and writes
``optimizer_toy.png`` (trajectories in x space over the contours of L, and in y space) into ``--out``.

``--device`` (``cpu``, ``cuda``, ``cuda:N``) places x and the physics (the L-BFGS-B inverse works on a float64
CPU copy, as scipy does, and hands its result back on the device).

Run:  python examples/optimizer_toy.py --out out/optimizer_toy
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402

from inverse.local_solvers import (  # noqa: E402
    GradientStepSolver,
    InverseGradientSolver,
    LBFGSBSolver,
    NewtonSolver,
    SolverOperator,
)
from inverse.operators import PhysicsOperator, SquareToy  # noqa: E402
from inverse.physgrad import physical_gradient_loss  # noqa: E402
from phisim.checks import check_device  # noqa: E402

METHODS = ("gd", "newton", "pg", "ig", "pg_lbfgsb")
LABELS = {
    "gd": "GD (η=0.01)",
    "newton": "Newton (η=1/3)",
    "pg": "PG, analytic inverse (η=0.3)",
    "ig": "inverse gradient (η=0.3)",
    "pg_lbfgsb": "PG, L-BFGS-B inverse (η=0.3)",
}


def _pg_run(
    operator: PhysicsOperator, x_start: torch.Tensor, iterations: int, eta: float
) -> list[torch.Tensor]:
    """Physical-gradient iterations on x directly: SGD(lr=1) on the proxy loss."""
    x = x_start.clone().requires_grad_(True)
    opt = torch.optim.SGD([x], lr=1.0)
    target = torch.zeros_like(x_start)  # L = |y|^2 is minimal at y* = 0
    path = [x.detach().clone()]
    for _ in range(iterations):
        opt.zero_grad()
        physical_gradient_loss(x, target, operator, eta=eta).backward()
        opt.step()
        path.append(x.detach().clone())
    return path


def run(iterations: int = 10, start: Sequence[float] = (3.0, 3.0), device: torch.device | str = "cpu"
        ) -> dict[str, np.ndarray]:
    """Runs all methods of E1 on ``y = (x1, x2²)``, ``L = y1² + y2²``.

    Args:
        iterations: Number of iterations per method.
        start: The initial ``x``.
        device: Device of ``x`` and of the physics.

    Returns:
        ``{method: trajectory}``, each of shape ``(iterations + 1, 2)`` in x space (float64).
    """
    op = SquareToy()
    x0 = torch.tensor([list(start)], dtype=torch.float64, device=check_device(device))
    zero = torch.zeros_like(x0)
    paths: dict[str, list[torch.Tensor]] = {}

    # The generic solvers minimise 1/2 |P(x) - y*|^2 = L/2: GD with eta = 0.01 on L is a step of 0.02 on L/2.
    # Newton's step does not depend on the loss's scale.
    solvers = (("gd", GradientStepSolver(step_size=0.02)), ("newton", NewtonSolver(step_size=1 / 3)))
    for name, solver in solvers:
        x = x0
        path = [x]
        for _ in range(iterations):
            x = solver(op, zero, x)
            path.append(x)
        paths[name] = path

    paths["pg"] = _pg_run(op, x0, iterations, eta=0.3)
    paths["ig"] = _pg_run(SolverOperator(op, InverseGradientSolver()), x0, iterations, eta=0.3)
    paths["pg_lbfgsb"] = _pg_run(SolverOperator(op, LBFGSBSolver(max_iter=100)), x0, iterations, eta=0.3)
    return {k: torch.cat(v).cpu().numpy() for k, v in paths.items()}


def plot(trajectories: dict[str, np.ndarray], path: Path) -> None:
    """Plots the trajectories in x space (over the contours of L) and in y space.

    Args:
        trajectories: ``{method: (n, 2) array}`` in x space.
        path: Output PNG file.
    """
    fig, (ax_x, ax_y) = plt.subplots(1, 2, figsize=(11, 5))
    g = np.linspace(-0.5, 3.5, 200)
    g1, g2 = np.meshgrid(g, g, indexing="ij")
    ax_x.contour(g1, g2, g1**2 + g2**4, levels=np.geomspace(0.01, 200, 15), colors="0.8", linewidths=0.8)
    for name, traj in trajectories.items():
        y = np.stack([traj[:, 0], traj[:, 1] ** 2], axis=1)
        style = "x--" if name == "pg_lbfgsb" else "o-"  # drawn over the analytic PG it coincides with
        ax_x.plot(traj[:, 0], traj[:, 1], style, ms=4, label=LABELS.get(name, name))
        ax_y.plot(y[:, 0], y[:, 1], style, ms=4, label=LABELS.get(name, name))
    for ax, space in ((ax_x, "x"), (ax_y, "y")):
        ax.plot([0], [0], "k*", ms=10)
        ax.set_xlabel(f"{space}1")
        ax.set_ylabel(f"{space}2")
        ax.set_title(f"trajectories in {space} space")
    ax_x.set_aspect("equal")
    ax_x.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def main(argv: Sequence[str] | None = None) -> dict[str, dict[str, object]]:
    """Command-line entry point: runs E1, prints the final x and distances, writes the figure.

    Args:
        argv: Command-line arguments (``--iterations``, ``--out``, ``--device``); None reads ``sys.argv``.

    Returns:
        ``{method: {"x": final x (2,), "distance": |x − 0|, "trajectory": (n, 2) array}}``.

    Raises:
        ParameterError: For an unknown device or one this machine does not have.
    """
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--iterations", type=int, default=10)
    parser.add_argument("--out", type=Path, default=Path("out/optimizer_toy"))
    parser.add_argument("--device", default="cpu", help="torch device: cpu, cuda or cuda:N (default cpu)")
    args = parser.parse_args(argv)
    device = check_device(args.device)
    args.out.mkdir(parents=True, exist_ok=True)

    trajectories = run(args.iterations, device=device)
    results: dict[str, dict[str, object]] = {}
    print(f"device {device}")
    print(f"{'method':<32s} {'final x':>24s} {'distance':>10s}")
    for name in METHODS:
        traj = trajectories[name]
        final = traj[-1]
        dist = float(np.linalg.norm(final))
        results[name] = {"x": final, "distance": dist, "trajectory": traj}
        print(f"{LABELS[name]:<32s} ({final[0]:10.6f}, {final[1]:10.6f}) {dist:10.6f}")
    plot(trajectories, args.out / "optimizer_toy.png")
    print(f"figure: {args.out / 'optimizer_toy.png'}")
    return results


if __name__ == "__main__":
    main()
