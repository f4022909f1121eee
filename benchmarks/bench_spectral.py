"""Timings of the spectral solvers and FFT engines (median of repeats, ms), as a Markdown table.

Run: ``OMP_NUM_THREADS=1 python benchmarks/bench_spectral.py [--n 256] [--device cpu]``. Compares, on the same
input: the zero-Dirichlet Poisson solve (phisim, pyfftw and torch engines) with the raw floor
``scipy.fft.idstn(dstn(f) / λ)``; one periodic spectral diffusion step with phisim's engines and a
plain ``numpy.fft`` round trip; FFTW with 1 and 2 threads. With ``--device cuda`` the phisim rows run on the GPU
with torch's FFT (synchronised around every call); the scipy and numpy floors stay on the CPU.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import scipy.fft as sfft
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from timing import time_fn  # noqa: E402

from phisim.checks import check_device  # noqa: E402
from phisim.solvers.diffusion import fourier_heat, heat_decay_factors  # noqa: E402
from phisim.solvers.poisson import laplacian_eigenvalues, spectral_poisson_solve  # noqa: E402
from phisim.spectral import fft  # noqa: E402


def engines_for(device: torch.device) -> tuple[str, ...]:
    """The FFT engines that run on ``device`` (pyfftw is CPU-only; torch's runs everywhere).

    Args:
        device: The torch device of the inputs.

    Returns:
        Engine names, as :func:`phisim.spectral.fft.available_engines` gives them.
    """
    return fft.available_engines() if device.type == "cpu" else ("torch",)


def main(argv: list[str] | None = None) -> list[tuple[str, float, float]]:
    """Time the solves, print the Markdown table.

    Args:
        argv: ``--n`` (cells per axis), ``--repeat`` and ``--device`` (the phisim rows run there; the scipy and
            numpy floors run on the CPU); ``None`` reads ``sys.argv``.

    Returns:
        The rows ``(name, median ms, relative difference to scipy)``.

    Raises:
        ParameterError: For an unknown device or one this machine does not have.
    """
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--n", type=int, default=256)
    ap.add_argument("--repeat", type=int, default=30)
    ap.add_argument("--device", default="cpu",
                    help="torch device of the phisim rows: cpu, cuda or cuda:N (default cpu); "
                    "the scipy/numpy floors stay on the CPU")
    args = ap.parse_args(argv)
    n, repeat, device = args.n, args.repeat, check_device(args.device)
    torch.set_num_threads(1)
    rng = np.random.default_rng(0)
    f = rng.standard_normal((1, n, n))
    t = torch.from_numpy(f).to(device)

    def bench(fn) -> float:
        return 1e3 * time_fn(fn, repeats=repeat, warmup=1, device=device)["median_s"]

    lam = laplacian_eigenvalues((n, n), 1.0, "dirichlet").numpy()
    rows = []
    ref = sfft.idstn(sfft.dstn(f[0], 2) / lam, 2)
    rows.append(
        (
            "Dirichlet Poisson: scipy dstn/idstn floor (CPU)",
            bench(lambda: sfft.idstn(sfft.dstn(f[0], 2) / lam, 2)),
            0.0,
        )
    )
    for threads in (1, 2) if device.type == "cpu" else (1,):  # FFTW threads mean nothing off the CPU
        with fft.fft_settings(threads=threads):
            for engine in engines_for(device):
                if engine == "torch" and threads == 2:
                    continue
                u = spectral_poisson_solve(t, 1.0, "dirichlet", engine=engine)[0].cpu().numpy()
                err = np.abs(u - ref).max() / np.abs(ref).max()
                ms = bench(lambda e=engine: spectral_poisson_solve(t, 1.0, "dirichlet", engine=e))
                where = f"threads={threads}" if device.type == "cpu" else str(device)
                rows.append((f"Dirichlet Poisson: phisim {engine} ({where})", ms, err))
    decay = heat_decay_factors((n, n), 8.0).numpy()
    rows.append(
        (
            "periodic heat step: numpy.fft rfft2/irfft2 (CPU)",
            bench(lambda: np.fft.irfft2(np.fft.rfft2(f) * decay, (n, n))),
            0.0,
        )
    )
    heat_ref = np.fft.irfft2(np.fft.rfft2(f) * decay, (n, n))
    for engine in engines_for(device):
        u = fourier_heat(t, 8.0, engine=engine).cpu().numpy()
        rows.append(
            (
                f"periodic heat step: phisim fourier_heat {engine} ({device})",
                bench(lambda e=engine: fourier_heat(t, 8.0, engine=e)),
                float(np.abs(u - heat_ref).max() / np.abs(heat_ref).max()),
            )
        )
    print(f"| {n}x{n}, float64, device {device} | median ms | rel. diff to the CPU floor |")
    print("|---|---|---|")
    for name, ms, err in rows:
        print(f"| {name} | {ms:.3f} | {err:.1e} |")
    return rows


if __name__ == "__main__":
    main()
