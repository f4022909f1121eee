"""Learning curves in HDF5: :class:`TrainingLog` appends records to ``/training/<method>``, flushed each time."""

from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import h5py
import numpy as np
import torch

from phisim.errors import FileFormatError, ParameterError
from phisim.io.h5util import PathLike, check_output_path, open_for_read, to_json
from phisim.io.journal import Journal, check_space, journal_path, write_failure

__all__ = ["TrainingLog", "read_training"]


class TrainingLog:
    """Append learning curves to ``/training/<method>`` of an HDF5 file, one record at a time.

    Each curve is a resizable 1-D float64 dataset next to an int64 ``iteration`` dataset of the same
    length. A record may leave out curves (they get NaN) and may introduce new ones (earlier entries are
    NaN), so e.g. a validation metric can be logged every 10th iteration. The file is flushed after every
    record, and re-opening an existing log continues it.

    Crash safety: every record is first appended to the checksummed journal ``<file>.journal`` (see
    :mod:`phisim.io`), which is deleted when the log closes cleanly. A log killed at any moment leaves
    every completed record readable by :func:`read_training` (from the journal, with a warning), and
    opening the file again (a resumed run) first rebuilds it from the journal
    (:func:`phisim.io.recover_file`). Write failures raise :class:`~phisim.errors.FileFormatError`.

    Args:
        target: A file path (opened in append mode and closed by :meth:`close`) or an open ``h5py.Group``
            / ``h5py.File`` (left open; see :meth:`SimulationWriter.training_log`).
        method: The method name, e.g. ``'adam'``, ``'physgrad'``, ``'hig'``.
        attrs: Optional settings stored as attributes of the method group (numbers or strings;
            anything else is stored as JSON).

    Raises:
        ParameterError: For an invalid method name.
        FileFormatError: If the file cannot be opened or holds a malformed log.

    Example:
        >>> with TrainingLog("results.h5", "adam", attrs={"lr": 1e-3}) as log:
        ...     for it in range(100):
        ...         log.append(it, loss=loss_value, metric=metric_value)  # doctest: +SKIP
    """

    def __init__(self, target: PathLike | h5py.Group, method: str, *, attrs: Mapping[str, Any] | None = None,
                 _journal: Journal | None = None):
        if not isinstance(method, str) or not method or "/" in method:
            raise ParameterError(f"method must be a non-empty name without '/', got {method!r}")
        self.method = method
        self._file = None
        self._journal = _journal
        self._own_journal = False
        if isinstance(target, h5py.Group):
            root = target
        else:
            if not isinstance(target, (str, os.PathLike)):
                raise ParameterError(f"target must be a file path or an open h5py group, got {type(target).__name__}")
            from phisim.io.recovery import recover_file

            path = check_output_path(target, append=True)
            recover_file(path)  # a journal left by a killed run: rebuild the file from it first
            try:
                self._file = h5py.File(path, "a")
            except OSError as exc:
                raise FileFormatError(f"cannot open {path} for appending a training log: {exc}") from exc
            root = self._file
        try:
            self.group = root.require_group("training").require_group(method)
        except (TypeError, ValueError) as exc:
            self.close()
            raise FileFormatError(
                f"{root.file.filename}: /training/{method} exists and is not a group"
            ) from exc
        for k, v in (attrs or {}).items():
            self.group.attrs[k] = v if isinstance(v, (int, float, str, bool, np.generic)) else to_json(v, k)
        if self._file is not None:
            try:
                self._start_journal(root)
            except BaseException:
                self.close()
                raise
        if "iteration" not in self.group:
            self.group.create_dataset("iteration", shape=(0,), maxshape=(None,), dtype=np.int64,
                                      chunks=(1024,))
        self._n = int(self.group["iteration"].shape[0])
        for name, ds in self.group.items():
            if not isinstance(ds, h5py.Dataset) or ds.ndim != 1 or ds.shape[0] != self._n:
                self.close()
                raise FileFormatError(
                    f"{self.group.name}/{name} is not a 1-D curve of the log's length {self._n}"
                )
        if self._journal is not None and not self._own_journal:
            self._snapshot(method, self.group)  # a log inside a SimulationWriter's file

    def _start_journal(self, root: h5py.File) -> None:
        """Open ``<file>.journal`` with a snapshot of every log already in the file (so it alone rebuilds them)."""
        self._journal = Journal(journal_path(root.filename), fresh=True)
        self._own_journal = True
        for method, g in root["training"].items():
            if isinstance(g, h5py.Group):
                self._snapshot(method, g)

    def _snapshot(self, method: str, g: h5py.Group) -> None:
        if self._journal is None:
            return
        curves = {n: ds[()].tolist() for n, ds in g.items() if isinstance(ds, h5py.Dataset) and n != "iteration"}
        it = g["iteration"][()].tolist() if "iteration" in g else []
        attrs = {k: (v.item() if isinstance(v, np.generic) else v) for k, v in g.attrs.items()
                 if isinstance(v, (int, float, str, bool, np.generic))}
        self._journal.write_json(b"L", {"method": method, "attrs": attrs, "iteration": it, "curves": curves})

    @property
    def n_records(self) -> int:
        """Number of records appended so far (including those of an earlier session)."""
        return self._n

    def append(self, iteration: int, **values: float) -> None:
        """Append one record and flush.

        Args:
            iteration: The iteration (or step/epoch) number.
            **values: Curve name -> number (python float, numpy scalar or 1-element tensor).

        Raises:
            ParameterError: For no values, non-numeric values or a closed log.
        """
        if not self.group.id.valid:
            raise ParameterError(f"TrainingLog {self.method!r} is closed")
        if not values:
            raise ParameterError("append needs at least one value, e.g. log.append(it, loss=0.5)")
        nums = {}
        for name, v in values.items():
            if name == "iteration" or "/" in name:
                raise ParameterError(f"invalid curve name {name!r}")
            if isinstance(v, torch.Tensor):
                if v.numel() != 1:
                    raise ParameterError(
                        f"curve {name!r}: expected one number, got a tensor of shape {tuple(v.shape)}"
                    )
                v = v.item()
            try:
                nums[name] = float(v)
            except (TypeError, ValueError) as exc:
                raise ParameterError(f"curve {name!r}: {v!r} is not a number") from exc
        check_space(self.group.file.filename, 4096)
        if self._journal is not None:  # the commit record, complete before the HDF5 write
            self._journal.write_json(b"R", {"method": self.method, "iteration": int(iteration), "values": nums})
        try:
            self._write(int(iteration), nums)
        except (OSError, RuntimeError) as exc:
            raise write_failure(self.group.file.filename, exc, "append a training record to") from exc
        self._n += 1

    def _write(self, iteration: int, nums: dict[str, float]) -> None:
        n = self._n
        for name in nums:
            if name not in self.group:
                ds = self.group.create_dataset(name, shape=(n,), maxshape=(None,), dtype=np.float64,
                                               chunks=(1024,))
                if n:
                    ds[:] = np.nan
        for name, ds in self.group.items():
            ds.resize((n + 1,))
            if name == "iteration":
                ds[n] = int(iteration)
            else:
                ds[n] = nums.get(name, np.nan)
        self.group.file.flush()

    def curves(self) -> dict[str, np.ndarray]:
        """All curves of this method (``iteration`` included) as numpy arrays."""
        return {name: ds[()] for name, ds in self.group.items()}

    def close(self) -> None:
        """Flush; close the file (and delete its journal) if this log opened it.

        Raises:
            FileFormatError: If the final flush fails; the journal is then kept (nothing is lost).
        """
        if self._file is not None and self._file.id.valid:
            try:
                self._file.flush()
                self._file.close()
            except (OSError, RuntimeError) as exc:
                if self._own_journal and self._journal is not None:
                    self._journal.close(delete=False)
                raise write_failure(self._file.filename, exc, "flush and close") from exc
        if self._own_journal and self._journal is not None and not self._journal.closed:
            self._journal.close(delete=True)

    def __enter__(self) -> TrainingLog:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _read_training_group(grp: h5py.Group, p: Path) -> dict[str, dict[str, np.ndarray]]:
    out: dict[str, dict[str, np.ndarray]] = {}
    for method, g in grp.items():
        if not isinstance(g, h5py.Group) or "iteration" not in g:
            raise FileFormatError(f"{p}: {g.name} is not a training log (no 'iteration' dataset)")
        n = g["iteration"].shape[0]
        curves = {}
        for name, ds in g.items():
            if not isinstance(ds, h5py.Dataset) or ds.ndim != 1:
                raise FileFormatError(f"{p}: {ds.name} is not a 1-D curve")
            curves[name] = ds[:n]
        out[method] = curves
    return out


