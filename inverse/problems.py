"""The reference experiments as problems: data on the fly, physics pair, network, loss, metric, methods.

A :class:`Problem` bundles what :func:`inverse.train.train` needs; a :class:`Method` names an update rule
(through the physics with Adam/SGD, physical gradients with a local inverse, supervised, HIG). The
settings follow ``EXPERIMENTS.md`` (E2 sine, E3 Poisson, E4 heat); sizes can be reduced for tests.

Conventions of the reference figures: the y-space loss ``l2`` is ``½ Σ`` over a sample's cells (a sum, not
a mean); Poisson and heat backpropagate the batch **sum**, sine and fluid the batch **mean**; the metric of
E3/E4 is the x L1 error per sample, ``Σ_cells |x − x*|`` (a sum over cells, not a mean), averaged over
samples. Each problem names its loss and metric with units in :attr:`Problem.loss_name` and
:attr:`Problem.metric_name`.

Every problem has a fixed held-out set (:meth:`Problem.heldout`): ``heldout_size`` samples (default 128, as
the published reference code's test set) drawn from a generator seeded with ``heldout_seed`` (default
``2**63 + 2024``, a seed the training stream never uses, so held-out samples are not training batches).
"""

from __future__ import annotations

import difflib
from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch import nn

from phisim.checks import check_int, check_number
from phisim.errors import ParameterError
from phisim.grid import Grid
from phisim.simulate.noise import random_rectangles, spectral_noise
from phisim.solvers.linalg import Solve

from .custom import load_problem
from .fluid_inverse import FluidProblem
from .local_solvers import InverseGradientSolver, LBFGSBSolver, NewtonSolver
from .nets import MLP, UNet
from .offline import dataset_problem
from .operators import Heat, PhysicsOperator, Poisson, Sine
from .pde_inverse import PDEProblem
from .problem import HELDOUT_SEED, HELDOUT_SIZE, Batch, Method, Problem

__all__ = ["HELDOUT_SEED", "HELDOUT_SIZE", "Method", "Batch", "Problem", "SineProblem", "PoissonProblem",
           "HeatProblem", "PROBLEMS", "get_problem"]


def _half_squared(y: torch.Tensor, y_target: torch.Tensor) -> torch.Tensor:
    return 0.5 * ((y - y_target) ** 2).reshape(y.shape[0], -1).sum(dim=1)


@dataclass
class SineProblem(Problem):
    """E2: find ``x`` with ``sin(a/x) = −1`` for ``a ∈ [0.1, 10.1)``; network ``a -> x`` (MLP, 461 parameters).

    The physics loss is the height above the minimum, ``h = sin(a/x) + 1`` per sample (also the metric);
    physical gradients take the Newton step of ``½(y − y*)²`` with ``y* = −1``. Supervised labels are the
    solutions closest to the fixed guess ``x0 = 1``. The analytic inverse (``pg_analytic`` and the labels)
    picks the solution closest in phase (``Sine(closest="phase")``, the paper's rounding rule
    ``n = round(a/(2π x0) − 3/4)``). Gradients w.r.t. ``x`` are clipped to ``[−1, 1]`` where the paper does
    (Adam through the physics, Newton, inverse gradient).
    """

    name: str = "sine"
    batch_size: int = 1000
    reduction: str = "mean"
    loss_name: str = "height sin(a/x)+1 per sample"
    metric_name: str = "height sin(a/x)+1 per sample"
    a_range: tuple[float, float] = (0.1, 10.1)

    def __post_init__(self):
        lr = 0.002
        self.methods = {
            "supervised": Method("supervised", "supervised", lr=lr),
            "adam": Method("adam", "physics", lr=lr, grad_clip=1.0),
            "pg_newton": Method("pg_newton", "physgrad", lr=lr, grad_clip=1.0,
                                local_solver=NewtonSolver(saddle_free=True)),
            "pg_inverse_gradient": Method("pg_inverse_gradient", "physgrad", lr=lr, grad_clip=1.0,
                                          local_solver=InverseGradientSolver()),
            "pg_analytic": Method("pg_analytic", "physgrad", lr=lr),
            "hig": Method("hig", "hig", optimizer="hig", lr=lr, rcond=1e-5),
            # HIG as it is normally run: a squared y-space loss and SGD with lr 1
            "hig_squared": Method("hig_squared", "hig", optimizer="hig", lr=1.0, rcond=1e-5,
                                  loss=_half_squared),
        }
        self.hig_physics = lambda out, a: torch.sin(a / out)

    def make_network(self) -> nn.Module:
        """MLP 1 → 10 → 20 → 10 → 1 with ReLU (461 parameters)."""
        return MLP([1, 10, 20, 10, 1])

    def sample(self, batch_size: int, generator: torch.Generator, device=None) -> Batch:
        """Uniform ``a``; ``y* = −1``; labels from the closest solution to ``x0 = 1``."""
        lo, hi = self.a_range
        a = lo + (hi - lo) * torch.rand(batch_size, 1, generator=generator, dtype=torch.float64)
        a = a.to(device=device, dtype=self.dtype)
        op = Sine(a[:, 0], closest="phase")  # the paper's rounding rule (appendix B.1)
        y_target = -torch.ones_like(a)
        labels = op.local_inverse(y_target, torch.ones_like(a))
        return Batch(a, y_target, None, op, labels=labels, physics_args=(a,))

    def predict(self, model: nn.Module, batch: Batch) -> torch.Tensor:
        """``x = net(a)``, shape ``(B, 1)``."""
        return model(batch.inputs)

    def loss(self, y: torch.Tensor, y_target: torch.Tensor) -> torch.Tensor:
        """Height above the minimum ``y − y* = sin(a/x) + 1`` per sample."""
        return (y - y_target).reshape(y.shape[0], -1).sum(dim=1)

    def metric(self, x: torch.Tensor, batch: Batch) -> torch.Tensor:
        """``sin(a/x) + 1`` per sample."""
        return self.loss(batch.operator(x), batch.y_target)


