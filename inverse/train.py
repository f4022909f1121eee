"""One training loop for every method: through the physics (Adam/SGD), physical gradients, supervised, HIG.

Every method sees the same data stream: batch ``i`` of a run with seed ``s`` is drawn from a generator
seeded with ``(s, i)``, so curves of different methods compare sample by sample, and a resumed run
continues the exact stream. The network initialisation is seeded with ``s`` too.

Per iteration the loop logs, into ``/training/<method>/...`` of an HDF5 file (:class:`phisim.io.TrainingLog`,
flushed every record):

* ``loss``, ``metric``: the problem's y-space loss and metric on the **training batch**, measured during the
  update (network in train mode, before the optimizer step), mean per sample;
* ``eval_loss``, ``eval_metric``: the same on the problem's fixed **held-out set** (:meth:`Problem.heldout`,
  ``heldout_size`` samples, its own seed) with the network in eval mode after the update, every
  ``eval_every`` iterations and after the last one (NaN in the other records);
* ``objective`` (the value backpropagated) and ``time``.

The group's attributes ``loss_name`` and ``metric_name`` say what the curves measure (e.g. "x L1 per sample
(sum over cells of |x−x*|)").
Checkpoints (model, optimizer, iteration) are written atomically every ``checkpoint_every`` iterations;
a killed run loses at most that interval and ``resume=True`` continues it, truncating the log to the
checkpoint. A file that already holds a run of the method is never written over silently: without
``resume=True`` or ``overwrite=True`` the run is refused before any work. The log records the planned
number of iterations and, at the end, a completion mark, so an interrupted run reads back as incomplete.

SIGINT and SIGTERM stop a run promptly (:func:`phisim.io.interrupts.interruptible`): the interrupt is raised
between file writes, the log is closed cleanly and no half-written checkpoint or model file remains.
"""

from __future__ import annotations

import dataclasses
import math
import os
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import h5py
import numpy as np
import torch
from torch import nn

from phisim.checks import check_bool, check_device, check_int, check_progress, check_seed
from phisim.errors import FileFormatError, NonFiniteError, ParameterError
from phisim.io import TrainingLog, recover_file
from phisim.io.h5util import check_output_path
from phisim.io.interrupts import check_interrupt, interruptible, uninterrupted
from phisim.io.journal import write_failure
from phisim.io.traininglog import training_run

from .distributed import convert_sync_batchnorm, init_from_env, launched_by_torchrun, rank_device
from .hig import HIG, GaussNewton
from .local_solvers import LocalSolver, SolverOperator
from .physgrad import physical_update
from .problems import Batch, Method, Problem, get_problem

__all__ = ["TrainResult", "train", "evaluate", "batch_generator", "make_optimizer", "checkpoint_path",
           "check_no_overwrite"]


@dataclass
class TrainResult:
    """Curves and the trained model of one run.

    Attributes:
        method: The method's name.
        model: The trained network.
        curves: ``{'iteration', 'loss', 'metric', 'eval_loss', 'eval_metric', 'objective', 'time'}`` as numpy
            arrays (this session's iterations plus, when resumed, the earlier ones read back from the log);
            ``loss``/``metric`` are training-batch values, ``eval_*`` held-out values (NaN where not
            evaluated).
        iterations: Iterations completed in total.
        seconds: Wall time of this session's training.
    """

    method: str
    model: nn.Module
    curves: dict[str, np.ndarray] = field(default_factory=dict)
    iterations: int = 0
    seconds: float = 0.0

    def final(self, name: str = "metric", window: int = 10) -> float:
        """Mean of the last ``window`` entries of a curve (NaNs ignored): a training-batch average for
        ``loss``/``metric``."""
        v = self.curves[name][-window:]
        return float(np.nanmean(v)) if np.isfinite(v).any() else float("nan")

    def final_eval(self, name: str = "metric") -> float:
        """The last held-out evaluation of ``name`` (``'metric'`` or ``'loss'``), i.e. of the final model."""
        v = np.asarray(self.curves.get(f"eval_{name}", []), dtype=np.float64)
        v = v[np.isfinite(v)]
        return float(v[-1]) if v.size else float("nan")


