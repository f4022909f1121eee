"""The same mistake reads the same in every command (issue 26, item 5 and "Bad input"): a missing file, a folder
instead of a file, an output that cannot be written, swapped arguments, an unknown dataset key. On the command
line: one line ``phisim: error: ...``, exit status 2, no traceback; in Python: a PhisimError subclass."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest
import torch

from inverse import cli_checks
from inverse.cli import main
from phisim import CenteredGrid, Grid, StaggeredGrid
from phisim.errors import FileFormatError, ParameterError, PhisimError


def _one_error_line(argv, capsys) -> str:
    code = main([str(a) for a in argv])
    err = capsys.readouterr().err
    assert code == 2, err
    assert err.startswith("phisim: error: ") and "Traceback" not in err, err
    assert len(err.strip().splitlines()) == 1, err
    return err.strip().removeprefix("phisim: error: ")


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """A results file, its model file and an input file of the sine problem (one training iteration)."""
    d = tmp_path_factory.mktemp("trained")
    assert main(["train", "sine", "adam", "--iterations", "1", "--quiet", "--out", str(d / "s.h5")]) == 0
    model = d / "s.h5.adam.model.pt"
    assert model.is_file()
    with h5py.File(d / "inputs.h5", "w") as f:
        f["a"] = np.zeros((3, 1), np.float32)
        f["group/b"] = np.zeros((3, 1), np.float32)
    return {"dir": d, "results": d / "s.h5", "model": model, "inputs": d / "inputs.h5"}


# ---- a missing file, a folder instead of a file ----------------------------------------------------------


def _file_arguments(t, bad):
    """Every command's input-file argument set to ``bad`` (the others valid): (argv, what the message names)."""
    return [
        (["info", bad], "file"),
        (["plot", bad], "file"),
        (["export", bad, "--csv", t["dir"] / "csv"], "results file"),
        (["predict", bad, t["inputs"], "--out", t["dir"] / "p.h5"], "model file"),
        (["predict", t["model"], bad, "--out", t["dir"] / "p.h5"], "input file"),
        (["simulate", "heat", "--config", bad, "--out", t["dir"] / "ds"], "config file"),
        (["train", f"{bad}:factory", "adam", "--iterations", "1"], "problem factory file"),
    ]


def test_a_missing_file_reads_the_same_in_every_command(trained, capsys, tmp_path):
    bad = tmp_path / "nope.h5"
    for argv, what in _file_arguments(trained, bad):
        assert _one_error_line(argv, capsys) == f"{what} {bad} does not exist", argv


def test_a_folder_instead_of_a_file_reads_the_same_in_every_command(trained, capsys, tmp_path):
    for argv, what in _file_arguments(trained, tmp_path):
        assert _one_error_line(argv, capsys) == f"{what} {tmp_path} is a folder, not a file", argv


def test_a_file_of_another_format_reads_the_same_where_hdf5_is_read(trained, capsys, tmp_path):
    text = tmp_path / "notes.txt"
    text.write_text("not hdf5\n")
    for argv, what in _file_arguments(trained, text)[:3]:  # info, plot, export
        assert _one_error_line(argv, capsys) == f"{what} {text} is not an HDF5 file (another format)", argv


# ---- an output that cannot be written --------------------------------------------------------------------


def test_an_unwritable_output_reads_the_same_in_every_command(trained, capsys):
    bad = Path("/dev/null/x")
    t = trained
    cases = [
        (["train", "sine", "adam", "--iterations", "1", "--out", bad], "output file"),
        (["compare", "sine", "adam", "--iterations", "1", "--plot", bad], "--plot file"),
        (["train", "sine", "adam", "--iterations", "1", "--out", t["dir"] / "o.h5", "--csv", bad], "CSV folder"),
        (["simulate", "heat", "--out", bad], "dataset folder"),
        (["plot", t["results"], "--out", bad], "output folder"),
        (["predict", t["model"], t["inputs"], "--key", "a", "--out", bad], "output file"),
        (["export", t["results"], "--csv", bad], "CSV folder"),
    ]
    for argv, what in cases:
        assert _one_error_line(argv, capsys) == f"{what} {bad} cannot be written: /dev/null is a file, not a folder"
    assert not (t["dir"] / "o.h5").exists()  # checked before any work


def test_an_output_folder_without_write_permission(tmp_path, capsys):
    import os

    locked = tmp_path / "locked"
    locked.mkdir()
    locked.chmod(0o500)
    try:
        if os.access(locked, os.W_OK):
            pytest.skip("running as a user that writes anywhere (root)")
        msg = _one_error_line(["simulate", "heat", "--out", locked / "ds"], capsys)
        assert msg == f"dataset folder {locked / 'ds'} cannot be written: {locked} is not writable"
    finally:
        locked.chmod(0o700)


