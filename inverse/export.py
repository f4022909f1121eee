"""Learning curves outside HDF5: CSV files, and optional TensorBoard logging during training.

TensorBoard is never required: :class:`TensorBoardLogger` writes event files when the ``tensorboard``
package is installed and otherwise warns once and does nothing.
"""

from __future__ import annotations

import csv
import os
import warnings
from pathlib import Path

import numpy as np

from phisim.errors import FileFormatError
from phisim.io import read_training

__all__ = ["export_csv", "TensorBoardLogger", "tensorboard_available"]


def export_csv(path: str | os.PathLike, out_dir: str | os.PathLike) -> list[Path]:
    """Write the training curves of a results file as CSV, one ``<method>.csv`` per method.

    Columns are ``iteration`` then every curve logged once per iteration; curves of another length (e.g. a
    held-out evaluation every n iterations) go to ``<method>_<curve>.csv`` with an index column ``row``.

    Args:
        path: HDF5 results file.
        out_dir: Folder for the CSV files (created).

    Returns:
        The files written.

    Raises:
        FileFormatError: The file cannot be read or holds no training curves.
    """

    curves = read_training(path)
    if not curves:
        raise FileFormatError(f"{path} holds no training curves (/training)")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    written = []
    for method, c in curves.items():
        n = len(c.get("iteration", []))
        main = ["iteration"] + [k for k, v in c.items() if k != "iteration" and len(v) == n]
        p = out / f"{method}.csv"
        with p.open("w", newline="", encoding="utf-8") as f:
            w = csv.writer(f)
            w.writerow(main)
            for i in range(n):
                w.writerow([_fmt(c[k][i]) for k in main])
        written.append(p)
        for k, v in c.items():
            if k in main:
                continue
            q = out / f"{method}_{k}.csv"
            with q.open("w", newline="", encoding="utf-8") as f:
                w = csv.writer(f)
                w.writerow(["row", k])
                for i, x in enumerate(v):
                    w.writerow([i, _fmt(x)])
            written.append(q)
    return written


def _fmt(x) -> str:
    x = np.asarray(x).item()
    return repr(float(x)) if isinstance(x, float) else str(x)


def tensorboard_available() -> bool:
    """Whether ``torch.utils.tensorboard`` can be used (the ``tensorboard`` package is installed)."""
    try:
        import tensorboard  # noqa: F401
    except ImportError:
        return False
    return True


class TensorBoardLogger:
    """Scalars of a training run to TensorBoard event files in ``log_dir/<method>`` (a no-op without TensorBoard).

    Args:
        log_dir: Folder of the event files.
        method: Run name (a sub-folder, so methods compare in one TensorBoard view).

    Attributes:
        active: Whether events are written.
    """

    _warned = False

    def __init__(self, log_dir: str | os.PathLike, method: str):
        self.writer = None
        if tensorboard_available():
            from torch.utils.tensorboard import SummaryWriter

            self.writer = SummaryWriter(log_dir=str(Path(log_dir) / method))
        elif not TensorBoardLogger._warned:
            warnings.warn("TensorBoard logging skipped: the tensorboard package is not installed "
                          "(pip install tensorboard)", stacklevel=2)
            TensorBoardLogger._warned = True
        self.active = self.writer is not None

    def log(self, iteration: int, record: dict) -> None:
        """Write every finite number of ``record`` as a scalar at step ``iteration``."""
        if self.writer is None:
            return
        for k, v in record.items():
            if isinstance(v, (int, float)) and np.isfinite(v):
                self.writer.add_scalar(k, float(v), int(iteration))

    def close(self) -> None:
        """Flush and close the event file."""
        if self.writer is not None:
            self.writer.close()
            self.writer = None