def batch_generator(seed: int, iteration: int, device=None) -> torch.Generator:
    """The generator of batch ``iteration`` of a run with ``seed`` (same stream for every method)."""
    g = torch.Generator(device="cpu")
    g.manual_seed((int(seed) * 1_000_003 + int(iteration)) % (2**63 - 1))
    return g


def make_optimizer(method: Method, model: nn.Module, problem: Problem) -> torch.optim.Optimizer:
    """The torch optimizer of a method (Adam, SGD with momentum, HIG or Gauss-Newton)."""
    if method.kind == "hig":
        cls = GaussNewton if method.optimizer == "gauss_newton" else HIG
        kwargs = dict(lr=method.lr, rcond=method.rcond, reduction=problem.reduction)
        if cls is HIG:
            kwargs["exponent"] = 0.5
        return cls(model, physics=problem.hig_physics, **kwargs)
    if method.optimizer == "adam":
        return torch.optim.Adam(model.parameters(), lr=method.lr)
    if method.optimizer == "sgd":
        return torch.optim.SGD(model.parameters(), lr=method.lr, momentum=method.momentum)
    raise ParameterError(f"unknown optimizer {method.optimizer!r} (adam, sgd, hig, gauss_newton)")


def _operator(method: Method, batch: Batch):
    solver: LocalSolver | None = method.local_solver
    return batch.operator if solver is None else SolverOperator(batch.operator, solver)


def _slice_batch(batch: Batch, index: slice) -> Batch:
    """The samples ``index`` of a batch (the operator restricted with :meth:`PhysicsOperator.select`)."""

    def cut(t):
        return None if t is None else t[index]

    return Batch(batch.inputs[index], batch.y_target[index], cut(batch.x_true), batch.operator.select(index),
                 cut(batch.labels), tuple(a[index] for a in batch.physics_args))


def _step(problem: Problem, method: Method, model: nn.Module, opt, batch: Batch, weight: float
          ) -> tuple[torch.Tensor, float]:
    """One update on ``batch`` (this process's share).

    The backpropagated objective is ``weight * Σ_samples objective_i``: ``weight`` is 1 (batch sum) or
    ``1/B`` (batch mean) for a single process, times the number of processes under data parallelism
    (whose gradient averaging then yields the full batch's gradient).

    Returns:
        ``(sums, objective)``: per-process sums of the y-space loss and the metric (a tensor of 2), and the
        objective value.
    """
    if method.kind == "hig":
        loss_fn = problem.loss if method.loss is None else method.loss
        info = opt.step(batch.inputs, batch.y_target, loss_fn=loss_fn, physics_args=batch.physics_args)
        with torch.no_grad():
            x = problem.predict(model, batch)
            loss = problem.loss(batch.operator(x), batch.y_target).sum()
            metric = problem.metric(x, batch).sum()
        return torch.stack([loss.double(), metric.double()]), float(info.loss)
    opt.zero_grad(set_to_none=True)
    x = problem.predict(model, batch)
    clip = method.grad_clip
    if clip is not None and method.kind != "physgrad":  # clamp the per-sample gradient w.r.t. x
        x.register_hook(lambda g: (g / weight).clamp(-clip, clip) * weight)
    if method.kind == "physics":
        per_sample = problem.loss(batch.operator(x), batch.y_target)
        objective = weight * per_sample.sum()
        loss_sum = per_sample.detach().sum()
    elif method.kind == "physgrad":
        x_tilde, y = physical_update(x, batch.y_target, _operator(method, batch), eta=method.eta,
                                     loss=problem.newton_loss)
        if clip is not None:
            x_tilde = x.detach() + (x_tilde - x.detach()).clamp(-clip, clip)
        per = 0.5 * ((x - x_tilde) ** 2).reshape(x.shape[0], -1).sum(dim=1)
        objective = weight * per.sum()
        with torch.no_grad():
            loss_sum = problem.loss(y, batch.y_target).sum()
    elif method.kind == "supervised":
        if batch.labels is None:
            raise ParameterError(f"problem {problem.name} provides no labels for supervised training")
        per = 0.5 * ((x - batch.labels) ** 2).reshape(x.shape[0], -1).sum(dim=1)
        objective = weight * per.sum()
        with torch.no_grad():
            if getattr(problem, "has_physics", True):
                loss_sum = problem.loss(batch.operator(x.detach()), batch.y_target).sum()
            else:  # offline data without a forward physics: no y-space loss
                loss_sum = torch.tensor(float("nan"), device=x.device)
    else:
        raise ParameterError(f"unknown method kind {method.kind!r}")
    if not torch.isfinite(objective):
        raise NonFiniteError(
            f"{method.name}: the training objective became {float(objective)}; lower the learning rate")
    objective.backward()
    opt.step()
    with torch.no_grad():
        metric_sum = problem.metric(x.detach(), batch).sum()
    return torch.stack([loss_sum.double(), metric_sum.double()]), float(objective.detach())


