"""The sphere's drag at Re = 100 from the momentum balance over boxes round it, beside the body readings.

Reads states saved by ``examples/sphere_drag.py --save-state``. Without ``--step``: the steady balance (without the
momentum change, :func:`phisim.fluid.control_volume_force` without ``previous``); with ``--step`` each state is advanced
by one ``imex2`` + QUICK step first and the momentum change in the box is included (for a flow still settling). In the
quarter box the boxes' lower sides lie on the free-slip mirror planes ``y = 0`` and ``z = 0`` (the reading takes the
mirror images there), so each box is a quarter of the whole box round the whole sphere and the drag is four times its
reading. Boxes: ``x`` from ``-a`` to ``b`` diameters, ``y, z`` up to ``c`` diameters (``--boxes a b c ...``).

    python data/validation/diagnostics/sphere_control_volume.py STATE.pt [STATE.pt ...] --out FILE.json
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import sys
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[3]
sys.path.insert(0, str(ROOT))
_spec = importlib.util.spec_from_file_location("sphere_drag", ROOT / "examples" / "sphere_drag.py")
sd = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(sd)

from phisim.fluid import FluidStepper, body_forces  # noqa: E402


def read(path: str, boxes, step: bool = False) -> dict:
    saved = torch.load(path, map_location="cpu", weights_only=True)
    n, box, quarter, dt = int(saved["n"]), tuple(saved["box"]), bool(saved["quarter"]), float(saved["dt"])
    up, down, width = box
    grid, body, state, nu = sd.setup(n, 100.0, torch.float64, "cpu", width=width, up=up, down=down, quarter=quarter)
    state = sd.load_state(path, grid, state.velocity.boundary, 100.0, box, quarter, torch.float64, "cpu")
    previous = None
    if step:  # one more step, so that the reading includes the momentum change in the box (a flow still settling)
        stepper = FluidStepper(grid, state.velocity.boundary, obstacles=body, viscosity=nu, dt=dt, dtype=torch.float64,
                               integrator=saved.get("integrator", "imex2"),
                               convection=saved.get("convection", "quick"))
        previous = state.velocity
        state = stepper(state)
    area = sd.AREA / 4 if quarter else sd.AREA
    out = {"state": str(path), "n": n, "t": state.time, "quarter": quarter, "cells": list(grid.resolution),
           "with_momentum_change": step}
    f = body_forces(state.velocity, state.pressure, body, dt=dt, viscosity=nu, time=state.time)
    out["cd_cells"] = float(f.coefficients(sd.U, area)[0, 0])
    m = body_forces(state.velocity, state.pressure, body, dt=dt, viscosity=nu, time=state.time,
                    pressure_at="momentum", shear_at="momentum")
    out["cd_momentum"] = float(m.coefficients(sd.U, area)[0, 0])
    out["cv"] = {}
    for a, b, c in boxes:
        out["cv"][f"{a:g},{b:g},{c:g}"] = sd.control_volume_drag(state, dt, nu, quarter, box=(a, b, c),
                                                                 previous=previous)
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("states", nargs="+")
    ap.add_argument("--boxes", type=float, nargs="+", default=[1.0, 1.5, 1.0, 1.5, 2.0, 1.5, 2.0, 3.0, 2.0])
    ap.add_argument("--step", action="store_true",
                    help="advance each state by one imex2 + QUICK step first and include the momentum change")
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    boxes = list(zip(args.boxes[0::3], args.boxes[1::3], args.boxes[2::3]))
    rows = [read(p, boxes, args.step) for p in args.states]
    text = json.dumps(rows, indent=1)
    print(text)
    if args.out:
        Path(args.out).write_text(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
