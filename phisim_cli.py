"""The ``phisim`` command's entry point and argument parser, light enough that ``phisim --help`` answers at once.

This module imports only the standard library: the parser (every sub-command, every option with its help text
and default) is built here, and the handlers of :mod:`inverse.cli` (which import torch, phisim and inverse) are
imported only once the arguments parsed, that is, never for ``--help`` or a usage error. It lives outside the
``inverse`` and ``phisim`` packages because importing any module of a package runs that package's
``__init__``, and both import torch.

Commands::

    phisim list                                   problems and their methods
    phisim train PROBLEM METHOD [...]             train one method (PROBLEM: a name or module:function)
    phisim compare PROBLEM METHOD [METHOD ...]    several methods on the same data stream
    phisim info FILE                              summary of an HDF5 file written by phisim
    phisim simulate SCENARIO [...]                a dataset in The Well's layout (--list: the scenarios)
    phisim plot FILE [...]                        pictures of a simulation or training file
    phisim predict MODEL INPUTS --out FILE        a trained model applied to an array of an HDF5 file
    phisim export FILE --csv DIR                  training curves as CSV
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

__all__ = ["build_parser", "add_workflow_parsers", "main", "COMMANDS"]

#: The sub-commands, in the order ``phisim --help`` lists them.
COMMANDS = ("list", "train", "compare", "info", "simulate", "plot", "predict", "export")

_PROBLEM_HELP = ("a registered problem (`phisim list` shows them), or a factory of your own as module:function "
                 "(an importable module) or path/to/file.py:function, e.g. examples/burgers_inverse.py:"
                 "burgers_problem; the factory returns an inverse.Problem (see docs/TUTORIAL_custom_physics.md)")


class _Formatter(argparse.ArgumentDefaultsHelpFormatter):
    """Help with every option's default: ``(default: X)`` appended unless the text already names its default.

    Options whose default is None say in their own text what happens when they are left out (e.g. "default: the
    scenario's"); on/off flags show ``(default: off)``. Descriptions keep their paragraphs (blank lines) and
    wrap each one.
    """

    def _fill_text(self, text, width, indent):
        return "\n\n".join(super(_Formatter, self)._fill_text(par, width, indent) for par in text.split("\n\n"))

    def _get_help_string(self, action):
        text = action.help or ""
        if "default" in text.lower() or action.default is argparse.SUPPRESS or not action.option_strings:
            return text
        if isinstance(action, (argparse._StoreTrueAction, argparse._StoreFalseAction)):
            return f"{text} (default: {'on' if action.default else 'off'})"
        if action.default is None:
            return text
        if isinstance(action.default, list) and not action.default:
            return f"{text} (default: none)"
        return f"{text} (default: %(default)s)"


def _sub(sub, name: str, help: str, description: str | None = None) -> argparse.ArgumentParser:
    return sub.add_parser(name, help=help, description=description or help, formatter_class=_Formatter)


def _training_options(sp: argparse.ArgumentParser) -> None:
    sp.add_argument("problem", help=_PROBLEM_HELP)
    sp.add_argument("--iterations", type=int, default=100, help="training iterations per method")
    sp.add_argument("--batch-size", type=int, default=None,
                    help="samples per iteration (default: the problem's batch_size)")
    sp.add_argument("--resolution", type=int, nargs="+", default=None, metavar="N",
                    help="grid cells per axis, e.g. 32 32 (default: the problem's resolution; a setting of "
                         "the problem, same as --setting resolution=[32,32])")
    sp.add_argument("--seed", type=int, default=0, help="seed of the network initialisation and the data stream")
    sp.add_argument("--device", default="cpu", help="torch device: cpu, cuda or cuda:N")
    sp.add_argument("--out", type=Path, default=None,
                    help="HDF5 file for the curves (and <out>.<method>.model.pt per method; default: nothing "
                         "is written)")
    sp.add_argument("--checkpoint-every", type=int, default=0,
                    help="iterations between checkpoints in --out (0: no checkpoints)")
    sp.add_argument("--resume", action="store_true", help="continue the method's run in --out from its checkpoint")
    sp.add_argument("--overwrite", action="store_true",
                    help="replace a run of the method that --out already holds (refused otherwise)")
    sp.add_argument("--quiet", action="store_true",
                    help="no progress bar (it is shown when stderr is a terminal)")
    sp.add_argument("--eval-every", type=int, default=None,
                    help="iterations between held-out evaluations (default: about 20 per run; 0: at the end only)")
    sp.add_argument("--heldout-size", type=int, default=None,
                    help="samples in the held-out set (default: the problem's heldout_size)")
    sp.add_argument("--dtype", choices=("float32", "float64"), default=None,
                    help="network and data precision (default: the problem's)")
    sp.add_argument("--setting", action="append", metavar="KEY=VALUE", default=[],
                    help="a setting of the problem (repeatable; values parsed as JSON where possible), "
                         "e.g. --setting lr=0.01 --setting resolution=[16,16]")
    sp.add_argument("--tensorboard", type=Path, default=None,
                    help="TensorBoard log folder, when tensorboard is installed (default: no logs)")
    sp.add_argument("--csv", type=Path, default=None,
                    help="folder for CSV copies of the curves, needs --out (default: none)")


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of the ``phisim`` command (standard library only)."""
    p = argparse.ArgumentParser(prog="phisim", formatter_class=_Formatter,
                                description="Differentiable PDE simulation and physical-gradient training: "
                                            "datasets, training runs, pictures and models from the command line.",
                                epilog="`phisim COMMAND --help` explains a command's options and their defaults.")
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")
    _sub(sub, "list", "list the problems and their methods")

    t = _sub(sub, "train", "train one method on a problem",
             "Train one method on a problem. PROBLEM is a registered name (`phisim list`) or your own factory, "
             "module:function or file.py:function.\n\nexample: phisim train examples/burgers_inverse.py:"
             "burgers_problem pg_inverse_gradient --out out/b.h5")
    _training_options(t)
    t.add_argument("method", help="a method of the problem (`phisim list` shows them), e.g. adam, pg")

    c = _sub(sub, "compare", "train several methods on the same data stream",
             "Train several methods on the same data stream and compare their curves. PROBLEM is a registered "
             "name or module:function / file.py:function.")
    _training_options(c)
    c.add_argument("methods", nargs="+", metavar="method", help="methods of the problem, e.g. adam pg")
    c.add_argument("--plot", type=Path, default=None,
                   help="PNG file of the learning curves (default: no picture)")

    i = _sub(sub, "info", "summarise an HDF5 file written by phisim (attributes, datasets, training runs)")
    i.add_argument("path", type=Path, help="the HDF5 file")

    add_workflow_parsers(sub)
    return p


def add_workflow_parsers(sub) -> None:
    """Add the workflow sub-commands (``simulate``, ``plot``, ``predict``, ``export``) to ``phisim``'s
    sub-parser collection ``sub``."""
    s = _sub(sub, "simulate", "generate a dataset of simulations in The Well's layout",
             "Generate a dataset of simulations in The Well's layout: OUT/data/{train,valid,test}/*.h5, "
             "OUT/stats.yaml and OUT/config.json. Settings come from the scenario's defaults (--list shows "
             "them), then --config, then the flags and --set.")
    s.add_argument("scenario", nargs="?", help="scenario name (--list shows them with their defaults)")
    s.add_argument("--list", action="store_true", help="list the scenarios, their parameters and defaults")
    s.add_argument("--config", type=Path, default=None,
                   help="YAML (needs PyYAML) or JSON file of settings, any key --list shows (default: none)")
    s.add_argument("--set", dest="settings", action="append", metavar="KEY=VALUE", default=[],
                   help="a setting (repeatable; values parsed as JSON where possible), e.g. --set viscosity=0.02")
    s.add_argument("--out", type=Path, default=None, help="dataset folder (default: data/<scenario>)")
    scen = "default: the scenario's, see --list"
    s.add_argument("--trajectories", type=int, default=None,
                   help="trajectories in the dataset (default: 8)")
    s.add_argument("--trajectories-per-file", type=int, default=None,
                   help="trajectories per HDF5 file, one parameter draw per file (default: 4)")
    s.add_argument("--steps", type=int, default=None, help=f"time steps per trajectory ({scen})")
    s.add_argument("--dt", type=float, default=None, help=f"time step ({scen})")
    s.add_argument("--resolution", type=int, nargs="+", default=None, metavar="N",
                   help=f"cells per axis: one N for every axis, or one per axis ({scen})")
    s.add_argument("--dim", type=int, default=None, help=f"spatial dimensions, 1, 2 or 3 ({scen})")
    s.add_argument("--seed", type=int, default=None,
                   help="seed of every random draw; same seed, same files (default: 0)")
    s.add_argument("--device", default=None, help="torch device of the simulation: cpu, cuda, cuda:N (default: cpu)")
    s.add_argument("--workers", type=int, default=1, help="parallel worker processes")
    s.add_argument("--overwrite", action="store_true", help="replace a dataset with other settings in --out")
    s.add_argument("--quiet", action="store_true", help="no progress bar (it is shown when stderr is a terminal)")

    pl = _sub(sub, "plot", "pictures of a file: frames, GIF/MP4 of a simulation, learning curves of a training",
              "Pictures of an HDF5 file: a PNG of frames and an animation of one field of a simulation file "
              "(3-D fields as a slice or a projection), the learning curves of a training file.")
    pl.add_argument("path", type=Path, help="the HDF5 file (a simulation or a training file)")
    pl.add_argument("--field", default=None,
                    help="field name, or speed / vorticity derived from the velocity (default: the first scalar "
                         "field other than a mask, else speed)")
    pl.add_argument("--sample", type=int, default=0, help="trajectory index")
    pl.add_argument("--frames", type=int, nargs="+", default=None, metavar="K",
                    help="frame indices of the PNG, negative from the end (default: a few frames spread over the "
                         "run)")
    pl.add_argument("--animation", choices=("gif", "mp4", "none"), default="gif",
                    help="animation of every frame (mp4 needs ffmpeg)")
    pl.add_argument("--fps", type=int, default=10, help="frames per second of the animation")
    pl.add_argument("--axis", default=None,
                    help="3-D fields: the axis normal to the slice or projection, x, y, z or 0, 1, 2 (default: z, "
                         "an x-y picture with y up)")
    pl.add_argument("--index", type=int, default=None,
                    help="3-D fields: cell index of the slice along --axis (default: the middle)")
    pl.add_argument("--projection", choices=("max", "mean", "min"), default=None,
                    help="3-D fields: project the whole volume along --axis (maximum intensity, mean or minimum) "
                         "instead of a slice (default: a slice)")
    pl.add_argument("--out", type=Path, default=None,
                    help="output folder (default: <dataset>/plots/<split>/ for a file <dataset>/data/<split>/*.h5, "
                         "else the file's folder; every picture's path is printed)")

    r = _sub(sub, "predict", "apply a trained model to an array of an HDF5 file",
             "Apply a trained model to an array of an HDF5 file; the array's trailing axes must fit the network, "
             "leading axes (trajectories, time) are kept.\n\nexample: phisim predict out/b.h5.pg.model.pt "
             "data.h5 --key t1_fields/velocity --out pred.h5")
    r.add_argument("model", type=Path, help="model file written by training (<out>.<method>.model.pt)")
    r.add_argument("inputs", type=Path, help="HDF5 file with the inputs")
    r.add_argument("--key", default=None,
                   help="dataset in the input file, e.g. t0_fields/density (default: the file's only dataset, "
                        "else 'inputs')")
    r.add_argument("--out", type=Path, required=True, help="HDF5 file for the predictions (required)")
    r.add_argument("--device", default="cpu", help="torch device: cpu, cuda or cuda:N")
    r.add_argument("--batch-size", type=int, default=64, help="inputs per forward pass")

    e = _sub(sub, "export", "export the training curves of a results file as CSV")
    e.add_argument("path", type=Path, help="HDF5 results file written by training (--out of train/compare)")
    e.add_argument("--csv", type=Path, required=True,
                   help="output folder, one <method>.csv per method (required)")


def main(argv: list[str] | None = None) -> int:
    """Run the ``phisim`` command: parse (here, without heavy imports), then run it in :mod:`inverse.cli`."""
    args = build_parser().parse_args(argv)
    from inverse.cli import run

    return run(args, command=argv is None)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
