"""Flows past bodies, phisim against PhiFlow 3.4: a smoke plume with two box obstacles and a cylinder wake.

Both codes run the same scene with an iterative (CG) pressure solve, warm-started from the previous step's
pressure, with the same stopping rule, one intra-op thread each, float64. Sides:

* ``phisim``           -- bodies as :class:`phisim.fluid.Body` (fractional faces, no-slip);
* ``phisim_obstacle``  -- the same shapes as staircase :class:`phisim.fluid.Obstacle` (PhiFlow's kind of body);
* ``phiflow``          -- PhiFlow 3.4 uncompiled, ``Obstacle(Box/Sphere)``, ``Solve('CG', 0, atol, x0=p)``;
* ``phiflow_jit``      -- the same step under ``math.jit_compile`` (its fastest mode; compile time excluded).

Scenes (``n x n`` cells, ``dx = 1``, ``dt = 1``):

* ``plume_boxes``: closed box, a Gaussian smoke source near the bottom, buoyancy 0.1, MacCormack smoke,
  semi-Lagrangian velocity, two cell-aligned boxes above the source;
* ``cylinder_wake``: inflow ``U = 0.5`` on the left, outflow (PhiFlow: zero-gradient, phisim: ``Open()``) on
  the right, walls above and below, a disc of radius ``0.06 n`` at ``(0.25 n, 0.52 n)``; semi-Lagrangian
  self-advection, explicit viscosity (``Re = U 2r / nu = 100``).

Stopping rule, the same in both codes: ``||b - A p||_2 <= atol`` with ``rtol = 0`` and
``atol = TOL * U / dx * sqrt(cells)`` (the RMS residual of the discrete divergence below ``TOL`` times the
velocity scale per cell; ``TOL = 1e-5``). A relative tolerance would not be the same rule: PhiFlow's CG
measures ``rtol`` against the residual of the warm start (``phiml.backend._linalg.stop_on_l2``), phisim
against ``||b||``.

Every measurement runs in a fresh child process: ``warm`` untimed steps (flow development, caches,
compilation), then ``steps`` individually timed steps, run ``repeat`` times from the same state (the lowest
time per step is kept); the median over the steps is one sample. Sides are interleaved in each round (order
rotated) and the best sample over ``rounds`` is reported, with the load average. Both the wall time and the
CPU time of the process (``time.process_time``) are recorded: with one thread, the CPU time leaves out the
time spent waiting for a core on a loaded machine.

Run (PhiFlow in ``benchmarks/.phiflow-venv``, see ``benchmarks/setup_phiflow.sh``)::

    python benchmarks/bench_flow_bodies.py [--sizes 128 256] [--rounds 3] [--doc]

``--device cuda`` runs the two phisim sides on a GPU (inputs built on the CPU and moved, every timed step
bracketed by CUDA synchronisations); the PhiFlow sides always run on the CPU (its venv has a CPU-only torch).

``--doc`` writes the table into ``docs/BENCHMARKS.md`` (between the ``flow-bodies`` markers); results go to
``benchmarks/results/flow_bodies.json``. One measurement: ``--child SIDE --scene S --size N``.
"""

from __future__ import annotations

import argparse
import datetime as _dt
import json
import os
import statistics
import subprocess
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
RESULTS = os.path.join(HERE, "results", "flow_bodies.json")
DOC = os.path.join(ROOT, "docs", "BENCHMARKS.md")
PHIFLOW_PYTHON = os.path.join(HERE, ".phiflow-venv", "bin", "python")
PATCHED_PATH = os.path.join(HERE, ".phiflow-venv", "phiml-patched")
SCENES = ("plume_boxes", "cylinder_wake")
SIDES = ("phisim", "phisim_obstacle", "phiflow", "phiflow_jit")
TOL = 1e-5
MARK_BEGIN, MARK_END = "<!-- flow-bodies:begin -->", "<!-- flow-bodies:end -->"


