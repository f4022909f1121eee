"""Your own physics in the trainer: define a problem from plain functions and train every method on it.

A problem is five ingredients (see ``docs/TUTORIAL_custom_physics.md`` for a walk-through):

* **data** ``data(batch_size, generator) -> x_true`` (or ``(x_true, y_target)``): a batch of ground-truth
  states drawn from the torch ``generator`` (so runs are reproducible); when only ``x_true`` is returned the
  targets are ``y* = physics(x_true)``. A :class:`~inverse.offline.DatasetSampler` reads them from a
  Well dataset directory instead (offline training).
* **physics** ``physics(x) -> y``: the differentiable, batched forward process ``(B, *x_shape) -> (B, *y_shape)``.
* **local inverse** ``local_inverse(y_target, x0) -> x`` or ``None``: an analytic/problem-specific inverse
  conditioned on the guess ``x0``. Without one, the generic inverses of :mod:`inverse.local_solvers`
  (inverse gradient, Newton, L-BFGS-B) still give physical-gradient methods.
* **loss** ``loss(y, y_target) -> (B,)`` (default ``½ Σ_cells (y − y*)²``) and **metric**
  ``metric(x, x_true) -> (B,)`` (default ``Σ_cells |x − x*|``).
* **network** ``network() -> nn.Module`` mapping the network input (default ``y*``) to ``x``.

:func:`make_problem` turns them into a :class:`CustomProblem`, a :class:`~inverse.problems.Problem` that
:func:`inverse.train.train` trains with every applicable method through the one loop: ``adam`` and ``sgd``
through the physics, ``pg`` (your local inverse), ``pg_inverse_gradient`` / ``pg_newton`` / ``pg_lbfgsb``
(generic local inverses), ``supervised`` (regress ``x_true``) and ``hig`` (half-inverse gradients).

The command line takes a factory as ``module:function`` or ``path/to/file.py:function``
(:func:`load_problem`), e.g. ``phisim train examples/burgers_inverse.py:burgers_problem adam``.
"""

from __future__ import annotations

import difflib
import importlib
import importlib.util
import sys
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
from torch import nn

from phisim.errors import ParameterError, ShapeError

from .local_solvers import InverseGradientSolver, LBFGSBSolver, NewtonSolver
from .operators import PhysicsOperator
from .problem import Batch, Method, Problem

__all__ = ["CallableOperator", "CustomProblem", "make_problem", "load_problem", "is_factory_spec",
           "canonical_factory"]


class CallableOperator(PhysicsOperator):
    """A :class:`~inverse.operators.PhysicsOperator` from a forward function and an optional local inverse.

    Args:
        physics: ``(B, *x_shape) -> (B, *y_shape)``, differentiable and batched.
        local_inverse: ``(y_target, x0) -> x`` or None (then :meth:`local_inverse` raises; wrap the
            operator in a :class:`~inverse.local_solvers.SolverOperator` for a generic inverse).
    """

    def __init__(self, physics: Callable[[torch.Tensor], torch.Tensor],
                 local_inverse: Callable[[torch.Tensor, torch.Tensor], torch.Tensor] | None = None):
        self.physics = physics
        self.inverse_fn = local_inverse

    def output_shape(self, x_shape):
        """Unknown in general (None): the output shape is checked against ``physics(x0)``."""
        return None

    def _forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.physics(x)

    def _local_inverse(self, y_target, x0, y0):
        if self.inverse_fn is None:
            raise ParameterError("this problem defines no local inverse; use a generic one (pg_inverse_gradient, "
                                 "pg_newton, pg_lbfgsb)")
        with torch.no_grad():
            return torch.as_tensor(self.inverse_fn(y_target, x0)).detach().to(x0.dtype)


def _default_loss(y: torch.Tensor, y_target: torch.Tensor) -> torch.Tensor:
    return 0.5 * ((y - y_target) ** 2).reshape(y.shape[0], -1).sum(dim=1)


def _default_metric(x: torch.Tensor, x_true: torch.Tensor) -> torch.Tensor:
    return (x - x_true.to(x.dtype)).abs().reshape(x.shape[0], -1).sum(dim=1)


