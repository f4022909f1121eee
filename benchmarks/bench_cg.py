"""Time per CG solve of ``phisim.solvers.linalg.cg`` on the 2-D zero-Dirichlet 5-point Laplacian.

Usage: ``.venv/bin/python benchmarks/bench_cg.py [--repeats 5] [--sizes 64 128 256] [--device cpu]``
prints a markdown table. The functions are importable by the benchmark runner:
:func:`cases` lists the cases, :func:`run_case` measures one, :func:`table` formats results.

The operator is a local stencil (``-Laplacian`` with ghost cells 0, i.e. PhiFlow's "ZERO"
extrapolation, unit spacing), the right-hand side the shared smooth input
``benchmarks.inputs.poisson_rhs`` (falls back to a fixed smooth bump plus noise when run elsewhere),
``rtol=1e-5``, ``atol=0``. Each case reports the median wall time of ``repeats`` solves after one
warm-up, the iterations, the true relative residual (computed in float64) and the outcome.
Modes: ``float64`` (plain CG), ``float32`` (default: float64-residual refinement around float32 CG),
``float32-plain`` (``refine=False``: float32 arithmetic only) and ``float64-mixed`` (float64 in and
out, float32 inner iterations).

``--iteration`` measures instead one CG iteration (operator, two dot products, three vector updates) against
its floor, in one interleaved run: ``.venv/bin/python benchmarks/bench_cg.py --iteration [--rounds 7]``.
An iteration is the difference of two solves stopped after ``K1`` and ``K2`` iterations, divided by
``K2 - K1`` (fixed per-solve costs cancel); CPU time of the process (one thread) is the primary clock, wall
time beside it. Sides, all on the face-Dirichlet ``-∇²_h`` (ghost ``-u``, dx = 1), batch 1:

* ``phisim``: :func:`phisim.solvers.linalg.cg` with :func:`phisim.ops.stencil.negative_laplacian`;
* ``phisim (E3 operator)``: ``cg`` with ``-stencil_laplacian(u, 1.0, 'dirichlet')``, the operator
  ``inverse.operators.Poisson`` passes;
* ``floor``: the same arithmetic written by hand with the fewest passes torch allows: the Laplacian as one
  product with a precomputed diagonal plus two shifted ``add_`` per axis into a preallocated output,
  ``torch.dot`` on flat views, ``add_``/``addcmul_`` in place, ``p = r + beta p`` by ``torch.add(out=)`` into a
  second buffer; in two variants, coefficients as 0-d tensors (no host read) and as Python numbers (one
  host read per dot), the faster of the two being the floor;
* ``numpy + BLAS``: the same loop in numpy (shifted slices, ``np.dot``, scipy's BLAS ``axpy``/``scal``).

``--peer`` times instead phisim's whole CG solve against PhiFlow's (the runner's ``poisson_cg`` case on both
sides, float64, PhiFlow in ``benchmarks/.phiflow-venv``) in ``--rounds`` interleaved rounds.

``--batch B`` solves B samples together: the floors are then per-sample coefficients applied by ``addcmul_`` with
the dots as one product and a sum or one ``torch.dot`` per sample (no numpy side). ``--laplacian`` adds the
Laplacian alone (field ``laplace``, ``stencil_laplacian``, ``negative_laplacian``, the
floor kernel, ``F.pad`` + five shifted slices, ``conv2d``/``conv3d``, numpy slicing), and the op counts per
iteration (ATen operators, by :class:`torch.utils._python_dispatch.TorchDispatchMode`) are printed for every
side. ``PHISIM_BENCH_ROOT=<dir>`` imports phisim from another tree (e.g. an older commit exported by
``git archive``); sides that tree lacks are skipped.
"""

from __future__ import annotations

import argparse
import collections
import json
import os
import statistics
import sys
import time

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):  # numpy's BLAS: one thread, set before
    os.environ.setdefault(_var, "1")  # it loads (a multi-threaded BLAS spins on the shared cores)

