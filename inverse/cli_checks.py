"""The checks of the ``phisim`` command's files and folders, in one place, with one wording per mistake.

Every command checks its paths with these helpers before any work starts, so the same mistake reads the same
whatever the command:

==============================  ========================================================================
mistake                         message (``what`` names the argument, e.g. "input file")
==============================  ========================================================================
missing file                    ``<what> <path> does not exist``
a folder instead of a file      ``<what> <path> is a folder, not a file``
a pipe or device                ``<what> <path> is not a regular file (a pipe, socket or device)``
output that cannot be written   ``<what> <path> cannot be written: <reason>``
a model and an HDF5 file        ``... is a model file, not an HDF5 file: the order is MODEL INPUTS`` (and
swapped                         the converse)
unknown dataset key             ``<path> has no dataset '<key>'; its datasets: a, b, ...; pass one with --key``
==============================  ========================================================================

Each raises a :class:`~phisim.errors.FileFormatError` (a file that is not what it should be) or a
:class:`~phisim.errors.ParameterError` (a path argument that cannot work); the command prints it as one line.
"""

from __future__ import annotations

import json
import math
import os
import stat
from pathlib import Path

import h5py
import numpy as np

from phisim.checks import existing_file
from phisim.errors import FileFormatError, ParameterError

__all__ = ["existing_file", "hdf5_file", "model_file", "writable_file", "writable_dir", "dataset_key",
           "json_summary", "finite_or_none", "NULL_NOTE_KEY"]

_ZIP = b"PK\x03\x04"  # torch.save writes a zip archive
_HDF5 = b"\x89HDF\r\n\x1a\n"


def _magic(p: Path) -> bytes:
    try:
        with open(p, "rb") as f:
            return f.read(8)
    except OSError as exc:
        raise FileFormatError(f"{p} cannot be read: {exc.strerror or exc}") from exc


def hdf5_file(path, what: str, *, argument_order: str | None = None) -> Path:
    """``path`` if it is an existing HDF5 file.

    Args:
        path: The file.
        what: What the file is for, e.g. ``"input file"``.
        argument_order: The command's usage (``"phisim predict MODEL INPUTS"``), named when a model file is
            given where an HDF5 file belongs.

    Raises:
        FileFormatError: Missing, a folder, a model file, or another format.
    """
    p = existing_file(path, what)
    head = _magic(p)
    if head.startswith(_ZIP):
        order = f": the order is {argument_order}" if argument_order else ""
        raise FileFormatError(f"{what} {p} is a model file (a torch archive), not an HDF5 file{order}")
    if not h5py.is_hdf5(p):
        kind = "empty" if p.stat().st_size == 0 else "another format"
        raise FileFormatError(f"{what} {p} is not an HDF5 file ({kind})")
    return p


def model_file(path, what: str = "model file", *, argument_order: str | None = None) -> Path:
    """``path`` if it is an existing file that looks like a model file (a torch archive).

    Raises:
        FileFormatError: Missing, a folder, or an HDF5 file (the arguments swapped; ``argument_order`` names the
            right order). Other formats are left to the model reader, which says what it found.
    """
    p = existing_file(path, what)
    if _magic(p).startswith(_HDF5) or h5py.is_hdf5(p):
        order = f": the order is {argument_order}" if argument_order else ""
        raise FileFormatError(f"{what} {p} is an HDF5 file, not a model file (<out>.<method>.model.pt){order}")
    return p


def _first_blocking_file(p: Path) -> Path | None:
    """The first existing non-folder on the way to ``p`` (``/dev/null`` for ``/dev/null/x``), if any."""
    for parent in reversed([p, *p.parents]):
        if parent.exists() and not parent.is_dir():
            return parent
    return None


def _check_can_create(p: Path, what: str) -> None:
    """The folder ``p`` exists and is writable, or its nearest existing folder is (so it can be created)."""
    existing = next(q for q in [p, *p.parents] if q.exists())
    if not os.access(existing, os.W_OK | os.X_OK):
        raise ParameterError(f"{what} {p} cannot be written: {existing} is not writable")