@dataclass
class CustomProblem(Problem):
    """A problem assembled from user functions (build it with :func:`make_problem`).

    Attributes:
        data: ``(batch_size, generator) -> x_true`` or ``(x_true, y_target)``.
        physics: The forward process ``x -> y``.
        network: Factory of the network ``input -> x``.
        local_inverse: ``(y_target, x0) -> x`` or None.
        network_input: ``y_target -> network input`` (default: ``y_target`` itself).
        loss_fn: ``(y, y_target) -> (B,)`` y-space loss of each sample.
        metric_fn: ``(x, x_true) -> (B,)``; default ``Σ_cells |x − x*|`` (the y-space loss when the data
            has no ``x_true``).
        metric_name: Name and unit of the metric, e.g. ``"x L1 per sample (sum over cells)"``.
        lr: Learning rate of the Adam-based methods.
        sgd_lr: Learning rate of SGD with momentum 0.9.
        solver_iterations: Iterations of the generic local inverses.
        rcond: Relative cut-off of the pseudo-inverses of the generic inverses and of HIG.
        spec: ``{'factory': 'module:function', 'settings': {...}}`` when built by :func:`load_problem` (used
            to rebuild the network from a model file).
    """

    data: Callable[..., Any] | None = None
    physics: Callable[[torch.Tensor], torch.Tensor] | None = None
    network: Callable[[], nn.Module] | None = None
    local_inverse: Callable[[torch.Tensor, torch.Tensor], torch.Tensor] | None = None
    network_input: Callable[[torch.Tensor], torch.Tensor] | None = None
    loss_fn: Callable[[torch.Tensor, torch.Tensor], torch.Tensor] | None = None
    metric_fn: Callable[[torch.Tensor, torch.Tensor], torch.Tensor] | None = None
    metric_name: str = "x L1 per sample (sum over cells)"
    lr: float = 1e-3
    sgd_lr: float = 1e-3
    solver_iterations: int = 5
    rcond: float = 1e-6
    spec: dict = field(default_factory=dict)

    def __post_init__(self):
        for name in ("data", "physics", "network"):
            if not callable(getattr(self, name)):
                raise ParameterError(f"make_problem needs a callable {name}=..., got {getattr(self, name)!r}")
        for name in ("local_inverse", "network_input", "loss_fn", "metric_fn"):
            v = getattr(self, name)
            if v is not None and not callable(v):
                raise ParameterError(f"{name} must be callable or None, got {type(v).__name__}")
        if self.reduction not in ("sum", "mean"):
            raise ParameterError(f"reduction must be 'sum' or 'mean', got {self.reduction!r}")
        lr, it = self.lr, self.solver_iterations
        self.methods = {
            "adam": Method("adam", "physics", lr=lr),
            "sgd": Method("sgd", "physics", optimizer="sgd", lr=self.sgd_lr, momentum=0.9),
            "pg_inverse_gradient": Method("pg_inverse_gradient", "physgrad", lr=lr,
                                          local_solver=InverseGradientSolver(max_iter=it, rcond=self.rcond)),
            "pg_newton": Method("pg_newton", "physgrad", lr=lr,
                                local_solver=NewtonSolver(max_iter=it, rcond=self.rcond)),
            "pg_lbfgsb": Method("pg_lbfgsb", "physgrad", lr=lr, local_solver=LBFGSBSolver(max_iter=4 * it)),
            "supervised": Method("supervised", "supervised", lr=lr),
        }
        if self.local_inverse is not None:
            self.methods["pg"] = Method("pg", "physgrad", lr=lr)
        if self.network_input is None:
            self.methods["hig"] = Method("hig", "hig", optimizer="hig", lr=lr, rcond=self.rcond)
            physics = self.physics
            self.hig_physics = lambda out: physics(out)
        self._operator = CallableOperator(self.physics, self.local_inverse)

    def make_network(self) -> nn.Module:
        """A fresh network from the ``network`` factory.

        Raises:
            ParameterError: The factory did not return a ``torch.nn.Module``.
        """
        net = self.network()
        if not isinstance(net, nn.Module):
            raise ParameterError(f"the network factory of {self.name!r} returned {type(net).__name__}, "
                                 "expected a torch.nn.Module")
        return net

    def sample(self, batch_size: int, generator: torch.Generator, device=None) -> Batch:
        """A batch from ``data``: ``x_true`` and ``y* = physics(x_true)`` (or the targets ``data`` returns).

        Raises:
            ParameterError: ``data`` returned something other than a tensor or a pair of tensors.
            ShapeError: The batch size of what ``data`` returned is not ``batch_size``.
        """
        out = self.data(batch_size, generator)
        if isinstance(out, torch.Tensor):
            x_true, y = out, None
        elif isinstance(out, (tuple, list)) and len(out) == 2:
            x_true, y = out
        else:
            raise ParameterError(f"data() of {self.name!r} must return x_true or (x_true, y_target), "
                                 f"got {type(out).__name__}")
        for what, t in (("x_true", x_true), ("y_target", y)):
            if t is not None and not isinstance(t, torch.Tensor):
                raise ParameterError(f"data() returned {what} of type {type(t).__name__}, expected a tensor")
            if t is not None and t.shape[0] != batch_size:
                raise ShapeError(f"data() returned {what} with batch {t.shape[0]}, asked for {batch_size}")
        if x_true is None and y is None:
            raise ParameterError("data() returned neither x_true nor y_target")
        if x_true is not None:
            x_true = x_true.to(device=device, dtype=self.dtype)
        if y is None:
            with torch.no_grad():
                y = self.physics(x_true)
        y = y.to(device=device, dtype=self.dtype)
        inputs = y if self.network_input is None else self.network_input(y)
        return Batch(inputs, y, x_true, self._operator, labels=x_true, physics_args=())

    def predict(self, model: nn.Module, batch: Batch) -> torch.Tensor:
        """``x = network(input)``; its shape must be ``x_true``'s.

        Raises:
            ShapeError: The network output has another shape than ``x_true``.
        """
        x = model(batch.inputs)
        if batch.x_true is not None and x.shape != batch.x_true.shape:
            raise ShapeError(f"the network of {self.name!r} returns shape {tuple(x.shape)}, but x_true has "
                             f"shape {tuple(batch.x_true.shape)}")
        return x

    def loss(self, y: torch.Tensor, y_target: torch.Tensor) -> torch.Tensor:
        """The per-sample y-space loss (``loss_fn`` or ``½ Σ_cells (y − y*)²``), shape ``(B,)``."""
        return (self.loss_fn or _default_loss)(y, y_target)

    def metric(self, x: torch.Tensor, batch: Batch) -> torch.Tensor:
        """The per-sample metric (``metric_fn``, else ``Σ_cells |x − x*|``, else the y-space loss)."""
        if self.metric_fn is not None:
            return self.metric_fn(x, batch.x_true)
        if batch.x_true is None:
            return self.loss(batch.operator(x), batch.y_target)
        return _default_metric(x, batch.x_true)


