"""Learning curves in HDF5: :class:`TrainingLog` appends records to ``/training/<method>``, flushed each time.

A run that states its length (``planned_iterations``) is marked incomplete until :meth:`TrainingLog.finish`:
:func:`read_training` returns every method's curves as :class:`TrainingCurves`, which say whether the run
completed and how far it got, and warns about incomplete ones. A file that already holds a method's
records is never written over silently: opening its log again needs ``resume=True`` (continue) or
``overwrite=True`` (replace).

A training-only file left with a journal by a killed log is repaired here (:func:`repair_training_file`);
a simulation file needs :func:`phisim.io.recover_file`, which rebuilds its frames with the writer.
"""

from __future__ import annotations

import os
import shutil
import warnings
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import h5py
import numpy as np
import torch

from phisim.errors import FileFormatError, IncompleteFileWarning, ParameterError
from phisim.io.h5util import PathLike, check_output_path, check_storable_name, open_for_read, to_json
from phisim.io.interrupts import uninterrupted
from phisim.io.journal import (
    Journal,
    JournalContent,
    check_space,
    journal_path,
    load_journal,
    read_journal,
    write_failure,
)

__all__ = ["TrainingLog", "TrainingCurves", "read_training", "read_training_group", "read_training_hdf5",
           "training_run", "repair_training_file", "rebuild_from_journal", "PLANNED", "COMPLETE"]

#: Attribute of ``/training/<method>``: the number of iterations the run was started for.
PLANNED = "planned_iterations"
#: Attribute of ``/training/<method>``: True once the run finished (False while it runs or after it stopped).
COMPLETE = "complete"


class TrainingCurves(dict):
    """The curves of one method (curve name -> 1-D array, ``iteration`` included) and the state of its run.

    A plain ``dict`` of arrays, with the group's attributes and a completion state on top.

    Attributes:
        attrs: The attributes of ``/training/<method>`` (settings, :data:`PLANNED`, :data:`COMPLETE`...).
    """

    def __init__(self, curves: Mapping[str, np.ndarray] | None = None, attrs: Mapping[str, Any] | None = None):
        super().__init__(curves or {})
        self.attrs = dict(attrs or {})

    @property
    def records(self) -> int:
        """Number of records (iterations logged)."""
        it = self.get("iteration")
        return 0 if it is None else int(len(it))

    @property
    def planned(self) -> int | None:
        """The iterations the run was started for (None: not recorded)."""
        v = self.attrs.get(PLANNED)
        return None if v is None else int(v)

    @property
    def complete(self) -> bool | None:
        """True: the run finished; False: it stopped early (killed, interrupted) or still runs; None: the log
        does not say (written without ``planned_iterations``, or by an earlier phisim)."""
        v = self.attrs.get(COMPLETE)
        return None if v is None else bool(v)

    @property
    def status(self) -> str:
        """One line: ``complete (N iterations)``, ``INCOMPLETE: stopped after k of N iterations ...`` or
        ``k records``."""
        n = self.records
        if self.complete:
            return f"complete ({n} iterations)"
        if self.complete is False:
            of = f" of {self.planned}" if self.planned is not None else ""
            return (f"INCOMPLETE: stopped after {n}{of} iterations (killed or interrupted, or still running); "
                    "resume it or overwrite it")
        return f"{n} records"


def _plain_attrs(attrs) -> dict:
    return {k: (v.item() if isinstance(v, np.generic) else v) for k, v in attrs.items()
            if isinstance(v, (int, float, str, bool, np.generic))}