def scene(name: str, n: int) -> dict:
    """Parameters of a scene on ``n x n`` cells (lengths in cells)."""
    if name == "plume_boxes":
        u = 1.0
        boxes = [((round(0.35 * n), round(0.45 * n)), (round(0.55 * n), round(0.52 * n))),
                 ((round(0.55 * n), round(0.68 * n)), (round(0.80 * n), round(0.74 * n)))]
        p = {"boxes": boxes, "dt": 1.0, "buoyancy": 0.1, "u": u}
    elif name == "cylinder_wake":
        u, r = 0.5, 0.06 * n
        p = {"center": (0.25 * n, 0.52 * n), "radius": r, "dt": 1.0, "u": u, "nu": u * 2 * r / 100.0}
    else:
        raise ValueError(f"unknown scene {name}")
    p["atol"] = TOL * p["u"] * n  # = TOL * U/dx * sqrt(n*n)
    return p


def _time_steps(step, state, steps: int, repeat: int, sync=lambda: None):
    """Time ``steps`` consecutive steps from ``state``, ``repeat`` times from the same start.

    ``sync`` waits for queued device work (CUDA) and runs before each clock reading.

    Returns the state after the steps and, per step, the lowest wall and CPU (process) time over the passes.
    """
    wall = [float("inf")] * steps
    cpu = [float("inf")] * steps
    start = state
    for _ in range(repeat):
        state = start
        for k in range(steps):
            sync()
            c0, t0 = time.process_time(), time.perf_counter()
            state = step(state)
            sync()
            wall[k] = min(wall[k], time.perf_counter() - t0)
            cpu[k] = min(cpu[k], time.process_time() - c0)
    return state, wall, cpu


# ------------------------------------------------------------------------------------------------------------
# phisim side (phisim's venv)
# ------------------------------------------------------------------------------------------------------------


def _run_phisim(name: str, n: int, warm: int, steps: int, repeat: int, staircase: bool,
                device: str = "cpu") -> dict:
    import torch

    sys.path.insert(0, ROOT)
    sys.path.insert(0, HERE)
    import inputs

    from phisim import CenteredGrid, Grid, Open, StaggeredGrid
    from phisim.boundary import Inflow
    from phisim.checks import check_device
    from phisim.fluid import Body, Box, FluidState, FluidStepper, Obstacle, Projection, Sphere, buoyancy, solid_flux
    from phisim.fluid.bodies import solid_layout
    from phisim.ops.advection import maccormack, semi_lagrangian
    from phisim.ops.differential import divergence
    from phisim.solvers.linalg import Solve
    from phisim.solvers.masked import MaskedPoisson

    # Like for like: both codes iterate (CG) to the same stopping rule (direct=False); phisim's direct solve of a
    # layout that keeps coming back (the wake's static disc) is measured by benchmarks/bench_bodies.py instead.
    infos = []
    orig = MaskedPoisson.solve

    def recording(self, rhs, **kw):
        out = orig(self, rhs, **kw)
        infos.append(out[1])
        return out

    MaskedPoisson.solve = recording
    dev = check_device(device)
    sync = (lambda: torch.cuda.synchronize(dev)) if dev.type == "cuda" else (lambda: None)
    dtype = torch.float64
    p = scene(name, n)
    grid = Grid((n, n), bounds=[(0.0, float(n)), (0.0, float(n))])
    solve = Solve(rtol=0.0, atol=p["atol"], max_iter=20000)
    dt = p["dt"]
    if name == "plume_boxes":
        init = inputs.smoke_initial((n, n), 1, dtype="float64")
        smoke = CenteredGrid(torch.as_tensor(init["smoke"]).to(dev), grid, "neumann")
        source = torch.as_tensor(init["inflow"]).to(dev)
        v = StaggeredGrid([torch.as_tensor(c).to(dev) for c in init["velocity"]], grid, "wall")
        solids = [Obstacle.box(lo, hi) if staircase else Body(Box(lo, hi)) for lo, hi in p["boxes"]]
        project = Projection(grid, v.boundary, solids, solve=solve, dtype=dtype, device=dev, direct=False)

        def step(state):
            m, vel, pr = state
            m = maccormack(m, vel, dt) + source * dt
            vel = semi_lagrangian(vel, vel, dt)
            vel = buoyancy(vel, m, dt, strength=p["buoyancy"])
            vel, pr, _ = project(vel, pressure_guess=pr)
            return m, vel, pr

        state = (smoke, v, None)
    else:
        u = p["u"]
        boundary = {"x": (Inflow((u, 0.0)), Open()), "y": "wall"}
        v = StaggeredGrid.from_function(lambda x: torch.stack([torch.full_like(x[..., 0], u),
                                                               torch.zeros_like(x[..., 0])], -1),
                                        grid, boundary, dtype=dtype, device=dev)
        solids = (Obstacle.sphere(p["center"], p["radius"]) if staircase
                  else Body(Sphere(p["center"], p["radius"])))

        stepper = FluidStepper(grid, v.boundary, obstacles=solids, viscosity=p["nu"], advection="semi_lagrangian",
                               pressure=solve, dt=dt, dtype=dtype, device=dev, direct=False)

        def step(state):
            t, vel, pr = state
            s = stepper(FluidState(vel, None, pr, t))
            return s.time, s.velocity, s.pressure

        state = (0.0, v, None)
    for _ in range(warm):
        state = step(state)
    infos.clear()
    state, times, cpu = _time_steps(step, state, steps, repeat, sync)
    its = [int(i.iterations.max()) for i in infos[:steps]]
    vel = state[1]
    # the continuity residual: the divergence of the face fluxes (sharp bodies store the fluid velocity on the
    # faces they cut; the flux there is theta u + (1 - theta) u_s plus the near-wall correction)
    layout = solid_layout(solids, grid, vel.boundary, float(state[0]) if name != "plume_boxes" else 0.0,
                          vel.dtype, vel.device)
    div = divergence(solid_flux(vel, layout)).values
    stats = {"max_u": max(float(c.abs().max()) for c in vel.values),
             "rms_div": float(div.pow(2).mean().sqrt())}
    if name == "plume_boxes":
        stats["smoke_sum"] = float(state[0].values.sum())
    return {"times_s": times, "cpu_s": cpu, "iterations": its, "stats": stats, "device": str(dev)}


