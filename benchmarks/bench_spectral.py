"""Timings of the spectral solvers and FFT engines (median of repeats, ms), as a Markdown table.

Run: ``OMP_NUM_THREADS=1 python benchmarks/bench_spectral.py [--n 256]``. Compares, on the same
input: the zero-Dirichlet Poisson solve (phisim, pyfftw and torch engines) with the raw floor
``scipy.fft.idstn(dstn(f) / λ)``; one periodic spectral diffusion step with phisim's engines and a
plain ``numpy.fft`` round trip; FFTW with 1 and 2 threads.
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np
import scipy.fft as sfft
import torch

from phisim import fft
from phisim.diffusion import fourier_heat, heat_decay_factors
from phisim.poisson import laplacian_eigenvalues, spectral_poisson_solve


def bench(fn, repeat: int = 30) -> float:
    fn()
    times = []
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return 1e3 * statistics.median(times)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--n", type=int, default=256)
    n = ap.parse_args().n
    torch.set_num_threads(1)
    rng = np.random.default_rng(0)
    f = rng.standard_normal((1, n, n))
    t = torch.from_numpy(f)
    lam = laplacian_eigenvalues((n, n), 1.0, "dirichlet").numpy()
    rows = []
    ref = sfft.idstn(sfft.dstn(f[0], 2) / lam, 2)
    rows.append(
        (
            "Dirichlet Poisson: scipy dstn/idstn floor",
            bench(lambda: sfft.idstn(sfft.dstn(f[0], 2) / lam, 2)),
            0.0,
        )
    )
    for threads in (1, 2):
        with fft.fft_settings(threads=threads):
            for engine in fft.available_engines():
                if engine == "torch" and threads == 2:
                    continue
                u = spectral_poisson_solve(t, 1.0, "dirichlet", engine=engine)[0].numpy()
                err = np.abs(u - ref).max() / np.abs(ref).max()
                ms = bench(lambda e=engine: spectral_poisson_solve(t, 1.0, "dirichlet", engine=e))
                rows.append((f"Dirichlet Poisson: phisim {engine} (threads={threads})", ms, err))
    decay = heat_decay_factors((n, n), 8.0).numpy()
    rows.append(
        (
            "periodic heat step: numpy.fft rfft2/irfft2",
            bench(lambda: np.fft.irfft2(np.fft.rfft2(f) * decay, (n, n))),
            0.0,
        )
    )
    for engine in fft.available_engines():
        rows.append(
            (
                f"periodic heat step: phisim fourier_heat {engine}",
                bench(lambda e=engine: fourier_heat(t, 8.0, engine=e)),
                0.0,
            )
        )
    print(f"| {n}x{n}, float64 | median ms | rel. diff to scipy |")
    print("|---|---|---|")
    for name, ms, err in rows:
        print(f"| {name} | {ms:.3f} | {err:.1e} |")


if __name__ == "__main__":
    main()
