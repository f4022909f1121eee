"""Reading simulation files in The Well's layout (:func:`read_simulation`, :class:`SimulationData`).

The layout is described in :mod:`phisim.io.writer`. A file whose writer did not close cleanly (a journal
``<file>.journal`` lies next to it) is read from the journal (:func:`sim_from_journal`): every complete frame,
never a partial one, with an :class:`~phisim.errors.IncompleteFileWarning`. Foreign Well files are read too:
their grid comes from the cell-centre coordinates and their boundary from ``/boundary_conditions``.
"""

from __future__ import annotations

import json
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import h5py
import numpy as np
import torch

from phisim.boundary import Boundary
from phisim.checks import check_int
from phisim.errors import FileFormatError, IncompleteFileWarning, ParameterError
from phisim.field import CenteredGrid, StaggeredGrid
from phisim.grid import AXIS_NAMES, Grid
from phisim.io.extras import read_constant_fields
from phisim.io.h5util import PathLike, attr_str, attr_str_list, need, need_attr, open_for_read, str_array
from phisim.io.journal import JournalContent, load_journal
from phisim.io.traininglog import journal_curves, read_training_group
from phisim.io.well import boundary_from_well, condition_from_json

__all__ = ["SimulationData", "read_simulation", "sim_from_journal"]


# ---- reader -------------------------------------------------------------------------------------------


@dataclass
class SimulationData:
    """The content of a simulation file (see :func:`read_simulation`).

    Attributes:
        path: The file.
        dataset_name: The Well ``dataset_name``.
        grid: The grid (bounds from ``/extras`` or, for foreign files, from the cell-centre coordinates).
        boundary: The boundary (exact from ``/extras``; for foreign files built from the Well types:
            PERIODIC -> Periodic, WALL -> NoSlipWall, OPEN -> Open).
        times: ``(T,)`` frame times.
        fields: Name -> values in phisim layout: scalars ``(B, T, *res)``, vectors ``(B, T, d, *res)``
            (cell centres, channel axis after time). Numpy arrays, or torch tensors with ``as_torch=True``.
        staggered: Name -> tuple of ``d`` exact face arrays ``(B, T, *face_shape(i))``.
        kinds: Name -> ``'scalar'``, ``'vector'`` or ``'staggered'``.
        parameters: Simulation parameters from the root attributes.
        config: The run configuration (parsed JSON) or ``None``.
        training: Method -> curve name -> 1-D array (``/training``).
        constant_fields: Name -> constant-in-time scalar field (e.g. an obstacle mask), ``(*res)`` when shared
            by all trajectories or ``(B, *res)``; numpy arrays.
    """

    path: Path
    dataset_name: str
    grid: Grid
    boundary: Boundary
    times: np.ndarray
    fields: dict[str, Any]
    staggered: dict[str, tuple]
    kinds: dict[str, str]
    parameters: dict[str, Any]
    config: Any = None
    training: dict[str, dict[str, np.ndarray]] = field(default_factory=dict)
    constant_fields: dict[str, np.ndarray] = field(default_factory=dict)

    @property
    def dt(self) -> float | None:
        """The constant output interval (the stored scalar ``dt``; else the spacing of two frames; else None)."""
        if "dt" in self.parameters:
            return float(self.parameters["dt"])
        return float(self.times[1] - self.times[0]) if len(self.times) > 1 else None

    @property
    def n_frames(self) -> int:
        """Number of frames ``T``."""
        return int(len(self.times))

    @property
    def batch_size(self) -> int:
        """Number of trajectories ``B``."""
        first = next(iter(self.fields.values()), None)
        return 0 if first is None else int(first.shape[0])

    def frame(self, name: str, index: int) -> CenteredGrid | StaggeredGrid:
        """Frame ``index`` of field ``name`` as a field (a ``StaggeredGrid`` for staggered fields).

        Raises:
            ParameterError: For an unknown name or an index out of range.
        """
        if name not in self.kinds:
            raise ParameterError(f"no field {name!r} in {self.path}; fields: {list(self.kinds)}")
        index = check_int(index, "frame index")
        if not -self.n_frames <= index < self.n_frames:
            raise ParameterError(f"frame {index} out of range for {self.n_frames} frames")
        if self.kinds[name] == "staggered":
            comps = tuple(torch.as_tensor(c[:, index]) for c in self.staggered[name])
            return StaggeredGrid(comps, self.grid, self.boundary)
        return CenteredGrid(torch.as_tensor(self.fields[name][:, index]), self.grid, self.boundary)


