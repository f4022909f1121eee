"""Prompt and clean interrupts: SIGINT/SIGTERM stop a long run at once, but never in the middle of a file write.

Two context managers, both no-ops outside the main thread (Python runs signal handlers only there):

* :func:`interruptible` makes SIGTERM behave like Ctrl-C: it raises :class:`Interrupted` (a
  ``KeyboardInterrupt``) in the main thread, so ``finally`` blocks and ``with`` statements close files
  cleanly instead of the process dying on the spot. Only a signal left at its default action is taken
  over, and the previous handlers come back on exit. The signal is also recorded, and
  :func:`check_interrupt`, called by long loops once per step, raises it again if it was swallowed (an
  exception raised inside a weakref callback or ``__del__`` is only printed). With ``raise_now=False`` the
  signal is only recorded, and the loops' :func:`check_interrupt` stop the run at the next step (quiet
  worker processes).
* :func:`uninterrupted` defers SIGINT and SIGTERM to the end of a short block that must not be cut in two
  (one frame or one record written to HDF5, a file renamed into place); the signal is then delivered to
  the handler that was in force, so nothing is lost and nothing is torn.

:class:`~phisim.io.SimulationWriter` and :class:`~phisim.io.TrainingLog` write every frame and record inside
:func:`uninterrupted`; the training loop and ``phisim simulate`` run inside :func:`interruptible`.
"""

from __future__ import annotations

import signal
import threading
from collections.abc import Iterator
from contextlib import contextmanager

__all__ = ["Interrupted", "interruptible", "uninterrupted", "check_interrupt", "SIGNALS"]

#: The signals handled here.
SIGNALS = tuple(s for s in (getattr(signal, "SIGINT", None), getattr(signal, "SIGTERM", None)) if s is not None)

_pending: list[int] = []
_depth = 0
_requested: list[int] = []  # signals received by interruptible's handlers (cleared when the block ends)


class Interrupted(KeyboardInterrupt):
    """A run stopped by a signal (SIGTERM, or SIGINT where :func:`interruptible` installed the handler).

    Attributes:
        signum: The signal number.
    """

    def __init__(self, signum: int):
        super().__init__(f"interrupted by {signal.Signals(signum).name}")
        self.signum = int(signum)


def _raise(signum, frame):
    _record(signum, frame)
    raise Interrupted(signum)


def _record(signum, frame):
    if signum not in _requested:
        _requested.append(signum)


def check_interrupt() -> None:
    """Raise :class:`Interrupted` if a signal arrived inside :func:`interruptible` (call it once per step of a
    long loop: it is cheap)."""
    if _requested:
        raise Interrupted(_requested[0])


def _defer(signum, frame):
    if signum not in _pending:
        _pending.append(signum)


def _main_thread() -> bool:
    return threading.current_thread() is threading.main_thread()


@contextmanager
def interruptible(raise_now: bool = True) -> Iterator[None]:
    """Within the block, SIGTERM (and SIGINT, if it has no handler) raise :class:`Interrupted`.

    Handlers a program installed itself, and ignored signals, are left alone.

    Args:
        raise_now: Raise in the handler (at once, wherever the main thread is). False: only record the
            signal; :func:`check_interrupt` raises it at the next step of the loop that calls it.
    """
    if not _main_thread():
        yield
        return
    saved = {}
    for s in SIGNALS:
        old = signal.getsignal(s)
        if old is signal.SIG_DFL:
            saved[s] = old
            signal.signal(s, _raise if raise_now else _record)
    try:
        yield
    finally:
        for s, old in saved.items():
            signal.signal(s, old)
        if saved:
            _requested.clear()


@contextmanager
def uninterrupted() -> Iterator[None]:
    """Defer SIGINT and SIGTERM to the end of the block, then deliver them to the handlers in force.

    Keep the block short (a write of one frame or record): the interrupt waits for it. Nested blocks defer
    to the end of the outermost one.
    """
    global _depth
    if not _main_thread():
        yield
        return
    saved = {}
    if _depth == 0:
        for s in SIGNALS:
            old = signal.getsignal(s)
            if old is not None:  # None: a handler not installed from Python, which cannot be restored
                saved[s] = old
                signal.signal(s, _defer)
    _depth += 1
    try:
        yield
    finally:
        _depth -= 1
        if _depth == 0:
            for s, old in saved.items():
                signal.signal(s, old)
            pending = [s for s in _pending if s in saved]
            _pending.clear()
            for s in pending:
                signal.raise_signal(s)  # the restored handler runs now (raises, exits or ignores it)
