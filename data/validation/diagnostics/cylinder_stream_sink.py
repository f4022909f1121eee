"""How much x-momentum the flux-form convection of ``'imex2'`` moves into the faces inside a resting body.

Those faces are reset to the body's velocity every step, so what the convection term carries into them leaves the
fluid without passing through the forces that ``body_forces`` reads (the cut cells' pressure, the wall shear). The
set-up of ``cylinder_stream_integrators.py`` (cylinder of diameter 1 in a uniform stream, Re = 100, t = 10); prints the
drag coefficient and, in the same units, the sum of ``C_x`` times the cell area over the faces inside the body
(``theta <= 0``) and over the cut faces.

``python data/validation/diagnostics/cylinder_stream_sink.py --n 8 --variants imex2 imex2+quick``
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[3]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

import cylinder_stream_integrators as stream  # noqa: E402

from phisim.fluid import body_forces  # noqa: E402
from phisim.fluid.bodies import solid_layout  # noqa: E402
from phisim.fluid.integrators import convection  # noqa: E402


def run(n: int, variant: str, t_end: float = 10.0) -> dict:
    integrator, _, scheme = variant.partition("+")
    scheme = scheme or "central"
    state, dt, _ = stream.simulate(n, integrator, scheme, t_end)
    grid = state.velocity.grid
    dx = grid.dx[0]
    q = 0.5 * stream.U**2 * 1.0
    f = body_forces(state.velocity, state.pressure, stream.body, dt=dt, viscosity=stream.NU, time=state.time)
    layout = solid_layout(stream.body, grid, state.velocity.boundary, state.time, torch.float64, "cpu")
    theta = layout.theta[0][0]
    c_x = convection(state.velocity, scheme).values[0][0] * dx * dx
    return {"n": n, "variant": variant, "t": state.time, "cd": float(f.total[0, 0]) / q,
            "inside": float(c_x[theta <= 0].sum()) / q, "cut": float(c_x[(theta > 0) & (theta < 1)].sum()) / q}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--n", type=int, nargs="+", default=[8])
    ap.add_argument("--variants", nargs="+", default=["imex2", "imex2+quick"])
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    for n in args.n:
        for variant in args.variants:
            print(json.dumps(run(n, variant)), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
