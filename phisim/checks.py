"""Cheap input checks shared by the physics functions; each raises a PhisimError subclass.

The one mechanism for argument checking in phisim and inverse. Constructors and keyword settings validate numbers,
integers, seeds, flags and choices with :func:`check_number`, :func:`check_int`, :func:`check_seed`,
:func:`check_bool` and :func:`check_choice`; two operands' batch sizes with :func:`check_batch_compatible` (equal,
or one of them 1, which is shared by every sample of the other); empty batches with :func:`check_nonempty_batch`;
what a user callable returned with :func:`check_callable_output`. Every message names the argument (or the
callable and the shape it returned against the one expected).

Plain functions rather than a runtime type-checking library (typeguard, beartype, pydantic): the checks are about
values as much as types (finite, in range, a seed torch accepts, a batch size that fits another operand's, a
callable's output shape), which annotations do not express; the errors must be phisim's own typed errors with a
hint, not a library's TypeError; and the helpers cost a few isinstance tests per call, with no decorator on hot
paths and no new dependency.
"""

from __future__ import annotations

import math
import stat
import sys
from pathlib import Path

import numpy as np
import torch

from phisim.errors import FileFormatError, NonFiniteError, ParameterError, ShapeError

__all__ = ["existing_file",
           "check_dt", "check_nonnegative", "check_positive", "check_finite", "all_finite", "check_device",
           "check_finite_number", "check_number", "check_int", "check_seed", "check_bool", "check_choice",
           "check_callable", "callable_name", "batch_size_of", "check_batch_compatible", "check_nonempty_batch",
           "check_callable_output", "check_progress"]


def check_dt(dt, name: str = "dt") -> float:
    """Validate a time step: a finite number ``>= 0``.

    Args:
        dt: The time step (a Python number or a 0-d tensor).
        name: Name used in the error message.

    Returns:
        ``dt`` as a float (tensors are left as they are so gradients w.r.t. ``dt`` survive).

    Raises:
        ParameterError: If ``dt`` is negative, NaN or infinite.
    """
    if isinstance(dt, bool) or isinstance(dt, (str, bytes)):
        raise ParameterError(f"{name} must be a number, got {dt!r}")
    value = float(dt.detach()) if isinstance(dt, torch.Tensor) and dt.numel() == 1 else dt
    try:
        value = float(value)
    except (TypeError, ValueError) as exc:
        raise ParameterError(f"{name} must be a number, got {dt!r}") from exc
    if not math.isfinite(value) or value < 0:
        raise ParameterError(f"{name} must be finite and >= 0, got {value}; a negative {name} would run time backwards")
    return dt if isinstance(dt, torch.Tensor) else value


def check_nonnegative(value, name: str) -> float:
    """Validate a finite coefficient ``>= 0`` (viscosity, diffusivity, ...).

    Raises:
        ParameterError: If the value is negative, NaN or infinite.
    """
    if isinstance(value, bool) or isinstance(value, (str, bytes)):
        raise ParameterError(f"{name} must be a number, got {value!r}")
    v = float(value.detach()) if isinstance(value, torch.Tensor) and value.numel() == 1 else value
    try:
        v = float(v)
    except (TypeError, ValueError) as exc:
        raise ParameterError(f"{name} must be a number, got {value!r}") from exc
    if not math.isfinite(v) or v < 0:
        raise ParameterError(f"{name} must be finite and >= 0, got {v}")
    return value if isinstance(value, torch.Tensor) else v


def check_positive(value, name: str) -> float:
    """Validate a finite number ``> 0``.

    Raises:
        ParameterError: If the value is not positive and finite.
    """
    v = check_nonnegative(value, name)
    if float(v) == 0:
        raise ParameterError(f"{name} must be > 0, got 0")
    return v


def all_finite(x: torch.Tensor) -> bool:
    """Whether every entry of ``x`` is finite.

    Fast path: one sum reduction (a NaN or Inf entry makes the sum non-finite); only when the sum is not
    finite (a non-finite entry, or an overflow of the sum) are the entries checked one by one. Costs a
    device sync on GPU.
    """
    if x.numel() == 0:
        return True
    if bool(torch.isfinite(x.sum())):
        return True
    return bool(torch.isfinite(x).all())


def check_finite(x: torch.Tensor, name: str) -> torch.Tensor:
    """Raise if ``x`` contains NaN or Inf (see :func:`all_finite`).

    Raises:
        NonFiniteError: Naming the input and how many entries are non-finite.
    """
    if not all_finite(x):
        finite = torch.isfinite(x)
        bad = int((~finite).sum())
        raise NonFiniteError(f"{name} contains {bad} NaN/Inf value(s) out of {x.numel()}")
    return x


