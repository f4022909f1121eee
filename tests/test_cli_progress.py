"""Progress by default on long work in a terminal (issue 26, item 6): training (``phisim train`` / ``compare``,
``inverse.train``) and ``phisim simulate`` show a bar on stderr when it is a terminal, and stay quiet when it is
not (pipes, logs, CI) or with ``--quiet`` / ``progress=False``."""

from __future__ import annotations

import io
import sys

import pytest

from inverse.cli import main
from inverse.train import train
from phisim.checks import check_progress
from phisim.errors import ParameterError


class _Stream(io.StringIO):
    def __init__(self, tty: bool):
        super().__init__()
        self.tty = tty

    def isatty(self) -> bool:
        return self.tty


def test_check_progress():
    assert check_progress(None, stream=_Stream(True)) is True
    assert check_progress(None, stream=_Stream(False)) is False
    assert check_progress(True, stream=_Stream(False)) is True
    assert check_progress(False, stream=_Stream(True)) is False
    closed = _Stream(True)
    closed.close()
    closed.isatty = lambda: (_ for _ in ()).throw(ValueError("closed"))
    assert check_progress(None, stream=closed) is False
    with pytest.raises(ParameterError, match="progress must be True, False or None"):
        check_progress("yes")


@pytest.fixture()
def terminal(monkeypatch):
    """stderr as a terminal (``True``) or a pipe (``False``): returns a function that sets it and its buffer."""

    def make(tty: bool) -> _Stream:
        stream = _Stream(tty)
        monkeypatch.setattr(sys, "stderr", stream)
        return stream

    return make


@pytest.mark.parametrize("tty, quiet, shown", [(True, False, True), (False, False, False), (True, True, False)])
def test_phisim_train_shows_progress_only_in_a_terminal(tty, quiet, shown, terminal, tmp_path):
    err = terminal(tty)
    argv = ["train", "sine", "adam", "--iterations", "3", "--out", str(tmp_path / "s.h5")] + (["--quiet"] * quiet)
    assert main(argv) == 0
    text = err.getvalue()
    assert ("sine/adam" in text and "3/3" in text) is shown, text


@pytest.mark.parametrize("tty, shown", [(True, True), (False, False)])
def test_inverse_train_shows_progress_by_default_in_a_terminal(tty, shown, terminal):
    err = terminal(tty)
    train("sine", "adam", iterations=2, batch_size=4)
    text = err.getvalue()
    assert ("sine/adam" in text and "2/2" in text) is shown, text


def test_inverse_train_progress_false_is_quiet_in_a_terminal(terminal):
    err = terminal(True)
    train("sine", "adam", iterations=2, batch_size=4, progress=False)
    assert "sine/adam" not in err.getvalue()


@pytest.mark.parametrize("tty, quiet, shown", [(True, False, True), (False, False, False), (True, True, False)])
def test_phisim_simulate_shows_progress_only_in_a_terminal(tty, quiet, shown, terminal, tmp_path):
    err = terminal(tty)
    argv = ["simulate", "heat", "--trajectories", "2", "--trajectories-per-file", "2", "--steps", "2",
            "--resolution", "8", "--set", "test_fraction=0", "--set", "valid_fraction=0",
            "--out", str(tmp_path / "heat")] + (["--quiet"] * quiet)
    assert main(argv) == 0
    text = err.getvalue()
    assert ("simulate heat" in text and "2/2" in text) is shown, text