class TrainingLog:
    """Append learning curves to ``/training/<method>`` of an HDF5 file, one record at a time.

    Each curve is a resizable 1-D float64 dataset next to an int64 ``iteration`` dataset of the same
    length. A record may leave out curves (they get NaN) and may introduce new ones (earlier entries are
    NaN), so e.g. a validation metric can be logged every 10th iteration. The file is flushed after every
    record. A log that already holds records is continued only with ``resume=True`` and replaced only with
    ``overwrite=True``; otherwise opening it raises :class:`~phisim.errors.FileFormatError` (no results are
    lost by accident).

    Run state: with ``planned_iterations`` the group gets the attributes ``planned_iterations`` and
    ``complete=False``; :meth:`finish` sets ``complete=True``. :func:`read_training` and ``phisim info``
    report a run that stopped before :meth:`finish` as incomplete, with how far it got.

    Crash safety: every record is first appended to the checksummed journal ``<file>.journal`` (see
    :mod:`phisim.io`), which is deleted when the log closes cleanly. A log killed at any moment leaves
    every completed record readable by :func:`read_training` (from the journal, with a warning), and
    opening the file again (a resumed run) first rebuilds it from the journal (:func:`repair_training_file`).
    A record is written with SIGINT/SIGTERM deferred (:func:`phisim.io.interrupts.uninterrupted`), so an
    interrupt never tears it. Write failures raise :class:`~phisim.errors.FileFormatError`.

    Args:
        target: A file path (opened in append mode and closed by :meth:`close`) or an open ``h5py.Group``
            / ``h5py.File`` (left open; see :meth:`SimulationWriter.training_log`).
        method: The method name, e.g. ``'adam'``, ``'physgrad'``, ``'hig'``.
        attrs: Optional settings stored as attributes of the method group (numbers or strings;
            anything else is stored as JSON).
        planned_iterations: The length of the run; marks the log incomplete until :meth:`finish`.
        overwrite: Replace an existing log of this method.
        resume: Continue an existing log of this method.
        journal: The journal of the :class:`~phisim.io.SimulationWriter` whose open file ``target`` belongs to
            (records go into it; see :meth:`SimulationWriter.training_log`).

    Raises:
        ParameterError: For an invalid method name, or both ``overwrite`` and ``resume``.
        FileFormatError: If the file cannot be opened, holds a malformed log, already holds records of this
            method (without ``overwrite``/``resume``), or is a simulation file left unrecovered by a killed
            writer (call :func:`phisim.io.recover_file` first).

    Example:
        >>> with TrainingLog("results.h5", "adam", attrs={"lr": 1e-3}) as log:
        ...     for it in range(100):
        ...         log.append(it, loss=loss_value, metric=metric_value)  # doctest: +SKIP
    """

    def __init__(self, target: PathLike | h5py.Group, method: str, *, attrs: Mapping[str, Any] | None = None,
                 planned_iterations: int | None = None, overwrite: bool = False, resume: bool = False,
                 journal: Journal | None = None):
        check_storable_name(method, "method")
        if overwrite and resume:
            raise ParameterError("overwrite=True and resume=True exclude each other: replace the log or continue it")
        if planned_iterations is not None and (isinstance(planned_iterations, bool) or not isinstance(
                planned_iterations, (int, np.integer)) or planned_iterations < 0):
            raise ParameterError(f"planned_iterations must be an int >= 0, got {planned_iterations!r}")
        self.method = method
        self._file = None
        self._journal = journal
        self._own_journal = False
        if isinstance(target, h5py.Group):
            root = target
        else:
            if not isinstance(target, (str, os.PathLike)):
                raise ParameterError(f"target must be a file path or an open h5py group, got {type(target).__name__}")
            path = check_output_path(target, append=True)
            repair_training_file(path)  # a journal left by a killed run: rebuild the file from it first
            try:
                self._file = h5py.File(path, "a")
            except OSError as exc:
                raise FileFormatError(f"cannot open {path} for appending a training log: {exc}") from exc
            root = self._file
        try:
            training = root.require_group("training")
            existing = training.get(method)
            if existing is not None and not isinstance(existing, h5py.Group):
                raise TypeError("not a group")
            held = _records(existing)
            if held and not (overwrite or resume):
                state = TrainingCurves({"iteration": np.zeros(held)}, _plain_attrs(existing.attrs)).status
                name = root.file.filename
                self.close()
                raise FileFormatError(
                    f"{name}: /training/{method} already holds a run ({state}); pass resume=True to "
                    "continue it or overwrite=True to replace it (phisim train/compare: --resume or --overwrite), "
                    "or write to another file"
                )
            if existing is not None and overwrite:
                del training[method]
            self.group = training.require_group(method)
        except (TypeError, ValueError) as exc:
            name = root.file.filename
            self.close()
            raise FileFormatError(f"{name}: /training/{method} exists and is not a group") from exc
        for k, v in (attrs or {}).items():
            self.group.attrs[k] = v if isinstance(v, (int, float, str, bool, np.generic)) else to_json(v, k)
        if planned_iterations is not None:
            self.group.attrs[PLANNED] = int(planned_iterations)
            self.group.attrs[COMPLETE] = False
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
                where = f"{self.group.file.filename}: {self.group.name}/{name}"
                self.close()
                raise FileFormatError(f"{where} is not a 1-D curve of the log's length {self._n}")
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
        self._journal.write_json(b"L", {"method": method, "attrs": _plain_attrs(g.attrs), "iteration": it,
                                        "curves": curves})

    @property
    def planned_iterations(self) -> int | None:
        """The iterations the run was started for (None: not given)."""
        v = self.group.attrs.get(PLANNED)
        return None if v is None else int(v)

    def finish(self) -> None:
        """Mark the run complete (attribute ``complete=True``), in the journal first; call it after the last
        record. A log never finished reads back as incomplete when it was given ``planned_iterations``.

        Raises:
            ParameterError: For a closed log.
        """
        if not self.group.id.valid:
            raise ParameterError(f"TrainingLog {self.method!r} is closed")
        with uninterrupted():
            if self._journal is not None:
                self._journal.write_json(b"A", {"method": self.method, "attrs": {COMPLETE: True}})
            try:
                self.group.attrs[COMPLETE] = True
                self.group.file.flush()
            except (OSError, RuntimeError) as exc:
                raise write_failure(self.group.file.filename, exc, "mark the run complete in") from exc

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
        with uninterrupted():  # an interrupt waits for the record: never half of one in the file
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
        with uninterrupted():
            if self._file is not None and self._file.id.valid:
                name = self._file.filename
                try:
                    self._file.flush()
                    self._file.close()
                except (OSError, RuntimeError) as exc:
                    if self._own_journal and self._journal is not None:
                        self._journal.close(delete=False)
                    raise write_failure(name, exc, "flush and close") from exc
            if self._own_journal and self._journal is not None and not self._journal.closed:
                self._journal.close(delete=True)

    def __enter__(self) -> TrainingLog:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _records(g) -> int:
    if not isinstance(g, h5py.Group) or not isinstance(g.get("iteration"), h5py.Dataset):
        return 0
    return int(g["iteration"].shape[0])


