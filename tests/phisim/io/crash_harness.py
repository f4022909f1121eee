"""Kill a tight append loop (SimulationWriter + TrainingLog) at random moments and check what survives.

Used by ``tests/phisim/io/test_crash_safety.py`` and ``benchmarks/bench_reliability.py``. The writer runs in
a forked child (no interpreter start per kill), reports every completed append through a pipe, and is
killed with SIGKILL after a random delay; the parent then reads the file back.
"""

from __future__ import annotations

import os
import random
import signal
import struct
import time
import warnings
from pathlib import Path

import numpy as np

from phisim.errors import PhisimError
from phisim.grid import Grid
from phisim.io import SimulationWriter, TrainingLog, read_simulation, read_training

GRID = Grid((12, 10))
B = 2


def frame_values(k: int) -> dict:
    """Frame ``k``: every value encodes ``k`` exactly (float32-representable)."""
    rho = np.full((B, *GRID.resolution), float(k), dtype=np.float32)
    rho[1] = -k
    v = tuple(np.full((B, *GRID.face_shape(a)), float(k) + 0.5 * a, dtype=np.float32) for a in range(2))
    return {"rho": rho, "v": v}


def _child(path: Path, mode: str, journal: bool, w: int) -> None:
    if mode == "simulation":
        writer = SimulationWriter(path, GRID, "wall", dataset_name="kill", fields={"rho": "scalar", "v": "staggered"},
                                  batch_size=B, journal=journal, compression_level=1)
        log = writer.training_log("adam")
    else:
        writer = None
        log = TrainingLog(path, "adam")
    os.write(w, b"R")
    k = 0
    while True:
        if writer is not None:
            writer.append(float(k), **frame_values(k))
            os.write(w, b"F" + struct.pack("<i", k))
        log.append(k, loss=float(k), metric=-0.5 * k)
        os.write(w, b"L" + struct.pack("<i", k))
        k += 1


def kill_once(path: Path, mode: str = "simulation", *, journal: bool = True, max_delay: float = 0.05,
              rng: random.Random | None = None) -> tuple[int, int]:
    """Run the loop in a forked child, SIGKILL it after a random delay; returns (frames done, records done)."""
    rng = rng or random.Random()
    r, w = os.pipe()
    pid = os.fork()
    if pid == 0:  # pragma: no cover - child
        os.close(r)
        try:
            _child(path, mode, journal, w)
        finally:
            os._exit(0)
    os.close(w)
    data = b""
    try:
        first = os.read(r, 1)
        if first != b"R":
            raise RuntimeError("the writer did not start")
        # Let a random number of iterations complete, then kill at a random moment within the next one or
        # two (scaled by the measured iteration time, so the kills land mid-loop on a busy machine too).
        t0 = time.perf_counter()
        target = rng.randint(0, 4)
        done = 0
        while done < target:
            chunk = os.read(r, 5)
            if not chunk:
                break
            data += chunk
            done += chunk[:1] == b"L"
        per_iteration = (time.perf_counter() - t0) / done if done else max_delay
        time.sleep(rng.uniform(0.0, 1.5 * per_iteration))
        os.kill(pid, signal.SIGKILL)
    finally:
        os.waitpid(pid, 0)
    while chunk := os.read(r, 65536):
        data += chunk
    os.close(r)
    frames = records = -1
    for i in range(0, len(data) - len(data) % 5, 5):
        tag, (k,) = data[i:i + 1], struct.unpack("<i", data[i + 1:i + 5])
        if tag == b"F":
            frames = k
        elif tag == b"L":
            records = k
    return frames + 1, records + 1


def check_file(path: Path, mode: str, frames_done: int, records_done: int) -> str | None:
    """None if the file yields every completed frame/record with the right values and nothing wrong, else why."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            if mode == "simulation":
                d = read_simulation(path)
                if d.n_frames < frames_done:
                    return f"{d.n_frames} frames read, {frames_done} completed"
                for k in range(d.n_frames):
                    exp = frame_values(k)
                    if d.times[k] != k or not np.array_equal(d.fields["rho"][:, k], exp["rho"]):
                        return f"frame {k} has wrong values"
                    if not all(np.array_equal(d.staggered["v"][a][:, k], exp["v"][a]) for a in range(2)):
                        return f"frame {k} has wrong face values"
                logs = d.training
            else:
                logs = read_training(path)
        except PhisimError as exc:
            return f"unreadable: {exc}"
    curves = logs.get("adam")
    n = 0 if curves is None else len(curves["iteration"])
    if n < records_done:
        return f"{n} training records read, {records_done} completed"
    if n and not (np.array_equal(curves["iteration"], np.arange(n)) and np.array_equal(curves["loss"], np.arange(n))
                  and np.array_equal(curves["metric"], -0.5 * np.arange(n))):
        return "training records with wrong values"
    return None
