"""Cheap input checks shared by the physics functions; each raises a PhisimError subclass."""

from __future__ import annotations

import math

import torch

from phisim.errors import NonFiniteError, ParameterError

__all__ = ["check_dt", "check_nonnegative", "check_positive", "check_finite", "all_finite", "check_device",
           "check_finite_number"]


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
