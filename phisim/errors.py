"""The error family of phisim: every error the library raises on purpose derives from PhisimError."""

from __future__ import annotations

import os
import sys
import warnings

__all__ = [
    "PhisimError",
    "ShapeError",
    "GridMismatchError",
    "BoundaryError",
    "ParameterError",
    "NonFiniteError",
    "SolveError",
    "FileFormatError",
    "IncompleteFileWarning",
    "SlowPathWarning",
]


class PhisimError(Exception):
    """Base class of all errors raised deliberately by phisim and inverse."""


class ShapeError(PhisimError, ValueError):
    """An array has the wrong number of dimensions or the wrong size for its grid."""


class GridMismatchError(PhisimError, ValueError):
    """Two fields live on different grids, sample locations or boundaries and cannot be combined."""


class BoundaryError(PhisimError, ValueError):
    """An unknown or inconsistent boundary specification (e.g. periodic on one side only)."""


class ParameterError(PhisimError, ValueError):
    """A physical or numerical parameter is out of range (negative dt, non-positive resolution, ...)."""


class NonFiniteError(PhisimError, FloatingPointError):
    """A state or an input contains NaN or Inf."""


class SolveError(PhisimError, RuntimeError):
    """A linear solve did not converge.

    Attributes:
        iterations: Iterations performed (per sample where known).
        residual: Residual norm reached (per sample where known).
    """

    def __init__(self, message: str, iterations=None, residual=None):
        super().__init__(message)
        self.iterations = iterations
        self.residual = residual


class FileFormatError(PhisimError, OSError):
    """A file is missing required content or is corrupt."""


class IncompleteFileWarning(UserWarning):
    """A file was not closed cleanly (its writer was killed or is still running); what was complete is read."""


class SlowPathWarning(UserWarning):
    """A fast path failed its own check and the slower exact path was taken: the result is the same, it only took
    longer (for example a capacitance block built by box solves instead of from the box's eigen-decomposition)."""


def warn_from_caller(message: str, category: type[Warning] = UserWarning) -> None:
    """``warnings.warn`` pointed at the first frame outside the phisim package (the user's line, however deep inside
    phisim the cause was found: through a stepper, a rollout or a function called directly)."""
    package = os.path.dirname(os.path.abspath(__file__)) + os.sep
    frame, level = sys._getframe(0), 1
    while frame is not None and os.path.abspath(frame.f_code.co_filename).startswith(package):
        frame, level = frame.f_back, level + 1
    warnings.warn(message, category, stacklevel=level)
