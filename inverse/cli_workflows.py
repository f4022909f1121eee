"""Sub-commands of ``phisim`` for the daily workflows: ``simulate``, ``plot``, ``predict``, ``export``.

Examples::

    phisim simulate smoke --trajectories 64 --workers 4 --out data/smoke
    phisim simulate burgers --config burgers.yaml --set dim=2 --set viscosity=0.02 --out data/burgers
    phisim simulate --list
    phisim plot data/smoke/data/train/smoke_00000.h5 --field vorticity --animation gif
    phisim predict out/poisson.h5.adam.model.pt inputs.h5 --key inputs --out predictions.h5
    phisim export out/poisson.h5 --csv out/curves
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

__all__ = ["add_workflow_parsers", "run_workflow", "WORKFLOW_COMMANDS", "parse_settings"]

WORKFLOW_COMMANDS = ("simulate", "plot", "predict", "export")


def parse_settings(items: list[str] | None) -> dict:
    """``['key=value', ...]`` to a dict; values parsed as JSON where possible (``3``, ``0.1``, ``true``,
    ``[32, 48]``), else kept as strings.

    Raises:
        ParameterError: An item without ``=``.
    """
    from phisim.errors import ParameterError

    out = {}
    for item in items or []:
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise ParameterError(f"settings are KEY=VALUE, got {item!r}")
        try:
            out[key.strip()] = json.loads(value)
        except ValueError:
            out[key.strip()] = value
    return out


def add_workflow_parsers(sub) -> None:
    """Add the workflow sub-commands to the ``phisim`` sub-parser collection ``sub``."""
    s = sub.add_parser("simulate", help="generate a dataset of simulations (The Well layout)")
    s.add_argument("scenario", nargs="?", help="scenario name (see --list)")
    s.add_argument("--list", action="store_true", help="list the scenarios and their parameters")
    s.add_argument("--config", type=Path, default=None, help="YAML or JSON file of settings")
    s.add_argument("--set", dest="settings", action="append", metavar="KEY=VALUE", default=[],
                   help="a setting (repeatable), e.g. --set viscosity=0.02")
    s.add_argument("--out", type=Path, default=None, help="dataset folder (default: data/<scenario>)")
    s.add_argument("--trajectories", type=int, default=None)
    s.add_argument("--trajectories-per-file", type=int, default=None)
    s.add_argument("--steps", type=int, default=None)
    s.add_argument("--dt", type=float, default=None)
    s.add_argument("--resolution", type=int, nargs="+", default=None)
    s.add_argument("--dim", type=int, default=None)
    s.add_argument("--seed", type=int, default=None)
    s.add_argument("--device", default=None)
    s.add_argument("--workers", type=int, default=1, help="parallel worker processes")
    s.add_argument("--overwrite", action="store_true", help="replace a dataset with other settings")
    s.add_argument("--quiet", action="store_true", help="no progress bar")

    p = sub.add_parser("plot", help="frames / GIF / MP4 of a simulation file, learning curves of a training file")
    p.add_argument("path", type=Path)
    p.add_argument("--field", default=None, help="field name, or speed / vorticity (derived from velocity)")
    p.add_argument("--sample", type=int, default=0, help="trajectory index")
    p.add_argument("--frames", type=int, nargs="+", default=None, help="frame indices of the PNG")
    p.add_argument("--animation", choices=("gif", "mp4", "none"), default="gif")
    p.add_argument("--fps", type=int, default=10)
    p.add_argument("--out", type=Path, default=None, help="output folder (default: beside the file)")

    r = sub.add_parser("predict", help="apply a trained model to inputs from an HDF5 file")
    r.add_argument("model", type=Path, help="model file written by training (<out>.<method>.model.pt)")
    r.add_argument("inputs", type=Path, help="HDF5 file with the inputs")
    r.add_argument("--key", default=None, help="dataset in the input file (e.g. t0_fields/density)")
    r.add_argument("--out", type=Path, required=True, help="HDF5 file for the predictions")
    r.add_argument("--device", default="cpu")
    r.add_argument("--batch-size", type=int, default=64)

    e = sub.add_parser("export", help="export the training curves of a results file as CSV")
    e.add_argument("path", type=Path)
    e.add_argument("--csv", type=Path, required=True, help="output folder (one <method>.csv per method)")


def _list_scenarios() -> str:
    from phisim.simulate import COMMON_PARAMETERS, SCENARIOS

    lines = []
    for name, sc in SCENARIOS.items():
        dims = "/".join(f"{d}-D" for d in sorted(sc.dims))
        lines.append(f"{name} ({dims}): {sc.description}")
        for key, par in sc.parameters.items():
            rng = f" [random in {par.low:g}..{par.high:g} per file]" if par.low is not None else ""
            lines.append(f"    {key} = {par.default!r}{rng}  {par.help}")
    lines.append("common settings: " + ", ".join(COMMON_PARAMETERS))
    return "\n".join(lines)


def run_workflow(args: argparse.Namespace) -> int:
    """Run one workflow sub-command (errors of the PhisimError family propagate to the caller)."""
    from phisim.errors import ParameterError

    if args.command == "simulate":
        if args.list:
            print(_list_scenarios())
            return 0
        if not args.scenario:
            raise ParameterError("name a scenario (phisim simulate --list shows them)")
        from phisim.simulate import load_config_file, resolve_config, simulate_dataset

        config = load_config_file(args.config) if args.config is not None else {}
        config.update(parse_settings(args.settings))
        res = args.resolution
        flags = {"trajectories": args.trajectories, "trajectories_per_file": args.trajectories_per_file,
                 "steps": args.steps, "dt": args.dt, "dim": args.dim, "seed": args.seed, "device": args.device,
                 "resolution": (res[0] if len(res) == 1 else res) if res else None}
        cfg = resolve_config(args.scenario, config, **flags)
        out = args.out or Path("data") / args.scenario
        r = simulate_dataset(out, cfg, workers=args.workers, progress=not args.quiet, overwrite=args.overwrite)
        if r["stats"] is not None:
            print(json.dumps({"dataset": str(r["root"]), "files": r["files"], "written": r["written"],
                              "skipped": r["skipped"], "trajectories": r["trajectories"],
                              "stats": str(r["stats"])}))
        return 0
    if args.command == "plot":
        from phisim.viz.plotfile import plot_file

        anim = None if args.animation == "none" else args.animation
        for p in plot_file(args.path, args.out, field=args.field, sample=args.sample, frames=args.frames,
                           animation=anim, fps=args.fps):
            print(p)
        return 0
    if args.command == "predict":
        from .models import predict_file

        print(predict_file(args.model, args.inputs, args.out, key=args.key, device=args.device,
                           batch_size=args.batch_size))
        return 0
    if args.command == "export":
        from .export import export_csv

        for p in export_csv(args.path, args.csv):
            print(p)
        return 0
    raise ParameterError(f"unknown command {args.command!r}")
