"""Command-line entry point ``phisim``: train and compare methods on the reference problems, inspect files.

Examples::

    phisim list
    phisim train poisson pg --iterations 200 --batch-size 16 --resolution 32 32 --out out/poisson.h5
    phisim compare heat adam pg --iterations 100 --out out/heat.h5 --plot out/heat.png
    phisim info out/poisson.h5
    phisim train examples/burgers_inverse.py:burgers_problem adam --setting resolution=16 --out out/b.h5
    phisim train well pg --setting data_dir=data/heat --out out/well.h5
    phisim simulate smoke --trajectories 16 --workers 2 --out data/smoke
    phisim plot data/smoke/data/train/smoke_00000.h5 --field vorticity
    phisim predict out/poisson.h5.pg.model.pt inputs.h5 --key inputs --out predictions.h5

``problem`` is a registered name (``phisim list``) or a factory of your own, ``module:function`` or
``file.py:function`` (see :mod:`inverse.custom`).

Data-parallel training: start the same command under ``torchrun``; the process group is initialised from
its environment (gloo on CPU, NCCL with ``--device cuda``, one GPU per process), process 0 writes the files
and prints, and N processes follow the one-process run::

    torchrun --standalone --nproc_per_node 2 -m inverse.cli train poisson adam --iterations 100 --out out/p.h5
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from phisim.errors import PhisimError

__all__ = ["main", "build_parser", "describe_file"]


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of the ``phisim`` command."""
    p = argparse.ArgumentParser(prog="phisim", description=__doc__.split("\n")[0])
    sub = p.add_subparsers(dest="command", required=True)
    sub.add_parser("list", help="list problems and their methods")

    def common(sp):
        sp.add_argument("problem", help="problem name (see `phisim list`)")
        sp.add_argument("--iterations", type=int, default=100)
        sp.add_argument("--batch-size", type=int, default=None)
        sp.add_argument("--resolution", type=int, nargs="+", default=None, help="grid size (Poisson/heat)")
        sp.add_argument("--seed", type=int, default=0)
        sp.add_argument("--device", default="cpu")
        sp.add_argument("--out", type=Path, default=None, help="HDF5 file for the curves")
        sp.add_argument("--checkpoint-every", type=int, default=0)
        sp.add_argument("--resume", action="store_true",
                        help="continue the method's run in --out from its checkpoint")
        sp.add_argument("--overwrite", action="store_true",
                        help="replace a run of the method that --out already holds (refused otherwise)")
        sp.add_argument("--quiet", action="store_true", help="no progress bar")
        sp.add_argument("--eval-every", type=int, default=None,
                        help="iterations between held-out evaluations (default: about 20 per run; 0: at the end only)")
        sp.add_argument("--heldout-size", type=int, default=None, help="samples in the held-out set")
        sp.add_argument("--dtype", choices=("float32", "float64"), default=None,
                        help="network and data precision (default: the problem's)")
        sp.add_argument("--setting", action="append", metavar="KEY=VALUE", default=[],
                        help="a problem setting (repeatable), e.g. --setting lr=0.01")
        sp.add_argument("--tensorboard", type=Path, default=None, help="TensorBoard folder (if installed)")
        sp.add_argument("--csv", type=Path, default=None, help="folder for CSV copies of the curves")

    t = sub.add_parser("train", help="train one method")
    common(t)
    t.add_argument("method")
    c = sub.add_parser("compare", help="train several methods on the same data stream")
    common(c)
    c.add_argument("methods", nargs="+")
    c.add_argument("--plot", type=Path, default=None, help="PNG of the learning curves")
    i = sub.add_parser("info", help="summarise an HDF5 file written by phisim")
    i.add_argument("path", type=Path)
    from .cli_workflows import add_workflow_parsers

    add_workflow_parsers(sub)
    return p


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


def _train(args, problem, method):
    from .distributed import is_main_process
    from .train import train

    r = train(problem, method, iterations=args.iterations, batch_size=args.batch_size, seed=args.seed,
              device=args.device, out=args.out, checkpoint_every=args.checkpoint_every, resume=args.resume,
              progress=not args.quiet, eval_every=args.eval_every, tensorboard=args.tensorboard,
              overwrite=args.overwrite)
    if args.csv is not None and args.out is not None and is_main_process():
        from .export import export_csv

        export_csv(args.out, args.csv)
    if is_main_process():
        print(json.dumps({
            "problem": problem.name, "method": method, "iterations": r.iterations,
            "loss_name": problem.loss_name, "metric_name": problem.metric_name,
            "final_loss": r.final("loss"), "final_metric": r.final("metric"),
            "final_measured_on": "training batches, mean of the last 10 iterations",
            "heldout_loss": r.final_eval("loss"), "heldout_metric": r.final_eval("metric"),
            "heldout_measured_on": f"final model, eval mode, {problem.heldout_size} held-out samples",
            "seconds": round(r.seconds, 3)}, ensure_ascii=False))
    return r


