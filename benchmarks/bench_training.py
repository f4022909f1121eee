"""Where the time of one E3 (Poisson) training iteration goes: data, physics, network.

For Adam through the physics and for Adam + physical gradients (PG) on
:class:`inverse.problems.PoissonProblem`, each configuration times ``--repeats`` iterations after
``--warmup`` and reports medians of

* ``data``: drawing a batch (spectral noise and the solve that makes ``y*``; ``--data-solver``),
* ``physics``: the training path's physics on the network output (Adam: the forward CG solve and the
  adjoint solve of its gradient; PG: the forward solve and the local inverse, i.e. ``physical_update``),
* ``network``: U-net forward, backward of a fixed output gradient, and the Adam step,
* ``iteration``: one complete iteration as :func:`inverse.train.train` runs it (``sample`` + ``_step``).

The physics share is ``(data + physics) / (data + physics + network)``; data generation counts as
physics because it is a solve. The training path's solver is selectable (``--solvers``): ``cg`` is the
experiment's plain CG to rtol 1e-5, ``spectral`` the CG preconditioned by the exact spectral solver.

Run:  python benchmarks/bench_training.py --resolution 64 --batch-size 128 --out docs/BENCHMARKS_TRAINING.md
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import time
from pathlib import Path

import torch

from inverse.physgrad import physical_update
from inverse.problems import get_problem
from inverse.train import _step, batch_generator, make_optimizer
from phisim.checks import check_device


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def _timed(fn, device: torch.device) -> tuple[float, object]:
    _sync(device)
    t0 = time.perf_counter()
    out = fn()
    _sync(device)
    return time.perf_counter() - t0, out


def bench(method_name: str, solver: str, args: argparse.Namespace) -> dict[str, float]:
    """Median seconds of the phases of one training iteration for one method and training solver.

    Args:
        method_name: ``'adam'`` or ``'pg'``.
        solver: Training-path solver of the Poisson problem (``'cg'`` or ``'spectral'``).
        args: Parsed options.

    Returns:
        Medians of ``data``, ``physics``, ``network``, ``iteration`` (seconds), the physics share, and
        ``iteration_check`` (the measured complete iteration over the sum of the three phases).
    """
    device = check_device(args.device)
    res = (args.resolution, args.resolution)
    problem = get_problem("poisson", resolution=res, solver=solver, data_solver=args.data_solver)
    method = problem.method(method_name)
    torch.manual_seed(0)
    model = problem.make_network().to(device=device, dtype=problem.dtype)
    opt = make_optimizer(method, model, problem)
    model.train()
    rows: dict[str, list[float]] = {"data": [], "physics": [], "network": [], "iteration": []}
    for k in range(args.warmup + args.repeats):
        t_data, batch = _timed(lambda k=k: problem.sample(args.batch_size, batch_generator(0, k), device=device),
                               device)
        with torch.no_grad():
            x0 = problem.predict(model, batch)

        def physics(x0=x0, batch=batch):
            if method.kind == "physics":
                x = x0.detach().requires_grad_(True)
                problem.loss(batch.operator(x), batch.y_target).sum().backward()
                return x.grad
            return physical_update(x0.detach(), batch.y_target, batch.operator, eta=method.eta,
                                   loss=problem.newton_loss)[0]

        t_phys, grad = _timed(physics, device)

        def network(batch=batch, grad=grad):
            opt.zero_grad(set_to_none=True)
            x = problem.predict(model, batch)
            (x * grad.to(x.dtype)).sum().backward()
            opt.step()

        t_net, _ = _timed(network, device)

        def iteration(k=k):
            b = problem.sample(args.batch_size, batch_generator(1, k), device=device)
            return _step(problem, method, model, opt, b, 1.0)

        t_it, _ = _timed(iteration, device)
        if k >= args.warmup:
            for key, t in zip(rows, (t_data, t_phys, t_net, t_it), strict=True):
                rows[key].append(t)
    med = {k: statistics.median(v) for k, v in rows.items()}
    parts = med["data"] + med["physics"] + med["network"]
    med["share"] = (med["data"] + med["physics"]) / parts
    med["iteration_check"] = med["iteration"] / parts
    return med


def main(argv: list[str] | None = None) -> dict:
    """Run the benchmark; print a markdown table and optionally write it (and the JSON) to ``--out``."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--resolution", type=int, default=64)
    p.add_argument("--batch-size", type=int, default=128)
    p.add_argument("--methods", nargs="+", default=["adam", "pg"], choices=["adam", "pg"])
    p.add_argument("--solvers", nargs="+", default=["cg", "spectral"], choices=["cg", "spectral"])
    p.add_argument("--data-solver", default="spectral", choices=["cg", "spectral"])
    p.add_argument("--warmup", type=int, default=1)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--device", default="cpu", help="torch device: cpu, cuda or cuda:N (default cpu)")
    p.add_argument("--out", type=Path, default=None, help="markdown file to write (JSON next to it)")
    args = p.parse_args(argv)
    check_device(args.device)  # a bad device fails before any case runs
    torch.set_num_threads(args.threads)
    results = {}
    lines = [
        f"E3 Poisson, {args.resolution}x{args.resolution}, batch {args.batch_size}, data solver "
        f"`{args.data_solver}`, device {args.device}, {args.threads} thread(s), torch {torch.__version__}, "
        f"{platform.processor() or platform.machine()}; medians of {args.repeats} iterations after {args.warmup}.",
        "",
        "| method | training solver | data [s] | physics [s] | network [s] | iteration [s] | physics share |",
        "|---|---|---:|---:|---:|---:|---:|",
    ]
    for m in args.methods:
        for s in args.solvers:
            r = bench(m, s, args)
            results[f"{m}/{s}"] = r
            lines.append(f"| {m} | {s} | {r['data']:.3f} | {r['physics']:.3f} | {r['network']:.3f} | "
                         f"{r['iteration']:.3f} | {100 * r['share']:.0f}% |")
            print(lines[-1], flush=True)
    text = "\n".join(lines) + "\n"
    print(text)
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(text)
        args.out.with_suffix(".json").write_text(json.dumps({"args": vars(args) | {"out": str(args.out)},
                                                              "results": results}, indent=1))
    return results


if __name__ == "__main__":
    main()
