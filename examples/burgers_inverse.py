"""Your own physics in the trainer: recover an earlier state of viscous Burgers' equation from a later one.

The problem (walked through in ``docs/TUTORIAL_custom_physics.md``):

* state ``x = u(t=0)``, a periodic 1-D velocity on ``[0, 2π)`` with ``resolution`` cells, a random sum of
  the first three Fourier modes;
* physics ``y = P(x) = u(t=T)``: ``steps`` steps of ``dt`` of ``u_t + u u_x = ν u_xx`` (semi-Lagrangian
  self-advection, then exact spectral diffusion; differentiable with autograd);
* a network maps ``y*`` to ``x = y* + MLP(y*)`` (a residual MLP ``resolution -> 64 -> 64 -> resolution`` whose
  last layer starts at zero, so training starts from the guess "nothing changed"); the y-space loss is
  ``½ Σ (P(x) − y*)²``, the metric ``Σ_cells |x − x*|`` per sample.

No analytic inverse exists; physical-gradient training uses a generic local inverse (inverse-gradient
iterations ``x ← x + J⁺ (y* − P(x))`` with the Jacobian from autograd).

Run from the command line::

    phisim compare examples/burgers_inverse.py:burgers_problem adam pg_inverse_gradient --iterations 200

or from Python: ``python examples/burgers_inverse.py --iterations 200 [--device cuda]``. The data are drawn on
the CPU and moved to ``--device``, so every device trains on the same samples.
"""

from __future__ import annotations

import argparse
import json
import math

import torch
from torch import nn

from inverse.custom import make_problem
from inverse.nets import MLP
from inverse.train import train
from phisim.checks import check_device
from phisim.field import CenteredGrid
from phisim.grid import Grid
from phisim.ops.advection import advect
from phisim.solvers.diffusion import diffuse


def burgers_physics(resolution: int = 32, steps: int = 8, dt: float = 0.1, viscosity: float = 0.1):
    """The forward process ``u(0) -> u(steps·dt)`` as a batched function ``(B, n) -> (B, n)``.

    Args:
        resolution: Cells on the periodic domain ``[0, 2π)``.
        steps: Number of time steps.
        dt: Time step.
        viscosity: Kinematic viscosity ``ν``.

    Returns:
        The function.
    """
    grid = Grid((resolution,), bounds=(2 * math.pi,))

    def physics(u0: torch.Tensor) -> torch.Tensor:
        u = CenteredGrid(u0.unsqueeze(1), grid, "periodic")  # a 1-D vector field (B, 1, n)
        for _ in range(steps):
            u = advect(u, u, dt)  # u_t + u u_x = 0
            u = diffuse(u, dt, viscosity=viscosity)  # u_t = ν u_xx (exact in time)
        return u.values[:, 0]

    return physics


def burgers_data(resolution: int = 32, modes: int = 3):
    """A data function ``(batch_size, generator) -> u0`` drawing ``Σ_k a_k sin(k x + φ_k)``, ``a_k ~ U(−1, 1)/k``.

    Args:
        resolution: Cells.
        modes: Number of Fourier modes ``k = 1..modes``.

    Returns:
        The function.
    """
    x = (torch.arange(resolution, dtype=torch.float64) + 0.5) * (2 * math.pi / resolution)
    k = torch.arange(1, modes + 1, dtype=torch.float64)

    def data(batch_size: int, generator: torch.Generator) -> torch.Tensor:
        a = (2 * torch.rand(batch_size, modes, generator=generator, dtype=torch.float64) - 1) / k
        phase = 2 * math.pi * torch.rand(batch_size, modes, generator=generator, dtype=torch.float64)
        return (a[:, :, None] * torch.sin(k[None, :, None] * x + phase[:, :, None])).sum(dim=1)

    return data


class ResidualMLP(nn.Module):
    """``x = y + MLP(y)`` with tanh hidden layers; the last layer starts at zero (the identity map).

    Args:
        n: Cells.
        hidden: Width of the two hidden layers.
    """

    def __init__(self, n: int, hidden: int = 64):
        super().__init__()
        self.mlp = MLP([n, hidden, hidden, n], activation="tanh")
        last = [m for m in self.mlp.modules() if isinstance(m, nn.Linear)][-1]
        nn.init.zeros_(last.weight)
        nn.init.zeros_(last.bias)

    def forward(self, y: torch.Tensor) -> torch.Tensor:
        """``(B, n) -> (B, n)``."""
        return y + self.mlp(y)


