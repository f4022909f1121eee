"""ETDRK steppers: phisim.pde against exponax 0.2.0 (JAX), one thread each on the CPU (or both sides on one GPU
with ``--device cuda``), interleaved rounds.

Run (after ``bash benchmarks/setup_jaxpeers.sh``)::

    .venv/bin/python benchmarks/bench_etdrk.py [--rounds 3] [--quick] [--dtype float32|float64]
        [--only ks1d,burgers1d,ns2d,heat2d,fft1d,fft2d] [--peer-venv benchmarks/.venv-jax]

Both sides solve the same problems with the same scheme, resolution, 2/3-rule dealiasing (exponax's cut-off,
``|m| <= N/3 - 1``, is passed to phisim), float precision and analytic initial state:

* 1-D conservative Kuramoto-Sivashinsky (``L = 100``, ``dt = 0.1``), ETDRK4;
* 1-D viscous Burgers ``u_t + (u^2/2)_x = nu u_xx`` (``L = 2 pi``, ``nu = 0.02``, ``dt = 5e-4``), ETDRK2 (exponax's
  default order; its ``conservative=True`` form, the one phisim uses);
* 2-D Navier-Stokes in vorticity form (``L = 2 pi``, ``nu = 1e-3``, ``dt = 1e-3``), ETDRK4;
* 2-D heat equation (``L = 2 pi``, ``nu = 0.01``, ``dt = 0.01``), exact in time (ETDRK0 on both sides);

batch 1 and 32, one step and a 100-step rollout (final state only). exponax runs in a child process
(``peer_exponax.py``) with ``XLA_FLAGS='--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1'``,
jit-compiled and vmapped over the batch, warmed up, timed with ``block_until_ready``; phisim runs in this process
with ``torch.set_num_threads(1)``. Each round times every case on both sides in turn. Each repetition is timed
twice: wall time and CPU time of the process (``time.process_time``, all threads; on a machine shared with other
jobs it leaves out the time the process waits for a core). The table reports each side's best wall time (minimum
over all repetitions and rounds) and the ratios phisim / exponax (below 1: phisim faster) of the best wall times,
of the CPU times (per-round mean over the repetitions, best round: the kernel books a worker thread's CPU time
late, so single repetitions of the JAX side can read too low, their sum over a round does not) and of the medians
over rounds of the per-round median wall times. ``--from-json`` rebuilds the table from a results file. "FFT floor"
rows time one forward and one inverse real FFT of the same state on both sides. One-step outputs of both are
compared (max difference relative to the max of the state; exponax's vorticity has the opposite sign convention,
which the comparison accounts for).
Results go to ``benchmarks/results/etdrk[_float64].json`` and the Markdown table to stdout and
``benchmarks/results/etdrk[_float64]_table.md``.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

HERE = Path(__file__).resolve().parent
CPU = torch.device("cpu")
sys.path.insert(0, str(HERE))
sys.path.insert(0, str(HERE.parent))

from peer_exponax import initial_state  # noqa: E402
from timing import jax_peer_environment, synchronize  # noqa: E402

from phisim.checks import check_device  # noqa: E402
from phisim.errors import ParameterError  # noqa: E402
from phisim.pde import Burgers, Diffusion, KuramotoSivashinsky, NavierStokesVorticity  # noqa: E402

EQS = ("ks1d", "burgers1d", "ns2d", "heat2d", "fft1d", "fft2d")


def make_cases(quick: bool, dtype: str = "float32", only: tuple[str, ...] = EQS) -> list[dict]:
    """The benchmark matrix.

    Args:
        quick: Only the smallest sizes (a smoke run).
        dtype: ``"float32"`` or ``"float64"`` (both sides).
        only: The equations to include (see :data:`EQS`).

    Returns:
        Case dictionaries (see ``peer_exponax.py``).
    """
    cases = []
    sizes_1d = [256, 1024] if quick else [256, 1024, 4096]
    sizes_2d = [128] if quick else [128, 256, 512]
    settings = {"ks1d": dict(dt=0.1, domain=100.0, order=4, viscosity=0.0),
                "burgers1d": dict(dt=5e-4, domain=2 * math.pi, order=2, viscosity=0.02),
                "ns2d": dict(dt=1e-3, domain=2 * math.pi, order=4, viscosity=1e-3),
                "heat2d": dict(dt=0.01, domain=2 * math.pi, order=0, viscosity=0.01)}
    for eq in ("ks1d", "burgers1d", "ns2d", "heat2d"):
        if eq not in only:
            continue
        for n in (sizes_1d if eq.endswith("1d") else sizes_2d):
            for batch in (1, 32):
                for mode in ("step", "rollout"):
                    if mode == "rollout" and batch == 32 and n > 128 and eq.endswith("2d"):
                        continue  # minutes per round; the single steps show the same per-step ratio
                    cases.append(dict(eq=eq, n=n, batch=batch, mode=mode, steps=1 if mode == "step" else 100,
                                      dtype=dtype, **settings[eq]))
    for eq in ("fft1d", "fft2d"):
        if eq not in only:
            continue
        for n in (sizes_1d if eq == "fft1d" else sizes_2d):
            for batch in (1, 32):
                cases.append(dict(eq=eq, n=n, batch=batch, mode="step", steps=1, dt=0.0, domain=2 * math.pi, order=0,
                                  viscosity=0.0, dtype=dtype))
    return cases


def reps_for(case: dict) -> int:
    """Timed repetitions per round, so that one round of one case takes roughly 0.1-1 s."""
    work = case["n"] ** (1 if case["eq"].endswith("1d") else 2) * case["batch"] * case["steps"]
    if case["eq"].startswith("fft"):
        work //= 20
    if case["eq"] in ("ks1d", "burgers1d"):
        work *= 4
    return int(max(3, min(300, 2e6 / max(work, 1))))


def build_phisim(case: dict, device: torch.device = CPU):
    """The phisim stepper (exponax's dealiasing cut-off, on ``device``) and the function to time."""
    n = case["n"]
    dtype = getattr(torch, case.get("dtype", "float32"))
    fraction = (2.0 / 3.0 * (n // 2) - 1) / (n // 2)
    u0 = torch.from_numpy(initial_state(case)).to(device)
    if case["eq"] == "fft2d":
        return (lambda: torch.fft.irfftn(torch.fft.rfftn(u0, dim=(-2, -1)), s=(n, n), dim=(-2, -1))), None, u0
    if case["eq"] == "fft1d":
        return (lambda: torch.fft.irfft(torch.fft.rfft(u0), n=n)), None, u0
    if case["eq"] == "ks1d":
        stepper = KuramotoSivashinsky(ndim=1, domain=case["domain"], resolution=n, dt=case["dt"], order=case["order"],
                                      dealias=fraction, dtype=dtype, device=device)
    elif case["eq"] == "burgers1d":
        stepper = Burgers(ndim=1, viscosity=case["viscosity"], domain=case["domain"], resolution=n, dt=case["dt"],
                          order=case["order"], dealias=fraction, dtype=dtype, device=device)
    elif case["eq"] == "heat2d":
        stepper = Diffusion(ndim=2, diffusivity=case["viscosity"], domain=case["domain"], resolution=n, dt=case["dt"],
                            dtype=dtype, device=device)
    else:
        stepper = NavierStokesVorticity(viscosity=case["viscosity"], domain=case["domain"], resolution=n,
                                        dt=case["dt"], order=case["order"], dealias=fraction, dtype=dtype,
                                        device=device)
    if case["mode"] == "step":
        return (lambda: stepper(u0)), stepper, u0
    steps = case["steps"]
    return (lambda: stepper.repeat(u0, steps)), stepper, u0


class Peer:
    """The exponax child process."""

    def __init__(self, python: str, x64: bool = False, device: torch.device = CPU):
        env = jax_peer_environment(device.type)
        env["JAX_ENABLE_X64"] = "1" if x64 else "0"
        self.proc = subprocess.Popen([python, str(HERE / "peer_exponax.py")], stdin=subprocess.PIPE,
                                     stdout=subprocess.PIPE, text=True, env=env, bufsize=1)

    def ask(self, request: dict) -> dict:
        """Send one request and read its answer."""
        self.proc.stdin.write(json.dumps(request) + "\n")
        self.proc.stdin.flush()
        line = self.proc.stdout.readline()
        if not line:
            raise RuntimeError("the exponax peer exited (run benchmarks/setup_jaxpeers.sh first)")
        return json.loads(line)

    def close(self) -> None:
        """Stop the child."""
        try:
            self.ask({"cmd": "quit"})
        except (RuntimeError, BrokenPipeError, json.JSONDecodeError):
            pass
        self.proc.wait(timeout=30)


def time_phisim(fn, reps: int, device: torch.device = CPU) -> tuple[list[float], list[float]]:
    """``reps`` timings of ``fn`` in seconds: wall times (up to the device's synchronisation) and process CPU
    times."""
    wall, cpu = [], []
    synchronize(device)
    for _ in range(reps):
        c0, t0 = time.process_time(), time.perf_counter()
        fn()
        synchronize(device)
        wall.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    return wall, cpu


def label(case: dict) -> str:
    """A short name of a case."""
    one_d = case["eq"].endswith("1d")
    size = f"{case['n']}" if one_d else f"{case['n']}²"
    what = "1 step" if case["mode"] == "step" else f"{case['steps']} steps"
    if case["eq"].startswith("fft"):
        return f"FFT floor {'1-D' if one_d else '2-D'} | {size} | {case['batch']} | rfft + irfft"
    name = {"ks1d": "KS 1-D ETDRK4", "burgers1d": "Burgers 1-D ETDRK2", "ns2d": "NS 2-D ETDRK4",
            "heat2d": "heat 2-D exact"}[case["eq"]]
    return f"{name} | {size} | {case['batch']} | {what}"


def summary(row: dict) -> dict:
    """The figures of one case from its per-repetition timings (milliseconds).

    Args:
        row: A result row with ``phisim_rounds_ms``, ``exponax_rounds_ms`` (wall) and ``phisim_cpu_rounds_ms``,
            ``exponax_cpu_rounds_ms`` (CPU), each a list of rounds of repetitions.

    Returns:
        Best wall times, their ratio, the ratio of the best per-round mean CPU times and of the median wall times.
    """
    def best(rounds):
        return min(min(r) for r in rounds)

    def best_mean(rounds):
        return min(sum(r) / len(r) for r in rounds)

    def median(rounds):
        return statistics.median(statistics.median(r) for r in rounds)

    ours, theirs = row["phisim_rounds_ms"], row["exponax_rounds_ms"]
    ours_cpu, theirs_cpu = row["phisim_cpu_rounds_ms"], row["exponax_cpu_rounds_ms"]
    return dict(phisim_best_ms=best(ours), exponax_best_ms=best(theirs), ratio_best=best(ours) / best(theirs),
                phisim_cpu_ms=best_mean(ours_cpu), exponax_cpu_ms=best_mean(theirs_cpu),
                ratio_cpu=best_mean(ours_cpu) / best_mean(theirs_cpu),
                phisim_median_ms=median(ours), exponax_median_ms=median(theirs),
                ratio_median=median(ours) / median(theirs))


def markdown_table(rows: list[dict]) -> str:
    """The Markdown table of result rows (see :func:`summary`)."""
    lines = ["| case | N | batch | work | phisim best ms | exponax best ms | ratio best | ratio CPU | ratio median | "
             "one-step agreement |", "|---|---|---|---|---|---|---|---|---|---|"]
    for row in rows:
        f = summary(row)
        agree = row.get("agreement")
        lines.append(f"| {label(row['case'])} | {f['phisim_best_ms']:.3f} | {f['exponax_best_ms']:.3f} | "
                     f"{f['ratio_best']:.2f} | {f['ratio_cpu']:.2f} | {f['ratio_median']:.2f} | "
                     f"{'' if agree is None else f'{agree:.1e}'} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> list[dict]:
    """Run the benchmark, print the Markdown table, write the JSON results and the table.

    Args:
        argv: Command-line arguments (``None``: ``sys.argv``).

    Returns:
        One row per case.
    """
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--quick", action="store_true", help="smallest sizes only")
    ap.add_argument("--dtype", default="float32", choices=("float32", "float64"))
    ap.add_argument("--only", default=",".join(EQS), help="comma-separated subset of " + ",".join(EQS))
    ap.add_argument("--peer-venv", default=str(HERE / ".venv-jax"))
    ap.add_argument("--out", default=None, help="JSON path (default benchmarks/results/etdrk[_float64].json)")
    ap.add_argument("--device", default="cpu", help="torch device of the phisim side: cpu, cuda or cuda:N (exponax "
                    "then runs on the GPU too)")
    ap.add_argument("--peer-python", default=None, help="the interpreter holding jax and exponax (default: the "
                    "--peer-venv's)")
    ap.add_argument("--from-json", default=None, help="print the table of an earlier results file and exit")
    args = ap.parse_args(argv)
    if args.from_json:
        saved = json.loads(Path(args.from_json).read_text())
        print(markdown_table(saved["rows"]))
        return saved["rows"]
    device = check_device(args.device)
    only = tuple(e.strip() for e in args.only.split(",") if e.strip())
    unknown = sorted(set(only) - set(EQS))
    if unknown:
        raise ParameterError(f"unknown cases {unknown}; known: {', '.join(EQS)}")
    suffix = "" if args.dtype == "float32" else "_" + args.dtype
    suffix += "" if device.type == "cpu" else "_cuda"
    out_path = Path(args.out or HERE / "results" / f"etdrk{suffix}.json")
    torch.set_num_threads(1)
    load_before = os.getloadavg()
    peer = Peer(args.peer_python or str(Path(args.peer_venv) / "bin" / "python"), x64=args.dtype == "float64",
                device=device)
    info = peer.ask({"cmd": "info"})
    cases = make_cases(args.quick, args.dtype, only)
    built = {}
    agreement = {}
    tmp = tempfile.mkdtemp(prefix="etdrk-bench-")
    for i, case in enumerate(cases):
        fn, stepper, u0 = build_phisim(case, device)
        for _ in range(2):
            fn()
        built[i] = fn
        if case["mode"] == "step":
            path = os.path.join(tmp, f"case{i}.npy")
            peer.ask({"cmd": "result", "case": case, "path": path})
            theirs = np.load(path)
            # exponax's vorticity has the opposite sign (its velocity is grad(inverse Laplacian(w)) rotated the
            # other way), so its step of w0 is minus phisim's step of -w0
            ours = (-stepper(-u0) if case["eq"] == "ns2d" else fn()).cpu().numpy()
            agreement[i] = float(np.abs(ours - theirs).max() / max(np.abs(theirs).max(), 1e-30))
        else:
            peer.ask({"cmd": "time", "case": case, "reps": 1})  # compile + warm-up
    ours_rounds = {i: [] for i in range(len(cases))}
    theirs_rounds = {i: [] for i in range(len(cases))}
    ours_cpu = {i: [] for i in range(len(cases))}
    theirs_cpu = {i: [] for i in range(len(cases))}
    t_start = time.time()
    for _ in range(args.rounds):
        for i, case in enumerate(cases):
            reps = reps_for(case)
            wall, cpu = time_phisim(built[i], reps, device)
            ours_rounds[i].append(wall)
            ours_cpu[i].append(cpu)
            answer = peer.ask({"cmd": "time", "case": case, "reps": reps})
            theirs_rounds[i].append(answer["times"])
            theirs_cpu[i].append(answer["cpu"])
    elapsed = time.time() - t_start
    peer.close()
    load_after = os.getloadavg()
    rows = []
    for i, case in enumerate(cases):
        rows.append(dict(case=case, agreement=agreement.get(i),
                         phisim_rounds_ms=[[t * 1e3 for t in r] for r in ours_rounds[i]],
                         exponax_rounds_ms=[[t * 1e3 for t in r] for r in theirs_rounds[i]],
                         phisim_cpu_rounds_ms=[[t * 1e3 for t in r] for r in ours_cpu[i]],
                         exponax_cpu_rounds_ms=[[t * 1e3 for t in r] for r in theirs_cpu[i]]))
        rows[-1].update(summary(rows[-1]))
    lines = [markdown_table(rows)]
    meta = dict(command="python " + " ".join([str(Path(__file__).relative_to(HERE.parent))] + (argv or sys.argv[1:])),
                rounds=args.rounds, dtype=args.dtype, elapsed_s=elapsed, loadavg_before=load_before,
                loadavg_after=load_after, cpu=platform.processor() or platform.machine(), cores=os.cpu_count(),
                torch=torch.__version__, peer=info, device=str(device),
                date=time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime()))
    lines.append(f"\nloadavg before {load_before}, after {load_after}; {elapsed:.0f} s of timed rounds; "
                 f"{args.dtype}; {meta['date']}")
    table = "\n".join(lines)
    print(table)
    out_path.parent.mkdir(parents=True, exist_ok=True)
    out_path.write_text(json.dumps(dict(meta=meta, rows=rows), indent=1))
    out_path.with_name(out_path.stem + "_table.md").write_text(table + "\n")
    return rows


if __name__ == "__main__":
    main()
