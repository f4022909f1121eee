"""Command-line entry point ``phisim``: train and compare methods on the reference problems, inspect files.

Examples::

    phisim list
    phisim train poisson pg --iterations 200 --batch-size 16 --resolution 32 32 --out out/poisson.h5
    phisim compare heat adam pg --iterations 100 --out out/heat.h5 --plot out/heat.png
    phisim info out/poisson.h5
    phisim train examples/burgers_inverse.py:burgers_problem adam --setting resolution=16 --out out/b.h5
    phisim train well supervised --setting data_dir=data/heat --setting field=temperature --out out/well.h5
    phisim simulate smoke --trajectories 16 --workers 2 --out data/smoke
    phisim plot data/smoke/data/train/smoke_00000.h5 --field vorticity
    phisim predict out/poisson.h5.pg.model.pt inputs.h5 --key inputs --out predictions.h5

The parser lives in the light module :mod:`phisim_cli` (standard library only: ``phisim --help`` imports
nothing else); this module runs the parsed commands. Paths are checked by :mod:`inverse.cli_checks` before
any work starts, so a mistake reads the same in every command.

``problem`` is a registered name (``phisim list``) or a factory of your own, ``module:function`` or
``file.py:function`` (see :mod:`inverse.custom`).

Data-parallel training: start the same command under ``torchrun``; the process group is initialised from
its environment (gloo on CPU, NCCL with ``--device cuda``, one GPU per process), process 0 writes the files
and prints, and N processes follow the one-process run::

    torchrun --standalone --nproc_per_node 2 -m inverse.cli train poisson adam --iterations 100 --out out/p.h5
"""

from __future__ import annotations

import os
import sys
import warnings
from pathlib import Path

import phisim_cli
from phisim.errors import ParameterError, PhisimError

from . import cli_checks

__all__ = ["main", "run", "build_parser", "describe_file"]

#: The parser of the ``phisim`` command (defined in :mod:`phisim_cli`, which imports nothing heavy).
build_parser = phisim_cli.build_parser


def describe_file(path: Path) -> str:
    """A short text summary of an HDF5 file: root attributes, datasets with shapes, training curves, and the
    state of every training run (complete, or incomplete with how far it got).

    Raises:
        FileFormatError: If the file cannot be read as HDF5.
    """
    import warnings

    import h5py
    import numpy as np

    from phisim.io import read_training
    from phisim.io.h5util import open_for_read
    from phisim.io.journal import journal_path

    f = open_for_read(path)  # typed errors for missing files, folders, pipes, truncated or locked files
    lines = [f"{path}"]
    with f:
        for k, v in f.attrs.items():
            lines.append(f"  @{k} = {v!r}"[:160])

        def visit(name, obj):
            if isinstance(obj, h5py.Dataset):
                extra = ""
                if name.startswith("training/") and obj.ndim == 1 and obj.shape[0] and obj.dtype.kind == "f":
                    last = obj[-min(10, obj.shape[0]):]
                    extra = f"  last10 mean={np.nanmean(last):.4g}"
                lines.append(f"  /{name} {obj.shape} {obj.dtype}{extra}")

        f.visititems(visit)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            runs = read_training(path, warn=False)  # from the journal when the writer did not close cleanly
    except PhisimError as exc:
        runs = {}
        lines.append(f"  training logs unreadable: {exc}")
    if journal_path(path).exists():
        lines.append(f"  NOT CLOSED CLEANLY: {journal_path(path).name} holds the latest records "
                     "(phisim.io.recover_file rebuilds the file)")
    for method, curves in runs.items():
        lines.append(f"  run {method}: {curves.status}")
    return "\n".join(lines)


def _problem(args):
    from .cli_workflows import parse_settings
    from .problems import get_problem

    settings = parse_settings(args.setting)
    if args.resolution is not None:
        settings["resolution"] = tuple(args.resolution)
    if args.heldout_size is not None:
        settings["heldout_size"] = args.heldout_size
    if args.dtype is not None:
        import torch

        settings["dtype"] = getattr(torch, args.dtype)
    return get_problem(args.problem, **settings)


def progress_flag(args) -> bool | None:
    """The ``progress=`` of a command: False with ``--quiet``, else None (a bar when stderr is a terminal)."""
    return False if getattr(args, "quiet", False) else None


def heldout_source(problem) -> str:
    """Where a problem's held-out samples come from, in words (for the summary of a training run)."""
    source = getattr(problem, "heldout_source", None)
    if source:
        return source
    return (f"{problem.heldout_size} held-out samples, seed {problem.heldout_seed} (drawn by the problem's own "
            "generator, apart from the training stream)")


