"""Cost of building a body layout (cut-cell fractions and stencils) and of steps that rebuild it (moving bodies).

A layout (:func:`phisim.fluid.solid_layout`) is built once for resting bodies and at every step for moving ones. The
cases, 3-D, float64, one thread, thread time:

* ``static N``: the resting sphere of ``examples/sphere_drag.py`` (wide box ``[-4, 10] x [-4, 4]^2`` diameters) with
  ``N`` cells per diameter: one ``solid_layout`` (after one untimed build of a small grid).
* ``carried N``: a sharp no-slip sphere of radius ``0.2`` carried at ``(0.5, 0.2, 0)`` through a closed unit box of
  ``N^3`` cells, split steps (``FluidStepper``, MacCormack, explicit viscosity ``nu = 0.01``, PCG pressure):
  the median step of ``--steps`` after two untimed ones.
* ``slip N``: the same with a free-slip sphere.
* ``resting N``: a step of the resting sphere of ``examples/sphere_drag.py`` in the quarter of the wide box with ``N``
  cells per diameter, ``integrator='imex2', convection='quick'`` (the stepper keeps the layout and its solves): the
  median step of ``--steps`` after two untimed ones.
* ``build N``: the same resting sphere's stepper built and its first step taken (the stepper's direct pressure solve
  and viscous capacitance solves are built there): the thread time of both together.

``--compare ROOT`` runs every case also with phisim imported from the checkout ``ROOT`` (another commit), each
sample in a fresh process, the two trees alternating, and prints the ratio of the medians; ``--doc`` writes the table
into ``docs/BENCHMARKS.md`` between the markers ``<!-- TAG:begin -->`` and ``<!-- TAG:end -->`` (``--tag``, default
``layout``), with ``--title`` as its heading and ``--changed`` (Markdown) as what the compared commits differ in.

Run:  python benchmarks/bench_layout.py [--static 8 12 16] [--carried 48 64] [--slip 48] [--resting 12] [--build 16]
      [--steps 5]
      [--rounds 2] [--compare ROOT] [--doc] [--tag layout] [--title T] [--changed TEXT] [--json out.json]
      [--device cpu]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shlex
import statistics
import subprocess
import sys
import time
from datetime import datetime
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent


def _static(n: int, device: str) -> dict:
    import torch

    sys.path.insert(0, str(ROOT / "examples"))
    import sphere_drag as sd

    from phisim.fluid import solid_layout

    small, body, state, _ = sd.setup(4, width=8, up=4, down=10, device=device)
    solid_layout(body, small, state.velocity.boundary, device=device)
    grid, body, state, _ = sd.setup(n, width=8, up=4, down=10, device=device)
    clock = _clock(device)
    synchronize(device)
    t0 = clock()
    solid_layout(body, grid, state.velocity.boundary, dtype=torch.float64, device=device)
    synchronize(device)
    return {"seconds": clock() - t0, "cells": list(grid.resolution)}


def _timed_steps(stepper, state, steps: int, device: str) -> dict:
    """The median of ``steps`` steps of ``stepper`` after two untimed ones, the grid's cells and the largest face
    velocity at the end."""
    times = []
    clock = _clock(device)
    for k in range(steps + 2):
        synchronize(device)
        t0 = clock()
        state = stepper(state)
        synchronize(device)
        if k >= 2:
            times.append(clock() - t0)
    return {"seconds": statistics.median(times), "cells": list(state.velocity.grid.resolution),
            "max_u": float(max(c.abs().max() for c in state.velocity.values))}


def _carried(n: int, steps: int, no_slip: bool, device: str) -> dict:
    import torch

    from phisim import Grid, StaggeredGrid
    from phisim.fluid import Body, FluidState, FluidStepper, Sphere

    grid = Grid((n, n, n), bounds=[(0.0, 1.0)] * 3)
    body = Body(Sphere((0.35, 0.4, 0.5), 0.2), velocity=(0.5, 0.2, 0.0), no_slip=no_slip)
    dx = grid.dx[0]
    nu = 0.01
    dt = min(0.5 * dx, 0.45 * dx**2 / (6 * nu))
    stepper = FluidStepper(grid, "wall", obstacles=body, viscosity=nu, dt=dt, dtype=torch.float64, device=device)
    state = FluidState(StaggeredGrid.zeros(grid, "wall", dtype=torch.float64, device=device))
    return _timed_steps(stepper, state, steps, device)


def _resting(n: int, steps: int, device: str) -> dict:
    import torch

    sys.path.insert(0, str(ROOT / "examples"))
    import sphere_drag as sd

    from phisim.fluid import FluidStepper

    grid, body, state, nu = sd.setup(n, width=8, up=4, down=10, quarter=True, device=device)
    stepper = FluidStepper(grid, state.velocity.boundary, obstacles=body, viscosity=nu, dt=0.5 * grid.dx[0],
                           dtype=torch.float64, device=device, integrator="imex2", convection="quick")
    return _timed_steps(stepper, state, steps, device)


def _build(n: int, device: str) -> dict:
    import torch

    sys.path.insert(0, str(ROOT / "examples"))
    import sphere_drag as sd

    from phisim.fluid import FluidStepper

    grid, body, state, nu = sd.setup(n, width=8, up=4, down=10, quarter=True, device=device)
    clock = _clock(device)
    synchronize(device)
    t0 = clock()
    stepper = FluidStepper(grid, state.velocity.boundary, obstacles=body, viscosity=nu, dt=0.5 * grid.dx[0],
                           dtype=torch.float64, device=device, integrator="imex2", convection="quick")
    state = stepper(state)
    synchronize(device)
    return {"seconds": clock() - t0, "cells": list(grid.resolution),
            "max_u": float(max(c.abs().max() for c in state.velocity.values))}


def _worker(case: str, n: int, steps: int, device: str = "cpu") -> dict:
    import torch

    import phisim  # first, so that examples/sphere_drag.py takes this one

    torch.set_num_threads(1)
    if case == "static":
        out = _static(n, device)
    elif case == "resting":
        out = _resting(n, steps, device)
    elif case == "build":
        out = _build(n, device)
    else:
        out = _carried(n, steps, no_slip=case == "carried", device=device)
    out["phisim"] = str(Path(phisim.__file__).resolve().parents[1])
    out["device"] = device
    return out


def _clock(device: str):
    """Thread time on the CPU (one thread: excludes waiting for a core), wall time on a GPU."""
    return time.thread_time if device == "cpu" else time.perf_counter


def synchronize(device: str) -> None:
    """Wait for the device's queued work (CUDA); nothing on the CPU."""
    import torch

    if str(device).startswith("cuda"):
        torch.cuda.synchronize(device)