def evaluate(problem: Problem, model: nn.Module, batch: Batch | None = None, *, device=None,
             chunk_size: int | None = None) -> dict[str, float]:
    """Mean per-sample loss and metric of ``model`` on a batch (default: the problem's held-out set).

    The network is put in eval mode (BatchNorm uses its running statistics) without gradients, and its
    previous mode is restored. Samples are evaluated in chunks of ``chunk_size`` (default: the problem's
    batch size); in eval mode a sample's prediction does not depend on the others.

    Args:
        problem: The problem (its ``predict``, ``loss`` and ``metric``).
        model: The network (unwrapped, not a ``DistributedDataParallel``).
        batch: The samples (default ``problem.heldout(device)``).
        device: Device of the held-out set.
        chunk_size: Samples per forward pass.

    Returns:
        ``{'loss': float, 'metric': float}``, means over the samples (``loss`` is NaN for a problem without
        forward physics, ``has_physics = False``).
    """
    batch = problem.heldout(device) if batch is None else batch
    n = int(batch.inputs.shape[0])
    chunk = max(1, int(chunk_size or problem.batch_size))
    was_training = model.training
    model.eval()
    loss_sum = metric_sum = 0.0
    try:
        with torch.no_grad():
            for start in range(0, n, chunk):
                part = batch if chunk >= n else _slice_batch(batch, slice(start, start + chunk))
                x = problem.predict(model, part)
                if getattr(problem, "has_physics", True):
                    loss_sum += float(problem.loss(part.operator(x), part.y_target).double().sum())
                else:  # offline data without a forward physics: no y-space loss, as in training
                    loss_sum = math.nan
                metric_sum += float(problem.metric(x, part).double().sum())
    finally:
        model.train(was_training)
    return {"loss": loss_sum / n, "metric": metric_sum / n}


def _save_checkpoint(path: Path, state: dict) -> None:
    tmp = path.with_suffix(path.suffix + ".tmp")
    try:
        torch.save(state, tmp)
        os.replace(tmp, path)  # atomic: a kill leaves the previous checkpoint intact
    except (OSError, RuntimeError) as exc:  # full disk, vanished folder: no temp file, old checkpoint kept
        tmp.unlink(missing_ok=True)
        raise write_failure(path, exc, "write the checkpoint") from exc
    except BaseException:  # an interrupt: no temp file left behind, the old checkpoint kept
        tmp.unlink(missing_ok=True)
        raise


def checkpoint_path(out: str | os.PathLike, method: str) -> Path:
    """The checkpoint file of ``method`` next to the log ``out``: ``<out>.<method>.ckpt``."""
    out = Path(out)
    return out.with_name(f"{out.name}.{method}.ckpt")


def check_no_overwrite(out: str | os.PathLike, method: str, *, resume: bool = False, overwrite: bool = False) -> None:
    """Refuse (before any work) a run that would write over results of ``method`` already in ``out``.

    Args:
        out: The log file.
        method: The method's name.
        resume: The run continues from its checkpoint: allowed when the checkpoint exists.
        overwrite: The run replaces the earlier one: always allowed.

    Raises:
        ParameterError: Both ``resume`` and ``overwrite``.
        FileFormatError: ``out`` holds records of ``method`` and neither flag allows writing over them, or
            ``resume`` has no checkpoint to continue from.
    """
    if resume and overwrite:
        raise ParameterError("resume and overwrite exclude each other: continue the run or replace it")
    if overwrite:
        return
    run = training_run(out, method)
    if run is None:
        return
    if not resume:
        raise FileFormatError(
            f"{out} already holds a run of {method!r} ({run.status}); pass resume=True (--resume) to continue it "
            "from its checkpoint or overwrite=True (--overwrite) to replace it, or write to another file"
        )
    ckpt = checkpoint_path(out, method)
    if not ckpt.exists():
        raise FileFormatError(
            f"{out} holds a run of {method!r} ({run.status}) but no checkpoint {ckpt.name} to resume it from "
            "(it ran without checkpoint_every); pass overwrite=True (--overwrite) to start it afresh"
        )