def writable_dir(path, what: str) -> Path:
    """Check that the output folder ``path`` can be written: it is a writable folder, or it can be created in
    the nearest existing folder above it. Nothing is created (a command that fails later leaves no folder).

    Raises:
        ParameterError: ``path`` or a folder on its way is a file, or the folder is not writable.
    """
    p = Path(path)
    blocking = _first_blocking_file(p)
    if blocking is not None:
        where = "it is a file, not a folder" if blocking == p else f"{blocking} is a file, not a folder"
        raise ParameterError(f"{what} {p} cannot be written: {where}")
    _check_can_create(p, what)
    return p


def writable_file(path, what: str, *, example: str = "out.h5") -> Path:
    """Check that the output file ``path`` can be written (its folder exists or can be created, and is
    writable; an existing file is writable). Nothing is created or changed.

    Raises:
        ParameterError: ``path`` is a folder, a folder on its way is a file, the folder is not writable, or the
            file is read-only.
    """
    p = Path(path)
    if p.is_dir():
        raise ParameterError(f"{what} {p} is a folder, not a file; give a file name such as {p / example}")
    if p.exists() and not stat.S_ISREG(p.stat().st_mode):
        raise ParameterError(f"{what} {p} is not a regular file (a pipe, socket or device)")
    blocking = _first_blocking_file(p.parent)
    if blocking is not None:
        raise ParameterError(f"{what} {p} cannot be written: {blocking} is a file, not a folder")
    existing = next(q for q in p.parents if q.exists())
    if not os.access(existing, os.W_OK | os.X_OK):
        raise ParameterError(f"{what} {p} cannot be written: {existing} is not writable")
    if p.exists() and not os.access(p, os.W_OK):
        raise ParameterError(f"{what} {p} cannot be written: the file is read-only")
    return p


def dataset_key(path, key: str | None, *, flag: str = "--key") -> str:
    """The dataset ``key`` of the HDF5 file ``path``; None picks the only dataset of the file, else ``inputs``.

    Raises:
        FileFormatError: The file holds no such dataset (the message lists the datasets it holds).
    """
    p = Path(path)
    with h5py.File(p, "r") as f:
        names: list[str] = []
        f.visititems(lambda n, o: names.append(n) if isinstance(o, h5py.Dataset) else None)
        if key is None:
            key = names[0] if len(names) == 1 else "inputs"
        key = key.lstrip("/")
        if key in names:
            return key
    if not names:
        raise FileFormatError(f"{p} holds no datasets")
    shown = ", ".join(names[:20]) + (f", ... ({len(names)} in all)" if len(names) > 20 else "")
    raise FileFormatError(f"{p} has no dataset {key!r}; its datasets: {shown}; pass one with {flag}")


def finite_or_none(value):
    """A number for JSON: NaN and ±Inf become None (``null``); containers are converted recursively."""
    if isinstance(value, (float, np.floating)) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: finite_or_none(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [finite_or_none(v) for v in value]
    return value


#: The key a summary gets when :func:`json_summary` wrote a non-finite number as ``null``.
NULL_NOTE_KEY = "null_means"


def json_summary(summary: dict, indent: int | None = None) -> str:
    """Strict JSON of a summary: NaN and ±Inf are written as ``null`` (JSON has neither), and the summary then
    says so under the key ``null_means``.

    Args:
        summary: A mapping of JSON values (floats may be NaN or infinite).
        indent: ``json.dumps``'s indent (None: one line).
    """
    clean = finite_or_none(summary)
    if _has_replaced(summary, clean):
        clean[NULL_NOTE_KEY] = "not a finite number: NaN (not measured, e.g. no physics loss) or infinite"
    return json.dumps(clean, ensure_ascii=False, allow_nan=False, indent=indent)


def _has_replaced(before, after) -> bool:
    if isinstance(before, dict):
        return any(_has_replaced(v, after[k]) for k, v in before.items())
    if isinstance(before, (list, tuple)):
        return any(_has_replaced(a, b) for a, b in zip(before, after))
    return before is not None and after is None
