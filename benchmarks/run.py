"""Benchmark runner: phisim against PhiFlow 3.4 and raw floors, written to ``docs/BENCHMARKS.md``.

Usage::

    python benchmarks/run.py --suite operators|poisson|heat|fluid|fft|all [--quick] [--reuse-peer]

* phisim cases (``benchmarks/cases_phisim.py``) are timed in this process: median of repeats after
  warm-up (``benchmarks/timing.py``; CUDA is synchronised around each call).
* PhiFlow cases (``benchmarks/peer_phiflow.py``) run one per child process in
  ``benchmarks/.phiflow-venv`` (``bash benchmarks/setup_phiflow.sh``); without that venv the peer
  columns say "not installed". ``--reuse-peer`` takes them from ``benchmarks/results/phiflow_<suite>.json``.
* Floors: scipy.sparse.linalg.spsolve and DST (scipy.fft, planned pyfftw) solves for Poisson;
  FFT round trips (pyfftw 1/2 threads, torch.fft 1/2 threads, scipy.fft, numpy.fft) for heat.
  The ``fft`` suite is that engine comparison on its own (``benchmarks/results/fft_engines.json``).
* Results go to ``benchmarks/results/<side>_<suite>.json``; ``docs/BENCHMARKS.md`` is rebuilt from
  every results file present, so running one suite keeps the other suites' tables.
  ``--quick`` (smallest size of each case, few repeats) writes to ``--out`` (default a temporary
  directory) and leaves the committed results and docs alone.
"""

from __future__ import annotations

import argparse
import datetime as _dt
import json
import os
import platform
import sys
import tempfile
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
sys.path.insert(0, HERE)
sys.path.insert(0, ROOT)

import inputs  # noqa: E402
import peer_phiflow  # noqa: E402  (standard library only at import time)
from timing import set_threads, time_fn  # noqa: E402

RESULTS = os.path.join(HERE, "results")
DOC = os.path.join(ROOT, "docs", "BENCHMARKS.md")
SUITES = ["operators", "poisson", "heat", "fluid", "fft"]

#: per suite: (phisim case, peer case, sizes, dtypes)
PAIRS = {
    "operators": [(c, c, peer_phiflow.OPERATOR_SIZES, ["float32"]) for c in peer_phiflow.SUITES["operators"]],
    "poisson": [
        ("poisson_direct", "poisson_cg", peer_phiflow.CASES["poisson_cg"][0], ["float64", "float32"]),
        ("poisson_cg", "poisson_cg", peer_phiflow.CASES["poisson_cg"][0], ["float64", "float32"]),
    ],
    "heat": [("heat_fourier", "heat_fourier", peer_phiflow.CASES["heat_fourier"][0], ["float32"])],
    "fluid": [
        ("smoke_step", "smoke_step", peer_phiflow.CASES["smoke_step"][0], ["float32"]),
        ("smoke_step", "smoke_step_jit", peer_phiflow.CASES["smoke_step_jit"][0], ["float32"]),
        ("smoke_step_cg", "smoke_step", peer_phiflow.CASES["smoke_step"][0], ["float32"]),
        ("smoke_step_cg", "smoke_step_jit", peer_phiflow.CASES["smoke_step_jit"][0], ["float32"]),
        ("smoke_backward8", "smoke_backward8", peer_phiflow.CASES["smoke_backward8"][0], ["float32"]),
        ("smoke_check", "smoke_check", ["64^2"], ["float64"]),
    ],
    "fft": [],
}
FFT_SIZES = ["64^2", "256^2", "1024^2", "64^2x128"]


# ---------------------------------------------------------------------------------------------
# floors
# ---------------------------------------------------------------------------------------------


def _dirichlet_eigenvalues(resolution, dtype):
    """Eigenvalues of the face-Dirichlet 5/7-point Laplacian (dx = 1) in the DST-II basis."""
    lam = np.zeros(resolution)
    for i, n in enumerate(resolution):
        k = np.arange(1, n + 1)
        shape = [1] * len(resolution)
        shape[i] = n
        lam = lam + (-4.0 * np.sin(np.pi * k / (2 * n)) ** 2).reshape(shape)
    return lam.astype(dtype)


def _dirichlet_matrix(resolution):
    """The sparse face-Dirichlet Laplacian (ghost = -inside) that the DST-II diagonalises."""
    import scipy.sparse as sp

    def d2(n):
        m = sp.diags([np.ones(n - 1), -2.0 * np.ones(n), np.ones(n - 1)], [-1, 0, 1], format="lil")
        m[0, 0] = m[n - 1, n - 1] = -3.0
        return m.tocsr()

    a = None
    for i in range(len(resolution)):
        term = sp.identity(1, format="csr")
        for j, m in enumerate(resolution):
            term = sp.kron(term, d2(m) if j == i else sp.identity(m, format="csr"), format="csr")
        a = term if a is None else a + term
    return a.tocsc()