def _train(args, problem, method):
    from .distributed import is_main_process
    from .train import train

    r = train(problem, method, iterations=args.iterations, batch_size=args.batch_size, seed=args.seed,
              device=args.device, out=args.out, checkpoint_every=args.checkpoint_every, resume=args.resume,
              progress=progress_flag(args), eval_every=args.eval_every, tensorboard=args.tensorboard,
              overwrite=args.overwrite)
    if args.csv is not None and args.out is not None and is_main_process():
        from .export import export_csv

        export_csv(args.out, args.csv)
    if is_main_process():
        print(cli_checks.json_summary({
            "problem": problem.name, "method": method, "iterations": r.iterations,
            "loss_name": problem.loss_name, "metric_name": problem.metric_name,
            "final_loss": r.final("loss"), "final_metric": r.final("metric"),
            "final_measured_on": "training batches, mean of the last 10 iterations",
            "heldout_loss": r.final_eval("loss"), "heldout_metric": r.final_eval("metric"),
            "heldout_measured_on": f"final model, eval mode, {heldout_source(problem)}",
            "seconds": round(r.seconds, 3)}))
    return r


def _check_args(args) -> None:
    """Check paths, numbers and the device before any work starts (a bad --out must not fail after training).

    Paths go through :mod:`inverse.cli_checks` (one wording per mistake in every command).
    """
    from phisim.checks import check_device
    from phisim.io.h5util import check_output_path

    cmd = args.command
    if getattr(args, "device", None) is not None:
        check_device(args.device)
    if cmd in ("train", "compare"):
        module = args.problem.rpartition(":")[0]
        if module.endswith(".py") or "/" in module:  # a factory given by its file
            cli_checks.existing_file(Path(module).expanduser(), "problem factory file")
        if args.out is not None:
            cli_checks.writable_file(args.out, "output file")
            check_output_path(args.out, append=True)  # an existing file must be HDF5 (runs are appended)
        if cmd == "compare" and args.plot is not None:
            cli_checks.writable_file(args.plot, "--plot file", example="curves.png")
        if args.csv is not None:
            if args.out is None:
                raise ParameterError("--csv writes the curves of --out; give --out FILE.h5 too")
            cli_checks.writable_dir(args.csv, "CSV folder")
        if args.tensorboard is not None:
            cli_checks.writable_dir(args.tensorboard, "TensorBoard folder")
    elif cmd == "info":
        cli_checks.hdf5_file(args.path, "file")
    elif cmd == "simulate":
        if args.config is not None:
            cli_checks.existing_file(args.config, "config file")
        if args.out is not None:
            cli_checks.writable_dir(args.out, "dataset folder")
    elif cmd == "plot":
        cli_checks.hdf5_file(args.path, "file")
        if args.out is not None:
            cli_checks.writable_dir(args.out, "output folder")
    elif cmd == "predict":
        order = "phisim predict MODEL INPUTS --out FILE"
        cli_checks.model_file(args.model, argument_order=order)
        from .models import read_model_file

        read_model_file(args.model)  # a damaged or foreign model file is named before the inputs are read
        cli_checks.hdf5_file(args.inputs, "input file", argument_order=order)
        args.key = cli_checks.dataset_key(args.inputs, args.key)
        cli_checks.writable_file(args.out, "output file")
    elif cmd == "export":
        cli_checks.hdf5_file(args.path, "results file")
        cli_checks.writable_dir(args.csv, "CSV folder")
    for name in ("iterations", "checkpoint_every"):
        v = getattr(args, name, None)
        if v is not None and v < 0:
            raise ParameterError(f"--{name.replace('_', '-')} must be >= 0, got {v}")
    if getattr(args, "batch_size", None) is not None and args.batch_size < 1:
        raise ParameterError(f"--batch-size must be >= 1, got {args.batch_size}")
    if getattr(args, "resolution", None) is not None and any(n < 1 for n in args.resolution):
        raise ParameterError(f"--resolution entries must be >= 1, got {args.resolution}")


def main(argv: list[str] | None = None) -> int:
    """Run the ``phisim`` command with the arguments ``argv`` (None: ``sys.argv``); returns the exit status.

    See :func:`run`.
    """
    return run(build_parser().parse_args(argv), command=argv is None)


def _one_line_warning(message, category, filename, lineno, file=None, line=None) -> None:
    text = " ".join(str(message).split())
    print(f"phisim: warning: {text}", file=sys.stderr if file is None else file)


