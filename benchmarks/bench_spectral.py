"""Timings of the spectral solvers and FFT engines (median of repeats, ms), as a Markdown table.

Run: ``OMP_NUM_THREADS=1 python benchmarks/bench_spectral.py [--n 256] [--device cpu]``. Compares, on the same
input: the zero-Dirichlet Poisson solve (phisim, pyfftw and torch engines) with the raw floor
``scipy.fft.idstn(dstn(f) / λ)``; one periodic spectral diffusion step with phisim's engines and a
plain ``numpy.fft`` round trip; FFTW with 1 and 2 threads. With ``--device cuda`` the phisim rows run on the GPU
with torch's FFT (synchronised around every call); the scipy and numpy floors stay on the CPU.

``--deterministic`` (CPU) instead times the default, bit-reproducible planner (``FFTW_ESTIMATE``: DCT/DST on
pocketfft, real FFTs on estimated FFTW plans) against measured plans (``FFTW_MEASURE``, the opt-in), per transform
and per solve, with the first call of each (planning included, as in a fresh process on a machine without
wisdom): the table of ``docs/BENCHMARKS.md``, "Deterministic plans".
"""

from __future__ import annotations

import argparse
import os
import sys
import time
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


def _deterministic_cases(rng: np.random.Generator) -> list[tuple[str, object]]:
    """``(name, fn)`` per case; ``fn()`` runs under the settings in force."""
    from phisim.solvers.diffusion import fourier_heat as heat

    def arr(shape, dtype):
        return torch.from_numpy(rng.standard_normal(shape)).to(dtype)

    cases: list[tuple[str, object]] = []
    for shape in ((256, 256), (512, 512)):
        x = arr(shape, torch.float64)
        cases.append((f"DCT-II 2-D {shape[0]}x{shape[1]} float64 (r2rn)",
                      lambda x=x: fft.r2rn(x, "dct2", engine="pyfftw")))
    x3 = arr((64, 64, 64), torch.float64)
    cases.append(("DST-II 3-D 64³ float64 (r2rn)", lambda: fft.r2rn(x3, "dst2", engine="pyfftw")))
    for dtype in (torch.float64, torch.float32):
        name = str(dtype).replace("torch.", "")
        for n in (256, 512):
            b = arr((1, n, n), dtype)
            cases.append((f"Dirichlet Poisson solve {n}² {name}",
                          lambda b=b: spectral_poisson_solve(b, 1.0, "dirichlet", engine="pyfftw")))
        b = arr((1, 256, 256), dtype)
        cases.append((f"Neumann Poisson solve 256² {name}",
                      lambda b=b: spectral_poisson_solve(b, 1.0, "neumann", engine="pyfftw", incompatible="project")))
        b3 = arr((1, 64, 64, 64), dtype)
        cases.append((f"Neumann Poisson solve 64³ {name}",
                      lambda b=b3: spectral_poisson_solve(b, 1.0, "neumann", engine="pyfftw", incompatible="project")))
    for shape, dtype in (((1, 256, 256), torch.float64), ((1, 256, 256), torch.float32),
                         ((1, 1024, 1024), torch.float32), ((1, 64, 64, 64), torch.float32),
                         ((1, 64, 96), torch.float32)):
        t = arr(shape, dtype)
        dims = "x".join(str(n) for n in shape[1:])
        cases.append((f"periodic heat step {dims} {str(dtype).replace('torch.', '')} (rfft/irfft)",
                      lambda t=t: heat(t, 2.0, engine="pyfftw")))
    x = arr((128, 128), torch.float64)
    cases.append(("rfftn 128² float64", lambda: fft.rfftn(x, engine="pyfftw")))
    return cases


def deterministic_plans(repeat: int) -> list[dict]:
    """Time the default (bit-reproducible) planner against measured plans; print the Markdown table.

    Measured plans are made per process here (``PHISIM_FFTW_WISDOM=off`` unless set): the first call of a case
    includes the measurement, as in a process on a machine without wisdom. Every first call starts from empty
    plan caches and an empty FFTW wisdom table.

    Args:
        repeat: Timed calls per case (median reported).

    Returns:
        One row per case: name, median and first-call ms of both planners, their ratio, and the largest
        relative difference between the two results (the same answer, other round-off).
    """
    os.environ.setdefault("PHISIM_FFTW_WISDOM", "off")
    if "pyfftw" not in fft.available_engines():
        raise SystemExit("--deterministic needs pyfftw")
    import pyfftw

    from phisim.spectral import fftw as fft_fftw

    torch.set_num_threads(1)
    rows = []
    for name, fn in _deterministic_cases(np.random.default_rng(0)):
        row: dict = {"case": name}
        results = {}
        for label, effort in (("default", "FFTW_ESTIMATE"), ("measure", "FFTW_MEASURE")):
            with fft.fft_settings(planner_effort=effort):
                fft_fftw.clear_plans()
                pyfftw.forget_wisdom()
                t0 = time.perf_counter()
                results[label] = fn()
                row[f"{label}_first_ms"] = 1e3 * (time.perf_counter() - t0)
                row[f"{label}_ms"] = 1e3 * time_fn(fn, repeats=repeat, warmup=1, min_total_s=0.2)["median_s"]
        a, b = (torch.view_as_real(r) if r.is_complex() else r for r in (results["default"], results["measure"]))
        row["ratio"] = row["default_ms"] / row["measure_ms"]
        row["rel_diff"] = float((a.double() - b.double()).abs().max() / b.double().abs().max())
        rows.append(row)
    fft_fftw.clear_plans()
    pyfftw.forget_wisdom()
    print("| case | default (ESTIMATE) ms | MEASURE ms | default / MEASURE | first call: default ms | "
          "first call: MEASURE ms | max rel. diff |")
    print("|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['case']} | {r['default_ms']:.3f} | {r['measure_ms']:.3f} | {r['ratio']:.2f} | "
              f"{r['default_first_ms']:.1f} | {r['measure_first_ms']:.1f} | {r['rel_diff']:.1e} |")
    return rows


def main(argv: list[str] | None = None) -> list[tuple[str, float, float]]:
    """Time the solves, print the Markdown table.

    Args:
        argv: ``--n`` (cells per axis), ``--repeat`` and ``--device`` (the phisim rows run there; the scipy and
            numpy floors run on the CPU), ``--deterministic`` (the planner comparison, CPU); ``None`` reads
            ``sys.argv``.

    Returns:
        The rows ``(name, median ms, relative difference to scipy)``; with ``--deterministic`` the rows of
        :func:`deterministic_plans`.

    Raises:
        ParameterError: For an unknown device or one this machine does not have.
    """
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--n", type=int, default=256)
    ap.add_argument("--repeat", type=int, default=30)
    ap.add_argument("--device", default="cpu",
                    help="torch device of the phisim rows: cpu, cuda or cuda:N (default cpu); "
                    "the scipy/numpy floors stay on the CPU")
    ap.add_argument("--deterministic", action="store_true",
                    help="time the default bit-reproducible planner against measured plans (CPU) instead")
    args = ap.parse_args(argv)
    if args.deterministic:
        check_device(args.device)
        return deterministic_plans(args.repeat)
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