def _sample(root: Path, case: str, n: int, steps: int, device: str) -> dict:
    code = (f"import sys, json; sys.path.insert(0, {str(root)!r}); sys.path.insert(1, {str(HERE)!r}); "
            f"import bench_layout as b; print(json.dumps(b._worker({case!r}, {n}, {steps}, {device!r})))")
    env = dict(os.environ, OMP_NUM_THREADS="1", MKL_NUM_THREADS="1")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, cwd=str(root))
    if out.returncode:
        raise RuntimeError(f"{case} {n} in {root} failed:\n{out.stderr[-2000:]}")
    res = json.loads(out.stdout.strip().splitlines()[-1])
    if Path(res["phisim"]) != root:
        raise RuntimeError(f"the worker for {root} imported phisim from {res['phisim']}")
    return res


def _commit(root: Path) -> str:
    r = subprocess.run(["git", "-C", str(root), "rev-parse", "--short", "HEAD"], capture_output=True, text=True)
    dirty = subprocess.run(["git", "-C", str(root), "status", "--porcelain", "--untracked-files=no"],
                           capture_output=True, text=True).stdout.strip()
    return (r.stdout.strip() or "?") + (" + changes" if dirty else "")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--static", type=int, nargs="*", default=[8, 12, 16])
    ap.add_argument("--carried", type=int, nargs="*", default=[48, 64])
    ap.add_argument("--slip", type=int, nargs="*", default=[48])
    ap.add_argument("--resting", type=int, nargs="*", default=[])
    ap.add_argument("--build", type=int, nargs="*", default=[])
    ap.add_argument("--steps", type=int, default=5)
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--compare", default=None, help="another checkout of phisim to run beside this one")
    ap.add_argument("--doc", action="store_true", help="write the table into docs/BENCHMARKS.md")
    ap.add_argument("--tag", default="layout", help="the markers of the table's section in docs/BENCHMARKS.md")
    ap.add_argument("--title", default="Building body layouts (resting and moving bodies), float64, one thread")
    ap.add_argument("--changed", default=None, help="what the compared trees differ in (Markdown), for the doc")
    ap.add_argument("--json", default=None, help="write the rows to this JSON file")
    ap.add_argument("--device", default="cpu", help="torch device: cpu, cuda or cuda:N (default cpu)")
    args = ap.parse_args(argv)
    sys.path.insert(0, str(ROOT))
    from phisim.checks import check_device

    device = str(check_device(args.device))  # a device this machine lacks stops here, before anything is written
    trees = [("this", ROOT)] + ([("compare", Path(args.compare).resolve())] if args.compare else [])
    cases = [("static", n) for n in args.static] + [("carried", n) for n in args.carried] + \
            [("slip", n) for n in args.slip] + [("resting", n) for n in args.resting] + \
            [("build", n) for n in args.build]
    rows = []
    started = datetime.now().isoformat(timespec="seconds")
    for case, n in cases:
        got = {name: [] for name, _ in trees}
        extra = {}
        for r in range(args.rounds):
            order = trees if r % 2 == 0 else trees[::-1]
            for name, root in order:
                res = _sample(root, case, n, args.steps, device)
                got[name].append(res["seconds"])
                extra[name] = res
        row = {"case": case, "n": n, "cells": extra["this"]["cells"], "device": device,
               **{name: statistics.median(v) for name, v in got.items()},
               **{f"{name}_all": v for name, v in got.items()},
               **{f"{name}_max_u": extra[name].get("max_u") for name, _ in trees}}
        if args.compare:
            row["ratio"] = row["compare"] / row["this"]
        rows.append(row)
        print(json.dumps(row), flush=True)
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps(rows, indent=1))
    if args.doc:
        _write_doc(rows, trees, started, args)
    return 0


