"""The training-problem interface: :class:`Problem` (data, physics, network, loss, metric, methods),
:class:`Method` (an update rule) and :class:`Batch`.

The reference experiments (:mod:`inverse.problems`), the fluid problem (:mod:`inverse.fluid_inverse`) and
problems of your own (:mod:`inverse.custom`) all build on these classes; this module imports none of them.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import torch
from torch import nn

from phisim.checks import check_callable, check_number
from phisim.errors import ParameterError

from .local_solvers import LocalSolver
from .operators import PhysicsOperator
from .physgrad import QuadraticLoss

HELDOUT_SEED = 2**63 + 2024
HELDOUT_SIZE = 128

__all__ = ["HELDOUT_SEED", "HELDOUT_SIZE", "Method", "Batch", "Problem"]


@dataclass(frozen=True)
class Method:
    """A training method.

    Attributes:
        name: Name used in logs and on the command line.
        kind: ``'physics'`` (backpropagate the y-space loss through the physics), ``'physgrad'`` (proxy
            loss with a local inverse), ``'supervised'`` (regress labels), ``'hig'`` (half-inverse
            gradients / Gauss-Newton).
        optimizer: ``'adam'``, ``'sgd'``, ``'hig'`` or ``'gauss_newton'``.
        lr: Learning rate.
        momentum: SGD momentum.
        eta: y-space step of the physical gradient.
        local_solver: Generic local inverse replacing the operator's own (None: the operator's).
        grad_clip: Clamp the per-sample gradient w.r.t. the network output ``x`` (for physical gradients:
            the update ``x̃ − x``) to ``[-c, c]`` before it reaches the network (E2).
        rcond: HIG truncation.
        loss: Per-sample y-space loss ``(y, y*) -> (B,)`` that HIG differentiates instead of the problem's
            :meth:`Problem.loss` (None: the problem's). E2's ``hig_squared`` uses ``½ (y − y*)²``.
    """

    name: str
    kind: str
    optimizer: str = "adam"
    lr: float = 1e-3
    momentum: float = 0.0
    eta: float = 1.0
    local_solver: LocalSolver | None = None
    grad_clip: float | None = None
    rcond: float = 1e-5
    loss: Callable | None = None

    def __post_init__(self):
        for name in ("lr", "momentum", "eta", "rcond"):
            check_number(getattr(self, name), f"method {self.name!r}: {name}", minimum=0)
        if self.lr == 0:
            raise ParameterError(f"method {self.name!r}: lr must be > 0 (a zero learning rate never trains)")
        check_number(self.grad_clip, f"method {self.name!r}: grad_clip", minimum=0, min_open=True, allow_none=True)
        if self.loss is not None:
            check_callable(self.loss, f"method {self.name!r}: loss")
        if self.local_solver is not None:
            check_callable(self.local_solver, f"method {self.name!r}: local_solver")


@dataclass
class Batch:
    """One batch of inverse problems.

    Attributes:
        inputs: Network input ``(B, ...)``.
        y_target: Targets ``y*`` ``(B, *y_shape)``.
        x_true: Ground truth ``x*`` (``None`` when unknown).
        operator: The physics pair for this batch (may hold per-sample parameters).
        labels: Supervised labels (``None`` when the problem has none).
        physics_args: Extra per-sample tensors for HIG's physics function.
    """

    inputs: torch.Tensor
    y_target: torch.Tensor
    x_true: torch.Tensor | None
    operator: PhysicsOperator
    labels: torch.Tensor | None = None
    physics_args: tuple = ()


@dataclass
class Problem:
    """Base class of the experiments; subclasses implement :meth:`sample`, :meth:`make_network`, :meth:`predict`.

    Attributes:
        name: Registered name.
        batch_size: Default batch size.
        reduction: ``'sum'`` or ``'mean'`` over the batch for the backpropagated objective.
        dtype: Network dtype.
        methods: The problem's methods by name.
        newton_loss: The y-space quadratic loss whose Newton step drives physical gradients.
        heldout_size: Samples in the fixed held-out set (:meth:`heldout`).
        heldout_seed: Seed of the held-out set's generator (independent of the training seed).
        loss_name: What the ``loss`` curve measures, with its reduction (files, plots, CLI).
        metric_name: What the ``metric`` curve measures, with its reduction.
    """

    name: str = "problem"
    batch_size: int = 1
    reduction: str = "sum"
    dtype: torch.dtype = torch.float32
    methods: dict[str, Method] = field(default_factory=dict)
    newton_loss: QuadraticLoss = field(default_factory=QuadraticLoss)
    heldout_size: int = HELDOUT_SIZE
    heldout_seed: int = HELDOUT_SEED
    loss_name: str = "y loss ½Σ_cells (y−y*)² per sample"
    metric_name: str = "x L1 per sample (sum over cells of |x−x*|)"
    _heldout_cache: dict = field(default_factory=dict, repr=False, compare=False, init=False)

    def method(self, name: str) -> Method:
        """The method called ``name``.

        Raises:
            ParameterError: For an unknown method, listing the known ones.
        """
        if name not in self.methods:
            raise ParameterError(f"problem {self.name!r} has no method {name!r}; choose from {sorted(self.methods)}")
        return self.methods[name]

    def make_network(self) -> nn.Module:
        """A freshly initialised network (seed torch before calling for reproducibility)."""
        raise NotImplementedError

    def heldout(self, device=None) -> Batch:
        """The fixed held-out set: ``heldout_size`` samples from a generator seeded with ``heldout_seed``.

        The same for every training seed, method and process; built once per device and cached.

        Raises:
            ParameterError: For a non-positive ``heldout_size``.
        """
        size = self.heldout_size
        if isinstance(size, bool) or not isinstance(size, int) or size < 1:
            raise ParameterError(f"heldout_size must be a positive int, got {size!r}")
        key = (str(torch.device(device) if device is not None else "cpu"), size, int(self.heldout_seed))
        if key not in self._heldout_cache:
            gen = torch.Generator(device="cpu")
            gen.manual_seed(int(self.heldout_seed))
            self._heldout_cache.clear()
            self._heldout_cache[key] = self.sample(size, gen, device=device)
        return self._heldout_cache[key]

    def sample(self, batch_size: int, generator: torch.Generator, device=None) -> Batch:
        """Draw a batch of problems from ``generator``."""
        raise NotImplementedError

    def predict(self, model: nn.Module, batch: Batch) -> torch.Tensor:
        """The physical state ``x`` the network predicts for ``batch``."""
        raise NotImplementedError

    def loss(self, y: torch.Tensor, y_target: torch.Tensor) -> torch.Tensor:
        """Per-sample y-space loss ``½ Σ_cells (y − y*)²``, shape ``(B,)``."""
        return 0.5 * ((y - y_target) ** 2).reshape(y.shape[0], -1).sum(dim=1)

    def metric(self, x: torch.Tensor, batch: Batch) -> torch.Tensor:
        """Per-sample x L1 error ``Σ_cells |x − x*|`` (a sum over cells), shape ``(B,)``."""
        return (x - batch.x_true.to(x.dtype)).abs().reshape(x.shape[0], -1).sum(dim=1)

    hig_physics: Callable | None = None


# ---- E2 -------------------------------------------------------------------------------------------------