def _check_args(args) -> None:
    """Check output paths and the device before any work starts (a bad --out must not fail after training)."""
    from phisim.checks import check_device
    from phisim.errors import ParameterError
    from phisim.io.h5util import check_output_path

    if getattr(args, "device", None) is not None:
        check_device(args.device)
    if getattr(args, "out", None) is not None and args.command not in ("simulate", "plot"):  # those are folders
        check_output_path(args.out, append=True)
    plot = getattr(args, "plot", None)
    if plot is not None:
        if plot.is_dir():
            raise ParameterError(f"--plot {plot} is a directory; give a file name such as {plot / 'curves.png'}")
        try:
            plot.parent.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise ParameterError(f"--plot {plot}: cannot create its folder ({exc.strerror or exc})") from exc
        import os

        if not os.access(plot.parent, os.W_OK):
            raise ParameterError(f"--plot {plot}: the folder {plot.parent} is not writable")
    for name in ("iterations", "checkpoint_every"):
        v = getattr(args, name, None)
        if v is not None and v < 0:
            raise ParameterError(f"--{name.replace('_', '-')} must be >= 0, got {v}")
    if getattr(args, "batch_size", None) is not None and args.batch_size < 1:
        raise ParameterError(f"--batch-size must be >= 1, got {args.batch_size}")
    if getattr(args, "resolution", None) is not None and any(n < 1 for n in args.resolution):
        raise ParameterError(f"--resolution entries must be >= 1, got {args.resolution}")


def main(argv: list[str] | None = None) -> int:
    """Run the ``phisim`` command; returns the exit status.

    User errors (bad arguments, files, devices, any :class:`~phisim.errors.PhisimError`) print one line
    ``phisim: error: ...`` and return 2; an unexpected error prints one line and returns 1 (set
    ``PHISIM_DEBUG=1`` for its traceback); Ctrl-C returns 130 and SIGTERM 143, within a second or two:
    files are closed cleanly on the way out, and the command itself (``argv`` None) then exits at once,
    without the interpreter's teardown of torch (a second or more on a busy machine). No traceback is
    printed otherwise.
    """
    import os

    args = build_parser().parse_args(argv)
    try:
        return _dispatch(args)
    except KeyboardInterrupt as exc:
        import signal

        signum = getattr(exc, "signum", signal.SIGINT)  # phisim.io.interrupts.Interrupted carries SIGTERM
        name = "" if signum == signal.SIGINT else f" ({signal.Signals(signum).name})"
        print(f"phisim: interrupted{name}", file=sys.stderr)
        if argv is None:  # the command: every file is closed, nothing is left to tear down
            sys.stdout.flush()
            sys.stderr.flush()
            os._exit(128 + signum)
        return 128 + signum
    except Exception as exc:  # noqa: BLE001 - the command line shows one line, never a traceback
        if os.environ.get("PHISIM_DEBUG"):
            raise
        print(f"phisim: error: {type(exc).__name__}: {exc} (set PHISIM_DEBUG=1 for the traceback)", file=sys.stderr)
        return 1


def _dispatch(args) -> int:
    """Run the parsed command; user errors (PhisimError) print one line and return 2."""
    started = False
    try:
        _check_args(args)
        if args.command == "list":
            from .problems import PROBLEMS

            for name, cls in PROBLEMS.items():
                try:
                    print(f"{name}: {', '.join(cls().methods)}")
                except (TypeError, PhisimError):  # needs settings, e.g. the dataset of `well`
                    print(f"{name}: supervised (needs --setting data_dir=DIR --setting field=NAME)")
            return 0
        if args.command == "info":
            print(describe_file(args.path))
            return 0
        from .cli_workflows import WORKFLOW_COMMANDS, run_workflow

        if args.command in WORKFLOW_COMMANDS:
            return run_workflow(args)
        from .distributed import is_main_process

        started = _start_process_group(args.device)
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
    except PhisimError as exc:
        print(f"phisim: error: {exc}", file=sys.stderr)
        return 2
    finally:
        if started:
            import torch.distributed as dist

            dist.destroy_process_group()


def _start_process_group(device: str) -> bool:
    """Under torchrun, initialise the process group from its environment; True when this call did."""
    import torch.distributed as dist

    from .distributed import init_from_env, launched_by_torchrun

    if not launched_by_torchrun() or (dist.is_available() and dist.is_initialized()):
        return False
    return init_from_env(device)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