def burgers_problem(resolution: int = 32, steps: int = 8, dt: float = 0.1, viscosity: float = 0.1,
                    batch_size: int = 16, lr: float = 1e-3, solver_iterations: int = 1, hidden: int = 64,
                    rcond: float = 1e-3):
    """The Burgers inverse problem as an :class:`inverse.custom.CustomProblem` (the CLI factory).

    Args:
        resolution: Cells.
        steps: Time steps of the forward simulation.
        dt: Time step.
        viscosity: Viscosity.
        batch_size: Samples per batch.
        lr: Adam learning rate.
        solver_iterations: Inverse-gradient iterations of the generic local inverse.
        hidden: Width of the two hidden layers of the residual MLP.
        rcond: Relative singular-value cut-off of the generic local inverses.

    Returns:
        The problem.
    """
    return make_problem(
        "burgers",
        data=burgers_data(resolution),
        physics=burgers_physics(resolution, steps, dt, viscosity),
        network=lambda: ResidualMLP(resolution, hidden),
        batch_size=batch_size,
        dtype=torch.float64,
        lr=lr,
        solver_iterations=solver_iterations,
        rcond=rcond,
    )


def evaluate(problem, network: nn.Module, samples: int = 256, seed: int = 123, device=None) -> dict:
    """Held-out x L1 and y loss per sample of ``network`` (eval mode) and of the identity guess ``x = y*``.

    Args:
        problem: The Burgers problem.
        network: A trained network.
        samples: Held-out samples.
        seed: Seed of their generator (a CPU generator; the samples are then moved to ``device``).
        device: Device of the samples (default: the network's).

    Returns:
        ``{'metric', 'loss', 'identity_metric', 'identity_loss'}`` (means over the samples).
    """
    if device is None:
        device = next(network.parameters()).device
    b = problem.sample(samples, torch.Generator().manual_seed(seed), device=device)
    network.eval()
    with torch.no_grad():
        x = network(b.inputs)
        return {"metric": float((x - b.x_true).abs().sum(1).mean()),
                "loss": float(problem.loss(problem.physics(x), b.y_target).mean()),
                "identity_metric": float((b.y_target - b.x_true).abs().sum(1).mean()),
                "identity_loss": float(problem.loss(problem.physics(b.y_target), b.y_target).mean())}


def main(argv: list[str] | None = None) -> dict:
    """Train Adam through the solver and physical gradients (generic inverse) on the same data; evaluate both.

    Args:
        argv: Command-line arguments.

    Returns:
        ``{method: {'train_metric', 'heldout_metric', 'heldout_loss', 'seconds'}}`` plus the identity baseline
        (the table of ``docs/TUTORIAL_custom_physics.md``) and the ``device``.

    Raises:
        ParameterError: For an unknown device or one this machine does not have.
    """
    import time

    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--iterations", type=int, default=200)
    p.add_argument("--resolution", type=int, default=32)
    p.add_argument("--batch-size", type=int, default=16)
    p.add_argument("--rcond", type=float, default=1e-3)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--device", default="cpu", help="torch device: cpu, cuda or cuda:N (default cpu)")
    args = p.parse_args(argv)
    device = check_device(args.device)
    problem = burgers_problem(resolution=args.resolution, batch_size=args.batch_size, rcond=args.rcond)
    out = {}
    for method in ("adam", "pg_inverse_gradient"):
        t = time.perf_counter()
        r = train(problem, method, iterations=args.iterations, seed=args.seed, device=device)
        ev = evaluate(problem, r.model, device=device)
        out[method] = {"train_metric": r.final("metric"), "heldout_metric": ev["metric"],
                       "heldout_loss": ev["loss"], "seconds": time.perf_counter() - t}
        out["identity"] = {"heldout_metric": ev["identity_metric"], "heldout_loss": ev["identity_loss"]}
    out["device"] = str(device)
    print(json.dumps(out))
    return out


if __name__ == "__main__":
    main()
