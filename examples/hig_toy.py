"""Half-inverse gradients on the toy problem of Schnell et al. (2022) (EXPERIMENTS.md, E6).

A network ``1 -> 7 tanh -> 2`` learns ``y_hat(x) = (sin 6x, cos 9x)`` for ``x in [-1, 1]`` through the
"physics" ``P(y) = (y1, lambda * y2)`` with the loss ``0.5 (y1 - y_hat1)^2 + 0.5 (lambda y2 - y_hat2)^2``.
For ``lambda = 1`` and ``lambda = 0.01`` it trains Adam, Gauss-Newton and HIG from the same initial
network on the same stream of mini-batches and records

* the validation loss (512 evenly spaced ``x``),
* the mean of the hidden tanh activations and their standard deviation over the validation inputs
  (per neuron, averaged over the 7 neurons): a saturated neuron has a spread near zero,
* the path in y-space (``P(f(x0))``) of one sample ``x0``.

``--device`` (``cpu``, ``cuda``, ``cuda:N``) places the network and the data; the mini-batches and the initial
weights are drawn on the CPU and moved, so every device trains from the same numbers.

Outputs (in ``--out``): ``hig_toy_lambda<lam>.h5`` with ``/training/<method>/{iteration, loss,
act_mean, act_std, y_path}`` and ``hig_toy_lambda<lam>.png`` (three panels).

Run:  python examples/hig_toy.py --iterations 3000 --out out/hig_toy
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import h5py
import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402

from inverse.hig import HIG, squared_error  # noqa: E402
from phisim.checks import check_device  # noqa: E402

METHODS = ("adam", "gn", "hig")
COLORS = {"adam": "tab:blue", "gn": "tab:red", "hig": "tab:green"}
LABELS = {"adam": "Adam", "gn": "Gauss-Newton", "hig": "HIG"}


def target(x: torch.Tensor) -> torch.Tensor:
    """The toy target ``(sin 6x, cos 9x)``.

    Args:
        x: Inputs of shape ``(B, 1)``.

    Returns:
        Targets of shape ``(B, 2)``.
    """
    return torch.cat([torch.sin(6 * x), torch.cos(9 * x)], dim=1)


def make_net(seed: int, dtype: torch.dtype, device: torch.device | str = "cpu") -> torch.nn.Sequential:
    """The toy network ``1 -> 7 tanh -> 2`` (PyTorch default initialisation).

    Args:
        seed: Seed of the initialisation (drawn on the CPU, so the weights are the same on every device).
        dtype: Parameter dtype.
        device: Device the network is moved to.

    Returns:
        The network.
    """
    torch.manual_seed(seed)
    return torch.nn.Sequential(torch.nn.Linear(1, 7), torch.nn.Tanh(), torch.nn.Linear(7, 2)).to(
        device=device, dtype=dtype
    )


def train(method: str, lam: float, args: argparse.Namespace) -> dict[str, np.ndarray]:
    """Train one method on the toy for one ``lambda``.

    Args:
        method: ``"adam"``, ``"gn"`` or ``"hig"``.
        lam: The output scale ``lambda``.
        args: Parsed command-line options.

    Returns:
        Curves: ``iteration``, ``loss``, ``act_mean``, ``act_std``, ``y_path`` (``(n_records, 2)``), ``time``.
    """
    dtype, device = getattr(torch, args.dtype), torch.device(args.device)
    net = make_net(args.seed, dtype, device)
    scale = torch.tensor([1.0, lam], dtype=dtype, device=device)

    def physics(out: torch.Tensor) -> torch.Tensor:
        return out * scale

    gen = torch.Generator().manual_seed(args.seed + 1)  # same batch stream for every method
    xv = torch.linspace(-1, 1, 512, dtype=dtype)[:, None].to(device)  # built on the CPU: the same on every device
    tv = target(xv)
    x0 = torch.tensor([[args.sample_x]], dtype=dtype, device=device)
    if method == "adam":
        opt = torch.optim.Adam(net.parameters(), lr=args.adam_lr)
    elif method == "gn":
        opt = HIG(net, physics=physics, lr=args.gn_lr, rcond=args.gn_rcond, exponent=1.0)
    else:
        opt = HIG(net, physics=physics, lr=args.hig_lr, rcond=args.hig_rcond, exponent=0.5)
    rec: dict[str, list] = {k: [] for k in ("iteration", "loss", "act_mean", "act_std", "y_path", "time")}
    every = max(1, args.iterations // args.records)
    t_start = time.perf_counter()

    def record(it: int) -> None:
        with torch.no_grad():
            hidden = torch.tanh(net[0](xv))
            rec["iteration"].append(it)
            rec["loss"].append(float(squared_error(physics(net(xv)), tv).mean()))
            rec["act_mean"].append(float(hidden.mean()))
            rec["act_std"].append(float(hidden.std(dim=0).mean()))  # spread over inputs, per neuron
            rec["y_path"].append(physics(net(x0))[0].tolist())
            rec["time"].append(time.perf_counter() - t_start)

    record(0)
    for it in range(1, args.iterations + 1):
        x = torch.rand(args.batch_size, 1, generator=gen, dtype=torch.float64).to(device=device, dtype=dtype) * 2 - 1
        t = target(x)
        if method == "adam":
            opt.zero_grad()
            squared_error(physics(net(x)), t).mean().backward()
            opt.step()
        else:
            opt.step(x, t)
        if it % every == 0 or it == args.iterations:
            record(it)
    return {k: np.asarray(v, dtype=np.float64) for k, v in rec.items()}


def plot(
    results: dict[str, dict[str, np.ndarray]], lam: float, sample_target: np.ndarray, path: Path
) -> None:
    """Three panels: validation loss, hidden activation mean +- std, y-space path of one sample.

    Args:
        results: Curves per method (from :func:`train`).
        lam: The output scale (for the title).
        sample_target: ``y_hat(x0)`` of the tracked sample, shape ``(2,)``.
        path: PNG file to write.
    """
    fig, ax = plt.subplots(1, 3, figsize=(12, 3.4))
    for m, r in results.items():
        ax[0].semilogy(r["iteration"], r["loss"], color=COLORS[m], label=LABELS[m])
        ax[1].plot(r["iteration"], r["act_mean"], color=COLORS[m], label=LABELS[m])
        ax[1].fill_between(
            r["iteration"],
            r["act_mean"] - r["act_std"],
            r["act_mean"] + r["act_std"],
            color=COLORS[m],
            alpha=0.2,
        )
        ax[2].plot(r["y_path"][:, 0], r["y_path"][:, 1], ".-", color=COLORS[m], ms=2, lw=0.8, label=LABELS[m])
    first = next(iter(results.values()))
    ax[2].plot(*first["y_path"][0], "o", color="lightgray", ms=8, label="start")
    ax[2].plot(*sample_target, "ko", ms=6, label="target")
    ax[0].set(xlabel="iteration", ylabel="validation loss", title=f"loss, lambda = {lam:g}")
    ax[1].set(xlabel="iteration", ylabel="tanh activation", title="hidden tanh: mean +- spread over inputs")
    ax[2].set(xlabel="y1", ylabel="lambda * y2", title="y-space path of one sample")
    for a in ax:
        a.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    """Command-line options.

    Args:
        argv: Arguments (``None``: ``sys.argv``).

    Returns:
        The parsed options.

    Raises:
        ParameterError: For an unknown device or one this machine does not have.
    """
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--iterations", type=int, default=3000, help="training steps per method")
    p.add_argument("--out", type=Path, default=Path("out/hig_toy"), help="output directory")
    p.add_argument("--lambdas", type=float, nargs="+", default=[1.0, 0.01])
    p.add_argument("--methods", nargs="+", default=list(METHODS), choices=METHODS)
    p.add_argument("--batch-size", type=int, default=256)
    p.add_argument("--adam-lr", type=float, default=0.01)
    p.add_argument("--gn-lr", type=float, default=1.0)
    p.add_argument("--gn-rcond", type=float, default=1e-3)
    p.add_argument("--hig-lr", type=float, default=1.0)
    p.add_argument("--hig-rcond", type=float, default=1e-6)
    p.add_argument("--records", type=int, default=200, help="number of recorded points per curve")
    p.add_argument("--sample-x", type=float, default=0.3, help="x of the sample whose y-path is drawn")
    p.add_argument("--dtype", default="float32", choices=["float32", "float64"])
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--device", default="cpu", help="torch device: cpu, cuda or cuda:N (default cpu)")
    args = p.parse_args(argv)
    if args.iterations < 1 or args.batch_size < 1 or args.records < 1:
        p.error("--iterations, --batch-size and --records must be >= 1")
    args.device = str(check_device(args.device))
    return args


def main(argv: list[str] | None = None) -> dict[float, dict[str, float]]:
    """Run the toy comparison and write HDF5 curves and PNG figures.

    Args:
        argv: Command-line arguments (``None``: ``sys.argv``).

    Returns:
        Final validation loss per ``lambda`` and method.
    """
    args = parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    finals: dict[float, dict[str, float]] = {}
    for lam in args.lambdas:
        results = {}
        for m in args.methods:
            results[m] = train(m, lam, args)
            print(
                f"lambda={lam:g} {LABELS[m]:>12}: final loss {results[m]['loss'][-1]:.3e} "
                f"act std {results[m]['act_std'][-1]:.3f} ({results[m]['time'][-1]:.1f} s)",
                flush=True,
            )
        finals[lam] = {m: float(r["loss"][-1]) for m, r in results.items()}
        x0 = torch.tensor([[args.sample_x]], dtype=torch.float64)
        sample_target = target(x0)[0].numpy()
        stem = f"hig_toy_lambda{lam:g}"
        with h5py.File(args.out / f"{stem}.h5", "w") as f:
            f.attrs["dataset_name"] = "hig_toy"
            f.attrs["lambda"] = lam
            f.attrs["device"] = args.device
            f.create_dataset("extras/config", data=json.dumps({k: str(v) for k, v in vars(args).items()}))
            f.create_dataset("extras/sample_target", data=sample_target)
            for m, r in results.items():
                g = f.create_group(f"training/{m}")
                for k, v in r.items():
                    g.create_dataset(k, data=v)
        plot(results, lam, sample_target, args.out / f"{stem}.png")
    return finals


if __name__ == "__main__":
    main()