# ------------------------------------------------------------------------------------------------------------
# PhiFlow side (benchmarks/.phiflow-venv)
# ------------------------------------------------------------------------------------------------------------


def _run_phiflow(name: str, n: int, warm: int, steps: int, repeat: int, jit: bool) -> dict:
    sys.path.insert(0, HERE)
    import inputs
    import numpy as np
    from phi.torch.flow import (
        Box,
        CenteredGrid,
        Obstacle,
        Solve,
        Sphere,
        StaggeredGrid,
        advect,
        batch,
        diffuse,
        extrapolation,
        field,
        fluid,
        math,
        resample,
        spatial,
        vec,
    )

    math.set_global_precision(64)
    p = scene(name, n)
    dt = p["dt"]
    bounds = Box(x=n, y=n)
    sp = spatial("x,y")
    atol = p["atol"]
    if name == "plume_boxes":
        init = inputs.smoke_initial((n, n), 1, dtype="float64")

        def scalar(arr):
            return CenteredGrid(math.tensor(np.asarray(arr), batch("b"), sp), extrapolation.ZERO_GRADIENT, bounds)

        inner = []
        for i, c in enumerate(init["velocity"]):  # inner faces only (zero-boundary grid)
            sl = [slice(None)] * 3
            sl[i + 1] = slice(1, -1)
            inner.append(math.tensor(np.asarray(c[tuple(sl)]), batch("b"), sp))
        v0 = StaggeredGrid(math.stack(inner, math.dual(vector="x,y")), 0, bounds)
        smoke0, source = scalar(init["smoke"]), scalar(init["inflow"])
        p0 = scalar(np.zeros((1, n, n)))
        obstacles = [Obstacle(Box(x=(lo[0], hi[0]), y=(lo[1], hi[1]))) for lo, hi in p["boxes"]]
        up = vec(x=0.0, y=p["buoyancy"])

        def step(smoke, velocity, pressure):
            smoke = advect.mac_cormack(smoke, velocity, dt) + source * dt
            force = resample(smoke * up, to=velocity)
            velocity = advect.semi_lagrangian(velocity, velocity, dt) + force * dt
            solve = Solve("CG", 0.0, atol, x0=pressure, max_iterations=20000, rank_deficiency=0)
            velocity, pressure = fluid.make_incompressible(velocity, obstacles, solve)
            return smoke, velocity, pressure

        state = (smoke0, v0, p0)
    else:
        u = p["u"]
        bc = {"x-": vec(x=u, y=0.0), "x+": extrapolation.ZERO_GRADIENT, "y-": 0, "y+": 0}
        v0 = StaggeredGrid(vec(x=u, y=0.0), bc, bounds, x=n, y=n)
        obstacles = [Obstacle(Sphere(x=p["center"][0], y=p["center"][1], radius=p["radius"]))]

        def step(t, velocity, pressure):
            velocity = advect.semi_lagrangian(velocity, velocity, dt)
            velocity = diffuse.explicit(velocity, p["nu"], dt)
            solve = Solve("CG", 0.0, atol, x0=pressure, max_iterations=20000)
            velocity, pressure = fluid.make_incompressible(velocity, obstacles, solve)
            return t, velocity, pressure

        state = (0.0, v0, None)  # first solve cold; later ones from the previous pressure
    run = math.jit_compile(step) if jit else step
    compile_s = None
    t0 = time.perf_counter()
    for k in range(warm):
        state = run(*state)
        if k == 0:
            compile_s = time.perf_counter() - t0
    its: list[int] = []
    tapes = []

    def once(st):
        if jit:
            return run(*st)
        with math.SolveTape(record_trajectories=False) as tape:
            out = run(*st)
        tapes.append(tape[0].iterations)
        return out

    state, times, cpu = _time_steps(once, state, steps, repeat)
    its = [int(math.max(t)) for t in tapes[:steps]]
    vel = state[1]
    div = field.divergence(vel).values.numpy("b,x,y")
    stats = {"max_u": float(math.max(abs(vel.values))),
             "rms_div": float(np.sqrt((div ** 2).mean()))}
    if name == "plume_boxes":
        stats["smoke_sum"] = float(state[0].values.numpy("b,x,y").sum())
    out = {"times_s": times, "cpu_s": cpu, "iterations": its, "stats": stats}
    if jit:
        out["first_call_s"] = compile_s
    return out


