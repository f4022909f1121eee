"""Normalisation statistics of a dataset folder in The Well's layout (the ``stats.yaml`` its loader reads).

The Well's ``WellDataset(path, well_split_name=..., use_normalization=True, normalization_type=...)`` opens
``<path>/stats.yaml`` and normalises every field with it. The file holds, per field name:

* ``mean``, ``std``, ``rms``: over every sample, frame and cell of the training split; a scalar for a
  ``t0`` field, one value per component for a ``t1`` field (``d`` values) and a ``t2`` field (``d x d``);
* ``mean_delta``, ``std_delta``, ``rms_delta``: the same for the frame-to-frame differences
  ``u[t+1] - u[t]`` of time-varying fields (the loader's delta normalisation).

Standard deviations are population values (divide by the count). The sums are accumulated in float64 one
trajectory at a time (Chan's pairwise update of mean and squared deviations), so memory stays at one
trajectory and the result does not depend on how the data are split into files.

Example:
    >>> write_statistics("out/demo")          # reads out/demo/data/train/*.h5, writes out/demo/stats.yaml
    ...                                        # doctest: +SKIP
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from pathlib import Path

import h5py
import numpy as np

from phisim.errors import FileFormatError, ParameterError
from phisim.io.h5util import PathLike, open_for_read
from phisim.io.interrupts import uninterrupted

__all__ = ["compute_statistics", "write_statistics", "format_statistics", "STATISTICS_KEYS"]

STATISTICS_KEYS = ("mean", "std", "rms", "mean_delta", "std_delta", "rms_delta")


class _Moments:
    """Running count, mean and sum of squared deviations per component (float64)."""

    def __init__(self):
        self.n = 0
        self.mean = None
        self.m2 = None

    def add(self, values: np.ndarray, n_tensor_axes: int) -> None:
        comp = values.shape[values.ndim - n_tensor_axes:] if n_tensor_axes else ()
        flat = np.asarray(values, dtype=np.float64).reshape(-1, *comp)
        if flat.shape[0] == 0:
            return
        n_b = flat.shape[0]
        mean_b = flat.mean(axis=0)
        m2_b = ((flat - mean_b) ** 2).sum(axis=0)
        if self.n == 0:
            self.n, self.mean, self.m2 = n_b, mean_b, m2_b
            return
        n = self.n + n_b
        delta = mean_b - self.mean
        self.mean = self.mean + delta * (n_b / n)
        self.m2 = self.m2 + m2_b + delta**2 * (self.n * n_b / n)
        self.n = n

    def result(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        var = self.m2 / self.n
        return self.mean, np.sqrt(var), np.sqrt(var + self.mean**2)


def _names(group) -> list[str]:
    raw = group.attrs.get("field_names", [])
    return [n.decode() if isinstance(n, bytes) else str(n) for n in np.atleast_1d(np.asarray(raw, dtype=object))]


def _files_of(source) -> list[Path]:
    if isinstance(source, (str, Path)) or hasattr(source, "__fspath__"):
        p = Path(source)
        if p.is_dir():
            files = sorted([*p.glob("*.h5"), *p.glob("*.hdf5")])
            if not files:
                raise FileFormatError(f"{p} holds no .h5/.hdf5 files")
            return files
        return [p]
    files = [Path(f) for f in source]
    if not files:
        raise ParameterError("compute_statistics needs at least one file")
    return files


def compute_statistics(source: PathLike | Iterable[PathLike]) -> dict[str, dict[str, float | list]]:
    """Per-field normalisation statistics of Well-layout files, in the structure of The Well's ``stats.yaml``.

    Args:
        source: One HDF5 file, a folder of ``.h5``/``.hdf5`` files (the training split, e.g.
            ``<dataset>/data/train``), or a sequence of files.

    Returns:
        ``{key: {field: value}}`` for every key in :data:`STATISTICS_KEYS`. Values are floats for ``t0``
        fields and nested lists (``d`` or ``d x d``) for ``t1``/``t2`` fields. Constant (not time-varying)
        fields appear under ``mean``/``std``/``rms`` only.

    Raises:
        FileFormatError: For unreadable files, files without the Well field groups, or a field whose
            tensor order differs between files.
        ParameterError: For an empty list of files.
    """
    moments: dict[str, _Moments] = {}
    deltas: dict[str, _Moments] = {}
    orders: dict[str, int] = {}
    for path in _files_of(source):
        with open_for_read(path) as f:
            for order in range(3):
                grp = f.get(f"t{order}_fields")
                if not isinstance(grp, h5py.Group):
                    raise FileFormatError(f"{path}: missing group /t{order}_fields (not a Well-layout file)")
                for name in _names(grp):
                    if name not in grp:
                        raise FileFormatError(f"{path}: /t{order}_fields lists {name!r} but has no such dataset")
                    if orders.setdefault(name, order) != order:
                        raise FileFormatError(f"{path}: field {name!r} is t{order} here but t{orders[name]} before")
                    ds = grp[name]
                    sample_varying = bool(ds.attrs.get("sample_varying", True))
                    time_varying = bool(ds.attrs.get("time_varying", True))
                    mom = moments.setdefault(name, _Moments())
                    chunks = range(ds.shape[0]) if sample_varying else [None]
                    for b in chunks:
                        try:
                            values = ds[()] if b is None else ds[b]
                        except (OSError, RuntimeError, ValueError) as exc:
                            raise FileFormatError(f"{path}: cannot read {ds.name}: {exc}") from exc
                        mom.add(values, order)
                        if time_varying and values.shape[0] > 1:
                            deltas.setdefault(name, _Moments()).add(np.diff(values.astype(np.float64), axis=0),
                                                                    order)
    if not moments:
        raise FileFormatError("no fields found: the files list no t0/t1/t2 fields")
    out: dict[str, dict] = {k: {} for k in STATISTICS_KEYS}
    for name, mom in moments.items():
        for key, value in zip(("mean", "std", "rms"), mom.result()):
            out[key][name] = _plain(value)
    for name, mom in deltas.items():
        for key, value in zip(("mean_delta", "std_delta", "rms_delta"), mom.result()):
            out[key][name] = _plain(value)
    return out


def _plain(value: np.ndarray):
    return float(value) if np.ndim(value) == 0 else np.asarray(value, dtype=np.float64).tolist()


def _yaml_float(x: float) -> str:
    if math.isnan(x):
        return ".nan"
    if math.isinf(x):
        return ".inf" if x > 0 else "-.inf"
    return f"{x:.17e}"  # always a '.' and a signed exponent: a float for YAML 1.1 and 1.2 readers


def _yaml_value(value, indent: int) -> list[str]:
    pad = " " * indent
    if isinstance(value, list):
        lines = []
        for item in value:
            if isinstance(item, list):
                lines.append(f"{pad}- [{', '.join(_yaml_float(float(v)) for v in item)}]")
            else:
                lines.append(f"{pad}- {_yaml_float(float(item))}")
        return lines
    raise ParameterError(f"cannot format {value!r}")


def format_statistics(stats: dict[str, dict]) -> str:
    """The statistics as YAML text (block style; field names quoted; no PyYAML needed).

    Args:
        stats: The output of :func:`compute_statistics`.

    Returns:
        The text of a ``stats.yaml`` file.
    """
    lines = ["# normalisation statistics written by phisim.io.stats (population std, float64 sums)"]
    for key, per_field in stats.items():
        lines.append(f"{key}:" if per_field else f"{key}: {{}}")
        for name, value in per_field.items():
            quoted = '"' + str(name).replace("\\", "\\\\").replace('"', '\\"') + '"'
            if isinstance(value, list):
                lines.append(f"  {quoted}:")
                lines.extend(_yaml_value(value, 2))
            else:
                lines.append(f"  {quoted}: {_yaml_float(float(value))}")
    return "\n".join(lines) + "\n"


def write_statistics(
    dataset_dir: PathLike,
    *,
    split: str = "train",
    filename: str = "stats.yaml",
    files: Sequence[PathLike] | None = None,
) -> Path:
    """Compute the statistics of a dataset folder's training split and write the loader's ``stats.yaml``.

    Args:
        dataset_dir: The dataset folder, laid out as The Well's ``<dataset_dir>/data/<split>/*.h5``.
        split: The split the statistics are computed over (The Well uses the training split).
        filename: Name of the file written in ``dataset_dir`` (the loader's default is ``stats.yaml``).
        files: Compute over these files instead of ``<dataset_dir>/data/<split>``.

    Returns:
        The path of the written file (written to a temporary name and renamed, so it is never torn).

    Raises:
        FileFormatError: If the split folder is missing or holds no readable Well files.
    """
    root = Path(dataset_dir)
    if files is None:
        folder = root / "data" / split
        if not folder.is_dir():
            raise FileFormatError(f"{folder} does not exist: expected the Well layout <dataset>/data/{split}/*.h5")
        source: PathLike | Sequence[PathLike] = folder
    else:
        source = files
    text = format_statistics(compute_statistics(source))
    target = root / filename
    tmp = target.with_name(target.name + ".tmp")
    try:
        with uninterrupted():  # written and renamed into place whole, or not at all
            tmp.write_text(text, encoding="utf-8")
            tmp.replace(target)
    except OSError as exc:
        tmp.unlink(missing_ok=True)
        raise FileFormatError(f"cannot write {target}: {exc}") from exc
    return target
