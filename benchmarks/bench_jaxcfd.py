"""phisim's periodic fluid step against jax-cfd 0.2.1 (XLA-compiled), the same scheme on both sides.

    bash benchmarks/setup_jaxpeers.sh                       # once: jax, jax-cfd, exponax in benchmarks/.venv-jax
    python benchmarks/bench_jaxcfd.py [--quick] [--rounds 3] [--write] [--sides phisim] [--sizes 64 128]
                                      [--variants fused general compiled]

Scheme (``../shared/PEERS.md``): on the periodic square ``[0, 2π)²`` (3-D cases: the cube ``[0, 2π)³``),
semi-Lagrangian self-advection, explicit viscosity, the exact FFT pressure projection. phisim:
``FluidStepper(grid, "periodic", advection="semi_lagrangian", viscosity_scheme="explicit")`` in eager mode, which
takes the fused periodic step (:class:`phisim.fluid.periodic.PeriodicStep`), beside the general path of the same
stepper (``fused=False``) and, with ``--variants ... compiled``, the stepper under ``torch.compile``
(``compile=True``). jax-cfd: ``semi_implicit_navier_stokes`` with semi-Lagrangian convection and
``pressure.solve_fast_diag`` under ``jax.jit`` (``jax.vmap`` for batches, ``funcutils.repeated`` for rollouts,
``jax.grad`` through rollouts). The two apply viscosity to the advected and to the old velocity respectively; the
energies after 100 float64 steps at 64² are printed as the like-for-like check. One thread per side
(``torch.set_num_threads(1)``; XLA single-threaded Eigen and intra-op), interleaved rounds; the table gives the
best time of each side and the ratio phisim / jax-cfd (< 1: phisim faster).
With ``--device cuda`` both sides run on the GPU (``--peer-python``: an interpreter with jax and jax-cfd; results
to ``benchmarks/results/jaxcfd_cuda.*``; ``docs/BENCHMARKS_GPU.md``).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import torch

HERE = Path(__file__).resolve().parent
CPU = torch.device("cpu")
sys.path.insert(0, str(HERE.parent))
sys.path.insert(0, str(HERE))

from peer_jaxcfd import TWO_PI, initial_velocity  # noqa: E402
from timing import jax_peer_environment, synchronize  # noqa: E402

from phisim import Grid, StaggeredGrid  # noqa: E402
from phisim.checks import check_device  # noqa: E402
from phisim.fluid import FluidState, FluidStepper  # noqa: E402

PEER_PYTHON = HERE / ".venv-jax" / "bin" / "python"
#: The phisim steps a run can time.
VARIANTS = ("fused", "general", "compiled")


def make_cases(quick: bool, sizes: list[int] | None = None) -> list[dict]:
    """The benchmark cases (float32 unless named); ``sizes`` replaces every case list by one-step cases."""
    base = {"dtype": "float32", "viscosity": 1e-3, "dt": 0.01, "batch": 1, "mode": "step", "steps": 1, "dim": 2}
    if sizes:
        return [dict(base, n=n) for n in sizes]
    sizes = [64, 128] if quick else [64, 128, 256, 512]
    cases = [dict(base, n=n) for n in sizes]
    cases += [dict(base, n=n, dtype="float64") for n in ([64] if quick else [64, 128, 256])]
    cases += [dict(base, n=n, batch=b) for n, b in ([(32, 128), (64, 32)] if quick else
                                                     [(32, 128), (64, 32), (128, 8)])]
    cases += [dict(base, n=n, mode="rollout", steps=100) for n in ([64] if quick else [64, 128, 256])]
    cases += [dict(base, n=n, mode="grad", steps=10) for n in ([64] if quick else [64, 128, 256])]
    cases += [dict(base, n=n, dim=3) for n in ([32] if quick else [64, 128])]
    return cases


def build_phisim(case: dict, device=None, variant: str = "fused"):
    """A function running ``case`` on the phisim side (on ``device``): ``variant`` ``'fused'`` (the default
    stepper: the fused periodic step), ``'general'`` (``fused=False``) or ``'compiled'`` (``compile=True``)."""
    dtype = torch.float64 if case["dtype"] == "float64" else torch.float32
    n, batch, dim = case["n"], case["batch"], case.get("dim", 2)
    grid = Grid((n,) * dim, bounds=[(0.0, TWO_PI)] * dim)
    dx = TWO_PI / n
    comps = []
    for c in range(dim):
        shape = grid.face_shape(c)
        axes = [(np.arange(shape[a]) + (0.0 if a == c else 0.5)) * dx for a in range(dim)]
        mesh = np.meshgrid(*axes, indexing="ij")
        comps.append(torch.as_tensor(np.stack([initial_velocity(mesh[0], mesh[1], c, b * TWO_PI / batch,
                                                                mesh[2] if dim == 3 else None)
                                               for b in range(batch)]), dtype=dtype, device=device))
    stepper = FluidStepper(grid, "periodic", viscosity=case["viscosity"], advection="semi_lagrangian",
                           viscosity_scheme="explicit", dt=case["dt"], dtype=dtype, device=device,
                           fused=variant != "general", compile=variant == "compiled")
    v0 = StaggeredGrid(tuple(comps), grid, stepper.boundary).with_boundary_faces()

    def run(v):
        s = FluidState(v)
        for _ in range(case["steps"]):
            s = stepper(s)
        return s.velocity

    if case["mode"] == "grad":
        def fn():
            v = v0.with_values(tuple(c.detach().requires_grad_(True) for c in v0.values))
            out = run(v)
            e = sum(c[(slice(None),) + (slice(0, n),) * dim].pow(2).mean() for c in out.values)
            e.backward()
            return v.values[0].grad
    else:
        def fn():
            with torch.no_grad():
                return run(v0)

    def energy():
        with torch.no_grad():
            out = run(v0)
        return sum(c[(slice(None),) + (slice(0, n),) * dim].double().pow(2).mean(dim=tuple(range(1, dim + 1)))
                   for c in out.values).tolist()

    return fn, energy


class Peer:
    """The jax-cfd child process (on the CPU, or on the GPU when the phisim side runs on CUDA)."""

    def __init__(self, python: Path = PEER_PYTHON, device: torch.device = CPU):
        env = jax_peer_environment(device.type)
        self.proc = subprocess.Popen([str(python), str(HERE / "peer_jaxcfd.py")], stdin=subprocess.PIPE,
                                     stdout=subprocess.PIPE, text=True, env=env, bufsize=1)

    def ask(self, req: dict) -> dict:
        self.proc.stdin.write(json.dumps(req) + "\n")
        self.proc.stdin.flush()
        line = self.proc.stdout.readline()
        if not line:
            raise RuntimeError("the jax-cfd peer stopped; run bash benchmarks/setup_jaxpeers.sh first")
        return json.loads(line)

    def close(self):
        try:
            self.ask({"cmd": "quit"}) if self.proc.poll() is None else None
        except (BrokenPipeError, RuntimeError):
            pass
        self.proc.wait(timeout=10)


def reps_for(case: dict) -> int:
    """Repeats per round: more for cheap cases."""
    work = case["n"] ** case.get("dim", 2) * case["batch"] * case["steps"] * (3 if case["mode"] == "grad" else 1)
    return max(2, min(20, int(2e6 / work)))


def _timed(fn, device: torch.device) -> float:
    """Seconds of one call in the phisim-only mode: this thread's CPU time on the CPU (a loaded machine's waits
    excluded), the wall time up to the device's synchronisation on a GPU."""
    if device.type != "cpu":
        synchronize(device)
        t = time.perf_counter()
        fn()
        synchronize(device)
        return time.perf_counter() - t
    t = time.thread_time()
    fn()
    return time.thread_time() - t