def _run_identity(problem: Problem, batch_size: int) -> dict:
    """The settings a checkpoint must share with the run resuming it (problem fields and batch size)."""
    keep = {}
    for k, v in vars(problem).items():
        if isinstance(v, (bool, int, float, str)) or (isinstance(v, tuple) and all(
                isinstance(e, (bool, int, float, str)) for e in v)):
            keep[k] = list(v) if isinstance(v, tuple) else v
    keep["batch_size"] = int(batch_size)
    return keep


def _identity_diff(saved: dict, now: dict, problem: Problem) -> dict:
    """Settings that differ between a checkpoint and the resuming run, ``{name: (saved, now)}``.

    A setting the checkpoint does not record (added to the problem after it was written) counts as equal
    when the run uses that setting's default, so checkpoints of earlier versions keep resuming.
    """
    defaults = {}
    if dataclasses.is_dataclass(problem):
        for f in dataclasses.fields(problem):
            if f.default is not dataclasses.MISSING:
                defaults[f.name] = list(f.default) if isinstance(f.default, tuple) else f.default
    diff = {}
    for k in sorted(set(saved) | set(now)):
        old = saved[k] if k in saved else defaults.get(k, None)
        if old != now.get(k):
            diff[k] = (saved.get(k), now.get(k))
    return diff


def _truncate_log(h5path: Path, method: str, n: int) -> None:
    recover_file(h5path)  # a log killed mid-write: rebuild the file from its journal first
    with uninterrupted(), h5py.File(h5path, "a") as f:  # every curve cut to the same length
        grp = f.get(f"training/{method}")
        if grp is None:
            return
        for ds in grp.values():
            if isinstance(ds, h5py.Dataset) and ds.shape[0] > n:
                ds.resize((n,))


def _read_log(h5path: Path, method: str) -> dict[str, np.ndarray]:
    with h5py.File(h5path, "r") as f:
        grp = f[f"training/{method}"]
        return {k: np.asarray(v) for k, v in grp.items() if isinstance(v, h5py.Dataset)}


def _write_model(out_path: Path, net: nn.Module, problem: Problem, method: Method, seed: int, iterations: int,
                 input_shape, batch_size: int, device) -> Path:
    """The end-of-run model file beside ``out_path`` (:func:`inverse.models.model_path`), named in the log."""
    from .models import model_path, save_model

    if input_shape is None:  # nothing trained in this session (a resumed, finished run): draw one sample
        input_shape = tuple(problem.sample(1, batch_generator(seed, 0), device=device).inputs.shape[1:])
    with uninterrupted():  # the model file and the log's pointer to it, both or neither
        path = save_model(model_path(out_path, method.name), net, problem, method=method.name, seed=seed,
                          iterations=iterations, input_shape=input_shape)
        with h5py.File(out_path, "a") as f:
            grp = f.require_group(f"training/{method.name}")
            grp.attrs["model_file"] = path.name
    return path


def _remove_results(out_path: Path, method: str) -> None:
    """Delete the checkpoint and model file of an earlier run that ``overwrite=True`` replaces."""
    from .models import model_path

    checkpoint_path(out_path, method).unlink(missing_ok=True)
    model_path(out_path, method).unlink(missing_ok=True)


