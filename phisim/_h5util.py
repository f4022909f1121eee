"""Small HDF5/JSON helpers shared by :mod:`phisim.io` and :mod:`phisim.traininglog`."""

from __future__ import annotations

import dataclasses
import json
import os
from pathlib import Path

import h5py
import numpy as np
import torch

from .errors import FileFormatError, ParameterError

PathLike = str | os.PathLike


def json_default(obj):
    if isinstance(obj, Path):
        return str(obj)
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, torch.Tensor):
        return obj.detach().cpu().tolist()
    if isinstance(obj, torch.dtype):
        return str(obj)
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return dataclasses.asdict(obj)
    if isinstance(obj, (set, frozenset)):
        return sorted(obj)
    raise TypeError(f"object of type {type(obj).__name__} is not JSON serialisable")


def to_json(obj, what: str) -> str:
    try:
        return json.dumps(obj, default=json_default, sort_keys=True)
    except (TypeError, ValueError) as exc:
        raise ParameterError(
            f"{what} must be JSON-serialisable (numbers, strings, lists, dicts, numpy/torch arrays, "
            f"dataclasses): {exc}"
        ) from exc


def open_for_read(path: PathLike) -> h5py.File:
    p = Path(path)
    if not p.exists():
        raise FileFormatError(f"{p} does not exist")
    if p.is_dir():
        raise FileFormatError(f"{p} is a directory, not an HDF5 file")
    try:
        return h5py.File(p, "r")
    except OSError as exc:
        if "lock" in str(exc).lower():
            raise FileFormatError(
                f"{p} is open for writing in another process (HDF5 file lock): wait for the writer to close "
                "it, or set HDF5_USE_FILE_LOCKING=FALSE to read the frames flushed so far"
            ) from exc
        size = p.stat().st_size
        raise FileFormatError(
            f"{p} ({size} bytes) is not a readable HDF5 file (corrupt, truncated or another format): {exc}"
        ) from exc
