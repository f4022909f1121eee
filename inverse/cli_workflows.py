"""Sub-commands of ``phisim`` for the daily workflows: ``simulate``, ``plot``, ``predict``, ``export``.

Their parsers are defined in :mod:`phisim_cli` (a light module: ``phisim --help`` imports nothing heavy);
their paths are checked by :mod:`inverse.cli_checks` before they run.

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

from phisim_cli import add_workflow_parsers  # the parsers live in the light module (kept here by name)

from . import cli_checks

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


def _list_scenarios() -> str:
    """Every scenario with its dimensions, its defaults (resolution, dt, steps) and its parameters, then the
    settings every scenario takes with their defaults."""
    from phisim.simulate import COMMON_PARAMETERS, SCENARIOS

    lines = []
    for name, sc in SCENARIOS.items():
        dims = "/".join(f"{d}-D" for d in sorted(sc.dims))
        lines.append(f"{name} ({dims}): {sc.description}")
        lines.append(f"    defaults: dim={sc.dims[0]}, resolution={sc.resolution}, dt={sc.dt:g}, steps={sc.steps}")
        for key, par in sc.parameters.items():
            rng = f" [random in {par.low:g}..{par.high:g} per file]" if par.low is not None else ""
            lines.append(f"    {key} = {par.default!r}{rng}  {par.help}")
    lines.append("settings of every scenario (--set KEY=VALUE, a --config file, or the flag of the same name):")
    for key, par in COMMON_PARAMETERS.items():
        default = "the scenario's" if par.default is None else repr(par.default)
        lines.append(f"    {key} = {default}  {par.help}")
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
        cli_checks.writable_dir(out, "dataset folder")
        r = simulate_dataset(out, cfg, workers=args.workers, progress=False if args.quiet else None,
                             overwrite=args.overwrite)
        if r["stats"] is not None:
            print(cli_checks.json_summary({
                "dataset": str(r["root"]), "files": r["files"], "written": r["written"], "skipped": r["skipped"],
                "trajectories": r["trajectories"], "files_per_split": r.get("files_per_split"),
                "stats": str(r["stats"])}))
        return 0
    if args.command == "plot":
        from phisim.viz.plotfile import plot_file

        anim = None if args.animation == "none" else args.animation
        slicing = {k: v for k, v in (("axis", _axis(args.axis)), ("index", args.index),
                                     ("projection", args.projection)) if v is not None}
        for p in plot_file(args.path, args.out, field=args.field, sample=args.sample, frames=args.frames,
                           animation=anim, fps=args.fps, **slicing):
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


def _axis(value: str | None):
    """``--axis``: a name (``x``, ``y``, ``z``) as it is, a number as an int."""
    if value is None:
        return None
    v = value.strip().lower()
    if v.lstrip("-").isdigit():
        return int(v)
    if v in ("x", "y", "z"):
        return v
    from phisim.errors import ParameterError

    raise ParameterError(f"--axis must be x, y, z or an axis number 0, 1, 2, got {value!r}")
