"""Reading and repairing files whose writer did not close cleanly, from their journal (see :mod:`._journal`)."""

from __future__ import annotations

import json
import os
import shutil
import warnings
from pathlib import Path

import h5py
import numpy as np
import torch

from phisim.errors import FileFormatError, IncompleteFileWarning
from phisim.io.journal import JournalContent, journal_path, read_journal, write_failure


def load_journal(p: Path) -> JournalContent | None:
    """The journal next to ``p`` decoded, with a warning, or None when there is none (clean file)."""
    jp = journal_path(p)
    if not jp.exists():
        return None
    content = read_journal(jp)
    torn = f"; a torn tail of {content.torn_bytes} bytes (an unfinished record) was skipped" \
        if content.torn_bytes else ""
    warnings.warn(
        f"{p} was not closed cleanly (the writer was killed, ran out of disk, or is still running): reading its "
        f"{len(content.frames)} complete frame(s) and {len(content.training)} training log(s) from the journal "
        f"{jp.name}{torn}. phisim.io.recover_file rebuilds a clean file.",
        IncompleteFileWarning,
        stacklevel=3,
    )
    return content


def sim_from_journal(content: JournalContent, p: Path, as_torch: bool, device):
    """A :class:`~phisim.io.SimulationData` built from a journal with a simulation header."""
    from phisim.boundary import Boundary
    from phisim.grid import Grid
    from phisim.io.simulation import SimulationData, _condition_from_json

    h = content.header
    try:
        grid = Grid(tuple(h["resolution"]), [tuple(b) for b in h["bounds"]])
        boundary = Boundary(tuple((_condition_from_json(lo), _condition_from_json(hi)) for lo, hi in h["boundary"]))
        config = json.loads(h["config"])
        B = int(h["batch_size"])
    except (KeyError, TypeError, ValueError) as exc:
        raise FileFormatError(f"{p}: malformed simulation header in its journal: {exc}") from exc
    kinds = dict(content.frames[-1][0]["kinds"]) if content.frames else dict(h["kinds"])
    T = len(content.frames)
    times = np.array([head["time"] for head, _ in content.frames], dtype=np.float64)
    dt = np.dtype(h["dtype"])
    fields, staggered = {}, {}
    d = grid.rank
    for name, kind in kinds.items():
        tail = grid.resolution if kind == "scalar" else grid.resolution + (d,)
        arr = np.empty((B, T, *tail), dtype=dt)
        for i, (_, arrays) in enumerate(content.frames):
            arr[:, i] = arrays[f"c:{name}"]
        fields[name] = arr if kind == "scalar" else np.moveaxis(arr, -1, 2)
        if kind == "staggered":
            comps = []
            for a in range(d):
                c = np.empty((B, T, *grid.face_shape(a)), dtype=dt)
                for i, (_, arrays) in enumerate(content.frames):
                    c[:, i] = arrays[f"s:{name}:{a}"]
                comps.append(c)
            staggered[name] = tuple(comps)
    if as_torch:
        fields = {n: torch.as_tensor(v, device=device) for n, v in fields.items()}
        staggered = {n: tuple(torch.as_tensor(c, device=device) for c in v) for n, v in staggered.items()}
    parameters = dict(h["parameters"])
    if "dt" not in parameters and T >= 2:  # an interval taken from the first two frames
        parameters["dt"] = float(times[1] - times[0])
    constants = {n: np.array(a) for n, a in content.constants.items()}
    return SimulationData(p, h["dataset_name"], grid, boundary, times, fields, staggered, kinds,
                          parameters, config, content.training_curves(), constants)


def recover_file(path) -> bool:
    """Rebuild a clean HDF5 file from its journal after a writer was killed, and delete the journal.

    Every complete frame and training record in the journal ends up in the new file (frames through a
    fresh :class:`~phisim.io.SimulationWriter`; for a file holding only training logs, the HDF5 content
    is kept when it is readable and the journaled logs replace their methods). The new file replaces the
    old one atomically. Do not call it while the writer is still running.

    Args:
        path: The HDF5 file.

    Returns:
        True if a journal was found and applied, False if there was none (the file was closed cleanly).

    Raises:
        FileFormatError: If the journal is unreadable or the new file cannot be written.
    """
    p = Path(path)
    jp = journal_path(p)
    if not jp.exists():
        return False
    content = read_journal(jp)
    tmp = p.with_name(p.name + ".recover.tmp")
    try:
        if content.header is not None:
            _rebuild_simulation(content, tmp)
        else:
            _copy_or_empty(p, tmp)
        with h5py.File(tmp, "a") as f:
            for method, log in content.training.items():
                _write_method(f, method, log)
        os.replace(tmp, p)
    except OSError as exc:
        tmp.unlink(missing_ok=True)
        raise write_failure(p, exc, "rebuild") from exc
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    jp.unlink(missing_ok=True)
    return True


def _rebuild_simulation(content: JournalContent, tmp: Path) -> None:
    from phisim.io.simulation import SimulationWriter

    data = sim_from_journal(content, tmp, False, None)
    h = content.header
    params = {k: v for k, v in h["parameters"].items()}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # uneven frame times were accepted (with a warning) when written
        w = SimulationWriter(tmp, data.grid, data.boundary, dataset_name=data.dataset_name, fields=dict(data.kinds),
                             parameters=params, batch_size=int(h["batch_size"]), config=data.config,
                             dtype=np.dtype(h["dtype"]), journal=False, uneven_intervals="warn",
                             constant_fields=data.constant_fields or None)
    with w, warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for i, t in enumerate(data.times):
            values = {}
            for name, kind in data.kinds.items():
                if kind == "staggered":
                    values[name] = tuple(c[:, i] for c in data.staggered[name])
                else:
                    values[name] = data.fields[name][:, i]
            w.append(float(t), **values)


def _copy_or_empty(p: Path, tmp: Path) -> None:
    try:
        with h5py.File(p, "r"):
            pass
        shutil.copyfile(p, tmp)
        with h5py.File(tmp, "a"):
            return
    except OSError:
        pass
    h5py.File(tmp, "w").close()


def _write_method(f: h5py.File, method: str, log: dict) -> None:
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