def poisson_floors(size: str, dtype: str, threads: int, repeats: int) -> list[dict]:
    """spsolve (factor + solve) and DST solves (scipy.fft, planned pyfftw) for one size."""
    import scipy.fft as sfft
    import scipy.sparse.linalg as spla

    res, nb = inputs.parse_size(size)
    f = inputs.poisson_rhs(res, nb, dtype=dtype)
    axes = tuple(range(1, len(res) + 1))
    lam = _dirichlet_eigenvalues(res, dtype)
    out = []
    base = {"size": size, "dtype": dtype}

    def scipy_dst():
        return sfft.idstn(
            sfft.dstn(f, type=2, axes=axes, workers=threads) / lam, type=2, axes=axes, workers=threads
        )

    r = time_fn(scipy_dst, repeats=repeats, warmup=2, min_total_s=0.3)
    out.append({**base, "floor": "scipy.fft dstn/idstn", "threads": threads, **_strip(r)})
    try:
        import pyfftw

        for t in sorted({1, threads}):
            a = pyfftw.empty_aligned(f.shape, dtype=dtype)
            b = pyfftw.empty_aligned(f.shape, dtype=dtype)
            c = pyfftw.empty_aligned(f.shape, dtype=dtype)
            fwd = pyfftw.FFTW(
                a, b, axes=axes, direction=["FFTW_RODFT10"] * len(axes), flags=("FFTW_MEASURE",), threads=t
            )
            inv = pyfftw.FFTW(
                b, c, axes=axes, direction=["FFTW_RODFT01"] * len(axes), flags=("FFTW_MEASURE",), threads=t
            )
            scale = (lam * np.prod([2 * n for n in res])).astype(dtype)
            a[...] = f

            def planned(fwd=fwd, inv=inv, b=b, c=c, scale=scale):
                fwd.execute()
                np.divide(b, scale, out=b)
                inv.execute()
                return c

            r = time_fn(planned, repeats=repeats, warmup=2, min_total_s=0.3)
            x = planned()
            ref = scipy_dst()
            ok = np.allclose(x, ref, rtol=1e-3 if dtype == "float32" else 1e-9, atol=1e-6 * np.abs(ref).max())
            out.append(
                {
                    **base,
                    "floor": f"pyfftw planned RODFT10/01 ({t} thr)",
                    "threads": t,
                    **_strip(r),
                    **({} if ok else {"error": "mismatch against scipy"}),
                }
            )
    except ImportError:
        out.append({**base, "floor": "pyfftw planned", "error": "pyfftw not installed"})
    if dtype == "float64" and nb == 1 and len(res) == 2:  # 3-D: SuperLU fill-in takes minutes and > 6 GB
        a_mat = _dirichlet_matrix(res)
        rhs = f.reshape(-1)
        reps = 1 if np.prod(res) >= 512**2 else 3
        r = time_fn(lambda: spla.spsolve(a_mat, rhs), repeats=reps, warmup=0 if reps == 1 else 1)
        out.append({**base, "floor": "scipy spsolve (factor+solve, SuperLU)", "threads": 1, **_strip(r)})
    return out