def check_device(device) -> torch.device:
    """Validate a torch device before any work starts.

    Args:
        device: A ``torch.device`` or its name (``'cpu'``, ``'cuda'``, ``'cuda:1'``, ``'mps'``).

    Returns:
        The ``torch.device``.

    Raises:
        ParameterError: For a malformed name, or an accelerator this machine does not have.
    """
    if isinstance(device, torch.device) and device.type == "cpu":
        return device  # the common case, without a look at the accelerators
    try:
        dev = torch.device(device)
    except (RuntimeError, TypeError, ValueError) as exc:
        raise ParameterError(f"unknown device {device!r}; use 'cpu', 'cuda' or 'cuda:N'") from exc
    if dev.type == "cuda":
        if not torch.cuda.is_available():
            raise ParameterError(f"device {device!r} was asked for but CUDA is not available here; use 'cpu'")
        if dev.index is not None and dev.index >= torch.cuda.device_count():
            raise ParameterError(f"device {device!r}: only {torch.cuda.device_count()} CUDA device(s) here")
    elif dev.type == "mps" and not (getattr(torch.backends, "mps", None) and torch.backends.mps.is_available()):
        raise ParameterError(f"device {device!r} was asked for but MPS is not available here; use 'cpu'")
    return dev


def check_finite_number(value, name: str) -> float:
    """Validate a finite real number of either sign (a strength, an offset, ...).

    Returns:
        The value (a float; 0-d tensors are returned unchanged so gradients survive).

    Raises:
        ParameterError: If the value is not a number, or NaN/Inf.
    """
    if isinstance(value, (bool, str, bytes)) or value is None:
        raise ParameterError(f"{name} must be a number, got {value!r}")
    v = value.detach() if isinstance(value, torch.Tensor) else value
    try:
        f = float(v)
    except (TypeError, ValueError, RuntimeError) as exc:
        raise ParameterError(f"{name} must be a single number, got {value!r}") from exc
    if not math.isfinite(f):
        raise ParameterError(f"{name} must be finite, got {f}")
    return value if isinstance(value, torch.Tensor) else f


# ---- one mechanism for arguments: numbers, integers, flags, choices, batches and callables' outputs --------
#
# Every public constructor and keyword setting validates its arguments with these helpers, so a string,
# ``None``, a list, NaN or an out-of-range integer where a number is expected always ends in a ParameterError
# that names the argument, a batch mismatch in a ShapeError naming both sizes, and a user callable that
# returns the wrong thing in a ShapeError/NonFiniteError naming the callable.

#: Largest integer a torch/numpy int64 holds: the default upper limit of :func:`check_int`.
INT64_MAX = 2**63 - 1
#: Seeds ``torch.Generator.manual_seed`` accepts: ``[-2**63, 2**64 - 1]``.
SEED_RANGE = (-(2**63), 2**64 - 1)