# ------------------------------------------------------------------------------------------------------------
# driver
# ------------------------------------------------------------------------------------------------------------


def _load() -> str:
    try:
        return open("/proc/loadavg").read().split()[0]
    except OSError:
        return "?"


def child(side: str, name: str, n: int, warm: int, steps: int, repeat: int, device: str = "cpu") -> dict:
    """One measurement in this process (the child); returns the JSON-able result.

    ``device`` places the phisim sides; the PhiFlow sides run on the CPU.
    """
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    import torch

    torch.set_num_threads(1)
    if side.startswith("phisim"):
        res = _run_phisim(name, n, warm, steps, repeat, staircase=side == "phisim_obstacle", device=device)
    else:
        import warnings

        warnings.filterwarnings("ignore")
        res = _run_phiflow(name, n, warm, steps, repeat, jit=side == "phiflow_jit")
        res["device"] = "cpu"
    t = res["times_s"]
    res.update(median_s=statistics.median(t), min_s=min(t), median_cpu_s=statistics.median(res["cpu_s"]))
    return res


def drive(side: str, name: str, n: int, warm: int, steps: int, repeat: int, timeout: float,
          device: str = "cpu") -> dict:
    """Run one measurement in a child process (phisim: this interpreter, on ``device``; PhiFlow: its venv, CPU)."""
    env = dict(os.environ, OMP_NUM_THREADS="1", MKL_NUM_THREADS="1")
    py = sys.executable
    if side.startswith("phiflow"):
        py = PHIFLOW_PYTHON
        if n * n > 46225:  # phiml's sparse build overflows int32 above ~215^2 cells: int64-patched copy
            env["PYTHONPATH"] = PATCHED_PATH
    else:
        env["PYTHONPATH"] = ROOT + os.pathsep + env.get("PYTHONPATH", "")
    cmd = [py, os.path.abspath(__file__), "--child", side, "--scene", name, "--size", str(n),
           "--warm", str(warm), "--steps", str(steps), "--repeat", str(repeat)]
    if not side.startswith("phiflow"):
        cmd += ["--device", device]
    base = {"side": side, "scene": name, "n": n, "load_before": _load()}
    t0 = time.perf_counter()
    try:
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, env=env)
    except subprocess.TimeoutExpired:
        return {**base, "error": f"timeout after {timeout:.0f} s"}
    base["wall_s"] = round(time.perf_counter() - t0, 1)
    base["load_after"] = _load()
    for line in reversed(proc.stdout.strip().splitlines()):
        if line.startswith("{"):
            return {**base, **json.loads(line)}
    tail = (proc.stderr or proc.stdout).strip().splitlines()[-3:]
    return {**base, "error": f"exit {proc.returncode}: {' | '.join(tail)[:400]}"}


