"""Half-inverse gradients (HIG) and Gauss-Newton as torch optimizers.

A network ``f_theta`` maps inputs ``x_i`` to outputs that a differentiable physics function ``P``
turns into ``y_i = P(f_theta(x_i))``. With ``g`` the gradient of the batch loss with respect to the
stacked outputs ``y`` and ``J = d y / d theta`` the stacked per-sample Jacobians (one block of
``dim_y`` rows per sample, ``(B * dim_y) x n_theta`` in all), the update is

    Delta theta = -lr * V diag(s^-kappa) U^T g,     J = U diag(s) V^T  (thin SVD),

where singular values below ``rcond * max(s)`` are *dropped* (their inverse is set to zero, never
clamped). ``kappa = 1/2`` is the half-inverse gradient (Schnell, Holl & Thuerey, "Half-Inverse
Gradients for Physical Deep Learning", ICLR 2022); ``kappa = 1`` is the truncated pseudo-inverse
Gauss-Newton step; ``kappa = -1`` reproduces the plain gradient ``J^T g``.

The per-sample Jacobians come from ``torch.func`` (``vmap`` over ``jacrev`` of a
``functional_call`` of the model), computed in chunks of samples when the whole batch does not
fit the configured memory budget. The update is applied to the parameters by plain SGD.

Example:
    >>> net = torch.nn.Sequential(torch.nn.Linear(1, 7), torch.nn.Tanh(), torch.nn.Linear(7, 2))
    >>> opt = HIG(net, physics=lambda out: out * torch.tensor([1.0, 0.01]), lr=1.0)
    >>> info = opt.step(x, targets)          # x: (B, 1), targets: (B, 2)
    >>> info.loss, info.n_kept, info.n_dropped
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import torch
from torch import nn
from torch.func import functional_call, jacrev, vmap

from phisim.checks import (
    all_finite,
    callable_name,
    check_batch_compatible,
    check_bool,
    check_callable,
    check_choice,
    check_int,
    check_number,
)
from phisim.errors import NonFiniteError, ParameterError, PhisimError, ShapeError

__all__ = [
    "JacobianMemoryError",
    "HIGStepInfo",
    "hig_update",
    "truncated_power_svd",
    "squared_error",
    "per_sample_jacobian",
    "HIG",
    "GaussNewton",
]

#: Default memory budget (bytes) for the Jacobian, its SVD and the per-chunk work on CPU.
DEFAULT_CPU_BUDGET = 4 * 2**30


class JacobianMemoryError(PhisimError, MemoryError):
    """The stacked Jacobian and its SVD do not fit the memory budget, even when built in chunks.

    Attributes:
        required: Estimated bytes needed for the smallest workable configuration.
        budget: The memory budget in bytes.
    """

    def __init__(self, message: str, required: int | None = None, budget: int | None = None):
        super().__init__(message)
        self.required = required
        self.budget = budget


@dataclass(frozen=True)
class HIGStepInfo:
    """Diagnostics of one HIG / Gauss-Newton step.

    Attributes:
        loss: Batch loss before the step (mean of the per-sample losses).
        singular_values: All singular values of the stacked Jacobian, descending, shape
            ``(min(B * dim_y, n_theta),)``, on the CPU.
        n_kept: Number of singular values at or above ``rcond * max(s)`` (used in the update).
        n_dropped: Number of singular values below the cut-off (their inverse set to zero).
        cutoff: The absolute cut-off ``rcond * max(s)``.
        update_norm: Euclidean norm of the parameter update ``Delta theta`` (learning rate included).
        n_chunks: Number of sample chunks the Jacobian was built in.
        times: Seconds spent in ``"jacobian"``, ``"svd"`` and ``"apply"`` (filled when the optimizer
            was built with ``timing=True``; CUDA is synchronised around each phase then).
    """

    loss: float
    singular_values: torch.Tensor
    n_kept: int
    n_dropped: int
    cutoff: float
    update_norm: float
    n_chunks: int
    times: dict[str, float] = field(default_factory=dict)


def _check_rcond_exponent(rcond: float, exponent: float) -> tuple[float, float]:
    return (check_number(rcond, "rcond", minimum=0),
            check_number(exponent, "exponent (0.5 for HIG, 1 for Gauss-Newton)"))


def _thin_svd(J: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Thin SVD ``J = U diag(s) Vh``, computed on the tall orientation.

    LAPACK's divide-and-conquer SVD is several times faster on a tall matrix than on the same matrix
    transposed (``(128, 1444)``: 10 ms wide vs 4 ms tall on one CPU core). A wide ``J`` (the usual HIG case,
    fewer output rows than parameters) is therefore factorised as ``J^T = U' diag(s) V'^T``, which gives
    ``U = V'`` and ``Vh = U'^T`` with the same singular values.
    """
    wide = J.shape[0] < J.shape[1]
    A = J.mT if wide else J
    try:
        U, s, Vh = torch.linalg.svd(A, full_matrices=False)
    except RuntimeError as err:  # LAPACK/cuSOLVER non-convergence: retry once in float64 on the CPU
        try:
            U, s, Vh = torch.linalg.svd(A.detach().double().cpu(), full_matrices=False)
            U, s, Vh = (t.to(J.device, J.dtype) for t in (U, s, Vh))
        except RuntimeError:
            raise PhisimError(f"SVD of the {tuple(J.shape)} Jacobian did not converge: {err}") from err
    return (Vh.mT, s, U.mT) if wide else (U, s, Vh)