def read_training(path: PathLike) -> dict[str, dict[str, np.ndarray]]:
    """Read every training log of a file.

    Args:
        path: The HDF5 file.

    Returns:
        Method -> curve name -> 1-D array (``iteration`` included); empty if the file has no ``/training``.

    Raises:
        FileFormatError: If the file is missing, not HDF5, or its ``/training`` group is malformed.
    """
    from phisim.io.recovery import load_journal

    p = Path(path)
    journal = load_journal(p)
    if journal is not None:  # not closed cleanly: the journal holds every complete record of its logs
        out: dict[str, dict[str, np.ndarray]] = {}
        if journal.header is None:  # a training-only file: keep readable logs the journal does not cover
            try:
                out = read_training_hdf5(p)
            except FileFormatError:
                out = {}
        out.update(journal.training_curves())
        return out
    return read_training_hdf5(p)


def read_training_hdf5(p: Path) -> dict[str, dict[str, np.ndarray]]:
    """The training logs as stored in the HDF5 file itself (no journal)."""
    with open_for_read(p) as f:
        grp = f.get("training")
        if grp is None:
            return {}
        if not isinstance(grp, h5py.Group):
            raise FileFormatError(f"{p}: /training is not a group")
        try:
            return _read_training_group(grp, p)
        except (OSError, RuntimeError) as exc:
            raise FileFormatError(f"{p}: damaged /training group: {exc}") from exc