import numpy as np  # noqa: E402
import torch  # noqa: E402

sys.path.insert(0, os.environ.get("PHISIM_BENCH_ROOT") or os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from phisim import CenteredGrid, Grid, laplace  # noqa: E402
from phisim.checks import check_device  # noqa: E402
from phisim.errors import SolveError  # noqa: E402
from phisim.ops import stencil  # noqa: E402
from phisim.solvers.linalg import Solve, cg  # noqa: E402
from phisim.solvers.poisson import stencil_laplacian  # noqa: E402

MODES = ("float64", "float32", "float32-plain", "float64-mixed")


def neg_laplace(x: torch.Tensor) -> torch.Tensor:
    """``-Laplacian`` (5-point, unit spacing, zero ghost cells) on ``(B, nx, ny)``; SPD."""
    xp = torch.nn.functional.pad(x[:, None], (1, 1, 1, 1))[:, 0]
    return 4 * x - xp[:, 2:, 1:-1] - xp[:, :-2, 1:-1] - xp[:, 1:-1, 2:] - xp[:, 1:-1, :-2]


def _rhs(n: int) -> torch.Tensor:
    try:
        from benchmarks import inputs

        return torch.as_tensor(inputs.poisson_rhs((n, n), 1, dtype="float64"))
    except Exception:  # the shared inputs are not importable: a fixed smooth bump plus noise
        i = torch.arange(n, dtype=torch.float64)
        bump = torch.exp(-((i[:, None] - n / 3) ** 2 + (i[None] - n / 2) ** 2) / (n / 8) ** 2)
        noise = torch.randn(n, n, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
        return (bump + 0.1 * noise)[None]


def cases(sizes: tuple[int, ...] = (64, 128, 256)) -> list[dict]:
    """The benchmark cases.

    Args:
        sizes: Grid sizes ``n`` (grids are ``n x n``).

    Returns:
        One dict per case with ``name``, ``n``, ``mode`` (see module docstring), ``rtol``.
    """
    return [{"name": f"cg_{n}^2_{mode}", "n": n, "mode": mode, "rtol": 1e-5} for n in sizes for mode in MODES]


def run_case(case: dict, repeats: int = 5, device: str = "cpu") -> dict:
    """Measure one case.

    Args:
        case: A dict from :func:`cases`.
        repeats: Timed solves (median reported) after one untimed warm-up solve.
        device: Torch device.

    Returns:
        The case dict extended by ``median_s``, ``iterations`` (max over the batch), ``rel_residual``
        (true, float64), ``status`` and ``refinements``.
    """
    n, mode = case["n"], case["mode"]
    b64 = _rhs(n).to(device)
    dtype = torch.float32 if mode.startswith("float32") else torch.float64
    refine = {"float64": None, "float32": None, "float32-plain": False, "float64-mixed": True}[mode]
    solve = Solve(rtol=case["rtol"], refine=refine, raise_on_failure=False)
    b = b64.to(dtype)

    def once():
        return cg(neg_laplace, b, solve=solve, return_info=True)

    sync = torch.cuda.synchronize if str(device).startswith("cuda") else (lambda: None)
    x, info = once()
    times = []
    for _ in range(repeats):
        sync()
        t0 = time.perf_counter()
        x, info = once()
        sync()
        times.append(time.perf_counter() - t0)
    bd = b.double()
    rel = torch.linalg.vector_norm(bd - neg_laplace(x.double())) / torch.linalg.vector_norm(bd)
    return {**case, "median_s": statistics.median(times), "iterations": int(info.iterations.max()),
            "rel_residual": float(rel), "status": info.status[0], "refinements": info.refinements}


def table(results: list[dict]) -> str:
    """Format results of :func:`run_case` as a markdown table.

    Args:
        results: Dicts returned by :func:`run_case`.

    Returns:
        The markdown table (one row per case).
    """
    rows = ["| grid | mode | time per solve (ms) | iterations | refinements | true rel. residual | status |",
            "|---|---|---:|---:|---:|---:|---|"]
    for r in results:
        rows.append(f"| {r['n']}^2 | {r['mode']} | {1e3 * r['median_s']:.1f} | {r['iterations']} | "
                    f"{r['refinements']} | {r['rel_residual']:.2e} | {r['status']} |")
    return "\n".join(rows)


# --------------------------------------------------------------------------------------------------
# one CG iteration against its floor

ITERATION_SHAPES = ((128, 128), (256, 256), (512, 512), (64, 64, 64))
ITERATION_DTYPES = ("float32", "float64")
_VIEWS = {"view", "_unsafe_view", "slice", "select", "narrow", "as_strided", "expand", "alias", "reshape",
          "unsqueeze", "squeeze", "t", "transpose", "lift_fresh", "detach", "_reshape_alias"}


def _iteration_rhs(shape: tuple[int, ...], dtype: torch.dtype, batch: int = 1) -> torch.Tensor:
    g = torch.Generator().manual_seed(1)
    return torch.randn((batch, *shape), generator=g, dtype=torch.float64).to(dtype)


def _e3_operator(u: torch.Tensor) -> torch.Tensor:
    return -stencil_laplacian(u, 1.0, "dirichlet")


def _phisim_operator(u: torch.Tensor) -> torch.Tensor:
    return stencil.negative_laplacian(u, 1.0, "dirichlet")


def _diagonal(shape: tuple[int, ...], dtype: torch.dtype) -> torch.Tensor:
    """Diagonal of the face-Dirichlet ``-∇²_h`` (dx = 1): ``2`` per axis, ``+1`` per box side beside the cell."""
    d = torch.zeros(shape, dtype=torch.float64)
    for a, n in enumerate(shape):
        edge = torch.full((n,), 2.0, dtype=torch.float64)
        edge[0] += 1.0
        edge[-1] += 1.0
        view = [1] * len(shape)
        view[a] = n
        d = d + edge.view(view)
    return d.to(dtype)[None]


def floor_laplacian(u: torch.Tensor, diag: torch.Tensor, out: torch.Tensor) -> torch.Tensor:
    """The floor's ``-∇²_h u`` (face Dirichlet, dx = 1): ``u * diag`` into ``out``, two shifted ``add_`` per axis."""
    torch.mul(u, diag, out=out)
    for dim in range(1, u.ndim):
        n = u.shape[dim]
        out.narrow(dim, 0, n - 1).sub_(u.narrow(dim, 1, n - 1))
        out.narrow(dim, 1, n - 1).sub_(u.narrow(dim, 0, n - 1))
    return out


def _floor_cg(b: torch.Tensor, diag: torch.Tensor, iterations: int, tensor_coefficients: bool) -> torch.Tensor:
    """``iterations`` CG iterations written by hand (see the module docstring)."""
    x = torch.zeros_like(b)
    r = b.clone()
    p = r.clone()
    spare = torch.empty_like(b)
    q = torch.empty_like(b)
    rf, qf = r.view(-1), q.view(-1)
    if tensor_coefficients:
        rz = torch.dot(rf, rf)
        for _ in range(iterations):
            floor_laplacian(p, diag, q)
            alpha = rz / torch.dot(p.view(-1), qf)
            x.addcmul_(alpha, p)
            r.addcmul_(alpha, q, value=-1)
            rz_new = torch.dot(rf, rf)
            p, spare = torch.addcmul(r, rz_new / rz, p, out=spare), p
            rz = rz_new
        return x
    rz = float(torch.dot(rf, rf))
    for _ in range(iterations):
        floor_laplacian(p, diag, q)
        alpha = rz / float(torch.dot(p.view(-1), qf))
        x.add_(p, alpha=alpha)
        r.add_(q, alpha=-alpha)
        rz_new = float(torch.dot(rf, rf))
        p, spare = torch.add(r, p, alpha=rz_new / rz, out=spare), p
        rz = rz_new
    return x


def _floor_cg_batched(b: torch.Tensor, diag: torch.Tensor, iterations: int, blas_dots: bool) -> torch.Tensor:
    """The batched floor: per-sample coefficients ``(B, 1, ...)`` applied by ``addcmul_``, per-sample dots by one
    product and a sum (``blas_dots=False``) or one ``torch.dot`` per sample (``True``); no convergence checks."""
    B = b.shape[0]
    shape = (B,) + (1,) * (b.ndim - 1)
    x = torch.zeros_like(b)
    r = b.clone()
    p = r.clone()
    spare = torch.empty_like(b)
    q = torch.empty_like(b)
    rows = [(r[i].view(-1), q[i].view(-1)) for i in range(B)]

    def dots(u, v, flat_u, flat_v):
        if blas_dots:
            return torch.stack([torch.dot(a, c) for a, c in zip(flat_u, flat_v)])
        return (u * v).flatten(1).sum(1)

    r_rows = [a for a, _ in rows]
    q_rows = [c for _, c in rows]
    rz = dots(r, r, r_rows, r_rows)
    for _ in range(iterations):
        floor_laplacian(p, diag, q)
        alpha = (rz / dots(p, q, [p[i].view(-1) for i in range(B)], q_rows)).view(shape)
        x.addcmul_(alpha, p)
        r.addcmul_(alpha, q, value=-1)
        rz_new = dots(r, r, r_rows, r_rows)
        p, spare = torch.addcmul(r, (rz_new / rz).view(shape), p, out=spare), p
        rz = rz_new
    return x


def _numpy_cg(b: np.ndarray, diag: np.ndarray, iterations: int) -> np.ndarray:
    """The same loop in numpy: shifted slices for the stencil, ``np.dot``, scipy's BLAS ``axpy``/``scal``."""
    from scipy.linalg import blas

    axpy, scal = blas.get_blas_funcs(("axpy", "scal"), (b,))
    x = np.zeros_like(b)
    r = b.copy()
    p = r.copy()
    q = np.empty_like(b)
    xf, rf, pf, qf = x.reshape(-1), r.reshape(-1), p.reshape(-1), q.reshape(-1)
    rz = float(np.dot(rf, rf))
    nd = b.ndim
    lo = [tuple(slice(0, -1) if a == d else slice(None) for a in range(nd)) for d in range(nd)]
    hi = [tuple(slice(1, None) if a == d else slice(None) for a in range(nd)) for d in range(nd)]
    for _ in range(iterations):
        np.multiply(p, diag, out=q)
        for d in range(nd):
            q[lo[d]] -= p[hi[d]]
            q[hi[d]] -= p[lo[d]]
        alpha = rz / float(np.dot(pf, qf))
        axpy(pf, xf, a=alpha)
        axpy(qf, rf, a=-alpha)
        rz_new = float(np.dot(rf, rf))
        scal(rz_new / rz, pf)
        axpy(rf, pf)
        rz = rz_new
    return x


def iteration_sides(shape: tuple[int, ...], dtype: str, batch: int = 1) -> dict:
    """The sides of one case: name -> ``run(iterations)``.

    Args:
        shape: Grid resolution.
        dtype: ``'float32'`` or ``'float64'``.
        batch: Samples solved together (above 1: the batched floors, no numpy side).

    Returns:
        A dict of callables that each run a CG of the given number of iterations (plus fixed costs).
    """
    dt = getattr(torch, dtype)
    b = _iteration_rhs(shape, dt, batch)
    diag = _diagonal(shape, dt)
    b_np, diag_np = b[0].numpy().copy(), diag[0].numpy().copy()

    def phisim_cg(operator):
        def run(iterations: int):
            # rtol 1e-5 is not met within the iterations timed; refine=False: the iterations in the input dtype
            return cg(operator, b, solve=Solve(rtol=1e-5, max_iter=iterations, refine=False, raise_on_failure=False))
        return run

    sides = {}
    if hasattr(stencil, "negative_laplacian"):
        sides["phisim"] = phisim_cg(_phisim_operator)
    sides["phisim (E3 operator)"] = phisim_cg(_e3_operator)
    if batch > 1:
        sides["floor, per-sample coefficients, product-sum dots"] = lambda k: _floor_cg_batched(b, diag, k, False)
        sides["floor, per-sample coefficients, one dot per sample"] = lambda k: _floor_cg_batched(b, diag, k, True)
        return sides
    sides["floor, 0-d tensor coefficients"] = lambda k: _floor_cg(b, diag, k, True)
    sides["floor, number coefficients"] = lambda k: _floor_cg(b, diag, k, False)
    sides["numpy + BLAS"] = lambda k: _numpy_cg(b_np, diag_np, k)
    return sides


def laplacian_sides(shape: tuple[int, ...], dtype: str) -> dict:
    """The Laplacian alone: name -> ``run(calls)``."""
    dt = getattr(torch, dtype)
    u = _iteration_rhs(shape, dt)
    diag = _diagonal(shape, dt)
    out = torch.empty_like(u)
    field = CenteredGrid(u, Grid(shape), "dirichlet")
    rank = len(shape)
    conv = torch.nn.functional.conv2d if rank == 2 else torch.nn.functional.conv3d
    kernel = torch.zeros((1, 1) + (3,) * rank, dtype=dt)
    centre = (0, 0) + (1,) * rank
    kernel[centre] = 2.0 * rank
    for a in range(rank):
        for s in (0, 2):
            idx = list(centre)
            idx[2 + a] = s
            kernel[tuple(idx)] = -1.0
    padded = torch.nn.functional.pad(u[:, None], (1, 1) * rank)
    u_np, diag_np = u[0].numpy().copy(), diag[0].numpy().copy()
    q_np = np.empty_like(u_np)

    def sliced(k):
        for _ in range(k):
            xp = torch.nn.functional.pad(u[:, None], (1, 1) * rank)[:, 0]
            inner = (slice(None),) + (slice(1, -1),) * rank
            acc = 2.0 * rank * xp[inner]
            for a in range(rank):
                for lo in (0, 2):
                    idx = list(inner)
                    idx[1 + a] = slice(lo, lo + shape[a])
                    acc = acc - xp[tuple(idx)]

    def numpy_slices(k):
        for _ in range(k):
            np.multiply(u_np, diag_np, out=q_np)
            for d in range(rank):
                lo = tuple(slice(0, -1) if a == d else slice(None) for a in range(rank))
                hi = tuple(slice(1, None) if a == d else slice(None) for a in range(rank))
                q_np[lo] -= u_np[hi]
                q_np[hi] -= u_np[lo]

    def repeat(fn):
        def run(k):
            for _ in range(k):
                fn()
        return run

    sides = {"laplace(CenteredGrid)": repeat(lambda: laplace(field)),
             "stencil_laplacian": repeat(lambda: stencil_laplacian(u, 1.0, "dirichlet"))}
    if hasattr(stencil, "negative_laplacian"):
        sides["negative_laplacian"] = repeat(lambda: stencil.negative_laplacian(u, 1.0, "dirichlet"))
    sides["floor kernel (mul + 2 shifted add_ per axis)"] = repeat(lambda: floor_laplacian(u, diag, out))
    sides["F.pad + shifted slices"] = sliced
    sides[f"conv{rank}d on a padded input"] = repeat(lambda: conv(padded, kernel))
    sides["numpy slices"] = numpy_slices
    return sides


def _times(run, k: int, repeats: int = 3) -> tuple[float, float]:
    """CPU and wall time of ``run(k)``, each the lowest of ``repeats`` calls (other work only adds time)."""
    cpu, wall = [], []
    for _ in range(repeats):
        c0, w0 = time.process_time(), time.perf_counter()
        run(k)
        cpu.append(time.process_time() - c0)
        wall.append(time.perf_counter() - w0)
    return min(cpu), min(wall)


class _Counter(torch.utils._python_dispatch.TorchDispatchMode):
    """Counts ATen operators: views, operators on arrays of the field's size, small (per-sample) operators."""

    def __init__(self, numel: int):
        super().__init__()
        self.numel = numel
        self.counts = collections.Counter()

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        out = func(*args, **(kwargs or {}))
        name = func.overloadpacket.__name__
        tensors = [t for t in list(args) + list((kwargs or {}).values()) + [out] if isinstance(t, torch.Tensor)]
        big = max((t.numel() for t in tensors), default=0) >= self.numel // 4
        self.counts["view" if name in _VIEWS else ("array" if big else "small")] += 1
        self.counts["host read" if name in ("_local_scalar_dense", "equal") else "_"] += 1
        return out


def op_counts(run, numel: int, k1: int = 5, k2: int = 15) -> dict:
    """ATen operators per iteration of ``run`` (difference of two runs): ``array``, ``small``, ``view`` and
    ``host read``."""
    out = {}
    for k in (k1, k2):
        counter = _Counter(numel)
        with counter:
            run(k)
        out[k] = counter.counts
    return {key: (out[k2][key] - out[k1][key]) / (k2 - k1) for key in ("array", "small", "view", "host read")}


def run_iterations(shapes=ITERATION_SHAPES, dtypes=ITERATION_DTYPES, rounds: int = 7, k1: int = 10, k2: int = 40,
                   laplacian: bool = False, batch: int = 1) -> list[dict]:
    """Interleaved rounds over every case and side; medians per side.

    Args:
        shapes: Grid resolutions.
        dtypes: ``'float32'``/``'float64'``.
        rounds: Rounds; in each, every case and side is timed once (sides in rotating order).
        k1, k2: The two iteration counts whose difference is timed.
        laplacian: Also time the Laplacian alone (``k2 - k1`` calls per sample).
        batch: Samples per solve.

    Returns:
        One dict per (case, side): ``shape``, ``dtype``, ``kind`` (``'iteration'``/``'laplacian'``), ``side``,
        ``cpu_us``/``wall_us`` (medians), ``cpu_all`` (every round), and ``ops`` (iterations only).
    """
    cases = []
    for shape in shapes:
        for dtype in dtypes:
            cases.append((shape, dtype, "iteration", iteration_sides(shape, dtype, batch)))
            if laplacian:
                cases.append((shape, dtype, "laplacian", laplacian_sides(shape, dtype)))
    samples = {(i, name): ([], []) for i, (_, _, _, sides) in enumerate(cases) for name in sides}
    for _, _, kind, sides in cases:  # warm-up (caches, allocator, BLAS)
        for run in sides.values():
            run(k1 if kind == "iteration" else 2)
    for rnd in range(rounds):
        for i, (_, _, kind, sides) in enumerate(cases):
            names = list(sides)
            names = names[rnd % len(names):] + names[:rnd % len(names)]
            for name in names:
                run = sides[name]
                if kind == "iteration":
                    c1, w1 = _times(run, k1)
                    c2, w2 = _times(run, k2)
                    cpu, wall = (c2 - c1) / (k2 - k1), (w2 - w1) / (k2 - k1)
                else:
                    cpu, wall = _times(run, k2 - k1)
                    cpu, wall = cpu / (k2 - k1), wall / (k2 - k1)
                samples[(i, name)][0].append(1e6 * cpu)
                samples[(i, name)][1].append(1e6 * wall)
    results = []
    for i, (shape, dtype, kind, sides) in enumerate(cases):
        numel = int(np.prod(shape)) * (batch if kind == "iteration" else 1)
        for name, run in sides.items():
            cpu, wall = samples[(i, name)]
            row = {"shape": list(shape), "dtype": dtype, "kind": kind, "side": name, "batch": batch,
                   "cpu_us": statistics.median(cpu), "wall_us": statistics.median(wall), "cpu_all": cpu,
                   "wall_all": wall}
            if kind == "iteration" and not name.startswith("numpy"):
                row["ops"] = op_counts(run, numel)
            results.append(row)
    return results


def _size(shape) -> str:
    return f"{shape[0]}^{len(shape)}" if len(set(shape)) == 1 else "x".join(map(str, shape))


def _ratios(group: list[dict], clock: str) -> dict:
    """Per side the median over rounds of (its time / the floor's time in the same round); the floor of an
    iteration is the faster floor variant of that round, of the Laplacian the floor kernel."""
    floors = [r for r in group if r["side"].startswith("floor")]
    rounds = len(floors[0][clock])
    floor = [min(r[clock][i] for r in floors) for i in range(rounds)]
    return {r["side"]: statistics.median(r[clock][i] / floor[i] for i in range(rounds)) for r in group}


def iteration_table(results: list[dict]) -> str:
    """Markdown tables: per case the sides' CPU/wall times and their ratio to the floor, then the op counts.

    Ratios are medians over rounds of the per-round ratio (the floor measured in the same round)."""
    rows = ["| size | dtype | side | CPU time (us) | wall (us) | / floor (CPU) | / floor (wall) | CPU, all rounds |",
            "|---|---|---|---:|---:|---:|---:|---|"]
    ops = ["| size | dtype | side | array ops | small ops | views | host reads |", "|---|---|---|---:|---:|---:|---:|"]
    keys = []
    for r in results:
        key = (tuple(r["shape"]), r["dtype"], r["kind"])
        if key not in keys:
            keys.append(key)
    for key in keys:
        group = [r for r in results if (tuple(r["shape"]), r["dtype"], r["kind"]) == key]
        cpu_ratio, wall_ratio = _ratios(group, "cpu_all"), _ratios(group, "wall_all")
        for r in group:
            label = r["side"] if key[2] == "iteration" else f"Laplacian: {r['side']}"
            rows.append(f"| {_size(key[0])} | {key[1]} | {label} | {r['cpu_us']:.1f} | {r['wall_us']:.1f} | "
                        f"{cpu_ratio[r['side']]:.2f}x | {wall_ratio[r['side']]:.2f}x | "
                        f"{', '.join(f'{v:.0f}' for v in r['cpu_all'])} |")
            if "ops" in r:
                o = r["ops"]
                ops.append(f"| {_size(key[0])} | {key[1]} | {r['side']} | {o['array']:.0f} | {o['small']:.0f} | "
                           f"{o['view']:.0f} | {o['host read']:.0f} |")
    return "\n".join(rows) + "\n\nATen operators per iteration:\n\n" + "\n".join(ops)


def run_peer(sizes=("128^2", "256^2", "512^2", "64^3"), dtype: str = "float64", rounds: int = 3,
             repeats: int = 3) -> list[dict]:
    """phisim's CG solve against PhiFlow's in interleaved rounds (the runner's ``poisson_cg`` case on both sides).

    Args:
        sizes: Grid sizes in the runner's notation (``'128^2'``).
        dtype: ``'float64'`` (PhiFlow's float32 CG does not reach rtol 1e-5 from 128^2 up).
        rounds: Rounds; each times both sides once per size, phisim first.
        repeats: Solves per side and round (median).

    Returns:
        One dict per size: ``phisim_ms``/``phiflow_ms`` (medians over rounds), ``ratios`` (PhiFlow / phisim per
        round), ``iterations`` (phisim, PhiFlow) and ``loads`` (load average before each pair).
    """
    bench = os.path.dirname(os.path.abspath(__file__))
    sys.path.insert(0, bench)
    import cases_phisim
    import peer_phiflow

    python = os.path.join(bench, ".phiflow-venv", "bin", "python")
    rows = {size: {"phisim": [], "phiflow": [], "loads": []} for size in sizes}
    for _ in range(rounds):
        for size in sizes:
            rows[size]["loads"].append(os.getloadavg()[0])
            a = cases_phisim.run_case("poisson_cg", size, dtype, repeats=repeats)
            b = peer_phiflow.drive("poisson_cg", size, dtype, python=python, threads=1, repeats=repeats)
            if a.get("error") or b.get("error"):
                raise SystemExit(f"{size}: phisim {a.get('error')}, PhiFlow {b.get('error')}")
            rows[size]["phisim"].append(1e3 * a["median_s"])
            rows[size]["phiflow"].append(1e3 * b["median_s"])
            rows[size]["iterations"] = (a.get("iterations"), b.get("iterations"))
    return [{"size": size, "phisim_ms": statistics.median(r["phisim"]), "phiflow_ms": statistics.median(r["phiflow"]),
             "ratios": [f / p for p, f in zip(r["phisim"], r["phiflow"])], "iterations": r["iterations"],
             "loads": r["loads"]} for size, r in rows.items()]


def main(argv: list[str] | None = None) -> None:
    """Run the cases and print the table.

    Args:
        argv: Command-line arguments (``--repeats``, ``--sizes``, ``--device``, ``--threads``).
    """
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--sizes", type=int, nargs="+", default=[64, 128, 256])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--iteration", action="store_true", help="one CG iteration against its floor (CPU)")
    ap.add_argument("--laplacian", action="store_true", help="with --iteration: the Laplacian alone too")
    ap.add_argument("--rounds", type=int, default=7, help="with --iteration: interleaved rounds")
    ap.add_argument("--shapes", nargs="+", default=None, help="with --iteration: e.g. 128x128 64x64x64")
    ap.add_argument("--batch", type=int, default=1, help="with --iteration: samples per solve")
    ap.add_argument("--peer", action="store_true",
                    help="phisim's CG solve against PhiFlow's (benchmarks/.phiflow-venv), float64, interleaved")
    ap.add_argument("--json", default=None, help="with --iteration: also write the results to this file")
    args = ap.parse_args(argv)
    check_device(args.device)
    torch.set_num_threads(args.threads)
    if args.peer:
        rows = run_peer(rounds=args.rounds)
        print("| size | phisim | PhiFlow | PhiFlow / phisim (median of rounds) | per round "
              "| iterations (phisim / PhiFlow) | load average |\n|---|---:|---:|---:|---|---|---|")
        for r in rows:
            print(f"| {r['size']} | {r['phisim_ms']:.1f} ms | {r['phiflow_ms']:.1f} ms | "
                  f"{statistics.median(r['ratios']):.2f}x | {', '.join(f'{v:.2f}' for v in r['ratios'])} | "
                  f"{r['iterations'][0]} / {r['iterations'][1]} | {', '.join(f'{v:.1f}' for v in r['loads'])} |")
        return
    if args.iteration:
        shapes = ITERATION_SHAPES if args.shapes is None else tuple(tuple(int(v) for v in s.split("x"))
                                                                   for s in args.shapes)
        load = os.getloadavg()
        t0 = time.perf_counter()
        results = run_iterations(shapes, rounds=args.rounds, laplacian=args.laplacian, batch=args.batch)
        print(f"One CG iteration against its floor: face-Dirichlet -Laplacian, batch {args.batch}, "
              f"threads={args.threads}, "
              f"torch {torch.__version__}, median of {args.rounds} interleaved rounds, "
              f"iteration = (t(40) - t(10)) / 30, "
              f"each t the lowest of 3 calls; "
              f"load average {load[0]:.2f} before, {os.getloadavg()[0]:.2f} after "
              f"{time.perf_counter() - t0:.0f} s\n")
        print(iteration_table(results))
        if args.json:
            with open(args.json, "w") as fh:
                json.dump({"load_before": load, "load_after": os.getloadavg(), "results": results}, fh)
        return
    try:
        results = [run_case(c, args.repeats, args.device) for c in cases(tuple(args.sizes))]
    except SolveError as e:  # raise_on_failure=False: only breakdowns or non-finite values get here
        raise SystemExit(f"unexpected solve failure: {e}") from e
    print(f"CG, zero-Dirichlet 5-point Laplacian, rtol=1e-5, device={args.device}, threads={args.threads}, "
          f"torch {torch.__version__}, median of {args.repeats}\n")
    print(table(results))


if __name__ == "__main__":
    main()