def truncated_power_svd(
    J: torch.Tensor, g: torch.Tensor, *, rcond: float = 1e-10, exponent: float = 0.5
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Compute ``V diag(s^-exponent) U^T g`` from the thin SVD of ``J``, dropping small singular values.

    Args:
        J: Matrix of shape ``(M, N)``, floating point (float32 or float64), finite.
        g: Vector of shape ``(M,)``, same dtype and device as ``J``, finite.
        rcond: Relative cut-off: singular values ``s < rcond * max(s)`` get an inverse of exactly zero
            (truncation, not clamping). Must be finite and ``>= 0``.
        exponent: Power ``kappa`` applied to the kept singular values as ``s^-kappa``
            (0.5: half-inverse, 1: pseudo-inverse, -1: ``J^T g``).

    Returns:
        ``(direction, s, kept)``: the direction of shape ``(N,)``, all singular values ``s`` of shape
        ``(min(M, N),)`` in descending order, and the boolean mask ``kept`` of the same shape.

    Raises:
        ShapeError: ``J`` is not 2-D or ``g`` is not a vector of length ``M``.
        ParameterError: Bad ``rcond``/``exponent``, non-floating or mismatched dtypes/devices.
        NonFiniteError: ``J`` or ``g`` contains NaN or Inf.
    """
    _check_rcond_exponent(rcond, exponent)
    if not isinstance(J, torch.Tensor) or not isinstance(g, torch.Tensor):
        raise ParameterError("J and g must be torch tensors")
    if J.ndim != 2:
        raise ShapeError(f"J must be a 2-D matrix (B*dim_y, n_theta), got shape {tuple(J.shape)}")
    if g.ndim != 1 or g.shape[0] != J.shape[0]:
        raise ShapeError(
            f"g must be a vector with one entry per row of J ({J.shape[0]}), got shape {tuple(g.shape)}"
        )
    if not J.is_floating_point() or J.dtype != g.dtype:
        raise ParameterError(f"J and g must share one floating dtype, got {J.dtype} and {g.dtype}")
    if J.device != g.device:
        raise ParameterError(f"J and g must be on one device, got {J.device} and {g.device}")
    if J.numel() == 0:
        raise ShapeError(f"J is empty, shape {tuple(J.shape)}")
    if not bool(torch.isfinite(J).all()):
        raise NonFiniteError("the Jacobian J contains NaN or Inf; check the network and the physics function")
    if not bool(torch.isfinite(g).all()):
        raise NonFiniteError("the loss gradient g contains NaN or Inf; check the loss function")
    U, s, Vh = _thin_svd(J)
    smax = s[0] if s.numel() else s.new_zeros(())
    kept = s >= rcond * smax
    kept &= s > 0  # a zero singular value carries no direction, whatever rcond says
    inv = torch.where(kept, s.clamp_min(torch.finfo(s.dtype).tiny) ** (-exponent), torch.zeros_like(s))
    direction = Vh.mT @ (inv * (U.mT @ g))
    return direction, s, kept


def hig_update(J: torch.Tensor, g: torch.Tensor, rcond: float = 1e-10, exponent: float = 0.5) -> torch.Tensor:
    """The HIG / Gauss-Newton direction ``V diag(s^-exponent) U^T g`` (no learning rate, no sign).

    The parameter update is ``Delta theta = -lr * hig_update(J, g, rcond, exponent)``. Singular values
    below ``rcond * max(s)`` are dropped (inverse set to zero).

    Args:
        J: Stacked Jacobian ``d y / d theta`` of shape ``(B * dim_y, n_theta)``.
        g: Loss gradient with respect to the stacked outputs, shape ``(B * dim_y,)``.
        rcond: Relative truncation threshold, finite and ``>= 0``.
        exponent: 0.5 for HIG, 1 for Gauss-Newton (pseudo-inverse), -1 for the plain gradient.

    Returns:
        The direction, shape ``(n_theta,)``, dtype and device of ``J``.

    Raises:
        ShapeError: Wrong shapes.
        ParameterError: Bad ``rcond``/``exponent`` or mismatched dtypes/devices.
        NonFiniteError: NaN or Inf in ``J`` or ``g``.
    """
    direction, _, _ = truncated_power_svd(J, g, rcond=rcond, exponent=exponent)
    return direction


def squared_error(y: torch.Tensor, targets: torch.Tensor) -> torch.Tensor:
    """Per-sample loss ``0.5 * sum((y - targets)^2)`` over all non-batch axes.

    Args:
        y: Outputs of shape ``(B, ...)``.
        targets: Targets of the same shape.

    Returns:
        Losses of shape ``(B,)``.

    Raises:
        ShapeError: The shapes differ.
    """
    if y.shape != targets.shape:
        raise ShapeError(
            f"outputs {tuple(y.shape)} and targets {tuple(targets.shape)} must have the same shape"
        )
    return 0.5 * (y - targets).pow(2).reshape(y.shape[0], -1).sum(dim=1)


def _trainable(model: nn.Module) -> dict[str, torch.Tensor]:
    return {name: p for name, p in model.named_parameters() if p.requires_grad}


def per_sample_jacobian(
    model: nn.Module,
    inputs: torch.Tensor,
    physics: Callable[..., torch.Tensor] | None = None,
    physics_args: Sequence[torch.Tensor] = (),
    *,
    chunk_size: int | None = None,
) -> torch.Tensor:
    """Stacked per-sample Jacobians ``d y_i / d theta`` of ``y = physics(model(x), *physics_args)``.

    Each sample is evaluated on its own (as a batch of one) with ``torch.func.functional_call``;
    ``vmap`` over ``jacrev`` gives all samples of a chunk at once. The model must treat samples
    independently (no batch-norm in training mode).

    Args:
        model: The network; its parameters with ``requires_grad=True`` are ``theta`` (in
            ``named_parameters()`` order), the others are constants.
        inputs: Network inputs of shape ``(B, ...)``.
        physics: Differentiable function ``(net_out, *physics_args) -> y`` acting on batches;
            ``None`` means the identity.
        physics_args: Extra per-sample tensors for ``physics`` (each of shape ``(B, ...)``, or ``(1, ...)``
            shared by every sample).
        chunk_size: Samples per ``vmap`` call; ``None`` means all ``B`` at once.

    Returns:
        ``J`` of shape ``(B * dim_y, n_theta)``; rows ``i*dim_y:(i+1)*dim_y`` belong to sample ``i``.

    Raises:
        ShapeError: Mismatched batch sizes or an empty batch.
        ParameterError: The model has no trainable parameters or ``chunk_size < 1``.
    """
    params = _trainable(model)
    if not params:
        raise ParameterError("the model has no trainable parameters (requires_grad=True)")
    if physics is not None:
        check_callable(physics, "physics")
    B = _batch_size(inputs, physics_args)
    physics_args = _expand_args(physics_args, B)
    chunk_size = check_int(chunk_size, "chunk_size", minimum=1, allow_none=True)
    if chunk_size is None:
        chunk_size = B
    names = list(params)
    detached = {k: v.detach() for k, v in params.items()}

    def single(p: dict[str, torch.Tensor], x: torch.Tensor, *args: torch.Tensor) -> torch.Tensor:
        out = functional_call(model, p, (x.unsqueeze(0),))
        if physics is not None:
            out = physics(out, *(a.unsqueeze(0) for a in args))
        return out.reshape(-1)

    jac_fn = vmap(jacrev(single), in_dims=(None, 0) + (0,) * len(physics_args))
    blocks = []
    for start in range(0, B, int(chunk_size)):
        stop = min(B, start + int(chunk_size))
        jac = jac_fn(detached, inputs[start:stop], *(a[start:stop] for a in physics_args))
        n = stop - start
        rows = [jac[k].reshape(n, jac[k].shape[1], -1) for k in names]
        blocks.append(torch.cat(rows, dim=2).reshape(-1, sum(r.shape[2] for r in rows)))
    return torch.cat(blocks, dim=0) if len(blocks) > 1 else blocks[0]


def _batch_size(inputs: torch.Tensor, physics_args: Sequence[torch.Tensor]) -> int:
    if not isinstance(inputs, torch.Tensor) or inputs.ndim < 1:
        raise ShapeError("inputs must be a tensor with a leading batch axis (B, ...)")
    B = inputs.shape[0]
    if B == 0:
        raise ShapeError("the batch is empty")
    for k, a in enumerate(physics_args):
        if not isinstance(a, torch.Tensor) or a.ndim < 1:
            shape = tuple(a.shape) if isinstance(a, torch.Tensor) else type(a).__name__
            raise ShapeError(f"physics_args[{k}] must have batch size {B} (or 1) on axis 0, got {shape}")
        if a.shape[0] not in (1, B):
            raise ShapeError(f"cannot evaluate the physics: inputs has batch size {B} but physics_args[{k}] has batch "
                             f"size {a.shape[0]}; it must be {B}, or 1 (shared by every sample)")
    return B


def _expand_args(physics_args: Sequence[torch.Tensor], B: int) -> tuple[torch.Tensor, ...]:
    """``physics_args`` with a batch of 1 shared by all ``B`` samples (expanded, no copy)."""
    return tuple(a.expand(B, *a.shape[1:]) if a.shape[0] != B else a for a in physics_args)


class HIG(torch.optim.Optimizer):
    """Half-inverse-gradient optimizer (``exponent=0.5``) for a network followed by physics.

    Each :meth:`step` evaluates ``y = physics(model(inputs), *physics_args)``, the per-sample losses
    ``loss_fn(y, targets)`` (shape ``(B,)``), the gradient ``g`` of their mean (``reduction="mean"``,
    as in the reference implementation) or sum with respect to ``y``, the stacked Jacobian
    ``d y / d theta`` and applies ``theta <- theta - lr * V diag(s^-exponent) U^T g`` (plain SGD).
    ``lr`` lives in ``param_groups[0]["lr"]``, so torch learning-rate schedulers work.

    Args:
        model: The network; all parameters with ``requires_grad=True`` are optimised.
        physics: Differentiable batch function ``(net_out, *physics_args) -> y``; ``None``: identity.
        lr: Learning rate ``eta`` (> 0). 1 is the usual choice for HIG and Gauss-Newton.
        rcond: Relative truncation threshold (>= 0): singular values below ``rcond * max(s)`` are dropped.
        exponent: Power of the inverted singular values (0.5: HIG, 1: Gauss-Newton).
        reduction: ``"mean"`` (``g`` of the mean per-sample loss) or ``"sum"``.
        memory_budget: Bytes allowed for the Jacobian, its SVD and the Jacobian work of one chunk.
            ``None``: 80% of the free CUDA memory on a GPU, 4 GiB on the CPU.
        chunk_size: Samples per Jacobian chunk; ``None`` chooses it from ``memory_budget``.
        timing: Record per-phase times in :class:`HIGStepInfo` (synchronises CUDA).

    Raises:
        ParameterError: Bad hyper-parameters or a model without trainable parameters.
    """

    def __init__(
        self,
        model: nn.Module,
        physics: Callable[..., torch.Tensor] | None = None,
        lr: float = 1.0,
        rcond: float = 1e-10,
        exponent: float = 0.5,
        *,
        reduction: str = "mean",
        memory_budget: int | None = None,
        chunk_size: int | None = None,
        timing: bool = False,
    ):
        if not isinstance(model, nn.Module):
            raise ParameterError(f"model must be a torch.nn.Module, got {type(model).__name__}")
        if physics is not None:
            check_callable(physics, "physics")
        lr = check_number(lr, "lr", minimum=0, min_open=True)
        rcond, exponent = _check_rcond_exponent(rcond, exponent)
        check_choice(reduction, "reduction", ("mean", "sum"))
        memory_budget = check_int(memory_budget, "memory_budget (bytes)", minimum=1, allow_none=True)
        chunk_size = check_int(chunk_size, "chunk_size", minimum=1, allow_none=True)
        timing = check_bool(timing, "timing")
        params = _trainable(model)
        if not params:
            raise ParameterError("the model has no trainable parameters (requires_grad=True)")
        super().__init__(
            list(params.values()), dict(lr=float(lr), rcond=float(rcond), exponent=float(exponent))
        )
        self.model = model
        self.physics = physics
        self.reduction = reduction
        self.memory_budget = memory_budget
        self.chunk_size = chunk_size
        self.timing = timing
        self.n_theta = sum(p.numel() for p in params.values())

    # -- memory planning -------------------------------------------------------------------------
    def _budget(self, device: torch.device) -> int:
        if self.memory_budget is not None:
            return int(self.memory_budget)
        if device.type == "cuda":
            free, _ = torch.cuda.mem_get_info(device)
            return int(0.8 * free)
        return DEFAULT_CPU_BUDGET

    def plan_chunks(self, batch_size: int, dim_y: int, dtype: torch.dtype, device: torch.device) -> int:
        """Choose the number of samples per Jacobian chunk for the memory budget.

        The resident part is the Jacobian (``M x N`` with ``M = B * dim_y``, ``N = n_theta``) plus the
        SVD (a working copy of ``J``, ``U``: ``M x K``, ``V^T``: ``K x N``, ``K = min(M, N)``); each sample
        of a chunk needs about twice its own Jacobian block (``dim_y x N``) while it is built.

        Args:
            batch_size: ``B``.
            dim_y: Output entries per sample.
            dtype: Floating dtype of the computation.
            device: Device of the computation.

        Returns:
            Samples per chunk, between 1 and ``batch_size`` (``self.chunk_size`` when given).

        Raises:
            JacobianMemoryError: Even one sample per chunk exceeds the budget.
        """
        item = torch.finfo(dtype).bits // 8
        M, N = batch_size * dim_y, self.n_theta
        K = min(M, N)
        resident = (2 * M * N + M * K + K * N) * item
        per_sample = 2 * dim_y * N * item
        budget = self._budget(device)
        if resident + per_sample > budget:
            raise JacobianMemoryError(
                f"the ({M} x {N}) Jacobian and its SVD need about {(resident + per_sample) / 2**20:.1f} MiB, "
                f"more than the memory budget of {budget / 2**20:.1f} MiB even when built one sample at a "
                "time; use a smaller batch, a smaller network, or raise memory_budget",
                required=resident + per_sample,
                budget=budget,
            )
        if self.chunk_size is not None:
            return min(batch_size, self.chunk_size)
        return max(1, min(batch_size, (budget - resident) // per_sample))

    # -- the step ------------------------------------------------------------------------------------
    def _sync(self, device: torch.device) -> None:
        if self.timing and device.type == "cuda":
            torch.cuda.synchronize(device)

    def step(  # type: ignore[override]
        self,
        inputs: torch.Tensor,
        targets: torch.Tensor | None = None,
        *,
        loss_fn: Callable[[torch.Tensor, torch.Tensor | None], torch.Tensor] | None = None,
        physics_args: Sequence[torch.Tensor] = (),
    ) -> HIGStepInfo:
        """One HIG (or Gauss-Newton) update of the model parameters.

        Args:
            inputs: Network inputs, shape ``(B, ...)``, on the device and dtype of the model.
            targets: Targets for ``loss_fn`` (shape of ``y`` for the default loss), or ``None``.
            loss_fn: ``(y, targets) -> (B,)`` per-sample losses; default :func:`squared_error`
                (``0.5 * ||y - targets||^2``), which needs ``targets``.
            physics_args: Extra per-sample tensors passed to ``physics`` after the network output.

        Returns:
            :class:`HIGStepInfo` with the loss before the step and the singular-value diagnostics.

        Raises:
            ShapeError: Batch sizes differ, ``loss_fn`` does not return shape ``(B,)``, empty batch.
            ParameterError: No loss function and no targets.
            NonFiniteError: The loss, its gradient or the Jacobian is NaN/Inf (parameters untouched).
            JacobianMemoryError: The Jacobian cannot fit the memory budget.
        """
        group = self.param_groups[0]
        lr, rcond, exponent = group["lr"], group["rcond"], group["exponent"]
        if loss_fn is None:
            if targets is None:
                raise ParameterError("step() needs targets for the default squared-error loss, or a loss_fn")
            loss_fn = squared_error
        B = _batch_size(inputs, physics_args)
        physics_args = _expand_args(physics_args, B)
        device = inputs.device
        times: dict[str, float] = {}

        # loss and g = d loss / d y (no graph through the parameters)
        with torch.no_grad():
            out = self.model(inputs)
            y = self.physics(out, *physics_args) if self.physics is not None else out
        who = f"physics {callable_name(self.physics)}" if self.physics is not None else "the model"
        if not isinstance(y, torch.Tensor) or y.ndim < 1 or y.shape[0] != B:
            shape = tuple(y.shape) if isinstance(y, torch.Tensor) else type(y).__name__
            raise ShapeError(f"{who} returned {shape}; its output must have batch size {B} on axis 0")
        if not all_finite(y.detach()):
            raise NonFiniteError(f"{who} returned NaN/Inf for inputs of shape {tuple(inputs.shape)}; the parameters "
                                 "were not changed")
        if isinstance(targets, torch.Tensor) and targets.ndim >= 1:
            check_batch_compatible(y, targets, ("the physics output", "targets"), "compute the loss")
        y = y.detach().requires_grad_(True)
        with torch.enable_grad():
            losses = loss_fn(y, targets)
            if not isinstance(losses, torch.Tensor) or losses.shape != (B,):
                shape = tuple(losses.shape) if isinstance(losses, torch.Tensor) else type(losses).__name__
                raise ShapeError(f"loss_fn {callable_name(loss_fn)} returned {shape}; it must return per-sample "
                                 f"losses of shape ({B},)")
            if not bool(torch.isfinite(losses).all()):
                raise NonFiniteError(
                    "the loss is NaN or Inf before the step; the parameters were not changed "
                    "(lower lr, raise rcond, or check the inputs)"
                )
            total = losses.mean() if self.reduction == "mean" else losses.sum()
            (g,) = torch.autograd.grad(total, y)
        dim_y = y[0].numel()

        # stacked Jacobian, chunked to the memory budget
        chunk = self.plan_chunks(B, dim_y, y.dtype, device)
        self._sync(device)
        t0 = time.perf_counter()
        J = per_sample_jacobian(self.model, inputs, self.physics, physics_args, chunk_size=chunk)
        self._sync(device)
        t1 = time.perf_counter()
        direction, s, kept = truncated_power_svd(J, g.reshape(-1).to(J.dtype), rcond=rcond, exponent=exponent)
        self._sync(device)
        t2 = time.perf_counter()
        delta = direction.mul(-lr)
        with torch.no_grad():
            offset = 0
            for p in self.param_groups[0]["params"]:
                n = p.numel()
                p.add_(delta[offset : offset + n].view_as(p).to(p.dtype))
                offset += n
        self._sync(device)
        t3 = time.perf_counter()
        if self.timing:
            times = {"jacobian": t1 - t0, "svd": t2 - t1, "apply": t3 - t2}
        n_kept = int(kept.sum())
        return HIGStepInfo(
            loss=float(losses.detach().mean()),
            singular_values=s.detach().cpu(),
            n_kept=n_kept,
            n_dropped=int(s.numel() - n_kept),
            cutoff=float(rcond * s[0]) if s.numel() else 0.0,
            update_norm=float(delta.norm()),
            n_chunks=math.ceil(B / chunk),
            times=times,
        )


class GaussNewton(HIG):
    """Truncated Gauss-Newton optimizer: :class:`HIG` with ``exponent=1`` (pseudo-inverse of ``J``).

    ``Delta theta = -lr * V diag(1/s) U^T g`` with singular values below ``rcond * max(s)`` dropped.
    With ``reduction="sum"``, the default loss and ``lr=1`` this is the full Gauss-Newton step on
    ``0.5 * ||y - targets||^2``.

    Args:
        model: The network.
        physics: Differentiable batch function ``(net_out, *physics_args) -> y``; ``None``: identity.
        lr: Learning rate (> 0).
        rcond: Relative truncation threshold (>= 0).
        **kwargs: ``reduction``, ``memory_budget``, ``chunk_size``, ``timing`` as for :class:`HIG`.

    Raises:
        ParameterError: Bad hyper-parameters.
    """

    def __init__(
        self,
        model: nn.Module,
        physics: Callable[..., torch.Tensor] | None = None,
        lr: float = 1.0,
        rcond: float = 1e-10,
        **kwargs,
    ):
        super().__init__(model, physics, lr=lr, rcond=rcond, exponent=1.0, **kwargs)