def train(
    problem: Problem | str,
    method: Method | str,
    *,
    iterations: int,
    batch_size: int | None = None,
    seed: int = 0,
    device: str | torch.device = "cpu",
    out: str | os.PathLike | None = None,
    checkpoint_every: int = 0,
    resume: bool = False,
    progress: bool | None = None,
    callback: Callable[[int, dict], None] | None = None,
    distributed: bool | None = None,
    eval_every: int | None = None,
    tensorboard: str | os.PathLike | None = None,
    overwrite: bool = False,
) -> TrainResult:
    """Train the problem's network with one method.

    Args:
        problem: A :class:`~inverse.problems.Problem` or its registered name (``'sine'``, ``'poisson'``...).
        method: A :class:`~inverse.problems.Method` or the name of one of the problem's methods.
        iterations: Total iterations (a resumed run continues up to this number).
        batch_size: Samples per batch (default: the problem's).
        seed: Seeds the network initialisation and the data stream.
        device: Torch device. Under data parallelism a CUDA device without an index becomes
            ``cuda:LOCAL_RANK`` (one GPU per process).
        out: HDF5 file receiving ``/training/<method>`` curves (and ``<out>.<method>.ckpt`` checkpoints). At the
            end of the run the trained network is written to ``<out>.<method>.model.pt``
            (:func:`inverse.models.load_model` rebuilds it; the log's attribute ``model_file`` names it).
        checkpoint_every: Iterations between checkpoints (0: none).
        resume: Continue from the checkpoint next to ``out`` when there is one. A log of the method that
            already holds records needs its checkpoint (otherwise the run is refused).
        progress: Show a tqdm progress bar on stderr (None: when stderr is a terminal, so interactive runs show
            it and pipes, logs and batch jobs stay quiet).
        callback: Called as ``callback(iteration, record)`` after every iteration.
        distributed: Data-parallel training over the processes of a ``torch.distributed`` group: every
            process draws the same batch and trains on its share (samples ``rank::world_size``) of a
            ``DistributedDataParallel`` model whose BatchNorm layers use the whole batch's statistics
            (:class:`~inverse.distributed.SyncBatchNorm`), so N processes follow the single-process
            trajectory up to round-off; process 0 writes the log and the checkpoints and shows progress.
            Under ``torchrun`` the group is initialised from its environment (NCCL for CUDA, gloo
            otherwise). ``None``: on when a group is initialised or the process was started by torchrun.
            Not for HIG.
        eval_every: Iterations between held-out evaluations (``None``: ``iterations // 20``, about 20 per
            run, and only the final one for runs under 20 iterations; 0: only after the last iteration).
            The final model is always evaluated.
        tensorboard: Folder for TensorBoard event files (``<folder>/<method>``); skipped with a warning when
            the ``tensorboard`` package is not installed.
        overwrite: Replace a run of the method that ``out`` already holds (its curves, checkpoint and model
            file). Without it (or ``resume``) such a run is refused before any work.

    Returns:
        The :class:`TrainResult`.

    Raises:
        ParameterError: Bad iteration counts, unknown method, ``resume`` without ``out``, both ``resume`` and
            ``overwrite``.
        FileFormatError: ``out`` already holds a run of the method (without ``resume``/``overwrite``), a
            checkpoint that cannot be read or belongs to another run.
        NonFiniteError: The objective diverged.
        KeyboardInterrupt: SIGINT, or SIGTERM (:class:`phisim.io.interrupts.Interrupted`): the run stopped,
            the log was closed and marked incomplete; ``resume=True`` continues from the last checkpoint.
    """
    with interruptible():  # SIGTERM stops the run as Ctrl-C does: files are closed cleanly on the way out
        return _train(**locals())


def _heldout_source(problem) -> str:
    """Where the problem's held-out samples come from: its ``heldout_source`` (e.g. a dataset's split), else its
    seeded generator."""
    return getattr(problem, "heldout_source", None) or f"{problem.heldout_size} samples, seed {problem.heldout_seed}"


