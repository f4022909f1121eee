"""No silent loss in training logs: refusing to write over a method's records, resume/overwrite, and the
planned-iterations / completion marks that tell a finished run from one that was killed or interrupted."""

from __future__ import annotations

import shutil
import warnings

import h5py
import numpy as np
import pytest

from phisim.errors import FileFormatError, IncompleteFileWarning, ParameterError
from phisim.io import SimulationWriter, TrainingCurves, TrainingLog, read_simulation, read_training, recover_file
from phisim.io.journal import journal_path
from phisim.io.traininglog import repair_training_file, training_run
from tests.phisim.io.crash_harness import GRID, frame_values


def _log(path, method="adam", n=3, **kw):
    with TrainingLog(path, method, **kw) as log:
        for it in range(log.n_records, log.n_records + n):
            log.append(it, loss=float(it))
        return log


def test_reopening_a_log_with_records_is_refused_unless_resume_or_overwrite(tmp_path):
    path = tmp_path / "r.h5"
    _log(path, attrs={"lr": 0.1})
    with pytest.raises(FileFormatError, match=r"already holds a run \(3 records\).*resume=True.*overwrite=True"):
        TrainingLog(path, "adam")
    with h5py.File(path, "r") as f:  # the refusal closed the file and changed nothing
        assert f["training/adam/loss"].shape == (3,)
    _log(path, "hig")  # another method in the same file is fine
    _log(path, resume=True)
    assert read_training(path)["adam"]["loss"].tolist() == [0.0, 1.0, 2.0, 3.0, 4.0, 5.0]
    _log(path, n=2, overwrite=True)
    logs = read_training(path)
    assert logs["adam"]["loss"].tolist() == [0.0, 1.0] and "lr" not in logs["adam"].attrs
    assert logs["hig"]["loss"].tolist() == [0.0, 1.0, 2.0]
    with pytest.raises(ParameterError, match="exclude"):
        TrainingLog(path, "adam", resume=True, overwrite=True)


def test_an_empty_log_may_be_reopened(tmp_path):
    path = tmp_path / "e.h5"
    TrainingLog(path, "adam").close()
    _log(path)
    assert read_training(path)["adam"].records == 3


def test_planned_iterations_and_completion_mark(tmp_path):
    path = tmp_path / "p.h5"
    with TrainingLog(path, "adam", planned_iterations=5) as log:
        for it in range(3):
            log.append(it, loss=1.0)
    with pytest.warns(IncompleteFileWarning, match=r"adam: INCOMPLETE: stopped after 3 of 5 iterations"):
        run = read_training(path)["adam"]
    assert isinstance(run, TrainingCurves) and run.complete is False and run.planned == 5 and run.records == 3
    with TrainingLog(path, "adam", planned_iterations=5, resume=True) as log:
        for it in range(3, 5):
            log.append(it, loss=1.0)
        log.finish()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        run = read_training(path)["adam"]
    assert run.complete is True and run.status == "complete (5 iterations)"
    with h5py.File(path, "r") as f:
        assert f["training/adam"].attrs["planned_iterations"] == 5 and bool(f["training/adam"].attrs["complete"])
    plain = tmp_path / "plain.h5"
    _log(plain)  # a log that states no length: no completion state, no warning
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        run = read_training(plain)["adam"]
    assert run.complete is None and run.status == "3 records"
    with pytest.raises(ParameterError, match="planned_iterations"):
        TrainingLog(tmp_path / "x.h5", "adam", planned_iterations=-1)


@pytest.mark.parametrize("finished", [False, True])
def test_completion_mark_survives_a_kill_through_the_journal(tmp_path, finished):
    path, killed = tmp_path / "live.h5", tmp_path / "killed.h5"
    log = TrainingLog(path, "adam", planned_iterations=4)
    for it in range(4 if finished else 2):
        log.append(it, loss=float(it))
    if finished:
        log.finish()
    shutil.copyfile(path, killed)  # the files as a SIGKILL would leave them
    shutil.copyfile(journal_path(path), journal_path(killed))
    log.close()
    with pytest.warns(IncompleteFileWarning, match="not closed cleanly"):
        run = read_training(killed, warn=False)["adam"]
    assert run.complete is finished and run.planned == 4
    assert repair_training_file(killed) and not journal_path(killed).exists()
    assert training_run(killed, "adam").complete is finished


def test_training_log_inside_a_simulation_file(tmp_path):
    path = tmp_path / "sim.h5"
    with SimulationWriter(path, GRID, "wall", dataset_name="t", fields={"rho": "scalar", "v": "staggered"},
                          batch_size=2) as w:
        log = w.training_log("adam", planned_iterations=2)
        w.append(0.0, **frame_values(0))
        log.append(0, loss=1.0)
        with pytest.raises(FileFormatError, match="already holds"):
            w.training_log("adam")
        log.append(1, loss=0.5)
        log.finish()
    d = read_simulation(path)
    assert d.training["adam"].complete is True and d.training["adam"]["loss"].tolist() == [1.0, 0.5]


def test_training_log_on_an_unrecovered_simulation_file_says_what_to_do(tmp_path):
    path, killed = tmp_path / "sim.h5", tmp_path / "killed.h5"
    w = SimulationWriter(path, GRID, "wall", dataset_name="t", fields={"rho": "scalar", "v": "staggered"},
                         batch_size=2)
    w.append(0.0, **frame_values(0))
    shutil.copyfile(path, killed)
    shutil.copyfile(journal_path(path), journal_path(killed))
    w.close()
    with pytest.raises(FileFormatError, match=r"simulation file.*recover_file"):
        TrainingLog(killed, "adam")
    assert recover_file(killed)
    _log(killed)
    assert read_simulation(killed).n_frames == 1 and read_training(killed)["adam"].records == 3


def test_phisim_info_reports_each_run(tmp_path):
    from inverse.cli import describe_file

    path = tmp_path / "info.h5"
    with TrainingLog(path, "adam", planned_iterations=10) as log:
        log.append(0, loss=1.0)
    with TrainingLog(path, "pg", planned_iterations=1) as log:
        log.append(0, loss=1.0)
        log.finish()
    text = describe_file(path)
    assert "run adam: INCOMPLETE: stopped after 1 of 10 iterations" in text
    assert "run pg: complete (1 iterations)" in text
    live = TrainingLog(path, "sgd")
    live.append(0, loss=2.0)
    killed = tmp_path / "killed.h5"
    shutil.copyfile(path, killed)
    shutil.copyfile(journal_path(path), journal_path(killed))
    live.close()
    text = describe_file(killed)
    assert "NOT CLOSED CLEANLY" in text and "run sgd: 1 records" in text
    np.testing.assert_array_equal(training_run(killed, "sgd")["loss"], [2.0])
