"""Throughput of ``phisim simulate``: trajectories per second with 1 and N worker processes.

Run: ``python benchmarks/bench_simulate.py [--scenario smoke] [--workers 2] [--trajectories 8]``.
Each configuration writes a fresh dataset folder in a temporary directory (simulation, HDF5 writing and
the statistics file included) and reports the wall time; the JSON line goes to stdout and, with
``--out``, to a file. The speed-up is bounded by the free cores of the machine (each worker gets
``cpu_count // workers`` torch threads).
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
from pathlib import Path

from phisim.simulate import resolve_config, simulate_dataset


def measure(scenario: str, workers: int, trajectories: int, resolution: int, steps: int) -> float:
    """Wall seconds of one dataset with ``trajectories`` trajectories, one per file."""
    cfg = resolve_config(scenario, trajectories=trajectories, trajectories_per_file=1, resolution=resolution,
                         steps=steps)
    with tempfile.TemporaryDirectory() as tmp:
        t = time.perf_counter()
        simulate_dataset(Path(tmp) / "ds", cfg, workers=workers, progress=False)
        return time.perf_counter() - t


def main() -> None:
    """Measure and print one JSON line per worker count."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scenario", default="smoke")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--trajectories", type=int, default=8)
    ap.add_argument("--resolution", type=int, default=32)
    ap.add_argument("--steps", type=int, default=40)
    ap.add_argument("--out", type=Path, default=None)
    a = ap.parse_args()
    rows = []
    for w in sorted({1, a.workers}):
        s = measure(a.scenario, w, a.trajectories, a.resolution, a.steps)
        rows.append({"scenario": a.scenario, "workers": w, "trajectories": a.trajectories,
                     "resolution": a.resolution, "steps": a.steps, "seconds": round(s, 3),
                     "trajectories_per_s": round(a.trajectories / s, 3), "cpu_count": os.cpu_count()})
        print(json.dumps(rows[-1]), flush=True)
    if a.out is not None:
        a.out.write_text(json.dumps(rows, indent=1) + "\n")


if __name__ == "__main__":
    main()
