"""Helpers shared by the phisim.io tests: the repository root and a runner that interrupts a command."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[3]


@pytest.fixture
def repo_root() -> Path:
    """The repository root (where ``phisim`` and ``inverse`` are importable from)."""
    return REPO


@dataclass
class Interrupted:
    """What an interrupted command did.

    Attributes:
        returncode: Its exit status.
        latency: Seconds from the signal to the exit of the process.
        stdout, stderr: Its output.
        children: Process ids of its child processes when the signal was sent.
    """

    returncode: int
    latency: float
    stdout: str
    stderr: str
    children: list[int] = field(default_factory=list)


def child_pids(pid: int) -> list[int]:
    """Process ids whose parent is ``pid`` (Linux ``/proc``; empty elsewhere)."""
    out = []
    for entry in Path("/proc").glob("[0-9]*"):
        try:
            stat = (entry / "stat").read_text()
        except OSError:
            continue
        fields = stat[stat.rindex(")") + 2:].split()
        if int(fields[1]) == pid:
            out.append(int(entry.name))
    return out


def process_gone(pid: int) -> bool:
    """Whether ``pid`` has exited (a zombie waiting for its new parent counts as exited)."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return True
    return stat[stat.rindex(")") + 2] in "ZX"


def _terminal_signals() -> None:
    """In a spawned command: Ctrl-C as at a terminal. A test run started in the background by a non-interactive
    shell inherits SIGINT ignored, and Python then installs no KeyboardInterrupt handler in its children."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


@pytest.fixture(autouse=True)
def _sigint_as_at_a_terminal():
    """This process's SIGINT as at a terminal for the duration of a test (see :func:`_terminal_signals`)."""
    if signal.getsignal(signal.SIGINT) is not signal.SIG_IGN:
        yield
        return
    signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, signal.SIG_IGN)


def _env() -> dict:
    """The environment of the commands: the repository importable, the same for every run compared."""
    return dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))


def run_and_interrupt(args: list[str], ready: Callable[[], bool], *, cwd: Path, sig: int = signal.SIGINT,
                      start_timeout: float = 120.0) -> Interrupted:
    """Run ``python args...``, send ``sig`` once ``ready()`` is true, and time how long the process takes to exit.

    Fails the test if the command ends before ``ready()`` or never becomes ready.
    """
    proc = subprocess.Popen([sys.executable, *args], cwd=cwd, env=_env(), stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, preexec_fn=_terminal_signals)
    try:
        t0 = time.monotonic()
        while not ready():
            if proc.poll() is not None:
                out, err = proc.communicate()
                pytest.fail(f"the command ended (status {proc.returncode}) before it was interrupted:\n{out}\n{err}")
            if time.monotonic() - t0 > start_timeout:
                pytest.fail("the command did not reach the point to interrupt it")
            time.sleep(0.01)
        children = child_pids(proc.pid)
        sent = time.monotonic()
        proc.send_signal(sig)
        proc.wait(timeout=60)
        latency = time.monotonic() - sent
        out, err = proc.communicate()
        return Interrupted(proc.returncode, latency, out, err, children)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def run_python(args: list[str], *, cwd: Path, timeout: float = 300.0) -> subprocess.CompletedProcess:
    """Run ``python args...`` to its end in the environment of :func:`run_and_interrupt` (runs whose bits are
    compared must not depend on the test process's torch settings, e.g. its thread count)."""
    return subprocess.run([sys.executable, *args], cwd=cwd, env=_env(), capture_output=True, text=True,
                          timeout=timeout, preexec_fn=_terminal_signals)


@pytest.fixture
def python() -> Callable[..., subprocess.CompletedProcess]:
    """:func:`run_python`."""
    return run_python


@pytest.fixture
def interrupt() -> Callable[..., Interrupted]:
    """:func:`run_and_interrupt`."""
    return run_and_interrupt


@pytest.fixture
def wait_gone() -> Callable[[list[int], float], list[int]]:
    """``wait_gone(pids, seconds)``: the pids still running after up to ``seconds``."""

    def wait(pids: list[int], seconds: float = 2.0) -> list[int]:
        deadline = time.monotonic() + seconds
        alive = [p for p in pids if not process_gone(p)]
        while alive and time.monotonic() < deadline:
            time.sleep(0.02)
            alive = [p for p in alive if not process_gone(p)]
        return alive

    return wait