# ---- E3 -------------------------------------------------------------------------------------------------


@dataclass
class _UNetGridProblem(Problem):
    """Shared part of E3 and E4: a 2-D grid with dx = 1, a U-net ``y* -> x`` (37,697 parameters) and the
    four methods Adam, SGD with momentum, Adam + physical gradients (the operator's own local inverse) and
    Adam + physical gradients with L-BFGS-B."""

    batch_size: int = 128
    reduction: str = "sum"
    resolution: tuple[int, int] = (64, 64)
    sgd_lr: float = 1e-3
    lbfgsb_iterations: int = 32

    def __post_init__(self):
        if isinstance(self.resolution, (str, bytes)) or not hasattr(self.resolution, "__len__") or len(
                self.resolution) != 2:
            raise ParameterError(f"resolution must be two cell counts (nx, ny), got {self.resolution!r}")
        self.resolution = tuple(check_int(n, "resolution", minimum=1) for n in self.resolution)
        self.batch_size = check_int(self.batch_size, "batch_size", minimum=1)
        self.lbfgsb_iterations = check_int(self.lbfgsb_iterations, "lbfgsb_iterations", minimum=1)
        self.sgd_lr = check_number(self.sgd_lr, "sgd_lr", minimum=0, min_open=True)
        self.methods = {
            "adam": Method("adam", "physics", lr=1e-3),
            "sgd": Method("sgd", "physics", optimizer="sgd", lr=self.sgd_lr, momentum=0.9),
            "pg": Method("pg", "physgrad", lr=1e-3),
            "pg_lbfgsb": Method("pg_lbfgsb", "physgrad", lr=1e-3,
                                local_solver=LBFGSBSolver(max_iter=self.lbfgsb_iterations)),
        }
        self._operator = None

    @property
    def grid(self):
        """The problem's grid (dx = 1)."""

        return Grid(self.resolution)

    def operator(self) -> PhysicsOperator:
        """The physics pair (built once)."""
        if self._operator is None:
            self._operator = self._make_operator()
        return self._operator

    def _make_operator(self) -> PhysicsOperator:
        raise NotImplementedError

    def make_network(self) -> nn.Module:
        """U-net, 4 levels, 16 filters, circular padding (37,697 parameters)."""
        return UNet(1, 1, levels=4, filters=16, padding_mode="circular")

    def predict(self, model: nn.Module, batch: Batch) -> torch.Tensor:
        """``x = net(y*)``, shape ``(B, *resolution)``."""
        return model(batch.inputs)[:, 0]


@dataclass
class PoissonProblem(_UNetGridProblem):
    """E3: recover the source ``x`` of Poisson's equation from ``y = ∇⁻² x`` (zero Dirichlet, dx = 1).

    Data: ``x*`` spectral noise (E3 recipe, unit std per sample), ``y* = P(x*)``. Network: U-net 4 levels,
    16 filters (37,697 parameters), input ``y*``, output ``x``. Methods: Adam through the CG solve
    (``adam``), SGD with momentum (``sgd``), Adam + physical gradients with the analytic Laplacian
    (``pg``) or L-BFGS-B (``pg_lbfgsb``, 10 iterations: each evaluation is a CG solve).

    ``solver`` selects the training path's forward solve: ``'cg'`` (plain CG to ``rtol``, the experiment's
    specification, default) or ``'spectral'`` (CG preconditioned by the exact spectral solver: one
    iteration). ``data_solver`` selects how ``y*`` is generated: ``'spectral'`` (the exact DST solve,
    default: ~100x faster than CG at 64²) or ``'cg'``. ``boundary`` places the zero Dirichlet value on the
    cell faces (``'face'``, phisim's convention, default) or in the ghost cells (``'ghost'``, the reference
    code's; see :class:`~inverse.operators.Poisson`). ``normalize=False`` leaves out the per-sample shift and
    scaling of ``x*`` to zero mean and unit standard deviation (the recipe's; an experiment on its effect).
    """

    name: str = "poisson"
    rtol: float = 1e-5
    sgd_lr: float = 1e-9
    lbfgsb_iterations: int = 10
    solver: str = "cg"
    data_solver: str = "spectral"
    boundary: str = "face"
    normalize: bool = True

    def __post_init__(self):
        super().__post_init__()
        for attr in ("solver", "data_solver"):
            if getattr(self, attr) not in ("cg", "spectral"):
                raise ParameterError(f"{attr} must be 'cg' or 'spectral', got {getattr(self, attr)!r}")
        if self.boundary not in ("face", "ghost"):
            raise ParameterError(f"boundary must be 'face' or 'ghost', got {self.boundary!r}")

    def _make_operator(self) -> PhysicsOperator:


        pre = "spectral" if self.solver == "spectral" else None
        return Poisson(dx=1.0, kinds="dirichlet", solve=Solve(rtol=self.rtol), preconditioner=pre,
                       convention=self.boundary)

    def sample(self, batch_size: int, generator: torch.Generator, device=None) -> Batch:
        """``x*`` spectral noise, ``y* = P(x*)``.

        With ``data_solver='spectral'`` (default) ``y*`` is the exact discrete solution (DST, float64,
        round-off accurate); ``'cg'`` solves it with the training operator's CG instead (to ``rtol``).
        """

        x = spectral_noise(self.grid, batch_size, power=2.0, scale=10.0, cutoff=0.1, generator=generator,
                           normalize=self.normalize, dtype=torch.float64).values.to(device=device, dtype=self.dtype)
        op = self.operator()
        with torch.no_grad():
            if self.data_solver == "spectral":
                y = op.exact_solve(x)
            else:
                y = op.forward(x)
        return Batch(y.unsqueeze(1), y, x, op)


