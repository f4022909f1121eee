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
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time

import torch

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from phisim.checks import check_device  # noqa: E402
from phisim.errors import SolveError  # noqa: E402
from phisim.solvers.linalg import Solve, cg  # noqa: E402

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
    args = ap.parse_args(argv)
    check_device(args.device)
    torch.set_num_threads(args.threads)
    try:
        results = [run_case(c, args.repeats, args.device) for c in cases(tuple(args.sizes))]
    except SolveError as e:  # raise_on_failure=False: only breakdowns or non-finite values get here
        raise SystemExit(f"unexpected solve failure: {e}") from e
    print(f"CG, zero-Dirichlet 5-point Laplacian, rtol=1e-5, device={args.device}, threads={args.threads}, "
          f"torch {torch.__version__}, median of {args.repeats}\n")
    print(table(results))


if __name__ == "__main__":
    main()