def run(args, *, command: bool = False) -> int:
    """Run a parsed ``phisim`` command; returns the exit status.

    User errors (bad arguments, files, devices, any :class:`~phisim.errors.PhisimError`) print one line
    ``phisim: error: ...`` and return 2; an unexpected error prints one line and returns 1 (set
    ``PHISIM_DEBUG=1`` for its traceback); warnings print as one line ``phisim: warning: ...``. Ctrl-C returns
    130 and SIGTERM 143, within a second or two: files are closed cleanly on the way out, and the command
    itself (``command=True``) then exits at once, without the interpreter's teardown of torch (a second or more
    on a busy machine). No traceback is printed otherwise.

    Args:
        args: The namespace of :func:`build_parser`.
        command: Whether this is the ``phisim`` process itself (it may exit at once after an interrupt).
    """
    try:
        with warnings.catch_warnings():
            warnings.showwarning = _one_line_warning
            return _dispatch(args)
    except KeyboardInterrupt as exc:
        import signal

        signum = getattr(exc, "signum", signal.SIGINT)  # phisim.io.interrupts.Interrupted carries SIGTERM
        name = "" if signum == signal.SIGINT else f" ({signal.Signals(signum).name})"
        print(f"phisim: interrupted{name}", file=sys.stderr)
        if command:  # the command: every file is closed, nothing is left to tear down
            sys.stdout.flush()
            sys.stderr.flush()
            os._exit(128 + signum)
        return 128 + signum
    except Exception as exc:  # noqa: BLE001 - the command line shows one line, never a traceback
        if os.environ.get("PHISIM_DEBUG"):
            raise
        text = " ".join(str(exc).split())
        print(f"phisim: error: {type(exc).__name__}: {text} (set PHISIM_DEBUG=1 for the traceback)", file=sys.stderr)
        return 1


def _list(args) -> int:
    from .problems import PROBLEMS

    for name, cls in PROBLEMS.items():
        try:
            print(f"{name}: {', '.join(cls().methods)}")
        except (TypeError, PhisimError):  # needs settings, e.g. the dataset of `well`
            print(f"{name}: supervised (needs --setting data_dir=DIR --setting field=NAME)")
    print("your own problem: module:function or path/to/file.py:function (see docs/TUTORIAL_custom_physics.md)")
    return 0


def _info(args) -> int:
    print(describe_file(args.path))
    return 0


def _training(args) -> int:
    from .distributed import is_main_process

    started = _start_process_group(args.device)
    try:
        problem = _problem(args)
        for m in [args.method] if args.command == "train" else args.methods:
            problem.method(m)  # every method known before the first one trains
            if args.out is not None:  # and none would write over an earlier run (--resume / --overwrite)
                from .train import check_no_overwrite

                check_no_overwrite(args.out, problem.method(m).name, resume=args.resume, overwrite=args.overwrite)
        if args.command == "train":
            _train(args, problem, args.method)
            return 0
        results = {m: _train(args, problem, m) for m in args.methods}
        if args.plot is not None and is_main_process():
            from phisim.viz.plot import plot_training_curves, save_figure

            ax = plot_training_curves({m: r.curves for m, r in results.items()}, problem.metric_name,
                                      title=f"{problem.name}: {problem.metric_name}")
            save_figure(ax.figure, args.plot)
        return 0
    finally:
        if started:
            import torch.distributed as dist

            dist.destroy_process_group()


def _workflow(args) -> int:
    from .cli_workflows import run_workflow

    return run_workflow(args)


#: Command -> handler; every handler imports what its command needs when it runs.
HANDLERS = {"list": _list, "info": _info, "train": _training, "compare": _training, "simulate": _workflow,
            "plot": _workflow, "predict": _workflow, "export": _workflow}


def _dispatch(args) -> int:
    """Check the arguments and run the command; user errors (PhisimError) print one line and return 2."""
    try:
        handler = HANDLERS.get(args.command)
        if handler is None:
            raise ParameterError(f"unknown command {args.command!r}; `phisim --help` lists them")
        _check_args(args)
        return handler(args)
    except PhisimError as exc:
        text = " ".join(str(exc).split())
        print(f"phisim: error: {text}", file=sys.stderr)
        return 2


def _start_process_group(device: str) -> bool:
    """Under torchrun, initialise the process group from its environment; True when this call did."""
    import torch.distributed as dist

    from .distributed import init_from_env, launched_by_torchrun

    if not launched_by_torchrun() or (dist.is_available() and dist.is_initialized()):
        return False
    return init_from_env(device)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(run(build_parser().parse_args(), command=True))