# ---- E4 -------------------------------------------------------------------------------------------------


@dataclass
class HeatProblem(_UNetGridProblem):
    """E4: recover the initial temperature ``x`` from ``y = exp(tν∇²) x`` (periodic 64², tν = 8, float64).

    Data: 4–10 soft-edged hot rectangles, ``y* = P(x*)``. The network's prediction gets the target's mean
    (diffusion keeps the mean). Methods: Adam through the physics (``adam``), SGD, Adam + physical
    gradients with the Wiener/Bayes-damped spectral inverse (``pg``) or L-BFGS-B with 32 iterations
    (``pg_lbfgsb``).
    """

    name: str = "heat"
    t_nu: float = 8.0
    sgd_lr: float = 1e-5  # 1e-3 and 1e-4 diverge within a few iterations (batch-sum loss); 1e-5 trains

    def _make_operator(self) -> PhysicsOperator:

        return Heat(nu_t=self.t_nu)

    def sample(self, batch_size: int, generator: torch.Generator, device=None) -> Batch:
        """``x*`` hot rectangles, ``y* = P(x*)`` in float64."""

        x = random_rectangles(self.grid, batch_size, generator=generator, dtype=torch.float64).values.to(device)
        op = self.operator()
        with torch.no_grad():
            y = op.forward(x)
        return Batch(y.unsqueeze(1).to(self.dtype), y, x, op)

    def predict(self, model: nn.Module, batch: Batch) -> torch.Tensor:
        """``x = net(y*)`` in float64 with the mean of ``y*`` imposed."""
        x = model(batch.inputs)[:, 0].to(torch.float64)
        return x - x.mean(dim=(1, 2), keepdim=True) + batch.y_target.mean(dim=(1, 2), keepdim=True)


PROBLEMS: dict[str, Callable[..., Problem]] = {
    "sine": SineProblem,
    "poisson": PoissonProblem,
    "heat": HeatProblem,
    "pde": PDEProblem,  # an earlier state of a phisim.pde equation from a later one (inverse.pde_inverse)
}


def _fluid_problem(**settings) -> Problem:
    """E5 (:class:`inverse.fluid_inverse.FluidProblem`), imported on first use (it imports this module)."""

    return FluidProblem(**settings)


PROBLEMS["fluid"] = _fluid_problem


def _well_problem(**settings) -> Problem:
    """Offline supervised training from a Well-layout dataset (:func:`inverse.offline.dataset_problem`)."""

    return dataset_problem(**settings)


PROBLEMS["well"] = _well_problem


def get_problem(name: str, **settings) -> Problem:
    """Instantiate a registered problem, e.g. ``get_problem('poisson', resolution=(32, 32), batch_size=8)``.

    A name ``module:function`` or ``path/to/file.py:function`` calls a factory of your own
    (:func:`inverse.custom.load_problem`). The problem records ``spec = {'factory': name, 'settings': ...}``
    (what :func:`inverse.load_model` uses to rebuild its network).

    Raises:
        ParameterError: For an unknown name or setting (the closest registered name is suggested).
    """
    if ":" in str(name):

        return load_problem(name, **settings)
    if name not in PROBLEMS:
        close = difflib.get_close_matches(str(name), list(PROBLEMS), n=1)
        hint = f"; did you mean {close[0]!r}?" if close else ""
        raise ParameterError(f"unknown problem {name!r}{hint} (choose from {sorted(PROBLEMS)}, or give a "
                             "factory as module:function)")
    try:
        problem = PROBLEMS[name](**settings)
    except TypeError as exc:
        raise ParameterError(f"bad settings for problem {name!r}: {exc}") from exc
    problem.spec = {"factory": name, "settings": dict(settings)}
    return problem

