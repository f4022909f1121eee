"""Crash safety of simulation and training files: SIGKILL at random moments, truncation, full disks."""

from __future__ import annotations

import random
import shutil
import warnings
from pathlib import Path

import h5py
import numpy as np
import pytest
import torch

from phisim.errors import FileFormatError, IncompleteFileWarning, PhisimError
from phisim.io import SimulationWriter, TrainingLog, read_simulation, read_training, recover_file
from phisim.io import journal as _journal
from tests.phisim.io.crash_harness import GRID, check_file, frame_values, kill_once

pytestmark = pytest.mark.skipif(not hasattr(__import__("os"), "fork"), reason="needs os.fork")


def _open_writer(path: Path, n: int) -> SimulationWriter:
    w = SimulationWriter(path, GRID, "wall", dataset_name="t", fields={"rho": "scalar", "v": "staggered"},
                         batch_size=2)
    log = w.training_log("adam")
    for k in range(n):
        w.append(float(k), **frame_values(k))
        log.append(k, loss=float(k), metric=-0.5 * k)
    return w


def test_killed_loop_few_times(tmp_path):
    rng = random.Random(3)
    for i in range(8):
        p = tmp_path / f"k{i}.h5"
        frames, records = kill_once(p, rng=rng, max_delay=0.03)
        assert check_file(p, "simulation", frames, records) is None


@pytest.mark.slow
def test_killed_append_loop_200_times_zero_bad(tmp_path):
    """SIGKILL a tight SimulationWriter + TrainingLog append loop 200 times, then a standalone log 60 times."""
    rng = random.Random(12345)
    bad, frames_total = [], 0
    for i in range(200):
        p = tmp_path / f"s{i}.h5"
        frames, records = kill_once(p, "simulation", rng=rng, max_delay=0.06)
        frames_total += frames
        why = check_file(p, "simulation", frames, records)
        if why is None and i % 20 == 0:  # a file rebuilt from its journal holds the same frames, cleanly
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                n_before = read_simulation(p).n_frames
            assert recover_file(p) and not _journal.journal_path(p).exists()
            with warnings.catch_warnings():
                warnings.simplefilter("error")
                assert read_simulation(p).n_frames == n_before
            why = check_file(p, "simulation", frames, records)
        if why:
            bad.append((i, why))
        p.unlink(missing_ok=True)
        _journal.journal_path(p).unlink(missing_ok=True)
    for i in range(60):
        p = tmp_path / f"t{i}.h5"
        _, records = kill_once(p, "training", rng=rng, max_delay=0.04)
        why = check_file(p, "training", 0, records)
        if why:
            bad.append((f"log {i}", why))
    assert bad == []
    assert frames_total > 200  # the kills hit running loops, not only their start


def test_journal_truncated_anywhere_yields_a_correct_prefix(tmp_path):
    """Power loss simulated by truncation: every cut of the journal reads as the frames complete before it."""
    path = tmp_path / "live.h5"
    w = _open_writer(path, 4)
    try:
        journal = _journal.journal_path(path).read_bytes()
        h5 = path.read_bytes()
    finally:
        w.close()
    assert not _journal.journal_path(path).exists()  # a clean close removes the journal
    record_ends, pos = [], 0
    while pos < len(journal):
        _, _, length, _ = _journal._HEAD.unpack_from(journal, pos)
        pos += _journal._HEAD.size + length
        record_ends.append(pos)
    cuts = sorted({0, 1, 5, *record_ends, *(e - 1 for e in record_ends), *(e + 7 for e in record_ends[:-1]),
                   *range(record_ends[0], len(journal), 997)})
    seen = set()
    for cut in cuts:
        path.write_bytes(h5)
        _journal.journal_path(path).write_bytes(journal[:cut])
        if cut < record_ends[0]:  # not even the header survived: the HDF5 file itself is read
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                d = read_simulation(path)
            assert d.n_frames == 4
            continue
        with pytest.warns(IncompleteFileWarning):
            d = read_simulation(path)
        complete = sum(1 for e in record_ends if e <= cut)
        for k in range(d.n_frames):
            np.testing.assert_array_equal(d.fields["rho"][:, k], frame_values(k)["rho"])
        seen.add(d.n_frames)
        assert 0 <= d.n_frames <= 4 and complete >= 1
    assert seen == {0, 1, 2, 3, 4}