# ---- swapped arguments, unknown keys ---------------------------------------------------------------------


def test_predict_with_its_arguments_swapped_says_so(trained, capsys):
    t = trained
    msg = _one_error_line(["predict", t["inputs"], t["model"], "--out", t["dir"] / "p.h5"], capsys)
    assert msg == (f"model file {t['inputs']} is an HDF5 file, not a model file (<out>.<method>.model.pt): the "
                   "order is phisim predict MODEL INPUTS --out FILE")
    assert "weights_only" not in msg
    msg = _one_error_line(["predict", t["model"], t["model"], "--out", t["dir"] / "p.h5"], capsys)
    assert msg == (f"input file {t['model']} is a model file (a torch archive), not an HDF5 file: the order is "
                   "phisim predict MODEL INPUTS --out FILE")


def test_an_unknown_dataset_key_lists_the_keys_that_exist(trained, capsys):
    t = trained
    msg = _one_error_line(["predict", t["model"], t["inputs"], "--key", "input", "--out", t["dir"] / "p.h5"], capsys)
    assert msg == f"{t['inputs']} has no dataset 'input'; its datasets: a, group/b; pass one with --key"
    assert not (t["dir"] / "p.h5").exists()


def test_predict_with_a_key_that_exists_runs(trained, capsys):
    t = trained
    assert main(["predict", str(t["model"]), str(t["inputs"]), "--key", "/a", "--out", str(t["dir"] / "p.h5")]) == 0
    with h5py.File(t["dir"] / "p.h5") as f:
        assert f["predictions"].shape[0] == 3 and f.attrs["input_key"] == "a"


# ---- the checks in Python ---------------------------------------------------------------------------------


def test_the_checks_raise_phisim_errors(tmp_path):
    calls = [
        (lambda: cli_checks.existing_file(tmp_path / "x", "file"), FileFormatError, "does not exist"),
        (lambda: cli_checks.existing_file(tmp_path, "file"), FileFormatError, "is a folder, not a file"),
        (lambda: cli_checks.hdf5_file(tmp_path / "x", "input file"), FileFormatError, "does not exist"),
        (lambda: cli_checks.model_file(tmp_path, "model file"), FileFormatError, "is a folder"),
        (lambda: cli_checks.writable_dir("/dev/null/x", "dataset folder"), ParameterError, "cannot be written"),
        (lambda: cli_checks.writable_file("/dev/null/x", "output file"), ParameterError, "cannot be written"),
        (lambda: cli_checks.writable_file(tmp_path, "output file"), ParameterError, "is a folder, not a file"),
    ]
    for call, error, match in calls:
        with pytest.raises(error, match=match) as info:
            call()
        assert isinstance(info.value, PhisimError)


def test_the_output_checks_create_nothing(tmp_path):
    cli_checks.writable_dir(tmp_path / "a" / "b", "dataset folder")
    cli_checks.writable_file(tmp_path / "c" / "d.h5", "output file")
    assert sorted(tmp_path.iterdir()) == []


def test_a_device_this_machine_lacks_is_a_parameter_error_where_fields_are_made():
    grid = Grid((8, 8))
    missing = "cuda:99" if torch.cuda.is_available() else "cuda"
    calls = [
        lambda: CenteredGrid.zeros(grid, "periodic", device=missing),
        lambda: StaggeredGrid.zeros(grid, "periodic", device=missing),
        lambda: CenteredGrid.from_function(lambda x: x[..., 0], grid, "periodic", device=missing),
        lambda: StaggeredGrid.from_function(lambda x: x, grid, "periodic", device=missing),
        lambda: CenteredGrid(torch.zeros(1, 8, 8), grid, "periodic").to(missing),
        lambda: grid.cell_centers(device=missing),
    ]
    for call in calls:
        with pytest.raises(ParameterError, match=re.escape(repr(missing))):
            call()
    assert CenteredGrid.zeros(grid, "periodic", device="cpu").device.type == "cpu"


def test_the_command_itself_prints_one_line_and_exits_with_2(tmp_path):
    script = Path(sys.executable).parent / "phisim"
    if not script.exists():
        pytest.skip("the phisim script is not installed in this environment")
    r = subprocess.run([str(script), "plot", str(tmp_path / "nope.h5")], capture_output=True, text=True)
    assert r.returncode == 2 and r.stdout == ""
    assert r.stderr == f"phisim: error: file {tmp_path / 'nope.h5'} does not exist\n"
