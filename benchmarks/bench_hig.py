"""Time per HIG step versus batch size and parameter count, split into Jacobian, SVD and apply.

The problem is the coupled-oscillator control of ``examples/hig_oscillators.py`` (24 RK4 steps as the
physics, 4 outputs per sample); the network is ``4 -> 3 x width tanh -> 24`` with the width varied to
change the parameter count. Each configuration runs ``--warmup`` steps, then ``--repeats`` timed steps;
the table reports medians (CUDA is synchronised around each phase).

Run:  python benchmarks/bench_hig.py --out docs/BENCHMARKS_HIG.md
"""

from __future__ import annotations

import argparse
import importlib.util
import platform
import statistics
import sys
from pathlib import Path

import torch

from inverse.hig import HIG
from phisim.checks import check_device

ROOT = Path(__file__).resolve().parents[1]


def _oscillators():
    spec = importlib.util.spec_from_file_location("hig_oscillators", ROOT / "examples" / "hig_oscillators.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def make_net(width: int, dtype: torch.dtype, device: torch.device) -> torch.nn.Sequential:
    """Control network ``4 -> 3 x width tanh -> 24``.

    Args:
        width: Hidden width.
        dtype: Parameter dtype.
        device: Device.

    Returns:
        The network.
    """
    torch.manual_seed(0)
    layers: list[torch.nn.Module] = []
    n_in = 4
    for _ in range(3):
        layers += [torch.nn.Linear(n_in, width), torch.nn.Tanh()]
        n_in = width
    layers.append(torch.nn.Linear(n_in, 24))
    return torch.nn.Sequential(*layers).to(device=device, dtype=dtype)


def bench(batch: int, width: int, args: argparse.Namespace) -> dict[str, float]:
    """Median seconds per phase of one HIG step for one configuration.

    Args:
        batch: Batch size.
        width: Hidden width.
        args: Parsed options.

    Returns:
        ``n_theta``, ``rows`` and median seconds for ``jacobian``, ``svd``, ``apply``, ``total``.
    """
    osc = _oscillators()
    device, dtype = check_device(args.device), getattr(torch, args.dtype)
    net = make_net(width, dtype, device)
    opt = HIG(net, physics=lambda c, s0: osc.simulate(c, s0), lr=1e-6, rcond=1e-10, timing=True)
    gen = torch.Generator().manual_seed(1)
    x = torch.rand(batch, 4, generator=gen, dtype=torch.float64).to(device=device, dtype=dtype)
    times: dict[str, list[float]] = {"jacobian": [], "svd": [], "apply": []}
    for k in range(args.warmup + args.repeats):
        info = opt.step(x, x, loss_fn=osc.loss_per_sample, physics_args=(x,))
        if k >= args.warmup:
            for key in times:
                times[key].append(info.times[key])
    med = {k: statistics.median(v) for k, v in times.items()}
    med["total"] = statistics.median([sum(t) for t in zip(*times.values())])
    med["n_theta"] = opt.n_theta
    med["rows"] = batch * 4
    return med


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    """Command-line options.

    Args:
        argv: Arguments (``None``: ``sys.argv``).

    Returns:
        The parsed options.
    """
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--batch-sizes", type=int, nargs="+", default=[8, 32, 128])
    p.add_argument("--widths", type=int, nargs="+", default=[10, 20, 40])
    p.add_argument("--warmup", type=int, default=2)
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    p.add_argument("--dtype", default="float32", choices=["float32", "float64"])
    p.add_argument("--out", type=Path, default=None, help="markdown file to write (default: print only)")
    return p.parse_args(argv)


def main(argv: list[str] | None = None) -> str:
    """Run the benchmark grid and return (and optionally write) the markdown table.

    Args:
        argv: Command-line arguments (``None``: ``sys.argv``).

    Returns:
        The markdown text.
    """
    args = parse_args(argv)
    check_device(args.device)  # a bad device fails before any case runs
    rows = []
    for width in args.widths:
        for batch in args.batch_sizes:
            r = bench(batch, width, args)
            rows.append((batch, width, r))
            print(
                f"B={batch:4d} width={width:3d} n_theta={r['n_theta']:6d}  total {1e3 * r['total']:8.2f} ms",
                flush=True,
            )
    cmd = "python benchmarks/bench_hig.py " + " ".join(argv if argv is not None else sys.argv[1:])
    cpu = platform.processor() or platform.machine()
    lines = [
        "# HIG step timings",
        "",
        "Time per HIG step on the coupled-oscillator problem (24 RK4 steps as the physics, 4 outputs per",
        "sample; network `4 -> 3 x width tanh -> 24`), median of "
        f"{args.repeats} steps after {args.warmup} warm-up steps, {args.dtype}, "
        f"device `{args.device}` ({cpu}),",
        f"torch {torch.__version__}, {torch.get_num_threads()} intra-op threads.",
        "Jacobian: `vmap(jacrev(functional_call))` over the batch; SVD: thin `torch.linalg.svd` of the",
        "`(B*4) x n_theta` matrix plus the product `V diag(s^-1/2) U^T g`; apply: the SGD parameter update.",
        "",
        f"Command: `{cmd.strip()}`",
        "",
        "| batch | width | n_theta | J rows | Jacobian [ms] | SVD [ms] | apply [ms] | total [ms] |",
        "|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for batch, width, r in rows:
        lines.append(
            f"| {batch} | {width} | {r['n_theta']} | {r['rows']} | {1e3 * r['jacobian']:.2f} | "
            f"{1e3 * r['svd']:.2f} | {1e3 * r['apply']:.3f} | {1e3 * r['total']:.2f} |"
        )
    text = "\n".join(lines) + "\n"
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(text)
    print(text)
    return text


if __name__ == "__main__":
    main()