def test_hdf5_truncated_with_journal_recovers_and_without_says_truncated(tmp_path):
    path = tmp_path / "cut.h5"
    w = _open_writer(path, 3)
    journal = _journal.journal_path(path).read_bytes()
    w.close()
    full = path.read_bytes()
    path.write_bytes(full[: len(full) // 2])
    with pytest.raises(FileFormatError, match="truncated") as e:
        read_simulation(path)
    assert "lock" not in str(e.value)
    _journal.journal_path(path).write_bytes(journal)
    with pytest.warns(IncompleteFileWarning, match="3 complete frame"):
        d = read_simulation(path)
    assert d.n_frames == 3 and d.training["adam"]["loss"].tolist() == [0.0, 1.0, 2.0]
    assert recover_file(path)
    d = read_simulation(path)
    assert d.n_frames == 3 and d.kinds == {"rho": "scalar", "v": "staggered"}
    assert not recover_file(path)


def test_training_log_resume_after_kill_rebuilds_file(tmp_path):
    path = tmp_path / "log.h5"
    with TrainingLog(path, "sgd") as log:
        for k in range(3):
            log.append(k, loss=1.0 + k)
    frames, records = kill_once(path, "training", max_delay=0.02)
    assert records >= 0
    path.write_bytes(b"\0" * 100)  # the HDF5 file destroyed completely; the journal alone restores both logs
    with pytest.warns(IncompleteFileWarning):
        logs = read_training(path)
    assert logs["sgd"]["loss"].tolist() == [1.0, 2.0, 3.0] and len(logs["adam"]["iteration"]) >= records
    with TrainingLog(path, "adam", resume=True) as log:  # reopening first rebuilds the file from the journal
        n = log.n_records
        log.append(n, loss=float(n), metric=-0.5 * n)
    logs = read_training(path)
    assert logs["sgd"]["loss"].tolist() == [1.0, 2.0, 3.0]
    np.testing.assert_array_equal(logs["adam"]["loss"], np.arange(n + 1))


# ---- full disk / vanished folder (injected write failures) ----------------------------------------------


def _enospc(*args, **kwargs):
    raise OSError(28, "No space left on device")


def test_full_disk_during_append_names_file_and_keeps_frames(tmp_path, monkeypatch):
    path = tmp_path / "full.h5"
    w = _open_writer(path, 2)
    monkeypatch.setattr(_journal.os, "write", _enospc)
    with pytest.raises(FileFormatError, match="full.h5.journal.*disk is full"):
        w.append(2.0, **frame_values(2))
    monkeypatch.undo()
    with pytest.warns(IncompleteFileWarning):
        assert read_simulation(path).n_frames == 2
    w.close()
    assert read_simulation(path).n_frames == 2


def test_full_disk_inside_hdf5_write_is_a_phisim_error(tmp_path, monkeypatch):
    path = tmp_path / "h5full.h5"
    w = _open_writer(path, 1)

    def fail(self, frames, t):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(SimulationWriter, "_write_frame", fail)
    with pytest.raises(FileFormatError, match="h5full.h5.*disk is full"):
        w.append(1.0, **frame_values(1))
    monkeypatch.undo()
    with pytest.warns(IncompleteFileWarning):
        d = read_simulation(path)
    assert d.n_frames >= 1
    w.close()


def test_full_disk_in_training_log_is_a_phisim_error(tmp_path, monkeypatch):
    path = tmp_path / "tl.h5"
    log = TrainingLog(path, "adam")
    log.append(0, loss=1.0)
    monkeypatch.setattr(_journal.os, "write", _enospc)
    with pytest.raises(FileFormatError, match="tl.h5.journal"):
        log.append(1, loss=2.0)
    monkeypatch.undo()
    log.close()
    assert read_training(path)["adam"]["loss"].tolist() == [1.0]


def test_vanished_folder_is_a_phisim_error(tmp_path):
    folder = tmp_path / "gone"
    path = folder / "v.h5"
    w = _open_writer(path, 1)
    w._file.close()
    w._journal.close(delete=False)
    shutil.rmtree(folder)
    with pytest.raises(PhisimError):
        w.append(1.0, **frame_values(1))


def test_unwritable_output_folder_fails_before_work(tmp_path, monkeypatch):
    import os

    real_access = os.access
    ro = tmp_path / "ro"
    monkeypatch.setattr(os, "access", lambda p, mode, **k: False if Path(p) == ro else real_access(p, mode))
    (tmp_path / "ro").mkdir()
    with pytest.raises(FileFormatError, match="not writable"):
        SimulationWriter(tmp_path / "ro" / "x.h5", GRID, "wall", dataset_name="t", fields={"rho": "scalar"},
                         batch_size=1)
    (tmp_path / "file").write_text("not a folder")
    with pytest.raises(FileFormatError, match="folder"):
        SimulationWriter(tmp_path / "file" / "x.h5", GRID, "wall", dataset_name="t", fields={"rho": "scalar"},
                         batch_size=1)


def test_checkpoint_full_disk_keeps_previous_and_leaves_no_temp(tmp_path, monkeypatch):
    import importlib

    train_mod = importlib.import_module("inverse.train")

    out = tmp_path / "run.h5"
    train_mod.train("sine", "adam", iterations=4, batch_size=4, out=out, checkpoint_every=2)
    ckpt = tmp_path / "run.h5.adam.ckpt"
    good = torch.load(ckpt, weights_only=False)
    assert good["iteration"] == 4
    real_save = torch.save

    def save_fails(obj, f, *a, **k):
        real_save(obj, f, *a, **k)  # a partial temp file is written, then the disk fills up
        raise RuntimeError("PytorchStreamWriter failed writing file data/0: file write failed")

    monkeypatch.setattr(train_mod.torch, "save", save_fails)
    with pytest.raises(FileFormatError, match=r"run.h5.adam.ckpt"):
        train_mod.train("sine", "adam", iterations=8, batch_size=4, out=out, checkpoint_every=2, resume=True)
    monkeypatch.undo()
    assert not (tmp_path / "run.h5.adam.ckpt.tmp").exists()
    assert torch.load(ckpt, weights_only=False)["iteration"] == 4  # the previous checkpoint still loads
    r = train_mod.train("sine", "adam", iterations=6, batch_size=4, out=out, checkpoint_every=2, resume=True)
    assert r.curves["iteration"].tolist() == list(range(6))


def test_checkpoint_with_other_settings_is_refused(tmp_path):
    from inverse.train import train

    out = tmp_path / "run.h5"
    train("sine", "adam", iterations=2, batch_size=4, out=out, checkpoint_every=2)
    with pytest.raises(FileFormatError, match="other settings.*batch_size"):
        train("sine", "adam", iterations=4, batch_size=8, out=out, checkpoint_every=2, resume=True)


def test_writer_failure_at_creation_leaves_nothing(tmp_path, monkeypatch):
    path = tmp_path / "c.h5"
    monkeypatch.setattr(_journal.os, "write", _enospc)
    with pytest.raises(FileFormatError, match="disk is full"):
        SimulationWriter(path, GRID, "wall", dataset_name="t", fields={"rho": "scalar"}, batch_size=1)
    assert list(tmp_path.iterdir()) == []
    assert h5py  # h5py stays importable after the failure (no crashed library state)