def _grid_from_coords(coords: list[np.ndarray], path: Path) -> Grid:
    bounds = []
    for a, c in enumerate(coords):
        c = np.asarray(c, dtype=np.float64)
        if c.ndim != 1 or len(c) == 0:
            raise FileFormatError(f"{path}: coordinate {AXIS_NAMES[a]} must be a non-empty 1-D array")
        dx = float(c[1] - c[0]) if len(c) > 1 else 1.0
        if dx <= 0:
            raise FileFormatError(f"{path}: coordinate {AXIS_NAMES[a]} is not increasing")
        bounds.append((float(c[0]) - dx / 2, float(c[-1]) + dx / 2))
    return Grid(tuple(len(c) for c in coords), bounds)


def _read_data(ds, T: int, expected_tail: tuple[int, ...], B: int, path: Path) -> np.ndarray:
    shape = ds.shape
    if len(shape) != 2 + len(expected_tail) or shape[0] != B or tuple(shape[2:]) != expected_tail:
        raise FileFormatError(
            f"{path}: {ds.name} has shape {shape}, expected (B={B}, T, {', '.join(map(str, expected_tail))})"
        )
    if shape[1] < T:  # only a file written without a journal and not closed cleanly; _read clips T first
        raise FileFormatError(f"{path}: {ds.name} holds {shape[1]} frames but /dimensions/time lists {T}")
    try:
        return ds[:, :T]
    except (OSError, RuntimeError, ValueError) as exc:
        raise FileFormatError(f"{path}: cannot read {ds.name} (damaged data): {exc}") from exc


def _complete_frames(f: h5py.File, T: int, p: Path) -> int:
    """Frames held by every frame dataset (a file written without a journal may be torn after ``T``)."""
    n = T
    for gname in ("t0_fields", "t1_fields", "staggered"):
        grp = f.get(gname)
        if isinstance(grp, h5py.Group):
            for ds in grp.values():
                if isinstance(ds, h5py.Dataset) and ds.ndim >= 2 and bool(ds.attrs.get("time_varying", True)):
                    n = min(n, ds.shape[1])
    if n < T:
        warnings.warn(f"{p}: /dimensions/time lists {T} frames but some fields hold only {n} (a torn write); "
                      f"reading the {n} complete ones", IncompleteFileWarning, stacklevel=4)
    return n


def read_simulation(path: PathLike, *, as_torch: bool = False, device=None) -> SimulationData:
    """Read a file written by :class:`SimulationWriter` (or another file in The Well's layout).

    Args:
        path: The HDF5 file.
        as_torch: Return field values as torch tensors (on ``device``) instead of numpy arrays.
        device: Torch device for ``as_torch``.

    Returns:
        A :class:`SimulationData` with every completed frame (from the journal, with an
        :class:`~phisim.errors.IncompleteFileWarning`, when the writer did not close cleanly). Of a
        foreign Well file only fields that vary
        over samples, time and every spatial axis are read; tensor (t2) fields are skipped.

    Raises:
        FileFormatError: If the file does not exist, is not HDF5, is truncated, lacks a required group or
            attribute, or holds datasets whose shapes do not fit its grid.
    """
    p = Path(path)
    journal = load_journal(p)
    if journal is not None and journal.header is not None:
        return sim_from_journal(journal, p, as_torch, device)
    with open_for_read(p) as f:
        try:
            data = _read(f, p, as_torch, device)
            if journal is not None:
                data.training.update(journal_curves(journal))
            return data
        except FileFormatError:
            raise
        except (OSError, RuntimeError, KeyError, ValueError, TypeError, IndexError) as exc:
            raise FileFormatError(
                f"{p}: damaged or malformed HDF5 content (written by another program?): {exc}"
            ) from exc


