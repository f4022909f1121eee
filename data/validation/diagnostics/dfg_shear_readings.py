"""The viscous part of the DFG drag read by the probes and by the momentum balance at the wall (docs/VALIDATION.md,
"The wall shear of thin boundary layers").

    python data/validation/diagnostics/dfg_shear_readings.py CASE NY T_END INTEGRATOR

Runs the case (examples/cylinder_benchmark.py's set-up, CFL 0.5, float64) to T_END with a FluidStepper of the given
integrator and prints one JSON line: the viscous part of (c_D, c_L) with ``shear_at='probes'`` and ``'momentum'``, the
samples 1, 1.5 (the default) and 2 cells out, and the pressure part (the cut cells).
"""
import json
import math
import os
import sys

ROOT = os.environ.get("REPO", os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "..", ".."))
sys.path.insert(0, ROOT)
sys.path.insert(0, os.path.join(ROOT, "examples"))
import cylinder_benchmark as cb  # noqa: E402
import torch  # noqa: E402

from phisim.fluid import FluidStepper, body_forces  # noqa: E402

torch.set_num_threads(1)
case, ny, t_end, integrator = sys.argv[1], int(sys.argv[2]), float(sys.argv[3]), sys.argv[4]
grid, body, state, um = cb.setup(case, ny)
dx = grid.dx[0]
dt = min(0.5 * dx / (1.5 * um), 0.45 * dx**2 / (4 * cb.NU))
n = int(math.ceil(t_end / dt))
dt = t_end / n
stepper = FluidStepper(grid, state.velocity.boundary, obstacles=body, viscosity=cb.NU, integrator=integrator, dt=dt,
                       dtype=torch.float64)
for _ in range(n):
    state = stepper(state)
scale = 2 / ((2 * um / 3) ** 2 * cb.D)
out = {"case": case, "ny": ny, "t": state.time, "integrator": integrator}
for shear in ("probes", "momentum"):
    for d in (1.0, 1.5, 2.0):
        f = body_forces(state.velocity, state.pressure, body, dt=dt, viscosity=cb.NU, time=state.time, shear_at=shear,
                        probe_distance=d)
        out[f"viscous_{shear}_{d}"] = [round(float(x) * scale, 5) for x in f.viscous[0]]
out["pressure_cells"] = [round(float(x) * scale, 5) for x in f.pressure[0]]
print(json.dumps(out), flush=True)