def best(results: list[dict], key: str = "median_s") -> dict:
    """Per (scene, n, side) the sample with the lowest ``key`` (median wall or CPU time per step)."""
    out: dict = {}
    for r in results:
        if "error" in r or key not in r:
            continue
        k = (r["scene"], r["n"], r["side"])
        if k not in out or r[key] < out[k][key]:
            out[k] = r
    return out


def _ms(s: float | None) -> str:
    if s is None:
        return "-"
    return f"{s * 1e3:.3g} ms" if s < 1 else f"{s:.3g} s"


def table(data: dict, key: str = "median_s") -> list[str]:
    """Markdown lines of the results (``data`` as saved in ``results/flow_bodies.json``) by ``key``."""
    b = best(data["results"], key)
    lines = [
        "| scene | size | phisim (Body) | phisim (Obstacle) | PhiFlow | PhiFlow jit | PhiFlow / phisim | "
        "PhiFlow jit / phisim | CG iterations per step: phisim Body, Obstacle / PhiFlow |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for name in SCENES:
        for n in data["sizes"]:
            r = {s: b.get((name, n, s)) for s in SIDES}
            if not any(r.values()):
                continue
            med = {s: (x[key] if x else None) for s, x in r.items()}

            def ratio(a, c, med=med):
                return f"{med[a] / med[c]:.1f}x" if med[a] and med[c] else "-"

            def its(s, r=r):
                x = r[s]
                return f"{statistics.mean(x['iterations']):.1f}" if x and x.get("iterations") else "-"

            lines.append(
                f"| {name} | {n}^2 | {_ms(med['phisim'])} | {_ms(med['phisim_obstacle'])} | {_ms(med['phiflow'])} | "
                f"{_ms(med['phiflow_jit'])} | **{ratio('phiflow', 'phisim')}** (Obstacle "
                f"{ratio('phiflow', 'phisim_obstacle')}) | **{ratio('phiflow_jit', 'phisim')}** (Obstacle "
                f"{ratio('phiflow_jit', 'phisim_obstacle')}) | {its('phisim')}, {its('phisim_obstacle')} / "
                f"{its('phiflow')} |"
            )
    return lines


GOALS = (("phiflow", 30.0), ("phiflow_jit", 15.0))


def goals(data: dict) -> list[str]:
    """The speed goals (phisim with Body at least 30x PhiFlow plain and 15x its jit mode), per scene and size."""
    cpu, wall = best(data["results"], "median_cpu_s"), best(data["results"], "median_s")
    lines = ["| goal | scene | size | CPU-time ratio | wall-time ratio | met (CPU / wall) |",
             "|---|---|---|---|---|---|"]
    for peer, target in GOALS:
        for name in SCENES:
            for n in data["sizes"]:
                rs = []
                for b, key in ((cpu, "median_cpu_s"), (wall, "median_s")):
                    ours, theirs = b.get((name, n, "phisim")), b.get((name, n, peer))
                    rs.append(theirs[key] / ours[key] if ours and theirs else None)
                if rs[0] is None and rs[1] is None:
                    continue
                label = "PhiFlow" if peer == "phiflow" else "PhiFlow jit"
                fmt = [f"{x:.1f}x" if x else "-" for x in rs]
                met = " / ".join("-" if x is None else ("yes" if x >= target else "no") for x in rs)
                lines.append(f"| >= {target:.0f}x {label} | {name} | {n}^2 | {fmt[0]} | {fmt[1]} | {met} |")
    return lines


def stats_lines(data: dict) -> list[str]:
    """Same-physics check: final-state statistics of the best samples."""
    b = best(data["results"])
    out = []
    for name in SCENES:
        for n in data["sizes"]:
            parts = []
            for s in SIDES:
                x = b.get((name, n, s))
                if x:
                    st = ", ".join(f"{k} {v:.4g}" for k, v in x["stats"].items())
                    parts.append(f"{s}: {st}")
            if parts:
                out.append(f"- {name} {n}^2 after {data['warm'] + data['steps']} steps: " + "; ".join(parts))
    return out


def section(data: dict) -> str:
    """The docs/BENCHMARKS.md section (between the markers)."""
    loads = [r.get("load_before") for r in data["results"]] + [r.get("load_after") for r in data["results"]]
    loads = [float(x) for x in loads if x not in (None, "?")]
    errors = [f"- {r['side']} {r['scene']} {r['n']}^2: {r['error']}" for r in data["results"] if "error" in r]
    lines = [
        MARK_BEGIN,
        "## Flows past bodies (smoke plume with two boxes, cylinder wake), float64, iterative pressure solves",
        "",
        "Per-step time, best over rounds of the median of the timed steps (see "
        "`benchmarks/bench_flow_bodies.py` for the scenes). Both codes: CG pressure solve warm-started from "
        "the previous pressure, the same stopping rule `||b - A p||_2 <= atol`, `rtol = 0`, "
        f"`atol = {TOL:g} * U/dx * sqrt(cells)`, float64, one intra-op thread each. PhiFlow: "
        "`fluid.make_incompressible(v, [Obstacle(...)], Solve('CG', 0, atol, x0=p))` (its CG has no "
        "preconditioner), plain and under `math.jit_compile`; phisim: `make_incompressible` (plume) / "
        "`navier_stokes_step` (wake) with the bodies as `Body` (fractional faces) or `Obstacle` (staircase, "
        "PhiFlow's kind), spectral-preconditioned CG. Iterations: mean over the timed steps "
        "(PhiFlow jit runs the same CG as plain). A relative tolerance would not be the same rule in the two "
        "codes: PhiFlow's CG measures `rtol` against the residual of its warm start "
        "(`phiml.backend._linalg.stop_on_l2`), phisim against `||b||`.",
        "",
    ] + goals(data) + [
        "",
        "CPU time of the process per step (`time.process_time`; one thread, so it excludes the time spent "
        "waiting for a core on the loaded machine):",
        "",
    ] + table(data, "median_cpu_s") + [
        "",
        "Wall-clock time per step (includes waiting for a core; the load varied between the samples):",
        "",
    ] + table(data, "median_s") + [
        "",
        f"- made by `{data['command']}` ({data['date']}, {data['machine']}, phisim on "
        f"{data.get('device', 'cpu')}, PhiFlow on the CPU); {data['rounds']} rounds, sides "
        f"interleaved in each round, {data['warm']} untimed + {data['steps']} timed steps per sample, the timed "
        f"steps run {data.get('repeat', 1)} times from the same state (lowest time per step), each sample in a "
        "fresh process.",
        f"- machine load (1-min load average, 2 cores) during the run: {min(loads):.1f} to {max(loads):.1f}"
        if loads else "- machine load: not recorded",
        f"- `uptime` before: `{data.get('uptime_before', '?')}`; after: `{data.get('uptime_after', '?')}`",
        "- same physics: statistics of the final state below (`max_u` the largest face velocity, `rms_div` the RMS "
        "of each code's own divergence over all cells, phisim's of its face fluxes (`solid_flux`); "
        "PhiFlow's wake value comes from the cells inside the disc, "
        "where its velocity is not projected: outside the body it is about 5e-6, like phisim's).",
    ] + stats_lines(data) + errors + [MARK_END]
    return "\n".join(lines)


def write_doc(data: dict, path: str = DOC) -> None:
    """Put :func:`section` into the document (replacing an earlier one between the markers)."""
    text = open(path).read() if os.path.exists(path) else ""
    sec = section(data)
    if MARK_BEGIN in text and MARK_END in text:
        a, rest = text.split(MARK_BEGIN, 1)
        _, z = rest.split(MARK_END, 1)
        text = a + sec + z
    else:
        anchor = "## Other benchmark scripts"
        text = text.replace(anchor, sec + "\n\n" + anchor) if anchor in text else text.rstrip() + "\n\n" + sec + "\n"
    with open(path, "w") as fh:
        fh.write(text)


def _uptime() -> str:
    try:
        return subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()
    except OSError:
        return "?"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[128, 256])
    ap.add_argument("--scenes", nargs="+", default=list(SCENES), choices=SCENES)
    ap.add_argument("--sides", nargs="+", default=list(SIDES), choices=SIDES)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--warm", type=int, default=6)
    ap.add_argument("--steps", type=int, default=5)
    ap.add_argument("--repeat", type=int, default=3, help="passes over the timed steps, from the same state")
    ap.add_argument("--timeout", type=float, default=1200.0)
    ap.add_argument("--doc", action="store_true", help="write the section into docs/BENCHMARKS.md")
    ap.add_argument("--doc-only", action="store_true", help="rebuild the section from the saved results")
    ap.add_argument("--out", default=RESULTS)
    ap.add_argument("--append", action="store_true", help="add to the saved results (more rounds, same settings)")
    ap.add_argument("--child", choices=SIDES)
    ap.add_argument("--scene", choices=SCENES)
    ap.add_argument("--size", type=int)
    ap.add_argument("--device", default="cpu",
                    help="torch device of the phisim sides: cpu, cuda or cuda:N (default cpu); the PhiFlow sides "
                    "always run on the CPU")
    a = ap.parse_args(argv)
    if a.child:
        print(json.dumps(child(a.child, a.scene, a.size, a.warm, a.steps, a.repeat, a.device)), flush=True)
        return 0
    if not a.doc_only and any(s.startswith("phisim") for s in a.sides):
        sys.path.insert(0, ROOT)
        from phisim.checks import check_device

        check_device(a.device)  # a bad device fails here, not in every child
    if a.doc_only:
        write_doc(json.load(open(a.out)))
        return 0
    import platform

    data = {"command": "python benchmarks/" + " ".join([os.path.basename(__file__)] + (argv or sys.argv[1:])),
            "date": _dt.datetime.now().isoformat(timespec="seconds"),
            "machine": f"{platform.machine()} {os.cpu_count()} cores, {platform.system()}",
            "device": a.device, "sizes": a.sizes,
            "rounds": a.rounds, "warm": a.warm, "steps": a.steps, "repeat": a.repeat, "tol": TOL,
            "uptime_before": _uptime(), "results": []}
    if a.device.startswith("cuda") and any(s.startswith("phisim") for s in a.sides):
        import torch

        data["machine"] += f", GPU {torch.cuda.get_device_name(a.device)}"
    if a.append and os.path.exists(a.out):
        old = json.load(open(a.out))
        if (old["warm"], old["steps"], old.get("repeat"), old["tol"], old.get("device", "cpu")) != (
                a.warm, a.steps, a.repeat, TOL, a.device):
            raise SystemExit("--append needs the saved run's --warm, --steps, --repeat, device and tolerance")
        data.update(results=old["results"], rounds=old["rounds"] + a.rounds, uptime_before=old["uptime_before"],
                    command=old["command"] + "`, then `" + data["command"],
                    sizes=sorted(set(old["sizes"]) | set(a.sizes)))
    for k in range(a.rounds):
        for name in a.scenes:
            for n in a.sizes:
                order = a.sides[k % len(a.sides):] + a.sides[: k % len(a.sides)]
                for side in order:
                    r = drive(side, name, n, a.warm, a.steps, a.repeat, a.timeout, a.device)
                    data["results"].append(r)
                    msg = r.get("error") or (f"median {_ms(r['median_s'])}, cpu {_ms(r['median_cpu_s'])}, iterations "
                                             f"{r.get('iterations')}")
                    print(f"[round {k + 1}] {name} {n}^2 {side}: {msg} (load {r['load_before']})", flush=True)
                data["uptime_after"] = _uptime()
                os.makedirs(os.path.dirname(a.out), exist_ok=True)
                with open(a.out, "w") as fh:
                    json.dump(data, fh, indent=1)
    print("\n".join(table(data, "median_cpu_s") + [""] + table(data)))
    if a.doc:
        write_doc(data)
    return 0


if __name__ == "__main__":
    sys.exit(main())