def label(case: dict) -> str:
    size = f"{case['n']}{'³' if case.get('dim', 2) == 3 else '²'}" + (f" x {case['batch']}" if case["batch"] > 1
                                                                      else "")
    what = {"step": "one step", "rollout": f"{case['steps']}-step rollout",
            "grad": f"forward + backward, {case['steps']} steps"}[case["mode"]]
    return f"{what}, {size}, {case['dtype']}"


def main(argv: list[str] | None = None) -> list[dict]:
    """Run the cases and print (optionally write) the table."""
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="small sizes only")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--write", action="store_true",
                    help="write benchmarks/results/jaxcfd.json and .md (jaxcfd_cuda.* for a GPU run)")
    ap.add_argument("--sides", nargs="+", default=["phisim", "jaxcfd"], choices=["phisim", "jaxcfd"],
                    help="which sides to run (default both; phisim alone needs no jax environment)")
    ap.add_argument("--sizes", type=int, nargs="+", default=None, help="one-step cases of these sizes only")
    ap.add_argument("--device", default="cpu", help="torch device of the phisim side: cpu, cuda or cuda:N (the "
                    "jax-cfd side then runs on the GPU too)")
    ap.add_argument("--peer-python", type=Path, default=PEER_PYTHON,
                    help="the interpreter holding jax and jax-cfd (default: benchmarks/.venv-jax)")
    ap.add_argument("--variants", nargs="+", default=["fused", "general"], choices=VARIANTS,
                    help="phisim steps to time: fused (the default stepper), general (fused=False), compiled "
                         "(compile=True: inductor; each case's stepper compiled once, the first call reported)")
    ap.add_argument("--modes", nargs="+", default=["step", "rollout", "grad"], choices=["step", "rollout", "grad"],
                    help="which cases: one step, 100-step rollouts, forward + backward through 10 steps")
    args = ap.parse_args(argv)
    device = check_device(args.device)
    torch.set_num_threads(1)
    with_peer = "jaxcfd" in args.sides
    if with_peer and not args.peer_python.exists():
        raise SystemExit("no jax-cfd environment: run bash benchmarks/setup_jaxpeers.sh first")
    cases = [c for c in make_cases(args.quick, args.sizes) if c["mode"] in args.modes]
    built, compile_s = {}, {}
    for c in cases:
        key = json.dumps(c, sort_keys=True)
        for variant in args.variants:
            t = time.perf_counter()
            fn = build_phisim(c, device, variant)[0]
            fn()
            synchronize(device)
            if variant == "compiled":
                compile_s[key] = time.perf_counter() - t
            built[key, variant] = fn
    if not with_peer:
        for c in cases:
            key = json.dumps(c, sort_keys=True)
            for variant in args.variants:
                if (key, variant) in built:
                    best = min(_timed(built[key, variant], device) for _ in range(args.rounds * reps_for(c)))
                    clock = "CPU time of this thread" if device.type == "cpu" else f"wall time, {device}"
                    print(f"{label(c)}: phisim {variant} {1e3 * best:.3f} ms (best of "
                          f"{args.rounds * reps_for(c)}, {clock})")
        return []
    peer = Peer(args.peer_python, device)
    info = peer.ask({"cmd": "info"})
    rows = {json.dumps(c, sort_keys=True): {"case": c, "peer": [], "compile_s": None,
                                            **{v: [] for v in args.variants}} for c in cases}
    load = os.getloadavg()[0]
    try:
        for _ in range(args.rounds):
            for c in cases:
                key = json.dumps(c, sort_keys=True)
                reps = reps_for(c)
                for variant in args.variants:
                    fn = built.get((key, variant))
                    if fn is None:
                        continue
                    fn()  # warm
                    synchronize(device)
                    for _ in range(reps):
                        t = time.perf_counter()
                        fn()
                        synchronize(device)
                        rows[key][variant].append(time.perf_counter() - t)
                out = peer.ask({"cmd": "time", "case": c, "reps": reps})
                rows[key]["peer"] += out["times"]
                if out.get("compile_s") is not None:
                    rows[key]["compile_s"] = out["compile_s"]
        check = dict(cases[0], n=64, dtype="float64", mode="rollout", steps=100, batch=1, dim=2)
        e_peer = peer.ask({"cmd": "energy", "case": check})["energy"]
        e_ours = build_phisim(check, device)[1]()
    finally:
        peer.close()
    load_end = os.getloadavg()[0]
    result = []
    names = {"fused": "phisim", "general": "general path", "compiled": "compiled"}
    head = "| case | " + " | ".join(f"{names[v]} ms" for v in args.variants) + " | jax-cfd ms | " + \
        " | ".join(f"{names[v]} / jax-cfd" for v in args.variants) + " | jax-cfd compile s |" + \
        (" phisim compile s |" if "compiled" in args.variants else "")
    lines = [head, "|" + "---|" * (head.count("|") - 1)]
    for key, r in rows.items():
        b = min(r["peer"])
        best = {v: (min(r[v]) if r[v] else None) for v in args.variants}
        result.append({"case": r["case"], "jaxcfd_s": b, "jaxcfd_median_s": statistics.median(r["peer"]),
                       "jaxcfd_compile_s": r["compile_s"], "phisim_compile_s": compile_s.get(key),
                       **{f"{v}_s": best[v] for v in args.variants},
                       **{f"{v}_median_s": (statistics.median(r[v]) if r[v] else None) for v in args.variants}})
        ms = " | ".join("" if best[v] is None else f"{1e3 * best[v]:.3f}" for v in args.variants)
        ratios = " | ".join("" if best[v] is None else (f"**{best[v] / b:.2f}**" if v == "fused" else
                                                        f"{best[v] / b:.2f}") for v in args.variants)
        cs = "" if r["compile_s"] is None else f"{r['compile_s']:.2f}"
        line = f"| {label(r['case'])} | {ms} | {1e3 * b:.3f} | {ratios} | {cs} |"
        if "compiled" in args.variants:
            line += f" {compile_s[key]:.1f} |" if key in compile_s else " |"
        lines.append(line)
    rel = abs(e_ours[0] - e_peer[0]) / e_peer[0]
    where = ("one thread per side" if device.type == "cpu" else
             f"both sides on the GPU ({torch.cuda.get_device_name(device)}; jax devices {info.get('devices')})")
    header = [f"jax {info['jax']}, jax-cfd {info['jax_cfd']}, torch {torch.__version__}; {where}; "
              f"{args.rounds} interleaved rounds, best of each side; load average {load:.2f} at the start, "
              f"{load_end:.2f} at the end.",
              f"Like-for-like check: kinetic energy after 100 float64 steps at 64²: phisim {e_ours[0]:.8f}, "
              f"jax-cfd {e_peer[0]:.8f} (relative difference {rel:.1e}).", ""]
    text = "\n".join(header + lines)
    print(text)
    if args.write:
        (HERE / "results").mkdir(exist_ok=True)
        name = "jaxcfd" if device.type == "cpu" else "jaxcfd_cuda"
        (HERE / "results" / f"{name}.json").write_text(json.dumps({"info": info, "rows": result, "load": load,
                                                                   "load_end": load_end, "device": str(device),
                                                                   "energy": [e_ours, e_peer]}, indent=1))
        (HERE / "results" / f"{name}.md").write_text(text + "\n")
    return result


if __name__ == "__main__":
    main()