def make_problem(
    name: str,
    *,
    data: Callable[..., Any],
    physics: Callable[[torch.Tensor], torch.Tensor],
    network: Callable[[], nn.Module],
    local_inverse: Callable[[torch.Tensor, torch.Tensor], torch.Tensor] | None = None,
    network_input: Callable[[torch.Tensor], torch.Tensor] | None = None,
    loss: Callable[[torch.Tensor, torch.Tensor], torch.Tensor] | None = None,
    metric: Callable[[torch.Tensor, torch.Tensor], torch.Tensor] | None = None,
    metric_name: str = "x L1 per sample (sum over cells)",
    batch_size: int = 16,
    reduction: str = "mean",
    dtype: torch.dtype = torch.float32,
    lr: float = 1e-3,
    sgd_lr: float = 1e-3,
    solver_iterations: int = 5,
    rcond: float = 1e-6,
) -> CustomProblem:
    """Build a :class:`CustomProblem` that :func:`inverse.train.train` trains with every method.

    Args:
        name: Name of the problem in logs and files.
        data: ``data(batch_size, generator) -> x_true`` or ``(x_true, y_target)``; draw all randomness from
            ``generator`` (a CPU ``torch.Generator``) so the data stream is reproducible.
        physics: Differentiable batched forward ``x -> y``.
        network: Zero-argument factory of the network (seed-controlled by the trainer).
        local_inverse: Problem-specific inverse ``(y_target, x0) -> x`` (gives the method ``pg``) or None.
        network_input: Map from ``y*`` to the network input (default ``y*``; HIG needs the default).
        loss: Per-sample y-space loss ``(y, y*) -> (B,)`` (default ``½ Σ (y − y*)²``); physical gradients
            take the Newton step of ``½‖y − y*‖²`` whatever this is.
        metric: Per-sample metric ``(x, x_true) -> (B,)`` (default ``Σ_cells |x − x*|``).
        metric_name: Name and unit of the metric.
        batch_size: Default batch size.
        reduction: ``'mean'`` or ``'sum'`` of the per-sample objective over the batch.
        dtype: Dtype of the network and the data.
        lr: Learning rate of the Adam-based methods.
        sgd_lr: Learning rate of SGD (momentum 0.9).
        solver_iterations: Iterations of the generic local inverses (L-BFGS-B gets four times as many).
        rcond: Relative cut-off of the generic inverses and HIG.

    Returns:
        The problem.

    Raises:
        ParameterError: A required function is missing or not callable, or a bad setting.
    """
    if batch_size < 1:
        raise ParameterError(f"batch_size must be >= 1, got {batch_size}")
    return CustomProblem(name=name, batch_size=int(batch_size), reduction=reduction, dtype=dtype, data=data,
                         physics=physics, network=network, local_inverse=local_inverse,
                         network_input=network_input, loss_fn=loss, metric_fn=metric, metric_name=metric_name,
                         lr=lr, sgd_lr=sgd_lr, solver_iterations=solver_iterations, rcond=rcond)


