"""Small HDF5/JSON helpers shared by the modules of :mod:`phisim.io`: JSON encoding, output-path checks,
typed opening for reading, and reading string attributes and required objects with errors that name the file."""

from __future__ import annotations

import dataclasses
import json
import os
from collections.abc import Sequence
from pathlib import Path

import h5py
import numpy as np
import torch

from phisim.checks import existing_file
from phisim.errors import FileFormatError, ParameterError
from phisim.io.journal import journal_path

PathLike = str | os.PathLike


def json_default(obj):
    """``json.dumps`` fallback for paths, numpy/torch values, dtypes, dataclasses and sets."""
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
    """``obj`` as sorted JSON; ParameterError naming ``what`` if it cannot be encoded."""
    try:
        return json.dumps(obj, default=json_default, sort_keys=True)
    except (TypeError, ValueError) as exc:
        raise ParameterError(
            f"{what} must be JSON-serialisable (numbers, strings, lists, dicts, numpy/torch arrays, "
            f"dataclasses): {exc}"
        ) from exc


def check_output_path(path: PathLike, *, append: bool = False) -> Path:
    """Check that an HDF5 output file can be written, before any work starts; create its folder.

    Args:
        path: The file to create (``append=False``: an existing file is replaced) or to append to.
        append: Whether an existing file will be opened for appending (it must then be HDF5).

    Returns:
        The path.

    Raises:
        FileFormatError: If the path is a folder or a special file, the folder cannot be created or
            written, or (``append``) an existing file is not HDF5.
    """
    p = Path(path)
    if p.exists() and not p.is_file():
        kind = "a directory" if p.is_dir() else "not a regular file"
        raise FileFormatError(f"output {p} is {kind}; give a file name such as {p / 'out.h5'}")
    try:
        p.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise FileFormatError(f"cannot create the folder of the output {p}: {exc.strerror or exc}") from exc
    if not os.access(p.parent, os.W_OK | os.X_OK):
        raise FileFormatError(f"cannot write the output {p}: its folder {p.parent} is not writable")
    if p.exists():
        if not os.access(p, os.W_OK):
            raise FileFormatError(f"cannot write the output {p}: the file is read-only")
        if append and p.stat().st_size > 0 and not h5py.is_hdf5(p) and not journal_path(p).exists():
            raise FileFormatError(
                f"output {p} exists and is not an HDF5 file; choose another file name or remove it"
            )
    return p


def open_for_read(path: PathLike) -> h5py.File:
    """Open an HDF5 file read-only with errors that say what is wrong (missing, folder, pipe, truncated...)."""
    p = existing_file(path, "HDF5 file")
    try:
        return h5py.File(p, "r")
    except OSError as exc:
        msg = str(exc)
        size = p.stat().st_size
        if "truncated file" in msg:
            raise FileFormatError(
                f"{p} ({size} bytes) is truncated (shorter than its HDF5 header says): it was cut short by a crash, "
                "a full disk or an incomplete copy. If it has a '.journal' sidecar, phisim.io.recover_file "
                "rebuilds it"
            ) from exc
        if "unable to lock file" in msg.lower():
            raise FileFormatError(
                f"{p} is open for writing in another process (HDF5 file lock): wait for the writer to close "
                "it, or set HDF5_USE_FILE_LOCKING=FALSE to read the frames flushed so far"
            ) from exc
        raise FileFormatError(
            f"{p} ({size} bytes) is not a readable HDF5 file (corrupt, truncated or another format): {exc}"
        ) from exc


# ---- attributes and required objects ------------------------------------------------------------------


#: Root attributes of The Well's layout (and ours): a simulation parameter may not take one of these names.
RESERVED_ROOT_NAMES = frozenset({"dataset_name", "grid_type", "n_spatial_dims", "n_trajectories",
                                 "simulation_parameters", "format", "phisim_format"})


def check_storable_name(name, what: str, reserved=frozenset()) -> str:
    """A name the file layout can store as a dataset, group or attribute name, and read back.

    Args:
        name: The name.
        what: What it names, for the message (``'field name'``, ``'parameter name'``, ``'method'``...).
        reserved: Names the layout keeps for itself in that place.

    Raises:
        ParameterError: For a non-string, an empty name, ``.``/``..``, a ``/``, a NUL or other control character,
            or a reserved name.
    """
    if not isinstance(name, str) or not name:
        raise ParameterError(f"{what} must be a non-empty string, got {name!r}")
    if name in (".", "..") or "/" in name or any(ord(c) < 32 for c in name):
        raise ParameterError(f"{what} {name!r} cannot be stored in HDF5: no '/', no control characters (NUL, "
                             "newline...), not '.' or '..'")
    if name in reserved:
        raise ParameterError(f"{what} {name!r} is reserved by the file layout; choose another name")
    return name


def str_array(names: Sequence[str]) -> np.ndarray:
    """A numpy array of variable-length UTF-8 strings (also for an empty list), for HDF5 attributes."""
    return np.array([str(n) for n in names], dtype=h5py.string_dtype())


def attr_str(value) -> str:
    """An HDF5 string attribute (``bytes``, ``str`` or a 0-d array) as ``str``."""
    if isinstance(value, bytes):
        return value.decode("utf-8")
    if isinstance(value, np.ndarray) and value.ndim == 0:
        return attr_str(value.item())
    return str(value)


def attr_str_list(value) -> list[str]:
    """An HDF5 attribute holding one string or an array of strings as a list of ``str``."""
    if isinstance(value, (str, bytes)):
        return [attr_str(value)]
    return [attr_str(v) for v in np.atleast_1d(np.asarray(value, dtype=object))]


def need(group, key: str, path: Path, kind=None):
    """``group[key]``, required: FileFormatError naming the file if it is missing, unreadable or not a ``kind``."""
    try:
        obj = group[key]
    except (KeyError, OSError, RuntimeError, ValueError) as exc:
        where = f"{group.name.rstrip('/')}/{key}"
        raise FileFormatError(
            f"{path}: missing or unreadable {where} ({exc}); "
            "not a Well/phisim simulation file, or a damaged one"
        ) from exc
    if kind is not None and not isinstance(obj, kind):
        raise FileFormatError(f"{path}: {obj.name} should be a {kind.__name__}")
    return obj


def need_attr(obj, key: str, path: Path):
    """The attribute ``key`` of ``obj``, required by The Well's layout (FileFormatError naming the file)."""
    if key not in obj.attrs:
        raise FileFormatError(f"{path}: {obj.name} lacks the attribute {key!r} required by The Well's layout")
    return obj.attrs[key]