def read_training_group(grp: h5py.Group, p: Path) -> dict[str, TrainingCurves]:
    """Every log of an open ``/training`` group: method -> :class:`TrainingCurves`.

    Raises:
        FileFormatError: A member that is not a log, or a curve that is not 1-D.
    """
    out: dict[str, TrainingCurves] = {}
    for method, g in grp.items():
        if not isinstance(g, h5py.Group) or "iteration" not in g:
            raise FileFormatError(f"{p}: {g.name} is not a training log (no 'iteration' dataset)")
        n = g["iteration"].shape[0]
        curves = {}
        for name, ds in g.items():
            if not isinstance(ds, h5py.Dataset) or ds.ndim != 1:
                raise FileFormatError(f"{p}: {ds.name} is not a 1-D curve")
            curves[name] = ds[:n]
        out[method] = TrainingCurves(curves, _plain_attrs(g.attrs))
    return out


def journal_curves(content: JournalContent) -> dict[str, TrainingCurves]:
    """The training logs a journal holds: method -> :class:`TrainingCurves`."""
    return {m: TrainingCurves(c, content.training[m].get("attrs", {}))
            for m, c in content.training_curves().items()}


def read_training(path: PathLike, *, warn: bool = True) -> dict[str, TrainingCurves]:
    """Read every training log of a file.

    Args:
        path: The HDF5 file.
        warn: Warn (:class:`~phisim.errors.IncompleteFileWarning`) about runs that stopped before their
            last iteration, saying how far they got.

    Returns:
        Method -> :class:`TrainingCurves` (curve name -> 1-D array, ``iteration`` included, with
        ``.complete`` and ``.status`` of the run); empty if the file has no ``/training``.

    Raises:
        FileFormatError: If the file is missing, not HDF5, or its ``/training`` group is malformed.
    """
    p = Path(path)
    journal = load_journal(p)
    if journal is not None:  # not closed cleanly: the journal holds every complete record of its logs
        out: dict[str, TrainingCurves] = {}
        if journal.header is None:  # a training-only file: keep readable logs the journal does not cover
            try:
                out = read_training_hdf5(p)
            except FileFormatError:
                out = {}
        out.update(journal_curves(journal))
    else:
        out = read_training_hdf5(p)
    if warn:
        stopped = [f"{m}: {c.status}" for m, c in out.items() if c.complete is False]
        if stopped:
            warnings.warn(f"{p} holds incomplete training runs: " + "; ".join(stopped), IncompleteFileWarning,
                          stacklevel=2)
    return out


