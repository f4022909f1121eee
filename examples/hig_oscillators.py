"""Control of linear coupled oscillators with half-inverse gradients (EXPERIMENTS.md, E6; pbdl-book).

Two masses with positions ``x`` and velocities ``v`` evolve by ``x' = v``,
``v' = -x + 0.2 * Lap x + u(t) * delta_last`` (``Lap``: the 1-D Laplacian with zero-flux ends,
``[[-1, 1], [1, -1]]`` for two masses; the control acts on the last mass), integrated with 24 RK4 steps
of ``dt = 0.5``. A network ``4 -> 3 x 20 tanh -> 24`` receives the target state and outputs the
24 control values; the target is the initial state (return to the start). The loss of a sample is
``sum((state_T - state_0)^2)``; the reported loss is its mean over the training set (loss per sample).

Methods: HIG (SGD lr 1, batch 32, rcond 1e-10), Adam (lr 1e-3, batch 256), Gauss-Newton (lr 1,
batch 32, rcond 1e-10). Each trains from the same initial network on the same 4096 random states for
``--epochs`` epochs or until ``--max-time`` seconds of training have passed.

``--device`` (``cpu``, ``cuda``, ``cuda:N``) places the network, the data and the physics; the data and the
initial weights are drawn on the CPU and moved, so every device starts from the same numbers.

Outputs (in ``--out``): ``hig_oscillators.h5`` with ``/training/<method>/{epoch, time, loss}`` and
``hig_oscillators.png`` (loss per sample over wall-clock time).

Run:  python examples/hig_oscillators.py --max-time 100 --out out/hig_oscillators
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

from inverse.hig import HIG  # noqa: E402
from phisim.checks import check_device  # noqa: E402
from phisim.errors import PhisimError  # noqa: E402

N_OSC = 2
N_STEPS = 24
DT = 0.5
COUPLING = 0.2
METHODS = ("hig", "adam", "gn")
COLORS = {"adam": "tab:blue", "gn": "tab:red", "hig": "tab:green"}
LABELS = {"adam": "Adam", "gn": "Gauss-Newton", "hig": "HIG"}


def laplacian(n: int) -> torch.Tensor:
    """1-D Laplacian of ``n`` masses with zero-flux ends (``-1`` on the end diagonal entries).

    Args:
        n: Number of masses (>= 1).

    Returns:
        ``(n, n)`` float64 matrix.
    """
    if n == 1:
        return torch.zeros(1, 1, dtype=torch.float64)
    lap = (
        -2 * torch.eye(n, dtype=torch.float64)
        + torch.diag(torch.ones(n - 1), 1)
        + torch.diag(torch.ones(n - 1), -1)
    )
    lap[0, 0] = lap[-1, -1] = -1
    return lap


def system_matrix(n: int) -> torch.Tensor:
    """The matrix ``A`` of the free motion ``s' = A s`` of ``state = (x_1..x_n, v_1..v_n)``.

    Args:
        n: Number of masses (>= 1).

    Returns:
        ``(2n, 2n)`` float64 matrix: ``x' = v``, ``v' = (-I + COUPLING * Lap) x``.
    """
    A = torch.zeros(2 * n, 2 * n, dtype=torch.float64)
    A[:n, n:] = torch.eye(n, dtype=torch.float64)
    A[n:, :n] = -torch.eye(n, dtype=torch.float64) + COUPLING * laplacian(n)
    return A


def rhs(state: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
    """Time derivative of ``state = (x_1..x_n, v_1..v_n)`` with the control ``u`` on the last mass.

    Args:
        state: ``(B, 2n)``.
        u: ``(B,)`` control values.

    Returns:
        ``(B, 2n)`` derivative.
    """
    n = state.shape[1] // 2
    x, v = state[:, :n], state[:, n:]
    acc = -x + COUPLING * x @ laplacian(n).to(state)
    acc = torch.cat([acc[:, :-1], acc[:, -1:] + u[:, None]], dim=1)
    return torch.cat([v, acc], dim=1)


_STEP_CACHE: dict[tuple, tuple[torch.Tensor, torch.Tensor]] = {}


def rk4_step_operators(n: int, dtype: torch.dtype, device: torch.device | str = "cpu"
                       ) -> tuple[torch.Tensor, torch.Tensor]:
    """The classical RK4 step of ``DT`` as a linear map, built once per ``(n, dtype, device)`` and cached.

    The system is linear with the control held constant within a step, so one RK4 step is exactly
    ``s_new = s @ Mt + u * c`` with ``M = I + h + h^2/2 + h^3/6 + h^4/24`` (``h = DT A``) and
    ``c = DT (I + h/2 + h^2/6 + h^3/24) b`` (``b`` the unit vector of the last velocity). Both are computed
    in float64 and cast once, so the training loop does no per-stage operator assembly.

    Args:
        n: Number of masses.
        dtype: dtype of the returned operators.
        device: Their device.

    Returns:
        ``(Mt, c)``: ``M`` transposed ``(2n, 2n)`` (for row-vector states) and ``c`` of shape ``(2n,)``.
    """
    key = (n, dtype, str(device))
    if key not in _STEP_CACHE:
        h = DT * system_matrix(n)
        eye = torch.eye(2 * n, dtype=torch.float64)
        h2 = h @ h
        h3 = h2 @ h
        M = eye + h + h2 / 2 + h3 / 6 + h3 @ h / 24
        b = torch.zeros(2 * n, dtype=torch.float64)
        b[-1] = 1.0
        c = DT * (eye + h / 2 + h2 / 6 + h3 / 24) @ b
        _STEP_CACHE[key] = (M.mT.contiguous().to(device=device, dtype=dtype), c.to(device=device, dtype=dtype))
    return _STEP_CACHE[key]


def simulate(controls: torch.Tensor, state0: torch.Tensor) -> torch.Tensor:
    """Integrate ``N_STEPS`` classical RK4 steps of ``DT`` with one control value per step.

    Uses the cached step operators of :func:`rk4_step_operators` (identical to evaluating the four RK4
    stages of :func:`rhs`, up to round-off).

    Args:
        controls: ``(B, N_STEPS)``, held constant within each step.
        state0: ``(B, 2n)`` initial states.

    Returns:
        ``(B, 2n)`` final states.
    """
    Mt, c = rk4_step_operators(state0.shape[1] // 2, state0.dtype, state0.device)
    s = state0
    for k in range(controls.shape[1]):
        s = s @ Mt + controls[:, k : k + 1] * c
    return s


def simulate_stages(controls: torch.Tensor, state0: torch.Tensor) -> torch.Tensor:
    """The same integration as :func:`simulate`, evaluating the four RK4 stages of :func:`rhs` every step.

    Kept as the reference that :func:`simulate` is tested against (and for benchmarks).

    Args:
        controls: ``(B, N_STEPS)``, held constant within each step.
        state0: ``(B, 2n)`` initial states.

    Returns:
        ``(B, 2n)`` final states.
    """
    s = state0
    for k in range(controls.shape[1]):
        u = controls[:, k]
        k1 = rhs(s, u)
        k2 = rhs(s + 0.5 * DT * k1, u)
        k3 = rhs(s + 0.5 * DT * k2, u)
        k4 = rhs(s + DT * k3, u)
        s = s + DT / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
    return s


def loss_per_sample(y: torch.Tensor, targets: torch.Tensor) -> torch.Tensor:
    """``sum((y - targets)^2)`` per sample (the reference's loss, without the factor 1/2).

    Args:
        y: ``(B, 2n)`` final states.
        targets: ``(B, 2n)`` target states.

    Returns:
        ``(B,)`` losses.
    """
    return (y - targets).pow(2).sum(dim=1)


def make_net(seed: int, dtype: torch.dtype, device: torch.device | str = "cpu") -> torch.nn.Sequential:
    """The control network ``4 -> 3 x 20 tanh -> 24``.

    Args:
        seed: Seed of the initialisation (drawn on the CPU, so the weights are the same on every device).
        dtype: Parameter dtype.
        device: Device the network is moved to.

    Returns:
        The network.
    """
    torch.manual_seed(seed)
    w = 2 * N_OSC
    return torch.nn.Sequential(
        torch.nn.Linear(w, 20),
        torch.nn.Tanh(),
        torch.nn.Linear(20, 20),
        torch.nn.Tanh(),
        torch.nn.Linear(20, 20),
        torch.nn.Tanh(),
        torch.nn.Linear(20, N_STEPS),
    ).to(device=device, dtype=dtype)


def evaluate(net: torch.nn.Module, data: torch.Tensor) -> float:
    """Mean loss per sample over ``data`` (states that are both the start and the target).

    Args:
        net: The control network.
        data: ``(N, 2n)`` states.

    Returns:
        The loss per sample.
    """
    with torch.no_grad():
        return float(loss_per_sample(simulate(net(data), data), data).mean())


def train(method: str, data: torch.Tensor, args: argparse.Namespace) -> dict[str, np.ndarray]:
    """Train one method for ``--epochs`` epochs or ``--max-time`` seconds (evaluation time excluded).

    Args:
        method: ``"hig"``, ``"adam"`` or ``"gn"``.
        data: ``(N, 2n)`` training states (their device and dtype are the training's).
        args: Parsed options.

    Returns:
        Curves ``epoch``, ``time`` (training seconds) and ``loss`` (per sample, whole training set).
    """
    net = make_net(args.seed, data.dtype, data.device)
    sync = torch.cuda.synchronize if data.device.type == "cuda" else (lambda: None)
    if method == "adam":
        opt = torch.optim.Adam(net.parameters(), lr=args.adam_lr)
        batch = args.adam_batch_size
    else:
        exponent = 0.5 if method == "hig" else 1.0
        opt = HIG(
            net, physics=lambda c, s0: simulate(c, s0), lr=args.hig_lr, rcond=args.rcond, exponent=exponent
        )
        batch = args.hig_batch_size
    curves = {"epoch": [0], "time": [0.0], "loss": [evaluate(net, data)]}
    elapsed = 0.0
    for epoch in range(1, args.epochs + 1):
        sync()
        t0 = time.perf_counter()
        failed = False
        for start in range(0, data.shape[0] - batch + 1, batch):
            xb = data[start : start + batch]
            if method == "adam":
                opt.zero_grad()
                loss_per_sample(simulate(net(xb), xb), xb).mean().backward()
                opt.step()
            else:
                try:
                    opt.step(xb, xb, loss_fn=loss_per_sample, physics_args=(xb,))
                except PhisimError as err:  # e.g. a diverged Gauss-Newton run: record and stop
                    print(f"{LABELS[method]} stopped in epoch {epoch}: {err}", flush=True)
                    failed = True
                    break
        sync()  # queued GPU work belongs to this epoch's training time
        elapsed += time.perf_counter() - t0
        loss = evaluate(net, data)
        curves["epoch"].append(epoch)
        curves["time"].append(elapsed)
        curves["loss"].append(loss)
        print(f"{LABELS[method]:>12} epoch {epoch:4d}  {elapsed:7.1f} s  loss/sample {loss:.3e}", flush=True)
        if failed or not np.isfinite(loss) or elapsed >= args.max_time:
            break
    return {k: np.asarray(v, dtype=np.float64) for k, v in curves.items()}


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
    p.add_argument("--epochs", type=int, default=10_000, help="maximum epochs per method")
    p.add_argument("--max-time", type=float, default=100.0, help="training seconds per method")
    p.add_argument("--out", type=Path, default=Path("out/hig_oscillators"), help="output directory")
    p.add_argument("--methods", nargs="+", default=list(METHODS), choices=METHODS)
    p.add_argument("--n-train", type=int, default=4096, help="number of training states")
    p.add_argument("--hig-batch-size", type=int, default=32)
    p.add_argument("--hig-lr", type=float, default=1.0)
    p.add_argument("--rcond", type=float, default=1e-10)
    p.add_argument("--adam-batch-size", type=int, default=256)
    p.add_argument("--adam-lr", type=float, default=1e-3)
    p.add_argument("--dtype", default="float32", choices=["float32", "float64"])
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--device", default="cpu", help="torch device: cpu, cuda or cuda:N (default cpu)")
    args = p.parse_args(argv)
    if args.epochs < 1 or args.n_train < max(args.hig_batch_size, args.adam_batch_size):
        p.error("--epochs must be >= 1 and --n-train at least the largest batch size")
    args.device = str(check_device(args.device))
    return args


def main(argv: list[str] | None = None) -> dict[str, float]:
    """Train the compared methods, write HDF5 curves and a PNG plot.

    Args:
        argv: Command-line arguments (``None``: ``sys.argv``).

    Returns:
        Final loss per sample per method.
    """
    args = parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    dtype = getattr(torch, args.dtype)
    gen = torch.Generator().manual_seed(args.seed + 1)
    data = torch.rand(args.n_train, 2 * N_OSC, generator=gen, dtype=torch.float64).to(device=args.device, dtype=dtype)
    results = {m: train(m, data, args) for m in args.methods}
    with h5py.File(args.out / "hig_oscillators.h5", "w") as f:
        f.attrs["dataset_name"] = "hig_oscillators"
        f.attrs["device"] = args.device
        f.create_dataset("extras/config", data=json.dumps({k: str(v) for k, v in vars(args).items()}))
        for m, r in results.items():
            g = f.create_group(f"training/{m}")
            for k, v in r.items():
                g.create_dataset(k, data=v)
    fig, ax = plt.subplots(figsize=(5, 3.4))
    for m, r in results.items():
        ax.semilogy(r["time"], r["loss"], ".-", color=COLORS[m], label=LABELS[m])
    ax.set(xlabel="training time [s]", ylabel="loss per sample", title="coupled oscillators")
    ax.legend()
    fig.tight_layout()
    fig.savefig(args.out / "hig_oscillators.png", dpi=80)
    plt.close(fig)
    return {m: float(r["loss"][-1]) for m, r in results.items()}


if __name__ == "__main__":
    main()