def _short(value, limit: int = 60) -> str:
    text = repr(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."


def _range_text(minimum, maximum, min_open: bool, max_open: bool) -> str:
    parts = []
    if minimum is not None:
        parts.append(f"{'>' if min_open else '>='} {minimum}")
    if maximum is not None:
        parts.append(f"{'<' if max_open else '<='} {maximum}")
    return " and ".join(parts)


def check_number(value, name: str, *, minimum: float | None = None, maximum: float | None = None,
                 min_open: bool = False, max_open: bool = False, allow_none: bool = False,
                 finite: bool = True) -> float | None:
    """Validate one real number (a Python/numpy number or a one-element tensor) and return it as a float.

    Args:
        value: The argument.
        name: Its name, for the message.
        minimum, maximum: Optional limits; ``min_open``/``max_open`` make them exclusive.
        allow_none: Whether ``None`` is accepted (and returned).
        finite: Whether NaN and Inf are refused (NaN is refused by any limit anyway).

    Raises:
        ParameterError: For a string, ``None``, a list, a bool, a complex number, NaN/Inf or a value out of range;
            the message names ``name``.
    """
    if value is None and allow_none:
        return None
    if value is None or isinstance(value, (bool, np.bool_, str, bytes, complex)):
        raise ParameterError(f"{name} must be a real number, got {_short(value)}")
    if isinstance(value, torch.Tensor):
        if value.numel() != 1 or value.is_complex():
            raise ParameterError(f"{name} must be a single real number, got a tensor of shape {tuple(value.shape)}")
        value = value.detach().cpu().item()
    elif isinstance(value, np.ndarray):
        if value.size != 1 or value.dtype.kind not in "iuf":
            raise ParameterError(f"{name} must be a single real number, got an array of shape {value.shape}")
        value = value.item()
    if not isinstance(value, (int, float, np.integer, np.floating)):
        raise ParameterError(f"{name} must be a real number, got {_short(value)} ({type(value).__name__})")
    try:
        v = float(value)
    except OverflowError as exc:
        raise ParameterError(f"{name} = {_short(value)} is too large for a float") from exc
    if math.isnan(v) or (finite and math.isinf(v)):
        raise ParameterError(f"{name} must be a finite number, got {v}")
    low = minimum is not None and (v <= minimum if min_open else v < minimum)
    high = maximum is not None and (v >= maximum if max_open else v > maximum)
    if low or high:
        raise ParameterError(f"{name} must be {_range_text(minimum, maximum, min_open, max_open)}, got {v:g}")
    return v


def check_int(value, name: str, *, minimum: int | None = None, maximum: int | None = INT64_MAX,
              allow_none: bool = False) -> int | None:
    """Validate an integer (a Python or numpy int, or a one-element integer tensor) and return it as an int.

    Floats are refused even when integral (``2.0``): a count, size or seed is an int.

    Args:
        value: The argument.
        name: Its name, for the message.
        minimum, maximum: Inclusive limits (default upper limit: the largest int64).
        allow_none: Whether ``None`` is accepted (and returned).

    Raises:
        ParameterError: For a string, ``None``, a float, a list, a bool or an out-of-range integer; the message
            names ``name``.
    """
    if value is None and allow_none:
        return None
    if isinstance(value, torch.Tensor) and value.numel() == 1 and not (value.is_floating_point()
                                                                       or value.is_complex()
                                                                       or value.dtype == torch.bool):
        value = int(value.item())
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)):
        raise ParameterError(f"{name} must be an integer, got {_short(value)} ({type(value).__name__})")
    v = int(value)
    if (minimum is not None and v < minimum) or (maximum is not None and v > maximum):
        raise ParameterError(f"{name} must be an integer {_range_text(minimum, maximum, False, False)}, got {v}")
    return v


def check_seed(seed, name: str = "seed", *, allow_none: bool = True) -> int | None:
    """Validate a random seed: an int that ``torch.Generator.manual_seed`` accepts (``-2**63 .. 2**64 - 1``).

    Raises:
        ParameterError: Naming ``name``.
    """
    return check_int(seed, name, minimum=SEED_RANGE[0], maximum=SEED_RANGE[1], allow_none=allow_none)


def check_bool(value, name: str) -> bool:
    """Validate a flag: ``True`` or ``False`` (numpy bools too), not ``1``, ``'yes'`` or ``None``.

    Raises:
        ParameterError: Naming ``name``.
    """
    if not isinstance(value, (bool, np.bool_)):
        raise ParameterError(f"{name} must be True or False, got {_short(value)}")
    return bool(value)


def check_choice(value, name: str, choices):
    """Validate that ``value`` is one of ``choices`` (compared by type and equality, so ``['a']``, tensors and
    other unhashable values are refused cleanly).

    Raises:
        ParameterError: Naming ``name`` and listing the choices.
    """
    for c in choices:
        if value is c or (type(value) is type(c) and value == c):
            return value
    raise ParameterError(f"{name} must be one of {tuple(choices)}, got {_short(value)}")


def callable_name(fn) -> str:
    """A readable name of a user callable: its ``__name__`` (``'<lambda>'`` for a lambda), else its ``repr``."""
    name = getattr(fn, "__name__", None)
    return repr(name) if isinstance(name, str) and name else _short(fn)


class NotCallableError(ParameterError, TypeError):
    """A ParameterError for an argument that must be callable; also a ``TypeError``, which such code raised before."""


def check_callable(value, name: str):
    """Validate that ``value`` is callable.

    Raises:
        NotCallableError: A :class:`ParameterError` (and ``TypeError``) naming ``name``.
    """
    if not callable(value):
        raise NotCallableError(f"{name} must be callable, got {_short(value)} ({type(value).__name__})")
    return value


def batch_size_of(x) -> int:
    """The batch size of a field (``.batch_size``), a tensor/array (``shape[0]``) or an int."""
    if isinstance(x, (int, np.integer)) and not isinstance(x, bool):
        return int(x)
    b = getattr(x, "batch_size", None)
    if isinstance(b, int):
        return b
    shape = getattr(x, "shape", None)
    if shape is None or len(shape) == 0:
        raise ShapeError(f"expected something with a leading batch axis, got {_short(x)}")
    return int(shape[0])


