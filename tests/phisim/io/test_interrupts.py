"""Prompt interrupts: SIGINT/SIGTERM stop `phisim simulate --workers N` and training within 2 s, leave only
complete files under final names, and a rerun resumes to the same bits as an uninterrupted run."""

from __future__ import annotations

import os
import signal
import warnings
from pathlib import Path

import h5py
import numpy as np
import pytest
import torch

from phisim.errors import IncompleteFileWarning
from phisim.io import interrupts, read_simulation, read_training
from phisim.io.journal import journal_path

pytestmark = pytest.mark.skipif(os.name != "posix" or not Path("/proc").is_dir(), reason="POSIX signals, /proc")

#: The bound asserted: the process has exited this long after the signal (the target is "within 2 s").
LATENCY_BOUND = 2.0

SIM_ARGS = ["simulate", "heat", "--trajectories", "3", "--trajectories-per-file", "1", "--steps", "4000",
            "--set", "save_every=200", "--resolution", "32", "--quiet"]
FRAMES = 4000 // 200 + 1


def _files(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def _leftovers(root: Path) -> list[Path]:
    return [p for p in root.rglob("*") if p.suffix in (".part", ".journal", ".tmp")
            or p.name.endswith((".part.journal", ".recover.tmp"))]


@pytest.mark.parametrize("sig", [signal.SIGINT, pytest.param(signal.SIGTERM, marks=pytest.mark.slow)],
                         ids=["SIGINT", "SIGTERM"])
def test_simulate_with_workers_stops_promptly_and_resumes_bit_for_bit(tmp_path, interrupt, wait_gone, python, sig):
    root = tmp_path / "d"
    data = root / "data"

    def ready():  # a file finished and another one being written
        return data.is_dir() and any(data.rglob("*.h5")) and any(data.rglob("*.h5.part"))

    r = interrupt(["-m", "inverse.cli", *SIM_ARGS, "--workers", "2", "--out", str(root)], ready, cwd=tmp_path,
                  sig=sig)
    print(f"simulate --workers 2, {signal.Signals(sig).name}: exited {r.latency:.3f} s after the signal")
    assert r.returncode == 128 + sig, r.stderr
    assert "phisim: interrupted" in r.stderr and "Traceback" not in r.stderr and "leaked" not in r.stderr, r.stderr
    assert r.latency < LATENCY_BOUND, f"{r.latency:.2f} s from the signal to the exit"
    assert len(r.children) >= 2 and wait_gone(r.children) == []  # the workers were stopped too
    assert _leftovers(root) == []
    finished = sorted(data.rglob("*.h5"))
    assert 1 <= len(finished) < 3
    for p in finished:  # every file under its final name is complete and clean
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            assert read_simulation(p).n_frames == FRAMES
    assert not (root / "stats.yaml").exists()

    rerun = python(["-m", "inverse.cli", *SIM_ARGS, "--workers", "2", "--out", str(root)], cwd=tmp_path)
    assert rerun.returncode == 0 and '"skipped": ' + str(len(finished)) in rerun.stdout, rerun.stderr  # continues
    ref = tmp_path / "ref"
    done = python(["-m", "inverse.cli", *SIM_ARGS, "--workers", "1", "--out", str(ref)], cwd=tmp_path)
    assert done.returncode == 0, done.stderr  # uninterrupted
    got, want = _files(root), _files(ref)
    assert sorted(got) == sorted(want) and "stats.yaml" in got
    assert [k for k in want if got[k] != want[k]] == []


TRAIN_ARGS = ["train", "sine", "adam", "--iterations", "40", "--batch-size", "2000", "--checkpoint-every", "8",
              "--eval-every", "8", "--quiet"]


@pytest.mark.parametrize("sig", [signal.SIGINT, pytest.param(signal.SIGTERM, marks=pytest.mark.slow)],
                         ids=["SIGINT", "SIGTERM"])
def test_training_stops_promptly_is_marked_incomplete_and_resumes_bit_for_bit(tmp_path, interrupt, python, sig):
    out = tmp_path / "run.h5"
    ckpt = tmp_path / "run.h5.adam.ckpt"

    r = interrupt(["-m", "inverse.cli", *TRAIN_ARGS, "--out", str(out)], ckpt.exists, cwd=tmp_path, sig=sig)
    print(f"phisim train, {signal.Signals(sig).name}: exited {r.latency:.3f} s after the signal")
    assert r.returncode == 128 + sig, r.stderr
    assert "phisim: interrupted" in r.stderr and "Traceback" not in r.stderr, r.stderr
    assert r.latency < LATENCY_BOUND, f"{r.latency:.2f} s from the signal to the exit"
    # the log was closed cleanly: no journal, no temporary checkpoint, no model file of an unfinished run
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run.h5", "run.h5.adam.ckpt"]
    with pytest.warns(IncompleteFileWarning, match=r"adam: INCOMPLETE: stopped after \d+ of 40 iterations"):
        log = read_training(out)["adam"]
    assert log.complete is False and log.planned == 40 and 8 <= log.records < 40
    np.testing.assert_array_equal(log["iteration"], np.arange(log.records))
    assert torch.load(ckpt, weights_only=False)["iteration"] % 8 == 0

    from inverse.cli import describe_file, main

    assert f"run adam: INCOMPLETE: stopped after {log.records} of 40 iterations" in describe_file(out)
    assert main([*TRAIN_ARGS, "--out", str(out)]) == 2  # without --resume the run is refused
    resumed = python(["-m", "inverse.cli", *TRAIN_ARGS, "--out", str(out), "--resume"], cwd=tmp_path)
    assert resumed.returncode == 0, resumed.stderr
    ref = tmp_path / "ref.h5"
    done = python(["-m", "inverse.cli", *TRAIN_ARGS, "--out", str(ref)], cwd=tmp_path)  # uninterrupted
    assert done.returncode == 0, done.stderr
    got, want = read_training(out)["adam"], read_training(ref)["adam"]
    assert got.complete and want.complete and got.records == 40
    for name in ("iteration", "loss", "metric", "objective", "eval_loss", "eval_metric"):
        np.testing.assert_array_equal(got[name], want[name], err_msg=name)
    a = torch.load(tmp_path / "run.h5.adam.model.pt", weights_only=False)
    b = torch.load(tmp_path / "ref.h5.adam.model.pt", weights_only=False)
    for k, v in b["state_dict" if "state_dict" in b else "model"].items():
        assert torch.equal(a["state_dict" if "state_dict" in a else "model"][k], v), k


# ---- the mechanism, in process ---------------------------------------------------------------------------


def test_uninterrupted_defers_a_signal_to_the_end_of_the_block():
    events = []
    with pytest.raises(KeyboardInterrupt):
        with interrupts.uninterrupted():
            signal.raise_signal(signal.SIGINT)
            events.append("block finished")
    assert events == ["block finished"]
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler


def test_interruptible_turns_sigterm_into_an_exception_and_restores_the_handler():
    old = signal.getsignal(signal.SIGTERM)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    try:
        with pytest.raises(interrupts.Interrupted) as e:
            with interrupts.interruptible():
                signal.raise_signal(signal.SIGTERM)
        assert e.value.signum == signal.SIGTERM and isinstance(e.value, KeyboardInterrupt)
        assert signal.getsignal(signal.SIGTERM) is signal.SIG_DFL
    finally:
        signal.signal(signal.SIGTERM, old)


def test_interrupt_during_a_record_leaves_a_consistent_log(tmp_path, monkeypatch):
    """A signal arriving inside TrainingLog.append is delivered after the record is complete."""
    from phisim.io import TrainingLog

    path = tmp_path / "log.h5"
    log = TrainingLog(path, "adam", planned_iterations=5)
    real_write = log._write

    def write_with_signal(iteration, nums):
        signal.raise_signal(signal.SIGINT)  # between the journal record and the HDF5 write
        real_write(iteration, nums)

    monkeypatch.setattr(log, "_write", write_with_signal)
    with pytest.raises(KeyboardInterrupt):
        log.append(0, loss=1.0, metric=2.0)
    log.close()
    assert not journal_path(path).exists()
    with h5py.File(path) as f:
        assert {k: v.shape for k, v in f["training/adam"].items()} == {"iteration": (1,), "loss": (1,),
                                                                      "metric": (1,)}
    with pytest.warns(IncompleteFileWarning, match="stopped after 1 of 5"):
        assert read_training(path)["adam"]["loss"].tolist() == [1.0]
