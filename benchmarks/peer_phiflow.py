"""PhiFlow 3.4 side of the benchmarks: one case per child process, one JSON line per case.

Runs inside ``benchmarks/.phiflow-venv`` (made by ``benchmarks/setup_phiflow.sh``)::

    PY=benchmarks/.phiflow-venv/bin/python
    $PY benchmarks/peer_phiflow.py --case poisson_cg --size 256^2 --dtype float64
    $PY benchmarks/peer_phiflow.py --suite poisson      # every case, one child process each
    $PY benchmarks/peer_phiflow.py --list

Each case prints ``{case, size, dtype, median_s, repeats, iterations?, patched?, error?, note?}``.
Inputs come from ``benchmarks/inputs.py`` (the same numbers as the phisim side). PhiFlow
is measured on its torch backend, on CPU, with a fixed thread count (``--threads``).

The module level imports only the standard library, so the runner (in phisim's venv) can
import the case table and :func:`drive` without PhiFlow installed.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))
VENV_PYTHON = os.path.join(HERE, ".phiflow-venv", "bin", "python")
PATCHED_PATH = os.path.join(HERE, ".phiflow-venv", "phiml-patched")
#: phiml's sparse-matrix build overflows int32 above this many cells (about 215 x 215).
PATCH_CELLS = 46225

OPERATOR_SIZES = ["64^2", "256^2", "1024^2", "64^3"]
#: (case, sizes, dtypes, builds a sparse matrix)
CASES: dict[str, tuple[list[str], list[str], bool]] = {
    "laplace_dirichlet": (OPERATOR_SIZES, ["float32"], False),
    "laplace_periodic": (OPERATOR_SIZES, ["float32"], False),
    "advect_semi_lagrangian": (OPERATOR_SIZES, ["float32"], False),
    "advect_maccormack": (OPERATOR_SIZES, ["float32"], False),
    "poisson_cg": (["64^2", "128^2", "256^2", "512^2", "64^3"], ["float64", "float32"], True),
    "heat_fourier": (["64^2x128", "1024^2"], ["float32"], False),
    "smoke_step": (["64^2", "128^2", "256^2", "32^3"], ["float32"], True),
    "smoke_step_jit": (["64^2", "128^2", "256^2", "32^3"], ["float32"], True),
    "smoke_backward8": (["64^2", "64^2x16"], ["float32"], True),
    "smoke_check": (["64^2"], ["float64"], True),
}
SUITES = {
    "operators": ["laplace_dirichlet", "laplace_periodic", "advect_semi_lagrangian", "advect_maccormack"],
    "poisson": ["poisson_cg"],
    "heat": ["heat_fourier"],
    "fluid": ["smoke_step", "smoke_step_jit", "smoke_backward8", "smoke_check"],
}


def _cells(size: str) -> int:
    base = size.split("x")[0]
    n, d = base.split("^")
    return int(n) ** int(d)


def needs_patch(case: str, size: str) -> bool:
    """Whether ``case`` at ``size`` needs the int64 sparse-index patch of phiml."""
    return CASES[case][2] and _cells(size) > PATCH_CELLS


def case_list(suite: str) -> list[tuple[str, str, str]]:
    """All ``(case, size, dtype)`` of a suite (``all`` for every suite)."""
    names = [c for s in SUITES.values() for c in s] if suite == "all" else SUITES[suite]
    return [(c, s, d) for c in names for s in CASES[c][0] for d in CASES[c][1]]


def drive(
    case: str,
    size: str,
    dtype: str,
    *,
    python: str = VENV_PYTHON,
    threads: int = 1,
    repeats: int = 5,
    timeout_s: float = 900.0,
    quick: bool = False,
) -> dict:
    """Run one case in a child process of the PhiFlow venv and return its JSON result.

    Never raises: a missing venv, a crash or a timeout comes back as ``{"error": ...}``.
    """
    base = {"case": case, "size": size, "dtype": dtype}
    if not os.path.exists(python):
        return {**base, "error": "not installed"}
    env = dict(os.environ)
    patched = needs_patch(case, size)
    if patched:
        if not os.path.isdir(os.path.join(PATCHED_PATH, "phiml")):
            return {**base, "error": "needs the phiml int64 patch (run benchmarks/setup_phiflow.sh)"}
        env["PYTHONPATH"] = PATCHED_PATH + os.pathsep + env.get("PYTHONPATH", "")
    env["OMP_NUM_THREADS"] = str(threads)
    cmd = [
        python,
        os.path.abspath(__file__),
        "--case",
        case,
        "--size",
        size,
        "--dtype",
        dtype,
        "--threads",
        str(threads),
        "--repeats",
        str(repeats),
    ] + (["--quick"] if quick else [])
    try:
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout_s, env=env)
    except subprocess.TimeoutExpired:
        return {**base, "error": f"timeout after {timeout_s:.0f} s", "patched": patched}
    for line in reversed(proc.stdout.strip().splitlines()):
        if line.startswith("{"):
            return json.loads(line)
    tail = (proc.stderr or proc.stdout).strip().splitlines()[-1:] or ["no output"]
    return {**base, "error": f"child exited {proc.returncode}: {tail[0][:300]}", "patched": patched}


# ----------------------------------------------------------------------------------------------
# Inside the PhiFlow venv
# ----------------------------------------------------------------------------------------------


def _run_case(case: str, size: str, dtype: str, repeats: int, quick: bool) -> dict:
    sys.path.insert(0, HERE)
    import inputs
    import numpy as np
    from phi.torch.flow import (
        Box,
        CenteredGrid,
        Solve,
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
    )
    from timing import time_fn, time_steps

    math.set_global_precision(64 if dtype == "float64" else 32)
    resolution, nb = inputs.parse_size(size)
    dim = len(resolution)
    names = "xyz"[:dim]
    sp = spatial(",".join(names))
    order = "b," + ",".join(names)
    bounds = Box(**{n: r for n, r in zip(names, resolution)})
    result: dict = {}

    def scalar(arr, bc):
        t = math.tensor(np.asarray(arr, dtype=dtype), batch("b"), sp)
        return CenteredGrid(t, bc, bounds)

    def staggered(comps):
        # inputs include the boundary faces; PhiFlow's zero-boundary grid stores inner faces only.
        inner = []
        for i, c in enumerate(comps):
            sl = [slice(None)] * (dim + 1)
            sl[i + 1] = slice(1, -1)
            inner.append(math.tensor(np.asarray(c[tuple(sl)], dtype=dtype), batch("b"), sp))
        values = math.stack(inner, math.dual(vector=",".join(names)))
        return StaggeredGrid(values, 0, bounds)

    slow = _cells(size) * nb >= 1024**2
    reps = 3 if (slow or quick) else repeats

    if case.startswith("laplace"):
        bc = 0 if case == "laplace_dirichlet" else extrapolation.PERIODIC
        u = scalar(inputs.scalar_field(resolution, nb, dtype=dtype), bc)
        result = time_fn(lambda: field.laplace(u), repeats=reps, warmup=2, min_total_s=0.5)
    elif case.startswith("advect"):
        u = scalar(inputs.scalar_field(resolution, nb, dtype=dtype), 0)
        v = staggered(
            inputs.staggered_velocity(
                resolution, nb, amplitude=inputs.ADVECTION["velocity_amplitude"], dtype=dtype
            )
        )
        dt = inputs.ADVECTION["dt"]
        fn = advect.semi_lagrangian if case == "advect_semi_lagrangian" else advect.mac_cormack
        result = time_fn(lambda: fn(u, v, dt), repeats=reps, warmup=2, min_total_s=0.5)
    elif case == "poisson_cg":

        @math.jit_compile_linear
        def lap(x):
            return field.laplace(x)

        rhs = scalar(inputs.poisson_rhs(resolution, nb, dtype=dtype), 0)
        x0 = rhs * 0
        p = inputs.POISSON
        solve = Solve("CG", p["rtol"], p["atol"], x0=x0, max_iterations=p["max_iter"])
        info = {}

        def once():
            with math.SolveTape() as tape:
                x = field.solve_linear(lap, rhs, solve)
            info["iterations"] = int(math.max(tape[solve].iterations))
            return x

        t_first = time.perf_counter()
        try:
            x = once()  # builds and caches the sparse matrix
            result = time_fn(once, repeats=3 if _cells(size) >= 512**2 else reps, warmup=0)
            result["iterations"] = info["iterations"]
            r = rhs.values.numpy(order) - field.laplace(x).values.numpy(order)
            result["true_rel_residual"] = float(np.linalg.norm(r) / np.linalg.norm(rhs.values.numpy(order)))
        except Exception as e:  # NotConverged in float32: report it with the time it took
            result = {
                "error": f"{type(e).__name__}: {str(e).splitlines()[0][:200]}",
                "time_to_error_s": time.perf_counter() - t_first,
            }
            res = getattr(e, "result", None)
            if res is not None:
                result["iterations"] = int(math.max(res.iterations))
        result["note"] = (
            "jit_compile_linear operator (sparse matrix built once, cached; timed solves exclude the build)"
        )
    elif case == "heat_fourier":
        u = scalar(inputs.periodic_scalar_field(resolution, nb, dtype=dtype), extrapolation.PERIODIC)
        h = inputs.HEAT
        result = time_fn(
            lambda: diffuse.fourier(u, h["viscosity"], h["dt"]), repeats=reps, warmup=2, min_total_s=0.5
        )
    elif case.startswith("smoke"):
        s = inputs.SMOKE
        init = inputs.smoke_initial(resolution, nb, dtype=dtype)
        smoke0 = scalar(init["smoke"], extrapolation.ZERO_GRADIENT)
        inflow = scalar(init["inflow"], extrapolation.ZERO_GRADIENT)
        v0 = staggered(init["velocity"])
        p0 = scalar(np.zeros((nb, *resolution)), extrapolation.ZERO_GRADIENT)
        up = math.vec(**{n: (s["buoyancy"] if i == dim - 1 else 0.0) for i, n in enumerate(names)})
        dt = s["dt"]

        def step(smoke, velocity, pressure):
            smoke = advect.mac_cormack(smoke, velocity, dt) + inflow * dt
            buoyancy = resample(smoke * up, to=velocity)
            velocity = advect.semi_lagrangian(velocity, velocity, dt) + buoyancy * dt
            solve = Solve(
                "CG", s["rtol"], s["atol"], x0=pressure, max_iterations=s["max_iter"], rank_deficiency=0
            )
            velocity, pressure = fluid.make_incompressible(velocity, (), solve)
            return smoke, velocity, pressure

        if case == "smoke_check":  # 20 steps, then statistics to compare with phisim's
            st = (smoke0, v0, p0)
            t0 = time.perf_counter()
            for _ in range(20):
                st = step(*st)
            sm = st[0].values.numpy(order)[0]
            vy = st[1].at_centers().values.vector[names[-1]].numpy(order)[0]
            result = {"median_s": time.perf_counter() - t0, "repeats": 1, "stats": inputs.smoke_stats(sm, vy)}
            state = st
        elif case == "smoke_step":
            timing, state = time_steps(lambda st: step(*st), (smoke0, v0, p0), repeats=reps, warmup=2)
            result = timing
            with math.SolveTape() as tape:
                step(*state)
            result["iterations"] = int(math.max(tape[0].iterations))  # pressure CG, one more step
        elif case == "smoke_step_jit":
            jstep = math.jit_compile(step)
            t0 = time.perf_counter()
            state = jstep(smoke0, v0, p0)
            result_first = time.perf_counter() - t0
            timing, state = time_steps(lambda st: jstep(*st), state, repeats=max(reps, 10), warmup=3)
            result = {**timing, "first_call_s": result_first}
        else:  # smoke_backward8

            def loss(velocity):
                st = (smoke0, velocity, p0)
                for _ in range(8):
                    st = step(*st)
                return math.sum(field.l2_loss(st[0]), "b")

            grad = field.gradient(loss, wrt="velocity", get_output=False)
            result = time_fn(lambda: grad(v0), repeats=3, warmup=1)
        smoke_vals = (state[0] if case != "smoke_backward8" else smoke0).values.numpy(order)
        if not np.all(np.isfinite(smoke_vals)):
            result["error"] = "non-finite state"
    else:
        raise ValueError(f"unknown case {case}")
    if os.environ.get("PEER_KEEP_TIMES") != "1":
        result.pop("times_s", None)
    return result


def main(argv: list[str] | None = None) -> int:
    """Command line: one case (``--case --size --dtype``), a whole suite (child per case), or ``--list``."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--case")
    ap.add_argument("--size")
    ap.add_argument("--dtype", default="float32")
    ap.add_argument("--suite", choices=list(SUITES) + ["all"])
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--list", action="store_true")
    a = ap.parse_args(argv)
    if a.list:
        for c in case_list(a.suite or "all"):
            print(*c)
        return 0
    if a.suite:
        for c, s, d in case_list(a.suite):
            print(
                json.dumps(
                    drive(c, s, d, python=sys.executable, threads=a.threads, repeats=a.repeats, quick=a.quick)
                ),
                flush=True,
            )
        return 0
    import warnings

    warnings.filterwarnings("ignore")
    sys.path.insert(0, HERE)
    from timing import set_threads

    set_threads(a.threads)
    import phi
    import phiml

    base = {
        "case": a.case,
        "size": a.size,
        "dtype": a.dtype,
        "threads": a.threads,
        "phiflow": phi.__version__,
        "phiml": phiml.__version__,
        "backend": "torch-cpu",
    }
    patched = "phiml-patched" in phiml.__file__
    if patched:
        base["patched"] = True
    t0 = time.perf_counter()
    try:
        res = _run_case(a.case, a.size, a.dtype, a.repeats, a.quick)
    except Exception as e:
        res = {"error": f"{type(e).__name__}: {str(e).splitlines()[0][:300] if str(e) else ''}"}
    res["wall_s"] = round(time.perf_counter() - t0, 2)
    print(json.dumps({**base, **res}), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