def training_run(path: PathLike, method: str) -> TrainingCurves | None:
    """The log of one method in a file (read as :func:`read_training` does, without warnings), or None when
    the file or the method's log does not exist or holds no records."""
    p = Path(path)
    if not p.exists() and not journal_path(p).exists():
        return None
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", IncompleteFileWarning)
        curves = read_training(p, warn=False).get(method)
    return curves if curves is not None and curves.records else None


def read_training_hdf5(p: Path) -> dict[str, TrainingCurves]:
    """The training logs as stored in the HDF5 file itself (no journal)."""
    with open_for_read(p) as f:
        grp = f.get("training")
        if grp is None:
            return {}
        if not isinstance(grp, h5py.Group):
            raise FileFormatError(f"{p}: /training is not a group")
        try:
            return read_training_group(grp, p)
        except (OSError, RuntimeError) as exc:
            raise FileFormatError(f"{p}: damaged /training group: {exc}") from exc


# ---- repair from the journal --------------------------------------------------------------------------


def write_journal_log(f: h5py.File, method: str, log: dict) -> None:
    """Write one training log decoded from a journal into ``/training/<method>`` of ``f`` (replacing it)."""
    grp = f.require_group("training")
    if method in grp:
        del grp[method]
    g = grp.create_group(method)
    for k, v in log.get("attrs", {}).items():
        g.attrs[k] = v
    n = len(log["iteration"])
    g.create_dataset("iteration", data=np.asarray(log["iteration"], dtype=np.int64), maxshape=(None,),
                     chunks=(1024,))
    for name, values in log["curves"].items():
        arr = np.full(n, np.nan)
        arr[: len(values)] = values
        g.create_dataset(name, data=arr, maxshape=(None,), chunks=(1024,))


def rebuild_from_journal(p: Path, content: JournalContent, build_base: Callable[[Path], None]) -> None:
    """Replace ``p`` atomically by a file that ``build_base(tmp)`` creates plus the journal's training logs,
    then delete the journal.

    Raises:
        FileFormatError: If the new file cannot be written (the old file and the journal are then kept).
    """
    tmp = p.with_name(p.name + ".recover.tmp")
    try:
        build_base(tmp)
        with h5py.File(tmp, "a") as f:
            for method, log in content.training.items():
                write_journal_log(f, method, log)
        os.replace(tmp, p)
    except OSError as exc:
        tmp.unlink(missing_ok=True)
        raise write_failure(p, exc, "rebuild") from exc
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    journal_path(p).unlink(missing_ok=True)


def _copy_or_empty(p: Path, tmp: Path) -> None:
    """``tmp``: a copy of ``p`` when that is a readable HDF5 file, else an empty HDF5 file."""
    try:
        with h5py.File(p, "r"):
            pass
        shutil.copyfile(p, tmp)
        with h5py.File(tmp, "a"):
            return
    except OSError:
        pass
    h5py.File(tmp, "w").close()


def repair_training_file(path: PathLike, content: JournalContent | None = None) -> bool:
    """Rebuild a training-only file from its journal after a log was killed, and delete the journal.

    The readable HDF5 content is kept and the journaled logs replace their methods. (A simulation file's
    journal needs :func:`phisim.io.recover_file`, which rebuilds the frames with the writer.)

    Args:
        path: The HDF5 file.
        content: The journal, when already decoded.

    Returns:
        True if a journal was found and applied, False if there was none.

    Raises:
        FileFormatError: If the journal is unreadable, belongs to a simulation file, or the new file cannot be
            written.
    """
    p = Path(path)
    if content is None:
        jp = journal_path(p)
        if not jp.exists():
            return False
        content = read_journal(jp)
    if content.header is not None:
        raise FileFormatError(
            f"{p} is a simulation file whose writer did not close cleanly ({len(content.frames)} frame(s) in its "
            f"journal); call phisim.io.recover_file({str(p)!r}) to rebuild it before adding training logs"
        )
    rebuild_from_journal(p, content, lambda tmp: _copy_or_empty(p, tmp))
    return True
