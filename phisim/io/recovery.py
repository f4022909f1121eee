"""Repairing files whose writer did not close cleanly, from their journal (see :mod:`phisim.io.journal`).

The top of :mod:`phisim.io`: a simulation file is rebuilt frame by frame with a fresh
:class:`~phisim.io.SimulationWriter`, a training-only file by :func:`phisim.io.traininglog.repair_training_file`.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np

from phisim.io.h5util import PathLike
from phisim.io.journal import JournalContent, journal_path, read_journal
from phisim.io.reader import sim_from_journal
from phisim.io.traininglog import rebuild_from_journal, repair_training_file
from phisim.io.writer import SimulationWriter

__all__ = ["recover_file"]


def recover_file(path: PathLike) -> bool:
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
    if content.header is None:
        return repair_training_file(p, content)
    rebuild_from_journal(p, content, lambda tmp: _rebuild_simulation(content, tmp))
    return True


def _rebuild_simulation(content: JournalContent, tmp: Path) -> None:
    data = sim_from_journal(content, tmp)
    h = content.header
    params = dict(h["parameters"])
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
