"""Learning curves in HDF5: :class:`TrainingLog` appends records to ``/training/<method>``, flushed each time."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import h5py
import numpy as np
import torch

from ._h5util import PathLike, open_for_read, to_json
from .errors import FileFormatError, ParameterError

__all__ = ["TrainingLog", "read_training"]


class TrainingLog:
    """Append learning curves to ``/training/<method>`` of an HDF5 file, one record at a time.

    Each curve is a resizable 1-D float64 dataset next to an int64 ``iteration`` dataset of the same
    length. A record may leave out curves (they get NaN) and may introduce new ones (earlier entries are
    NaN), so e.g. a validation metric can be logged every 10th iteration. The file is flushed after every
    record, and re-opening an existing log continues it.

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

    def __init__(self, target: PathLike | h5py.Group, method: str, *, attrs: Mapping[str, Any] | None = None):
        if not isinstance(method, str) or not method or "/" in method:
            raise ParameterError(f"method must be a non-empty name without '/', got {method!r}")
        self.method = method
        if isinstance(target, h5py.Group):
            self._file = None
            root = target
        else:
            path = Path(target)
            path.parent.mkdir(parents=True, exist_ok=True)
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
        self._n = n + 1

    def curves(self) -> dict[str, np.ndarray]:
        """All curves of this method (``iteration`` included) as numpy arrays."""
        return {name: ds[()] for name, ds in self.group.items()}

    def close(self) -> None:
        """Flush; close the file if this log opened it."""
        if self._file is not None and self._file.id.valid:
            self._file.flush()
            self._file.close()

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
    p = Path(path)
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