def check_batch_compatible(a, b, names: tuple[str, str] = ("a", "b"), what: str = "combine") -> int:
    """The common batch size of two operands: equal sizes, or one of them 1 (broadcast to the other).

    Args:
        a, b: Batch sizes, tensors (``shape[0]``) or fields (``batch_size``).
        names: What the two operands are, for the message.
        what: The operation, for the message (``'add'``, ``'solve'``...).

    Returns:
        The broadcast batch size.

    Raises:
        ShapeError: Naming both operands and both sizes.
    """
    ba, bb = batch_size_of(a), batch_size_of(b)
    if ba == bb or bb == 1:
        return ba
    if ba == 1:
        return bb
    raise ShapeError(
        f"cannot {what}: {names[0]} has batch size {ba} but {names[1]} has batch size {bb}; batch sizes must be "
        "equal, or one of them 1 (broadcast: it is then shared by every sample)"
    )


def check_nonempty_batch(x, name: str) -> None:
    """Refuse an empty batch (batch size 0), which no phisim operation processes.

    Raises:
        ShapeError: Naming ``name``.
    """
    if batch_size_of(x) == 0:
        raise ShapeError(f"{name} has an empty batch (batch size 0); pass at least one sample")


def check_callable_output(out, expected_shape, fn, name: str, *, finite: bool = True):
    """Check what a user callable returned: a tensor of exactly ``expected_shape`` and, with ``finite``, no NaN/Inf.

    Nothing is broadcast: a flat tensor, a batch of 1 where ``B`` was expected or a missing axis is an error.

    Args:
        out: The returned value.
        expected_shape: The shape it must have.
        fn: The callable (named in the message by :func:`callable_name`), or None when ``name`` names it.
        name: Its role (``'preconditioner'``, ``'local inverse'``...).
        finite: Also check for NaN/Inf (one reduction; a device sync on accelerators).

    Returns:
        ``out``.

    Raises:
        ShapeError: Not a tensor, or another shape; naming the callable and both shapes.
        NonFiniteError: NaN/Inf in the output.
    """
    expected = tuple(expected_shape)
    who = name if fn is None else f"{name} {callable_name(fn)}"
    if not isinstance(out, torch.Tensor):
        raise ShapeError(f"{who} returned {type(out).__name__}, expected a tensor of shape "
                         f"{expected}")
    if tuple(out.shape) != expected:
        raise ShapeError(f"{who} returned shape {tuple(out.shape)}, expected {expected}")
    if finite and not all_finite(out.detach()):
        bad = int((~torch.isfinite(out.detach())).sum())
        raise NonFiniteError(f"{who} returned {bad} NaN/Inf value(s) (shape {expected})")
    return out


def check_progress(progress, name: str = "progress", stream=None) -> bool:
    """Whether long work shows a progress bar: ``True``/``False`` as given; ``None`` (the default of the
    functions that take ``progress=``) shows one when ``stream`` (default ``sys.stderr``, where the bar goes)
    is a terminal, and stays quiet in pipes, log files, CI and batch jobs.

    Raises:
        ParameterError: Neither a bool nor None.
    """
    if progress is None:
        stream = sys.stderr if stream is None else stream
        isatty = getattr(stream, "isatty", None)
        try:
            return bool(isatty()) if isatty is not None else False
        except (ValueError, OSError):  # a closed or detached stream
            return False
    if not isinstance(progress, (bool, np.bool_)):
        raise ParameterError(f"{name} must be True, False or None (a bar when stderr is a terminal), got "
                             f"{_short(progress)}")
    return bool(progress)


def existing_file(path, what: str) -> Path:
    """``path`` as a Path if it is an existing regular file: the one wording of these mistakes for the library
    and every command (``"<what> <path> does not exist"``, ``"... is a folder, not a file"``, ``"... is not a
    regular file"``).

    Args:
        path: The file.
        what: What the file is for, e.g. ``"input file"`` (starts the message).

    Raises:
        FileFormatError: Missing, a folder, or not a regular file (a pipe, socket or device).
    """
    p = Path(path)
    if not p.exists():
        raise FileFormatError(f"{what} {p} does not exist")
    if p.is_dir():
        raise FileFormatError(f"{what} {p} is a folder, not a file")
    if not stat.S_ISREG(p.stat().st_mode):
        raise FileFormatError(f"{what} {p} is not a regular file (a pipe, socket or device)")
    return p
