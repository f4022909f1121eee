"""Data-parallel helpers: process-group start-up from ``torchrun``'s environment, per-rank devices, and a
batch normalisation whose statistics are those of the whole (all-process) batch.

``torchrun --nproc_per_node N script.py`` starts N processes with ``RANK``, ``LOCAL_RANK``, ``WORLD_SIZE``,
``MASTER_ADDR`` and ``MASTER_PORT`` in their environment. :func:`init_from_env` turns that into a
``torch.distributed`` process group (NCCL for CUDA devices, gloo otherwise), and :func:`rank_device` gives
each process its own GPU (``cuda:LOCAL_RANK``).

Why :class:`SyncBatchNorm`: with data parallelism each process sees ``B/N`` samples; a plain BatchNorm layer
normalises with the statistics of that share, so N processes do not follow the one-process trajectory.
This layer all-reduces the per-channel sums (differentiably, so the backward pass is exact too) and
normalises with the statistics of the whole batch, on any device and backend (torch's own
``nn.SyncBatchNorm`` refuses CPU tensors, so it cannot run under gloo).
"""

from __future__ import annotations

import os

import torch
import torch.distributed as dist
from torch import nn

from phisim.errors import ParameterError

__all__ = ["launched_by_torchrun", "init_from_env", "rank_device", "is_main_process", "SyncBatchNorm",
           "convert_sync_batchnorm"]

_ENV = ("RANK", "WORLD_SIZE", "LOCAL_RANK", "MASTER_ADDR", "MASTER_PORT")


def launched_by_torchrun() -> bool:
    """Whether this process was started by ``torchrun`` (its environment variables are set)."""
    return all(k in os.environ for k in ("RANK", "WORLD_SIZE", "MASTER_ADDR", "MASTER_PORT"))


def rank_device(device: str | torch.device) -> torch.device:
    """The device of this process: a CUDA device without an index becomes ``cuda:LOCAL_RANK``.

    Args:
        device: The requested device (``'cpu'``, ``'cuda'``, ``'cuda:1'``...). An explicit index is kept.

    Returns:
        The torch device.
    """
    device = torch.device(device)
    if device.type == "cuda" and device.index is None:
        return torch.device("cuda", int(os.environ.get("LOCAL_RANK", "0")))
    return device


def init_from_env(device: str | torch.device = "cpu", backend: str | None = None) -> bool:
    """Initialise the default process group from ``torchrun``'s environment, once.

    Args:
        device: The training device; a CUDA device selects NCCL (and ``torch.cuda.set_device`` of this
            process's GPU), anything else gloo.
        backend: Override the backend.

    Returns:
        True when a process group is initialised (now or before), False when not launched by torchrun.

    Raises:
        ParameterError: For malformed torchrun variables.
    """
    if not dist.is_available():
        return False
    if dist.is_initialized():
        return True
    if not launched_by_torchrun():
        return False
    try:
        world = int(os.environ["WORLD_SIZE"])
        rank = int(os.environ["RANK"])
    except ValueError as exc:
        raise ParameterError(f"malformed torchrun environment: {exc}") from exc
    dev = rank_device(device)
    if backend is None:
        backend = "nccl" if dev.type == "cuda" else "gloo"
    if dev.type == "cuda":
        torch.cuda.set_device(dev)
    dist.init_process_group(backend, init_method="env://", rank=rank, world_size=world)
    return True


def is_main_process() -> bool:
    """True in process 0 of an initialised group, and in a single process."""
    return not (dist.is_available() and dist.is_initialized()) or dist.get_rank() == 0


class _AllReduceSum(torch.autograd.Function):
    """Sum over processes; the backward pass sums the incoming gradients the same way (each process's
    input feeds every process's output)."""

    @staticmethod
    def forward(ctx, t: torch.Tensor) -> torch.Tensor:
        out = t.clone()
        dist.all_reduce(out)
        return out

    @staticmethod
    def backward(ctx, grad: torch.Tensor) -> torch.Tensor:
        out = grad.contiguous().clone()
        dist.all_reduce(out)
        return out


def _all_reduce(t: torch.Tensor) -> torch.Tensor:
    return _AllReduceSum.apply(t)


class SyncBatchNorm(nn.modules.batchnorm._BatchNorm):
    """Batch normalisation over the union of every process's batch (any device, any backend).

    In training mode inside an initialised process group with more than one process, the per-channel mean
    and (biased) variance are computed over all processes' samples with two differentiable all-reduces
    (sums, then squared deviations), so the forward and backward passes equal those of one process holding
    the whole batch up to round-off. Running statistics use the unbiased variance of the whole batch, as
    ``nn.BatchNorm`` does. Outside a group, or in eval mode, it is a plain BatchNorm. Parameter and buffer
    names equal ``nn.BatchNorm2d``'s, so state dicts load either way.
    """

    def _check_input_dim(self, input: torch.Tensor) -> None:
        if input.dim() < 2:
            raise ValueError(f"expected at least 2-D input (batch, channels, ...), got {input.dim()}-D")

    def forward(self, input: torch.Tensor) -> torch.Tensor:
        """Normalise ``input`` ``(B, C, ...)`` with whole-batch statistics in training mode."""
        if not (self.training and dist.is_available() and dist.is_initialized() and dist.get_world_size() > 1):
            return super().forward(input)
        self._check_input_dim(input)
        dims = [0, *range(2, input.dim())]
        shape = (1, -1) + (1,) * (input.dim() - 2)
        count = torch.tensor([input.numel() // input.shape[1]], dtype=input.dtype, device=input.device)
        sums = _all_reduce(torch.cat([input.sum(dims), count]))
        n = sums[-1]
        mean = sums[:-1] / n
        centred = input - mean.view(shape)
        var = _all_reduce((centred * centred).sum(dims)) / n
        out = centred * torch.rsqrt(var + self.eps).view(shape)
        if self.affine:
            out = out * self.weight.view(shape) + self.bias.view(shape)
        if self.track_running_stats:
            with torch.no_grad():
                self.num_batches_tracked.add_(1)
                m = 1.0 / float(self.num_batches_tracked) if self.momentum is None else self.momentum
                self.running_mean.mul_(1 - m).add_(mean.detach() * m)
                self.running_var.mul_(1 - m).add_(var.detach() * (n / (n - 1)).clamp(min=0) * m)
        return out


def convert_sync_batchnorm(module: nn.Module) -> nn.Module:
    """Replace every ``nn.BatchNorm1d/2d/3d`` in ``module`` by :class:`SyncBatchNorm` (same parameters).

    Args:
        module: A network (changed in place where possible).

    Returns:
        The network with synchronised batch normalisation.
    """
    if isinstance(module, nn.modules.batchnorm._BatchNorm) and not isinstance(module, SyncBatchNorm):
        ref = next(iter([*module.parameters(), *module.buffers()]), None)
        kw = {} if ref is None else {"device": ref.device, "dtype": ref.dtype if ref.is_floating_point() else None}
        new = SyncBatchNorm(module.num_features, module.eps, module.momentum, module.affine,
                            module.track_running_stats, **kw)
        new.load_state_dict(module.state_dict())
        if module.affine:
            new.weight, new.bias = module.weight, module.bias
        new.train(module.training)
        return new
    for name, child in module.named_children():
        module.add_module(name, convert_sync_batchnorm(child))
    return module