def is_factory_spec(name: str) -> bool:
    """True for ``module:function`` / ``file.py:function`` problem names (not a registered name)."""
    return isinstance(name, str) and ":" in name and not name.startswith(":") and not name.endswith(":")


def _is_file_module(module: str) -> bool:
    return module.endswith(".py") or "/" in module or "\\" in module


def _import_module(module: str):
    if _is_file_module(module):
        path = Path(module).expanduser().resolve()
        if not path.is_file():  # the wording of the command line's file checks
            state = "is a folder, not a file" if path.is_dir() else "does not exist"
            raise ParameterError(f"problem factory file {module} {state}")
        mod_name = f"_phisim_user_{abs(hash(str(path)))}"
        if mod_name in sys.modules:
            return sys.modules[mod_name]
        spec = importlib.util.spec_from_file_location(mod_name, path)
        mod = importlib.util.module_from_spec(spec)
        sys.modules[mod_name] = mod
        try:
            spec.loader.exec_module(mod)
        except Exception:
            del sys.modules[mod_name]
            raise
        return mod
    if "" not in sys.path and str(Path.cwd()) not in sys.path:
        sys.path.insert(0, str(Path.cwd()))  # like `python -m`: modules in the working directory
    try:
        return importlib.import_module(module)
    except ModuleNotFoundError as exc:
        raise ParameterError(f"cannot import problem module {module!r}: {exc}") from exc


def canonical_factory(spec: str) -> tuple[str, str | None]:
    """The factory name a model file stores, and the source file it came from.

    ``file.py:function`` becomes ``/absolute/path/file.py:function`` (resolved against the working directory
    now, so it names the same file from any other folder later); ``module:function`` stays as it is, and its
    module's file is returned as well (the fallback when the module is not importable from elsewhere, e.g. a
    module found only because the working directory was on the path).

    Args:
        spec: ``'package.module:function'`` or ``'file.py:function'``.

    Returns:
        ``(factory, source_file)``; ``source_file`` is an absolute path or None (a module without a file).

    Raises:
        ParameterError: Not a factory name.
    """
    if not is_factory_spec(spec):
        raise ParameterError(f"a problem factory is named 'module:function' or 'file.py:function', got {spec!r}")
    module, _, func = spec.rpartition(":")
    if _is_file_module(module):
        path = Path(module).expanduser().resolve()
        return f"{path}:{func}", str(path)
    mod = sys.modules.get(module)
    file = getattr(mod, "__file__", None) if mod is not None else None
    return spec, (str(Path(file).resolve()) if file else None)


def load_problem(spec: str, **settings) -> Problem:
    """Build a problem from a factory named ``module:function`` or ``path/to/file.py:function``.

    The factory is called with ``settings`` as keyword arguments and must return a
    :class:`~inverse.problems.Problem` (e.g. from :func:`make_problem`).

    Args:
        spec: ``'package.module:function'`` or ``'file.py:function'``.
        **settings: Keyword arguments of the factory.

    Returns:
        The problem, with ``problem.spec = {'factory': ..., 'settings': settings, 'source': ...}`` recorded for
        model files: the factory as :func:`canonical_factory` names it (a file's absolute path, so a model
        file rebuilds its network from any working directory) and the file it came from.

    Raises:
        ParameterError: Unknown module or function (the closest names are suggested), bad settings, or a
            factory that returns something other than a Problem.
    """
    if not is_factory_spec(spec):
        raise ParameterError(f"a problem factory is named 'module:function' or 'file.py:function', got {spec!r}")
    module, _, func = spec.rpartition(":")
    mod = _import_module(module)
    factory = getattr(mod, func, None)
    if factory is None:
        names = [n for n in dir(mod) if not n.startswith("_") and callable(getattr(mod, n))]
        close = difflib.get_close_matches(func, names, n=1)
        hint = f"; did you mean {close[0]!r}?" if close else ""
        raise ParameterError(f"module {module!r} has no function {func!r}{hint}")
    if not callable(factory):
        raise ParameterError(f"{spec} is not callable")
    try:
        problem = factory(**settings)
    except TypeError as exc:
        raise ParameterError(f"bad settings for problem factory {spec}: {exc}") from exc
    if not isinstance(problem, Problem):
        raise ParameterError(f"problem factory {spec} returned {type(problem).__name__}, expected an "
                             "inverse.Problem (build one with inverse.make_problem)")
    factory_name, source = canonical_factory(spec)
    problem.spec = {"factory": factory_name, "settings": dict(settings), "source": source}
    return problem
