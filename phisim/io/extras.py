"""Parts of :mod:`phisim.io` kept apart: the constant output interval and constant-in-time fields.

The Well's files hold frames at one constant time interval (its loader cuts windows by frame index), so
:class:`~phisim.io.SimulationWriter` checks every appended time against the interval and stores it as the
scalar ``dt`` (``/scalars/dt``, a root attribute listed in ``simulation_parameters``). Constant fields
(e.g. an obstacle mask) are stored in ``/t0_fields`` with ``time_varying=False``, as The Well does.
"""

from __future__ import annotations

import json
import math
import warnings
from collections.abc import Mapping
from pathlib import Path

import h5py
import numpy as np
import torch

from phisim.errors import FileFormatError, ParameterError, ShapeError
from phisim.io.h5util import check_storable_name

UNEVEN_MODES = ("error", "warn")
INTERVAL_RTOL = 1e-6


class IntervalCheck:
    """Checks that frame times are equally spaced and stores the spacing as the scalar ``dt``.

    Args:
        interval: The fixed output interval, or None to take it from the first two frames.
        mode: ``'error'`` (raise :class:`ParameterError`) or ``'warn'`` (a ``UserWarning``) on an uneven step.
        path: The file, for messages.
    """

    def __init__(self, interval: float | None, mode: str, path: Path):
        if mode not in UNEVEN_MODES:
            raise ParameterError(f"uneven_intervals must be one of {UNEVEN_MODES}, got {mode!r}")
        if interval is not None:
            try:
                interval = float(interval)
            except (TypeError, ValueError) as exc:
                raise ParameterError(f"output_interval must be a positive number, got {interval!r}") from exc
            if not (math.isfinite(interval) and interval > 0):
                raise ParameterError(f"output_interval must be positive and finite, got {interval}")
        self.interval = interval
        self.mode = mode
        self.path = path

    def check(self, t: float, previous: float, file: h5py.File) -> None:
        """Validate the next frame time ``t`` against the last written one (``-inf`` before the first frame)."""
        if not math.isfinite(previous):
            return
        step = t - previous
        if self.interval is None:
            self.interval = step
            store_dt(file, step)
        elif abs(step - self.interval) > INTERVAL_RTOL * self.interval:
            msg = (f"{self.path}: frame at t = {t!r} is {step!r} after the previous one, but the output "
                   f"interval is {self.interval!r}; The Well's format needs equally spaced frames (write "
                   "frames at fixed times and shorten the last sub-step to land on them, or pass "
                   "uneven_intervals='warn')")
            if self.mode == "error":
                raise ParameterError(msg)
            warnings.warn(msg, UserWarning, stacklevel=3)


def store_dt(file: h5py.File, dt: float) -> None:
    """Store the output interval as ``/scalars/dt`` and as the root attribute ``dt`` (a simulation parameter)."""
    sc = file["scalars"]
    if "dt" in sc:
        del sc["dt"]
    ds = sc.create_dataset("dt", data=np.asarray(dt, dtype=np.float64))
    ds.attrs["sample_varying"] = False
    ds.attrs["time_varying"] = False
    names = [n.decode() if isinstance(n, bytes) else str(n) for n in sc.attrs.get("field_names", [])]
    if "dt" not in names:
        sc.attrs["field_names"] = np.array([*names, "dt"], dtype=h5py.string_dtype())
    params = [n.decode() if isinstance(n, bytes) else str(n) for n in file.attrs.get("simulation_parameters", [])]
    if "dt" not in params:
        file.attrs["simulation_parameters"] = np.array([*params, "dt"], dtype=h5py.string_dtype())
    file.attrs["dt"] = float(dt)


def constant_arrays(values: Mapping[str, object] | None, resolution: tuple[int, ...], batch: int,
                    reserved: Mapping[str, str]) -> dict[str, np.ndarray]:
    """Validate constant fields: name -> ``(*res)`` (shared by all samples) or ``(B, *res)`` numeric arrays."""
    out: dict[str, np.ndarray] = {}
    for name, value in (values or {}).items():
        check_storable_name(name, "constant field name", reserved={"time", *reserved})
        if isinstance(value, torch.Tensor):
            value = value.detach().cpu().numpy()
        arr = np.asarray(value)
        if arr.dtype.kind not in "fiub":
            raise ShapeError(f"constant field {name!r}: expected a numeric array, got dtype {arr.dtype}")
        if tuple(arr.shape) not in (tuple(resolution), (batch, *resolution)):
            raise ShapeError(f"constant field {name!r} must have shape {tuple(resolution)} or "
                             f"{(batch, *resolution)}, got {arr.shape}")
        if not np.isfinite(arr.astype(np.float64)).all():
            raise ParameterError(f"constant field {name!r} holds NaN or inf")
        out[name] = arr
    return out


def write_constant_fields(file: h5py.File, arrays: Mapping[str, np.ndarray], batch: int, dtype, rank: int) -> None:
    """Write constant fields into ``/t0_fields`` (``time_varying=False``) and list them there."""
    if not arrays:
        return
    grp = file["t0_fields"]
    names = [n.decode() if isinstance(n, bytes) else str(n) for n in grp.attrs.get("field_names", [])]
    for name, arr in arrays.items():
        ds = grp.create_dataset(name, data=arr.astype(dtype))
        ds.attrs["sample_varying"] = bool(arr.ndim == rank + 1)
        ds.attrs["time_varying"] = False
        ds.attrs["dim_varying"] = np.ones(rank, dtype=bool)
        names.append(name)
    grp.attrs["field_names"] = np.array(names, dtype=h5py.string_dtype())
    file["extras"].attrs["constant_fields"] = json.dumps(list(arrays))


def read_constant_fields(file: h5py.File, resolution: tuple[int, ...], path: Path) -> dict[str, np.ndarray]:
    """Constant (not time-varying) scalar fields of ``/t0_fields``: name -> ``(*res)`` or ``(B, *res)``."""
    grp = file.get("t0_fields")
    out: dict[str, np.ndarray] = {}
    if not isinstance(grp, h5py.Group):
        return out
    for raw in np.atleast_1d(np.asarray(grp.attrs.get("field_names", []), dtype=object)):
        name = raw.decode() if isinstance(raw, bytes) else str(raw)
        ds = grp.get(name)
        if not isinstance(ds, h5py.Dataset) or bool(ds.attrs.get("time_varying", True)):
            continue
        if tuple(ds.shape[-len(resolution):]) != tuple(resolution):
            raise FileFormatError(f"{path}: constant field {ds.name} has shape {ds.shape}, grid {resolution}")
        out[name] = ds[()]
    return out