def _train(problem, method, *, iterations, batch_size, seed, device, out, checkpoint_every, resume, progress,
           callback, distributed, eval_every, tensorboard, overwrite) -> TrainResult:
    if isinstance(problem, str):
        problem = get_problem(problem)
    if isinstance(method, str):
        method = problem.method(method)
    iterations = check_int(iterations, "iterations", minimum=0)
    checkpoint_every = check_int(checkpoint_every, "checkpoint_every", minimum=0)
    seed = check_seed(seed, allow_none=False)
    resume, overwrite = check_bool(resume, "resume"), check_bool(overwrite, "overwrite")
    progress = check_progress(progress)
    if (resume or checkpoint_every) and out is None:
        raise ParameterError("checkpoints and resume need an output file (out=...)")
    batch_size = problem.batch_size if batch_size is None else batch_size
    if isinstance(batch_size, bool) or not isinstance(batch_size, (int, np.integer)) or batch_size < 1:
        raise ParameterError(f"batch_size must be an int >= 1, got {batch_size!r}")
    batch_size = int(batch_size)
    if eval_every is None:
        eval_every = iterations // 20  # about 20 evaluations; a run under 20 iterations: only at the end
    if isinstance(eval_every, bool) or not isinstance(eval_every, int) or eval_every < 0:
        raise ParameterError(f"eval_every must be an int >= 0, got {eval_every!r}")
    device = check_device(device)
    if out is not None:
        check_output_path(out, append=True)  # before any work: a bad --out fails now, not after training
        check_no_overwrite(out, method.name, resume=resume, overwrite=overwrite)
    elif overwrite and resume:
        raise ParameterError("resume and overwrite exclude each other: continue the run or replace it")

    import torch.distributed as dist

    if distributed is None:
        distributed = (dist.is_available() and dist.is_initialized()) or launched_by_torchrun()
    if distributed:
        if not init_from_env(device):
            raise ParameterError("distributed=True needs an initialised torch.distributed process group "
                                 "(call dist.init_process_group) or a start by torchrun")
        device = rank_device(device)
    rank, world = (dist.get_rank(), dist.get_world_size()) if distributed else (0, 1)
    if distributed and out is not None:
        dist.barrier()  # every process has read the log (check_no_overwrite) before process 0 writes it
    if distributed and method.kind == "hig":
        raise ParameterError("HIG builds the Jacobian of the whole batch; run it in a single process")
    if world > batch_size:
        raise ParameterError(f"batch_size {batch_size} is smaller than the number of processes {world}")

    torch.manual_seed(seed)
    net = problem.make_network().to(device=device, dtype=problem.dtype)
    if distributed:
        net = convert_sync_batchnorm(net)
        model = nn.parallel.DistributedDataParallel(net, device_ids=[device] if device.type == "cuda" else None)
    else:
        model = net
    opt = make_optimizer(method, model, problem)
    weight = world * (1.0 / batch_size if problem.reduction == "mean" else 1.0)
    start = 0
    out_path = Path(out) if out is not None else None
    ckpt_path = checkpoint_path(out_path, method.name) if out_path is not None else None
    resumed = False
    if resume and ckpt_path is not None and ckpt_path.exists():
        try:
            state = torch.load(ckpt_path, map_location=device, weights_only=False)
        except Exception as exc:  # noqa: BLE001 - any unreadable checkpoint is a file-format problem
            raise FileFormatError(f"cannot read checkpoint {ckpt_path}: {exc}") from exc
        if state.get("problem") != problem.name or state.get("method") != method.name or state.get("seed") != seed:
            raise FileFormatError(
                f"checkpoint {ckpt_path} belongs to problem={state.get('problem')} method={state.get('method')} "
                f"seed={state.get('seed')}, not {problem.name}/{method.name}/seed {seed}"
            )
        saved = state.get("settings")
        now = _run_identity(problem, batch_size)
        diff = {} if saved is None else _identity_diff(saved, now, problem)
        if diff:
            raise FileFormatError(
                f"checkpoint {ckpt_path} was written with other settings (saved, now): {diff}; resume with the "
                "same settings, or start afresh without resume (or delete the checkpoint)"
            )
        net.load_state_dict(state["model"])
        opt.load_state_dict(state["optimizer"])
        start = int(state["iteration"])
        resumed = True
        if rank == 0:
            _truncate_log(out_path, method.name, start)
    elif overwrite and out_path is not None and rank == 0:
        _remove_results(out_path, method.name)  # the curves themselves are replaced by the log below

    if distributed:
        dist.barrier()  # process 0 may have truncated the log
    log = None
    if out_path is not None and rank == 0:
        log = TrainingLog(out_path, method.name, planned_iterations=iterations, overwrite=overwrite and not resumed,
                          resume=resumed, attrs={
            "problem": problem.name, "kind": method.kind, "optimizer": method.optimizer, "lr": method.lr,
            "eta": method.eta, "batch_size": batch_size, "seed": seed,
            "local_solver": type(method.local_solver).__name__ if method.local_solver is not None else "analytic",
            "loss_name": problem.loss_name, "metric_name": problem.metric_name,
            "loss_measured_on": "training batch, train mode, before the update",
            "eval_measured_on": f"held-out set: {_heldout_source(problem)}, eval mode, after the update",
            "heldout_size": problem.heldout_size, "heldout_seed": str(problem.heldout_seed),
        })
    curves: dict[str, list] = {k: [] for k in ("iteration", "loss", "metric", "eval_loss", "eval_metric",
                                               "objective", "time")}
    bar = None
    if progress and rank == 0:
        from tqdm.auto import tqdm

        bar = tqdm(total=iterations, initial=start, desc=f"{problem.name}/{method.name}")
    tb = None
    if tensorboard is not None and rank == 0:
        from .export import TensorBoardLogger

        tb = TensorBoardLogger(tensorboard, method.name)
    t0 = time.perf_counter()
    input_shape = None
    model.train()
    try:
        for it in range(start, iterations):
            check_interrupt()  # a SIGTERM swallowed by a callback (weakref, __del__) still stops the run here
            batch = problem.sample(batch_size, batch_generator(seed, it), device=device)
            if input_shape is None:
                input_shape = tuple(batch.inputs.shape[1:])
            if distributed:
                batch = _slice_batch(batch, slice(rank, None, world))
            sums, objective = _step(problem, method, model, opt, batch, weight)
            if distributed:  # collectives on the training device (NCCL needs CUDA tensors)
                dist.all_reduce(sums)
                t = torch.tensor([objective], dtype=torch.float64, device=sums.device)
                dist.all_reduce(t)
                objective = float(t) / world
            loss, metric = (float(v) / batch_size for v in sums)
            record = {"loss": loss, "metric": metric, "objective": objective, "time": time.perf_counter() - t0}
            if it + 1 == iterations or (eval_every and (it + 1) % eval_every == 0):
                held = evaluate(problem, net, device=device)  # every process, no collectives: same numbers
                record["eval_loss"], record["eval_metric"] = held["loss"], held["metric"]
            else:
                record["eval_loss"] = record["eval_metric"] = math.nan
            for k, v in record.items():
                curves[k].append(v)
            curves["iteration"].append(it)
            if log is not None:
                log.append(it, **record)
            if callback is not None:
                callback(it, record)
            if tb is not None:
                tb.log(it, record)
            if bar is not None:
                bar.update(1)
                bar.set_postfix(loss=f"{loss:.3g}", metric=f"{metric:.3g}",
                                **({"heldout": f"{record['eval_metric']:.3g}"}
                                   if math.isfinite(record["eval_metric"]) else {}))
            if checkpoint_every and (it + 1) % checkpoint_every == 0 and rank == 0:
                _save_checkpoint(ckpt_path, {"iteration": it + 1, "model": net.state_dict(),
                                             "optimizer": opt.state_dict(), "problem": problem.name,
                                             "method": method.name, "seed": seed,
                                             "settings": _run_identity(problem, batch_size)})
        if log is not None:
            log.finish()  # the completion mark: a run stopped before this reads back as incomplete
    finally:
        if bar is not None:
            bar.close()
        if log is not None:
            log.close()
        if tb is not None:
            tb.close()
    seconds = time.perf_counter() - t0
    if out_path is not None and rank == 0:  # before the barrier: no process reads the log while it is written
        _write_model(out_path, net, problem, method, seed, iterations, input_shape, batch_size, device)
    if distributed:
        dist.barrier()
    if out_path is not None:
        arrays = _read_log(out_path, method.name)
    else:
        arrays = {k: np.asarray(v, dtype=np.int64 if k == "iteration" else np.float64) for k, v in curves.items()}
    if not math.isfinite(seconds):
        seconds = float("nan")
    return TrainResult(method.name, net, arrays, iterations, seconds)