def _read(f: h5py.File, p: Path, as_torch: bool, device) -> SimulationData:
    dataset_name = attr_str(need_attr(f, "dataset_name", p))
    grid_type = attr_str(need_attr(f, "grid_type", p))
    if grid_type != "cartesian":
        raise FileFormatError(f"{p}: grid_type {grid_type!r} is not supported (only 'cartesian')")
    ndim = int(need_attr(f, "n_spatial_dims", p))
    B = int(need_attr(f, "n_trajectories", p))
    dims = need(f, "dimensions", p, h5py.Group)
    spatial = attr_str_list(need_attr(dims, "spatial_dims", p))
    if len(spatial) != ndim or not 1 <= ndim <= 3:
        raise FileFormatError(f"{p}: spatial_dims {spatial} does not match n_spatial_dims={ndim}")
    tds = need(dims, "time", p, h5py.Dataset)
    if tds.ndim != 1:
        raise FileFormatError(f"{p}: /dimensions/time must be 1-D (sample-varying times are not supported)")
    times = np.asarray(tds[:], dtype=np.float64)
    T = _complete_frames(f, len(times), p)
    times = times[:T]
    coords = [np.asarray(need(dims, name, p, h5py.Dataset)[()]) for name in spatial]

    extras = f.get("extras")
    grid = None
    boundary = None
    kinds: dict[str, str] = {}
    config = None
    if isinstance(extras, h5py.Group) and "bounds" in extras.attrs:
        try:
            bounds = json.loads(attr_str(extras.attrs["bounds"]))
            grid = Grid(tuple(len(c) for c in coords), [tuple(b) for b in bounds])
            sides = json.loads(attr_str(extras.attrs["boundary"]))
            boundary = Boundary(
                tuple((condition_from_json(lo), condition_from_json(hi)) for lo, hi in sides)
            )
            kinds = dict(json.loads(attr_str(extras.attrs.get("field_kinds", "{}"))))
            if "config" in extras:
                config = json.loads(attr_str(extras["config"][()]))
        except (ValueError, TypeError, KeyError) as exc:
            raise FileFormatError(f"{p}: /extras holds malformed phisim metadata: {exc}") from exc
    if grid is None:
        grid = _grid_from_coords(coords, p)
    if boundary is None:
        boundary = boundary_from_well(f, grid, spatial, p)
    if boundary.rank != grid.rank:
        raise FileFormatError(f"{p}: boundary has {boundary.rank} axes, the grid {grid.rank}")

    parameters = {}
    for name in attr_str_list(f.attrs.get("simulation_parameters", str_array([]))):
        if name in f.attrs:
            v = f.attrs[name]
            parameters[name] = v.item() if isinstance(v, np.generic) else v

    res, d = grid.resolution, grid.rank
    fields: dict[str, Any] = {}
    for order in (0, 1):
        grp = need(f, f"t{order}_fields", p, h5py.Group)
        for name in attr_str_list(grp.attrs.get("field_names", str_array([]))):
            ds = need(grp, name, p, h5py.Dataset)
            varying = (bool(ds.attrs.get("sample_varying", True)) and bool(ds.attrs.get("time_varying", True))
                       and bool(np.all(ds.attrs.get("dim_varying", True))))
            if not varying:
                continue
            tail = res if order == 0 else res + (d,)
            arr = _read_data(ds, T, tail, B, p)
            fields[name] = arr if order == 0 else np.moveaxis(arr, -1, 2)
            kinds.setdefault(name, "scalar" if order == 0 else "vector")
    need(f, "t2_fields", p, h5py.Group)
    kinds = {n: k for n, k in kinds.items() if n in fields}

    staggered = {}
    for name, kind in kinds.items():
        if kind != "staggered":
            continue
        grp = need(f, "staggered", p, h5py.Group)
        staggered[name] = tuple(
            _read_data(need(grp, f"{name}_{AXIS_NAMES[a]}", p, h5py.Dataset), T, grid.face_shape(a), B, p)
            for a in range(d)
        )

    training = read_training_group(f["training"], p) if isinstance(f.get("training"), h5py.Group) else {}
    if as_torch:
        fields = {n: torch.as_tensor(v, device=device) for n, v in fields.items()}
        staggered = {n: tuple(torch.as_tensor(c, device=device) for c in v) for n, v in staggered.items()}
    constants = read_constant_fields(f, grid.resolution, p)
    return SimulationData(p, dataset_name, grid, boundary, times, fields, staggered, kinds, parameters,
                          config,
                          training, constants)


def sim_from_journal(content: JournalContent, p: Path, as_torch: bool = False, device=None) -> SimulationData:
    """A :class:`SimulationData` built from a journal with a simulation header (every complete frame).

    Raises:
        FileFormatError: A malformed header.
    """
    h = content.header
    try:
        grid = Grid(tuple(h["resolution"]), [tuple(b) for b in h["bounds"]])
        boundary = Boundary(tuple((condition_from_json(lo), condition_from_json(hi)) for lo, hi in h["boundary"]))
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
                          parameters, config, journal_curves(content), constants)