def _command(argv) -> str:
    """The arguments as a shell would take them, with ``--changed``'s text (the doc's next line) elided."""
    out, skip = [], False
    for arg in argv:
        if skip:
            out.append("'...'")
            skip = False
            continue
        out.append(shlex.quote(arg))
        skip = arg == "--changed"
    return " ".join(out)


def _write_doc(rows, trees, started, args) -> None:
    label = {"static": "resting sphere, one layout", "carried": "carried no-slip sphere, one step",
             "slip": "carried free-slip sphere, one step", "resting": "resting sphere, quarter box, one `imex2` step",
             "build": "resting sphere, quarter box, `imex2` stepper built + first step"}
    head = "| case | cells | this tree | other tree | other / this |\n|---|---|---|---|---|\n"
    lines = []
    for r in rows:
        cells = " x ".join(str(c) for c in r["cells"])
        other = f"{r['compare']:.3g} s" if "compare" in r else "-"
        ratio = f"**{r['ratio']:.2f}x**" if "ratio" in r else "-"
        lines.append(f"| {label[r['case']]} (n = {r['n']}) | {cells} | {r['this']:.3g} s | {other} | {ratio} |")
    cmd = "python benchmarks/bench_layout.py " + _command(sys.argv[1:])
    trees_txt = "; ".join(f"{name}: `{_commit(root)}`" for name, root in trees)
    velocities = "; ".join(
        f"{r['case']} {r['n']}: " + " / ".join(f"{r.get(f'{name}_max_u'):.10g}" for name, _ in trees)
        for r in rows if r.get("this_max_u") is not None)
    changed = args.changed or "see the two commits' logs"
    begin, end = f"<!-- {args.tag}:begin -->", f"<!-- {args.tag}:end -->"
    body = (
        f"{begin}\n## {args.title}\n\n"
        "Thread time of one `solid_layout` of the resting sphere of `examples/sphere_drag.py` (wide box), the "
        "median step of a sphere carried through a closed box (the layout is rebuilt every step), the median "
        "`imex2` step of the resting sphere (quarter box) and the building of its stepper with the first step, as "
        "the table lists them; each sample in a fresh process, "
        "the trees alternating (`benchmarks/bench_layout.py`).\n\n" + head + "\n".join(lines) + "\n\n"
        f"- made by `{cmd}` ({started}, {platform.machine()} {os.cpu_count()} cores, {platform.system()}); "
        f"{args.rounds} samples per tree and case, medians; trees: {trees_txt} (the other tree: a `git worktree` of "
        "that commit).\n"
        f"- What changed: {changed} (largest face velocity at the end of each step case, this / other tree: "
        f"{velocities}).\n"
        f"{end}\n")
    doc = ROOT / "docs" / "BENCHMARKS.md"
    text = doc.read_text()
    if begin in text:
        a, rest = text.split(begin, 1)
        _, b = rest.split(end + "\n", 1)
        text = a + body + b
    else:
        marker = "<!-- cg-floor:begin -->"
        text = text.replace(marker, body + "\n" + marker, 1) if marker in text else text + "\n" + body
    doc.write_text(text)


if __name__ == "__main__":
    raise SystemExit(main())