def fft_round_trips(size: str, dtype: str, threads_list=(1, 2), repeats: int = 7) -> list[dict]:
    """One spectral diffusion step as a raw round trip ``irfftn(rfftn(u) * decay)`` per FFT engine."""
    import scipy.fft as sfft
    import torch

    res, nb = inputs.parse_size(size)
    u = inputs.periodic_scalar_field(res, nb, dtype=dtype)
    axes = tuple(range(1, len(res) + 1))
    cdtype = np.complex64 if dtype == "float32" else np.complex128
    k2 = np.zeros(res[:-1] + (res[-1] // 2 + 1,))
    for i, n in enumerate(res):
        k = np.fft.rfftfreq(n) if i == len(res) - 1 else np.fft.fftfreq(n)
        shape = [1] * len(res)
        shape[i] = k.size
        k2 = k2 + (2 * np.pi * k.reshape(shape)) ** 2
    decay = np.exp(-inputs.HEAT["viscosity"] * inputs.HEAT["dt"] * k2).astype(dtype)
    base = {"size": size, "dtype": dtype}
    out = []
    ref = np.fft.irfftn(np.fft.rfftn(u, axes=axes) * decay, s=res, axes=axes)

    def add(engine, t, fn):
        r = time_fn(fn, repeats=repeats, warmup=2, min_total_s=0.3)
        y = np.asarray(fn())
        ok = np.allclose(y, ref, rtol=0, atol=(1e-4 if dtype == "float32" else 1e-10) * np.abs(ref).max())
        out.append(
            {**base, "engine": engine, "threads": t, **_strip(r), **({} if ok else {"error": "mismatch"})}
        )

    add("numpy.fft", 1, lambda: np.fft.irfftn(np.fft.rfftn(u, axes=axes) * decay, s=res, axes=axes))
    for t in threads_list:
        add(
            "scipy.fft",
            t,
            lambda t=t: sfft.irfftn(sfft.rfftn(u, axes=axes, workers=t) * decay, s=res, axes=axes, workers=t),
        )
    ut = torch.from_numpy(u)
    dt_ = torch.from_numpy(decay)
    old = torch.get_num_threads()
    for t in threads_list:
        torch.set_num_threads(t)
        add("torch.fft", t, lambda: torch.fft.irfftn(torch.fft.rfftn(ut, dim=axes) * dt_, s=res, dim=axes))
    torch.set_num_threads(old)
    try:
        import pyfftw

        for t in threads_list:
            a = pyfftw.empty_aligned(u.shape, dtype=dtype)
            spec = pyfftw.empty_aligned(u.shape[:-1] + (res[-1] // 2 + 1,), dtype=cdtype)
            b = pyfftw.empty_aligned(u.shape, dtype=dtype)
            fwd = pyfftw.FFTW(a, spec, axes=axes, flags=("FFTW_MEASURE",), threads=t)
            inv = pyfftw.FFTW(
                spec, b, axes=axes, direction="FFTW_BACKWARD", flags=("FFTW_MEASURE",), threads=t
            )
            scaled = (decay / np.prod(res)).astype(dtype)
            a[...] = u

            def planned(fwd=fwd, inv=inv, spec=spec, b=b, scaled=scaled):
                fwd.execute()
                np.multiply(spec, scaled, out=spec)
                inv.execute()
                return b

            add("pyfftw planned", t, planned)
    except ImportError:
        out.append({**base, "engine": "pyfftw planned", "error": "pyfftw not installed"})
    try:
        from phisim.spectral import fft as pfft

        for eng in pfft.available_engines():
            for t in threads_list:

                def via_phisim(eng=eng, t=t):
                    with pfft.fft_settings(threads=t):
                        spec = pfft.rfftn(ut, axes=axes, engine=eng)
                        return pfft.irfftn(spec * dt_, s=res, axes=axes, engine=eng).numpy()

                torch.set_num_threads(t)
                add(f"phisim.spectral.fft engine={eng}", t, via_phisim)
        torch.set_num_threads(old)
    except Exception as e:  # the phisim.spectral.fft API is optional here
        out.append({**base, "engine": "phisim.spectral.fft", "error": f"n/a: {type(e).__name__}: {str(e)[:120]}"})
    return out


def _strip(r: dict) -> dict:
    return {k: v for k, v in r.items() if k != "times_s"}


# ---------------------------------------------------------------------------------------------
# running suites
# ---------------------------------------------------------------------------------------------


def _meta(args, suite: str) -> dict:
    import torch

    return {
        "suite": suite,
        "command": " ".join(["python benchmarks/run.py"] + sys.argv[1:]),
        "date": _dt.datetime.now().isoformat(timespec="seconds"),
        "machine": f"{platform.machine()} {os.cpu_count()} cores ({_cpu_name()}), {platform.system()}",
        "threads": args.threads,
        "torch": torch.__version__,
        "numpy": np.__version__,
        "quick": args.quick,
    }


def _cpu_name() -> str:
    try:
        with open("/proc/cpuinfo") as fh:
            for line in fh:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown CPU"


def _merge_best(path: str, meta: dict, results: list[dict]) -> tuple[dict, list[dict]]:
    """Keep, per (case/floor/engine, size, dtype, threads), the lower median of this run and the saved file.

    Used for the PhiFlow side (code that does not change between runs) because the benchmark
    machine is shared: a run's median can only be inflated by other load. phisim and the floors are
    always timed together in one run, so the goals against floors compare figures of the same run.
    """
    old = _load(path)
    if not old:
        return {**meta, "runs": 1}, results

    def key(r):
        return (r.get("case"), r.get("floor"), r.get("engine"), r["size"], r["dtype"], r.get("threads"))

    best = {key(r): r for r in old["results"]}
    for r in results:
        k = key(r)
        prev = best.get(k)
        if prev is None or "median_s" not in prev or ("median_s" in r and r["median_s"] < prev["median_s"]):
            best[k] = {**r, "runs": (prev or {}).get("runs", 1) + (1 if prev else 0)}
        else:
            best[k] = {**prev, "runs": prev.get("runs", 1) + 1}
    order = [key(r) for r in results] + [k for k in best if k not in {key(r) for r in results}]
    runs = old["meta"].get("runs", 1) + 1
    commands = sorted(set(old["meta"].get("commands", [old["meta"]["command"]]) + [meta["command"]]))
    return {
        **meta,
        "runs": runs,
        "commands": commands,
        "first_date": old["meta"].get("first_date", old["meta"]["date"]),
    }, [best[k] for k in order]


def _save(path: str, meta: dict, results: list[dict], merge: bool = False) -> None:
    if merge:
        meta, results = _merge_best(path, meta, results)
    os.makedirs(os.path.dirname(path), exist_ok=True)
    tmp = path + ".tmp"
    with open(tmp, "w") as fh:
        json.dump({"meta": meta, "results": results}, fh, indent=1)
    os.replace(tmp, path)


def _load(path: str) -> dict | None:
    if not os.path.exists(path):
        return None
    with open(path) as fh:
        return json.load(fh)


def _log(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def _fmt_row(r: dict) -> str:
    if "error" in r:
        return r["error"]
    return f"{r['median_s'] * 1e3:.3f} ms" + (f", {r['iterations']} it" if "iterations" in r else "")


def run_suite(suite: str, args) -> None:
    """Run one suite's phisim, peer and floor cases and save the results JSON files."""
    from cases_phisim import run_case

    out = args.out
    meta = _meta(args, suite)
    reps = 2 if args.quick else args.repeats
    pick = (lambda xs: xs[:1]) if args.quick else (lambda xs: xs)
    pairs = PAIRS[suite]
    if pairs and not args.peer_only:
        ph = []
        seen = set()
        for pc, _, sizes, dtypes in pairs:
            for s in pick(sizes):
                for d in pick(dtypes):
                    if (pc, s, d) in seen:
                        continue
                    seen.add((pc, s, d))
                    r = run_case(pc, s, d, repeats=reps, device=args.device)
                    _log(f"[phisim] {pc} {s} {d}: {_fmt_row(r)}")
                    ph.append(r)
        _save(os.path.join(out, f"phisim_{suite}.json"), meta, ph)
    if pairs and not args.reuse_peer and not args.no_peer:
        pr = []
        seen = set()
        for _, qc, sizes, dtypes in pairs:
            for s in pick(sizes):
                for d in pick(dtypes):
                    if (qc, s, d) in seen or d not in peer_phiflow.CASES[qc][1]:
                        continue
                    seen.add((qc, s, d))
                    r = peer_phiflow.drive(qc, s, d, threads=args.threads, repeats=reps, quick=args.quick)
                    _log(f"[phiflow] {qc} {s} {d}: {_fmt_row(r)}")
                    pr.append(r)
        _save(os.path.join(out, f"phiflow_{suite}.json"), meta, pr, merge=not args.fresh)
    if suite in ("poisson", "heat", "fft") and not args.peer_only:
        fl = []
        if suite == "poisson":
            for s in pick(peer_phiflow.CASES["poisson_cg"][0]):
                for d in pick(["float64", "float32"]):
                    rows = poisson_floors(s, d, args.threads, reps if args.quick else 7)
                    for r in rows:
                        _log(f"[floor] {r['floor']} {s} {d}: {_fmt_row(r)}")
                    fl += rows
        else:
            sizes = peer_phiflow.CASES["heat_fourier"][0] if suite == "heat" else FFT_SIZES
            for s in pick(sizes):
                for d in ["float32"] if suite == "heat" or args.quick else ["float32", "float64"]:
                    rows = fft_round_trips(s, d, repeats=reps if args.quick else 7)
                    for r in rows:
                        _log(f"[floor] {r['engine']} {s} {d} thr={r.get('threads')}: {_fmt_row(r)}")
                    fl += rows
        name = "fft_engines.json" if suite == "fft" else f"floors_{suite}.json"
        set_threads(args.threads)
        _save(os.path.join(out, name), meta, fl)  # floors: same run as phisim, never merged


# ---------------------------------------------------------------------------------------------
# the document
# ---------------------------------------------------------------------------------------------


def _ms(r: dict | None) -> str:
    if r is None:
        return "not run"
    if "error" in r:
        e = r["error"]
        if e.startswith("n/a"):
            return "n/a"
        if e == "not installed":
            return "not installed"
        return "error"
    v = r["median_s"] * 1e3
    return f"{v:.3g} ms" if v < 1000 else f"{v / 1e3:.3g} s"


def _index(data: dict | None, key: str = "case") -> dict:
    if not data:
        return {}
    return {(r.get(key), r["size"], r["dtype"]): r for r in data["results"]}


def _ratio(peer: dict | None, ours: dict | None) -> float | None:
    if (
        not peer
        or not ours
        or "median_s" not in peer
        or "median_s" not in ours
        or "error" in ours
        or "error" in peer
    ):
        return None
    return peer["median_s"] / ours["median_s"]


def _short_error(e: str) -> str:
    """A table-sized version of an error message."""
    e = e.replace("['", "").replace("']", "").replace("|", "/")
    if "precision_floor" in e:
        tail = e.split("residual", 1)[-1].split(". ", 1)[0]
        return "SolveError: float32 precision floor, residual" + tail
    if "did not converge" in e and "Max residual" in e:
        return (
            "NotConverged within 20000 iterations, max residual " + e.rsplit("Max residual:", 1)[-1].strip()
        )
    return e[:120]


def _notes(ours: dict | None, peer: dict | None) -> str:
    n = []
    if peer:
        if peer.get("patched"):
            n.append("PhiFlow patched (int64 index)")
        if "error" in peer and peer["error"] != "not installed":
            n.append(
                f"PhiFlow: {_short_error(peer['error'])}"
                + (f" after {peer['time_to_error_s']:.3g} s" if "time_to_error_s" in peer else "")
            )
        if "true_rel_residual" in peer:
            n.append(f"PhiFlow true rel. residual {peer['true_rel_residual']:.2g}")
    if ours and peer and "stats" in ours and "stats" in peer:
        n.append(
            "after 20 steps (phisim / PhiFlow): "
            + ", ".join(f"{k} {ours['stats'][k]:.4g} / {peer['stats'][k]:.4g}" for k in ours["stats"])
        )
    if ours and "error" in ours and not ours["error"].startswith("n/a"):
        n.append(f"phisim: {_short_error(ours['error'])}")
    if ours and ours.get("error", "").startswith("n/a"):
        n.append(ours["error"][4:][:100])
    return "; ".join(n)


def _suite_table(suite: str, base: str) -> list[str]:
    ph = _load(os.path.join(base, f"phisim_{suite}.json"))
    pf = _load(os.path.join(base, f"phiflow_{suite}.json"))
    phi_i, pf_i = _index(ph), _index(pf)
    peer_missing = not os.path.exists(peer_phiflow.VENV_PYTHON) and pf is None
    lines = [
        "| phisim case | PhiFlow case | size | dtype | phisim | PhiFlow | ratio PhiFlow/phisim "
        "| iterations (phisim / PhiFlow) | notes |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for pc, qc, sizes, dtypes in PAIRS[suite]:
        for s in sizes:
            for d in dtypes:
                ours = phi_i.get((pc, s, d))
                peer = pf_i.get((qc, s, d))
                if ours is None and peer is None:
                    continue
                ratio = _ratio(peer, ours)
                its = " / ".join(str(x.get("iterations", "")) if x else "" for x in (ours, peer))
                its = "" if its.strip(" /") == "" else its
                pstr = "not installed" if (peer is None and peer_missing) else _ms(peer)
                lines.append(
                    f"| {pc} | {qc} | {s} | {d} | {_ms(ours)} | {pstr} | "
                    f"{'' if ratio is None else f'{ratio:.2f}x'} | {its} | {_notes(ours, peer)} |"
                )
    meta = [x["meta"] for x in (ph, pf) if x]
    cmds = sorted({m["command"] for m in meta})
    out = lines + [""]
    for m in meta:
        side = "phisim" if m is (ph or {}).get("meta") else "PhiFlow"
        cmd = ", ".join(f"`{c}`" for c in m.get("commands", [m["command"]]))
        runs = f"lowest median of {m['runs']} runs, latest " if m.get("runs", 1) > 1 else ""
        out.append(
            f"- {side} side: {cmd} ({runs}{m['date']}, {m['machine']}, {m['threads']} thread(s), "
            f"torch {m['torch']})"
        )
    return out if cmds else lines


def _floor_table(name: str, base: str, key: str) -> list[str]:
    data = _load(os.path.join(base, name))
    if not data:
        return []
    lines = [f"| {key} | size | dtype | threads | median |", "|---|---|---|---|---|"]
    for r in data["results"]:
        lines.append(f"| {r.get(key)} | {r['size']} | {r['dtype']} | {r.get('threads', '')} | {_ms(r)} |")
    m = data["meta"]
    cmd = ", ".join(f"`{c}`" for c in m.get("commands", [m["command"]]))
    runs = f"lowest median of {m['runs']} runs, latest " if m.get("runs", 1) > 1 else ""
    lines += ["", f"- made by {cmd} ({runs}{m['date']}, {m['machine']})"]
    return lines


def _fastest(
    data: dict | None,
    size: str,
    dtype: str,
    key: str,
    exclude: str = "phisim",
    max_threads: int | None = None,
) -> dict | None:
    """The fastest floor/engine row for a size and dtype (optionally using at most ``max_threads``)."""
    if not data:
        return None
    c = [
        r
        for r in data["results"]
        if r["size"] == size
        and r["dtype"] == dtype
        and "median_s" in r
        and "error" not in r
        and not str(r.get(key, "")).startswith(exclude)
        and (max_threads is None or r.get("threads", 1) <= max_threads)
    ]
    return min(c, key=lambda r: r["median_s"]) if c else None


def _fft_decision(base: str) -> list[str]:
    data = _load(os.path.join(base, "fft_engines.json"))
    if not data:
        return []
    lines = [
        "| size | dtype | numpy.fft | scipy.fft 1 thr | scipy.fft 2 thr | torch.fft 1 thr | torch.fft 2 thr "
        "| "
        "pyfftw 1 thr | pyfftw 2 thr | phisim.spectral.fft (pyfftw, 1 thr) | fastest |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    idx = {(r["size"], r["dtype"], r.get("engine"), r.get("threads")): r for r in data["results"]}
    combos = sorted(
        {(r["size"], r["dtype"]) for r in data["results"]},
        key=lambda x: (FFT_SIZES.index(x[0]) if x[0] in FFT_SIZES else 9, x[1]),
    )
    for s, d in combos:
        cells = [
            _ms(idx.get((s, d, e, t)))
            for e, t in [
                ("numpy.fft", 1),
                ("scipy.fft", 1),
                ("scipy.fft", 2),
                ("torch.fft", 1),
                ("torch.fft", 2),
                ("pyfftw planned", 1),
                ("pyfftw planned", 2),
                ("phisim.spectral.fft engine=pyfftw", 1),
            ]
        ]
        f = _fastest(data, s, d, "engine")
        lines.append(
            f"| {s} | {d} | " + " | ".join(cells) + f" | {f['engine']} ({f['threads']} thr) |" if f else " |"
        )
    m = data["meta"]
    cmd = ", ".join(f"`{c}`" for c in m.get("commands", [m["command"]]))
    runs = f"lowest median of {m['runs']} runs, latest " if m.get("runs", 1) > 1 else ""
    lines += [
        "",
        f"- made by {cmd} ({runs}{m['date']}, {m['machine']}); "
        "one step = rfftn, multiply by the precomputed decay, irfftn; inputs from `benchmarks/inputs.py`.",
        "- `phisim.spectral.fft` rows call `phisim.spectral.fft.rfftn/irfftn` (torch tensors in and out, autograd "
        "wrappers, plan cache) with the same multiply; the gap to the raw engine is the wrapper's cost.",
        "",
    ]
    # the decision: which engine wins at one thread, and whether a second FFTW thread pays off
    wins: dict = {}
    gains = []
    overheads = []
    for s_, d in combos:
        f = _fastest(data, s_, d, "engine", max_threads=1)
        if f:
            wins[f["engine"]] = wins.get(f["engine"], 0) + 1
        one, two = idx.get((s_, d, "pyfftw planned", 1)), idx.get((s_, d, "pyfftw planned", 2))
        if one and two and "median_s" in one and "median_s" in two:
            gains.append((s_, d, one["median_s"] / two["median_s"]))
        ph = idx.get((s_, d, "phisim.spectral.fft engine=pyfftw", 1))
        if one and ph and "median_s" in ph and "median_s" in one:
            overheads.append((s_, d, ph["median_s"] / one["median_s"]))
    if wins:
        best = max(wins, key=wins.get)
        lines.append(
            f"**Decision.** With one thread, {best} is fastest in {wins[best]} of {sum(wins.values())} "
            f"size/dtype cases ({', '.join(f'{k}: {v}' for k, v in sorted(wins.items()))})."
        )
        if gains:
            g = ", ".join(f"{s_} {d} {x:.2f}x" for s_, d, x in gains)
            lines.append(
                f"A second FFTW thread speeds the planned round trip up by: {g} (1 thread / 2 threads); "
                "it pays off only on large grids and only while the other core is idle, and torch's "
                "two-thread pool stalls badly when it is not. Default for phisim on CPU: "
                f"**{best.split()[0]}, 1 thread** (more threads only by explicit setting)."
            )
        if overheads:
            o = ", ".join(f"{s_} {d} {x:.2f}x" for s_, d, x in overheads)
            lines.append(f"phisim.spectral.fft (pyfftw engine) relative to the raw planned pyfftw round trip: {o}.")
    return lines


def _goals(base: str) -> list[str]:
    """Evaluate the project's speed goals against the saved results."""
    L = ["| goal | measured | met? |", "|---|---|---|"]
    threads = max(
        [
            (_load(os.path.join(base, f"phisim_{s}.json")) or {}).get("meta", {}).get("threads", 1)
            for s in SUITES
        ]
    )

    def get(side, suite, case, size, dtype="float32"):
        return _index(_load(os.path.join(base, f"{side}_{suite}.json"))).get((case, size, dtype))

    def row(goal, value, ok):
        L.append(f"| {goal} | {value} | {'-' if ok is None else ('yes' if ok else 'no')} |")

    for c in peer_phiflow.SUITES["operators"]:
        r = _ratio(get("phiflow", "operators", c, "256^2"), get("phisim", "operators", c, "256^2"))
        row(
            f"{c} >= 3x faster than PhiFlow at 256^2 (CPU)",
            "n/a" if r is None else f"{r:.2f}x",
            None if r is None else r >= 3,
        )
    floors = _load(os.path.join(base, "floors_poisson.json"))
    for s in peer_phiflow.CASES["poisson_cg"][0]:
        ours = get("phisim", "poisson", "poisson_direct", s, "float64")
        f = _fastest(floors, s, "float64", "floor", exclude="scipy spsolve", max_threads=threads)
        r = (
            None
            if not ours or "median_s" not in ours or "error" in ours or not f
            else ours["median_s"] / f["median_s"]
        )
        row(
            f"direct Poisson within 2x of the raw transform at {s} (float64)",
            "n/a" if r is None else f"{r:.2f}x of {f['floor']}",
            None if r is None else r <= 2,
        )
    heat = _load(os.path.join(base, "floors_heat.json"))
    for s in peer_phiflow.CASES["heat_fourier"][0]:
        ours = get("phisim", "heat", "heat_fourier", s)
        f = _fastest(heat, s, "float32", "engine", max_threads=threads)
        r = (
            None
            if not ours or "median_s" not in ours or "error" in ours or not f
            else ours["median_s"] / f["median_s"]
        )
        row(
            f"heat within 1.5x of the fastest raw FFT round trip at {s}",
            "n/a" if r is None else f"{r:.2f}x of {f['engine']} ({f['threads']} thr)",
            None if r is None else r <= 1.5,
        )
    for label, qc, size, target in [
        ("smoke step >= 10x faster than PhiFlow at 128^2", "smoke_step", "128^2", 10),
        ("smoke step >= 3x faster than PhiFlow jit at 64^2", "smoke_step_jit", "64^2", 3),
    ]:
        r = _ratio(get("phiflow", "fluid", qc, size), get("phisim", "fluid", "smoke_step", size))
        row(label, "n/a" if r is None else f"{r:.2f}x", None if r is None else r >= target)
    for size in peer_phiflow.CASES["smoke_backward8"][0]:
        r = _ratio(
            get("phiflow", "fluid", "smoke_backward8", size), get("phisim", "fluid", "smoke_backward8", size)
        )
        row(
            f"8-step forward+backward >= 10x faster than PhiFlow at {size}",
            "n/a" if r is None else f"{r:.2f}x",
            None if r is None else r >= 10,
        )
    L += ["", f"Floors in these goals use at most {threads} thread(s), like the phisim side."]
    return L


INTRO = """# Benchmarks

Speed of phisim against its main peer, PhiFlow 3.4.0 (phiml 1.16.1, torch backend), and against raw
floors (scipy, FFT engines). All figures are **medians** of repeated calls after warm-up, measured
in the same run on the same inputs (`benchmarks/inputs.py`, generated from a seed), and compared
as ratios (ratio = PhiFlow time / phisim time; above 1 means phisim is faster).

**Machine:** {machine}. The machine's 2 cores were shared with other work while these were
taken, so single figures carry noise of tens of per cent; ratios are the meaningful part.
**Threads:** {threads} intra-op thread(s) for both sides (`torch.set_num_threads`, `OMP_NUM_THREADS`).
One thread per side is the fair setting on this shared 2-core machine: with two threads a process
stalls whenever the other core is busy (a 64^2 torch.fft round trip went from 0.025 ms with one
thread to ~200 ms with two while other work ran). FFT engines are shown with 1 and 2 threads.
PhiFlow figures are the lowest median over the runs made (its code does not change between runs;
other load only inflates a median); phisim and floor figures come from one run, the latest.

How PhiFlow is measured (see `benchmarks/peer_phiflow.py`):
- one case per child process of `benchmarks/.phiflow-venv` (`bash benchmarks/setup_phiflow.sh`);
- Poisson: its recommended path, the Laplacian decorated with `math.jit_compile_linear` (the sparse
  matrix is built once and cached; timed solves exclude the build), `Solve('CG', 1e-5, 0)`;
  float64 is the primary comparison, float32 beside it;
- grids above ~215x215 cells need a one-line int64 patch in phiml's sparse-matrix compression
  (applied to a separate copy of phiml, used only by those cases): marked "patched";
- zero Dirichlet differs in the two codes: PhiFlow's "ZERO extrapolation" puts 0 in the ghost cell,
  phisim puts the value on the face (ghost = -inside); the stencils cost the same, the CG
  iteration counts differ slightly;
- smoke step: `advect.mac_cormack` for the smoke, `advect.semi_lagrangian` for the velocity,
  buoyancy, `fluid.make_incompressible` with the maintainers' closed-box workaround
  `Solve('CG', 1e-3, 1e-3, x0=previous pressure, rank_deficiency=0)`; uncompiled and under
  `math.jit_compile` (its fastest mode; compile time excluded, reported in the JSON);
- 8-step forward+backward: `field.gradient` of `sum(l2_loss(smoke))` w.r.t. the initial velocity.

phisim's side of the smoke step composes `advection.maccormack`, `advection.semi_lagrangian`,
`fluid.buoyancy` and `fluid.make_incompressible` in the same order. `smoke_step` uses phisim's
default projection (the direct spectral pressure solve of an obstacle-free box, exact);
`smoke_step_cg` forces masked CG (spectral preconditioner) with PhiFlow's tolerances and warm start.

Caveats when reading the tables:
- The pressure solves differ by design: phisim's default projection in an obstacle-free box is the
  direct spectral solve (exact), PhiFlow's is CG to rtol/atol 1e-3. `smoke_step_cg` forces phisim's
  masked CG; its spectral preconditioner is exact for a box, so it needs one iteration, and the row
  measures the CG machinery's overhead rather than a comparable iteration count.
- The `smoke_check` row runs 20 steps (float64) in both codes from the same state and lists summary
  statistics of the result: they agree to about three digits, so both sides do the same work.
- float32 Poisson to rtol 1e-5 is below float32's precision from 128^2 up: PhiFlow's torch backend
  runs to the iteration limit (20,000) and raises NotConverged; phisim's CG (float64-refined
  residuals) stops early with a "precision floor" SolveError. Both are listed as errors with the
  time they took; float64 is the comparison that counts.

Regenerate: `bash benchmarks/setup_phiflow.sh` once, then `python benchmarks/run.py --suite all`
(`--reuse-peer` re-times only phisim and takes PhiFlow's figures from
`benchmarks/results/phiflow_<suite>.json`).
"""


#: Sections written by other scripts (between these markers); a rebuild keeps them as they are.
KEPT_SECTIONS = (
    ("<!-- flow-bodies:begin -->", "<!-- flow-bodies:end -->"),  # benchmarks/bench_flow_bodies.py
    ("<!-- bodies-pcg:begin -->", "<!-- bodies-pcg:end -->"),  # benchmarks/bench_bodies.py
    ("<!-- step-cost:begin -->", "<!-- step-cost:end -->"),  # benchmarks/bench_simulate.py --step-cost
    ("<!-- cg-floor:begin -->", "<!-- cg-floor:end -->"),  # benchmarks/bench_cg.py --iteration
    ("<!-- jaxcfd:begin -->", "<!-- jaxcfd:end -->"),  # benchmarks/bench_jaxcfd.py
    ("<!-- etdrk:begin -->", "<!-- etdrk:end -->"),  # benchmarks/bench_etdrk.py
)


def _kept_sections(path: str) -> list[str]:
    """The marked sections of the current document (see :data:`KEPT_SECTIONS`)."""
    if not os.path.exists(path):
        return []
    with open(path) as fh:
        text = fh.read()
    out = []
    for begin, end in KEPT_SECTIONS:
        if begin in text and end in text.split(begin, 1)[1]:
            out.append(begin + text.split(begin, 1)[1].split(end, 1)[0] + end)
    return out


def write_doc(base: str, path: str) -> None:
    """Rebuild the benchmark document from every results file under ``base`` (marked sections are kept)."""
    kept = _kept_sections(path)
    meta = None
    for s in SUITES:
        for side in ("phisim", "phiflow", "floors"):
            d = _load(os.path.join(base, f"{side}_{s}.json"))
            if d:
                meta = d["meta"]
                break
    meta = meta or (_load(os.path.join(base, "fft_engines.json")) or {}).get("meta", {})
    parts = [INTRO.format(machine=meta.get("machine", "unknown"), threads=meta.get("threads", "?"))]
    parts += ["## Goals", ""] + _goals(base) + [""]
    titles = {
        "operators": "Operators (laplace, advection), float32, batch 1",
        "poisson": "Poisson, zero Dirichlet, rtol 1e-5",
        "heat": "Spectral heat step (periodic), float32",
        "fluid": "Smoke (closed box, buoyancy), float32",
    }
    for s in ["operators", "poisson", "heat", "fluid"]:
        parts += [f"## {titles[s]}", ""] + _suite_table(s, base) + [""]
        if s == "poisson":
            ft = _floor_table("floors_poisson.json", base, "floor")
            if ft:
                parts += (
                    [
                        "### Poisson floors (not peers: limits)",
                        "",
                        "Face-Dirichlet Laplacian (the one the DST-II "
                        "diagonalises), dx = 1; spsolve includes the sparse LU factorisation.",
                        "",
                    ]
                    + ft
                    + [""]
                )
        if s == "heat":
            ft = _floor_table("floors_heat.json", base, "engine")
            if ft:
                parts += ["### Heat floors: one raw FFT round trip", ""] + ft + [""]
    fd = _fft_decision(base)
    if fd:
        parts += ["## FFT engines on this machine (decides phisim's default)", ""] + fd + [""]
    visc = os.path.join(HERE, "results", "viscosity.md")
    if os.path.exists(visc):  # written by benchmarks/bench_viscosity.py --write
        with open(visc) as fh:
            parts += ["## Viscosity step (MAC velocity): explicit vs spectral implicit", "", fh.read().strip(), ""]
    rel = os.path.join(RESULTS, "reliability.json")
    if os.path.exists(rel):  # written by bench_reliability.py
        from bench_reliability import markdown

        with open(rel) as fh:
            parts += markdown(json.load(fh))
    for sec in kept:
        parts += [sec, ""]
    others = [
        f
        for f in ("bench_cg.py", "bench_hig.py", "bench_spectral.py", "bench_viscosity.py", "bench_reliability.py",
                  "bench_bodies.py", "bench_flow_bodies.py", "bench_simulate.py")
        if os.path.exists(os.path.join(HERE, f))
    ]
    if others:
        parts += ["## Other benchmark scripts", "",
                  "Each takes `--device` (`cpu`, the default, `cuda` or `cuda:N`; CUDA is synchronised around every "
                  "timed region and the device is recorded with the results). CPU-only parts stay on the CPU: the "
                  "scipy/numpy floors of `bench_spectral.py`, the planner, journal and kill parts of "
                  "`bench_reliability.py`, the PhiFlow sides of `bench_flow_bodies.py`.", ""]
        parts += [f"- `benchmarks/{f}`" for f in others] + [""]
    os.makedirs(os.path.dirname(path), exist_ok=True)
    with open(path, "w") as fh:
        fh.write("\n".join(parts))


def main(argv: list[str] | None = None) -> int:
    """Command-line entry point (see the module docstring)."""
    ap = argparse.ArgumentParser(description="phisim benchmarks against PhiFlow and raw floors")
    ap.add_argument("--suite", default="all", choices=SUITES + ["all"])
    ap.add_argument(
        "--quick", action="store_true", help="smallest size per case, 2 repeats, results to --out"
    )
    ap.add_argument("--reuse-peer", action="store_true", help="take PhiFlow figures from the saved JSON")
    ap.add_argument(
        "--no-peer", action="store_true", help="skip PhiFlow (peer columns from saved JSON if any)"
    )
    ap.add_argument("--peer-only", action="store_true", help="run only the PhiFlow side")
    ap.add_argument(
        "--fresh",
        action="store_true",
        help="overwrite saved PhiFlow/floor results instead of keeping the lower median per case",
    )
    ap.add_argument("--doc-only", action="store_true", help="rebuild docs/BENCHMARKS.md from saved results")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--device", default="cpu")
    ap.add_argument(
        "--out", default=None, help="results directory (default benchmarks/results; quick: a temp dir)"
    )
    ap.add_argument(
        "--doc", default=None, help="document path (default docs/BENCHMARKS.md; quick: <out>/BENCHMARKS.md)"
    )
    args = ap.parse_args(argv)
    if not args.doc_only:
        from phisim.checks import check_device

        check_device(args.device)  # a bad device fails before any suite runs
    if args.out is None:
        args.out = tempfile.mkdtemp(prefix="phisim-bench-") if args.quick else RESULTS
    doc = args.doc or (os.path.join(args.out, "BENCHMARKS.md") if args.quick else DOC)
    set_threads(args.threads)
    if not args.doc_only:
        for s in SUITES if args.suite == "all" else [args.suite]:
            t0 = time.perf_counter()
            run_suite(s, args)
            _log(f"suite {s} done in {time.perf_counter() - t0:.0f} s")
    if args.reuse_peer or args.no_peer:
        # peer JSON lives in the committed results directory
        for s in SUITES:
            src = os.path.join(RESULTS, f"phiflow_{s}.json")
            dst = os.path.join(args.out, f"phiflow_{s}.json")
            if (
                os.path.abspath(src) != os.path.abspath(dst)
                and os.path.exists(src)
                and not os.path.exists(dst)
            ):
                with open(src) as a, open(dst, "w") as b:
                    b.write(a.read())
    write_doc(args.out, doc)
    _log(f"wrote {doc} (results in {args.out})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
