"""HDF5 files for simulations and training results, in the layout of The Well (PolymathicAI/the_well).

A file written by :class:`SimulationWriter` holds ``B`` trajectories (the batch) of ``T`` frames on one grid:

.. code-block:: text

    /                          attrs: dataset_name, grid_type='cartesian', n_spatial_dims, n_trajectories=B,
                                      simulation_parameters=[names], and one attribute per parameter
    /dimensions                attrs: spatial_dims=['x', 'y'(, 'z')]
        time      (T,)         attrs: sample_varying=False, time_varying=True
        x, y, z   (n_axis,)    cell-centre coordinates; sample_varying=False, time_varying=False
    /boundary_conditions/<axis>_<type>       e.g. x_periodic, y_wall, y_open
                               attrs: bc_type (PERIODIC | WALL | OPEN), associated_dims=[axis],
                                      associated_fields=[], sample_varying=False, time_varying=False
        mask      (n_axis,)    bool, True at the boundary cells (index 0 and/or -1) with this type
    /scalars                   attrs: field_names=[parameter names]
        <param>   ()           attrs: sample_varying=False, time_varying=False
        dt        ()           the constant output interval (also a root attribute and simulation parameter)
    /t0_fields                 attrs: field_names; scalar fields (B, T, *res); constant fields such as an
                               obstacle mask (*res) or (B, *res) with time_varying=False
    /t1_fields                 attrs: field_names; vector fields (B, T, *res, d) at cell centres, channel LAST
    /t2_fields                 attrs: field_names=[] (no tensor fields are written)
        every field: attrs sample_varying=True, time_varying=True, dim_varying=[True] * d
    -- phisim additions, which The Well's tools ignore --
    /staggered/<name>_<axis>   (B, T, *face_shape(axis)): the exact MAC face values of a StaggeredGrid
    /extras                    attrs: phisim_format, bounds (JSON), boundary (JSON), field_kinds (JSON)
        config    ()           the run configuration as a JSON string (``"null"`` when none was given)
    /training/<method>/        1-D curves written by :class:`TrainingLog`: iteration, loss, metric, ...

Boundary types are derived from :class:`~phisim.boundary.Boundary` side by side: ``Periodic`` gives PERIODIC;
``NoSlipWall``, ``FreeSlipWall``, ``Dirichlet`` and ``Neumann`` give WALL (a closed side with a prescribed
value or flux); ``Open`` gives OPEN. The exact conditions (values, fluxes, wall velocities) are kept in
``/extras`` so :func:`read_simulation` rebuilds the same ``Boundary``.

Frames are equally spaced in time, as The Well's loader assumes: the writer checks every appended time
against the output interval (given, or taken from the first two frames) and refuses (or, by a setting,
warns about) a frame off it.

Frames are written one at a time into resizable datasets (chunks of one sample and one frame, gzip with
the shuffle filter) and the file is flushed after every frame. A frame is written with SIGINT/SIGTERM deferred
(:func:`phisim.io.interrupts.uninterrupted`): an interrupt stops the run after the frame, never inside it.

Crash safety: HDF5 rewrites metadata in place, so a writer killed mid-flush (or a file cut short by a power
loss) can leave a file HDF5 rejects as a whole. Every frame is therefore first appended to an append-only,
checksummed sidecar ``<file>.journal`` (see :mod:`phisim.io.journal`), which is deleted when the writer closes
cleanly. While a journal exists (the writer was killed, or is still running), :func:`~phisim.io.read_simulation` reads
from it: every frame whose record is complete, never a partial one, with a warning naming the torn tail.
:func:`~phisim.io.recover_file` rebuilds a clean HDF5 file from the journal. The journal costs one raw (uncompressed)
copy of the frames on disk while the run lasts (``journal=False`` turns it off, leaving best-effort safety:
the reader then clips to the frames every dataset holds). Write failures (full disk, vanished folder) raise
:class:`~phisim.errors.FileFormatError` naming the file.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import h5py
import numpy as np
import torch

from phisim.boundary import Boundary
from phisim.errors import FileFormatError, ParameterError, ShapeError
from phisim.field import CenteredGrid, StaggeredGrid
from phisim.grid import AXIS_NAMES, Grid
from phisim.io.extras import IntervalCheck, constant_arrays, write_constant_fields
from phisim.io.h5util import RESERVED_ROOT_NAMES, PathLike, check_output_path, check_storable_name, str_array, to_json
from phisim.io.interrupts import uninterrupted
from phisim.io.journal import Journal, check_space, journal_path, write_failure
from phisim.io.traininglog import TrainingLog
from phisim.io.well import condition_to_json, well_bc_type

__all__ = ["SimulationWriter", "FIELD_KINDS", "FORMAT_NAME"]

FIELD_KINDS = ("scalar", "vector", "staggered")
FORMAT_NAME = "phisim-well/1"
_COMPRESSION = "gzip"


# ---- helpers ------------------------------------------------------------------------------------------


def _np_dtype(dtype) -> np.dtype:
    if dtype is None:
        return np.dtype(np.float32)
    if isinstance(dtype, torch.dtype):
        torch_to_np = {torch.float32: np.float32, torch.float64: np.float64, torch.float16: np.float16}
        dtype = torch_to_np.get(dtype, dtype)
    try:
        dt = np.dtype(dtype)
    except TypeError as exc:
        raise ParameterError(f"dtype {dtype!r} is not a floating dtype") from exc
    if dt.kind != "f":
        raise ParameterError(f"fields are stored as floating point; got dtype {dt}")
    return dt


def _as_numpy(values, what: str) -> np.ndarray:
    if isinstance(values, torch.Tensor):
        values = values.detach().cpu()
        if values.is_complex():
            raise ShapeError(f"{what}: complex values cannot be stored; store real and imaginary parts")
        return values.numpy()
    arr = np.asarray(values)
    if arr.dtype.kind not in "fiub":
        raise ShapeError(f"{what}: expected a numeric array, got dtype {arr.dtype}")
    return arr


# ---- writer -------------------------------------------------------------------------------------------


def _set_varying(obj, *, sample: bool, time: bool, dims: int | None = None) -> None:
    obj.attrs["sample_varying"] = bool(sample)
    obj.attrs["time_varying"] = bool(time)
    if dims is not None:
        obj.attrs["dim_varying"] = np.ones(dims, dtype=bool)


class SimulationWriter:
    """Write a batch of simulated trajectories to an HDF5 file in The Well's layout, one frame at a time.

    The file layout is described in the module docstring. Every :meth:`append` writes one frame of every
    declared field and flushes the file, so a run killed at any point leaves a readable file with all
    completed frames.

    Args:
        path: File to create (parent folders are created; an existing file is replaced).
        grid: The simulation grid.
        boundary: The domain boundary (a :class:`~phisim.boundary.Boundary` or anything
            :meth:`Boundary.create` accepts); it gives the Well ``boundary_conditions`` groups.
        dataset_name: The Well ``dataset_name`` root attribute.
        fields: Field name -> kind. ``'scalar'``: ``(B, *res)`` values, stored in ``/t0_fields``.
            ``'vector'``: ``(B, d, *res)`` cell-centred values (stored channel-last in ``/t1_fields``);
            a :class:`StaggeredGrid` given for the first frame turns the field into ``'staggered'``.
            ``'staggered'``: a :class:`StaggeredGrid` or a sequence of ``d`` face arrays; stored averaged
            to the cell centres in ``/t1_fields`` and exactly in ``/staggered/<name>_<axis>``.
        parameters: Simulation parameters (name -> number), written as root attributes, listed in
            ``simulation_parameters`` and stored in ``/scalars``.
        batch_size: Number of trajectories ``B`` (the Well's ``n_trajectories``).
        config: The run configuration (JSON-serialisable), stored in ``/extras/config``.
        dtype: Storage dtype of fields and coordinates (default float32, as in The Well). Use
            ``torch.float64`` for an exact double-precision round trip; other input is cast to it.
        compression_level: gzip level 0-9.
        output_interval: The constant time between frames (The Well's files are sampled at one interval).
            Stored as the scalar ``dt`` (``/scalars/dt`` and a root attribute listed in
            ``simulation_parameters``). None: taken from the first two frames. A parameter named ``dt``
            is this interval.
        uneven_intervals: What an appended time off the interval (relative tolerance 1e-6) gets:
            ``'error'`` (default) raises :class:`ParameterError`, ``'warn'`` writes it with a ``UserWarning``.
        constant_fields: Scalar fields that do not change in time (e.g. an obstacle mask): name ->
            ``(*res)`` values shared by all trajectories or ``(B, *res)`` values. Stored in ``/t0_fields``
            with ``time_varying=False`` (as The Well stores constant fields) and read back into
            :attr:`SimulationData.constant_fields`.
        journal: Keep the crash-safety journal ``<path>.journal`` while writing (see the module docstring).

    Raises:
        ParameterError: For unknown field kinds, bad names, non-numeric parameters, a non-positive
            batch size, a non-serialisable config, a non-positive interval or a ``dt`` parameter that
            contradicts it.

    Example:
        >>> with SimulationWriter("run.h5", grid, "periodic", dataset_name="plume",
        ...                       fields={"density": "scalar", "velocity": "staggered"},
        ...                       parameters={"viscosity": 0.01}, batch_size=4) as w:
        ...     for step in range(n):
        ...         w.append(step * dt, density=rho, velocity=v)  # doctest: +SKIP
    """

    def __init__(
        self,
        path: PathLike,
        grid: Grid,
        boundary,
        *,
        dataset_name: str,
        fields: Mapping[str, str],
        parameters: Mapping[str, float] | None = None,
        batch_size: int,
        config: Any = None,
        dtype=None,
        compression_level: int = 4,
        output_interval: float | None = None,
        uneven_intervals: str = "error",
        constant_fields: Mapping[str, Any] | None = None,
        journal: bool = True,
    ):
        if not isinstance(grid, Grid):
            raise ParameterError(f"grid must be a phisim Grid, got {type(grid).__name__}")
        if isinstance(batch_size, bool) or not isinstance(batch_size, (int, np.integer)) or batch_size < 1:
            raise ParameterError(f"batch_size must be a positive int, got {batch_size!r}")
        if not isinstance(dataset_name, str) or not dataset_name:
            raise ParameterError("dataset_name must be a non-empty string")
        if not fields:
            raise ParameterError("declare at least one field, e.g. fields={'density': 'scalar'}")
        if not 0 <= int(compression_level) <= 9:
            raise ParameterError(f"compression_level must be in 0..9, got {compression_level}")
        self.grid = grid
        self.boundary = Boundary.create(boundary, grid.rank)
        self.batch_size = int(batch_size)
        self.dtype = _np_dtype(dtype)
        self.kinds: dict[str, str] = {}
        for name, kind in fields.items():
            check_storable_name(name, "field name", reserved={"time"})
            if kind not in FIELD_KINDS:
                raise ParameterError(f"field {name!r}: kind must be one of {FIELD_KINDS}, got {kind!r}")
            self.kinds[name] = kind
        params = {}
        for name, value in (parameters or {}).items():
            check_storable_name(name, "parameter name", reserved=RESERVED_ROOT_NAMES)
            if isinstance(value, torch.Tensor) and value.numel() == 1:
                value = value.item()
            if isinstance(value, np.generic):
                value = value.item()
            if not isinstance(value, (int, float, bool)):
                raise ParameterError(
                    f"parameter {name!r} = {value!r} is not a number; put non-numeric settings in config="
                )
            params[name] = value
        self.parameters = params
        if "dt" in params and output_interval is not None and float(params["dt"]) != float(output_interval):
            raise ParameterError(f"parameter dt={params['dt']} contradicts output_interval={output_interval}")
        if output_interval is None and "dt" in params:
            output_interval = params["dt"]
        self._interval = IntervalCheck(output_interval, uneven_intervals, Path(path))
        if self._interval.interval is not None:
            self.parameters["dt"] = self._interval.interval
        constants = constant_arrays(constant_fields, grid.resolution, self.batch_size, self.kinds)
        config_json = to_json(config, "config")
        self._level = int(compression_level)
        self.path = Path(path)
        self._file = None
        self._journal = None
        check_output_path(self.path)
        jpath = journal_path(self.path)
        try:
            jpath.unlink(missing_ok=True)  # a journal of an earlier run of the replaced file
            self._file = h5py.File(self.path, "w")
        except OSError as exc:
            raise write_failure(self.path, exc, "create the HDF5 file") from exc
        self._n = 0
        self._last_time = -math.inf
        try:
            self._write_header(dataset_name, config_json)
            write_constant_fields(self._file, constants, self.batch_size, self.dtype, grid.rank)
            self._file.flush()
            if journal:
                self._journal = Journal(jpath, fresh=True)
                self._journal.write_json(b"S", {
                    "dataset_name": dataset_name, "resolution": list(grid.resolution),
                    "bounds": [list(b) for b in grid.bounds],
                    "boundary": [[condition_to_json(c) for c in side] for side in self.boundary.sides],
                    "kinds": self.kinds, "parameters": self.parameters, "config": config_json,
                    "batch_size": self.batch_size, "dtype": self.dtype.str,
                })
                if constants:
                    keys = [[n, list(a.shape), a.dtype.str] for n, a in constants.items()]
                    self._journal.write_frame({"arrays": keys}, list(constants.values()), kind=b"C")
        except BaseException as exc:
            self._abort()
            if isinstance(exc, (OSError, RuntimeError)) and not isinstance(exc, FileFormatError):
                raise write_failure(self.path, exc, "write the header of") from exc
            raise

    # -- layout --
    def _write_header(self, dataset_name: str, config_json: str) -> None:
        f, g, B, d = self._file, self.grid, self.batch_size, self.grid.rank
        f.attrs["dataset_name"] = dataset_name
        f.attrs["grid_type"] = "cartesian"
        f.attrs["n_spatial_dims"] = d
        f.attrs["n_trajectories"] = B
        f.attrs["simulation_parameters"] = str_array(list(self.parameters))
        for name, value in self.parameters.items():
            f.attrs[name] = value

        dims = f.create_group("dimensions")
        dims.attrs["spatial_dims"] = str_array(AXIS_NAMES[:d])
        t = dims.create_dataset("time", shape=(0,), maxshape=(None,), dtype=np.float64, chunks=(1024,))
        _set_varying(t, sample=False, time=True)
        for a in range(d):
            centres = g.center_coords(a, torch.float64).numpy().astype(self.dtype)
            c = dims.create_dataset(AXIS_NAMES[a], data=centres)
            _set_varying(c, sample=False, time=False)

        bcs = f.create_group("boundary_conditions")
        for a in range(d):
            by_type: dict[str, list[int]] = {}
            for side, cond in zip((0, -1), self.boundary.sides[a]):
                by_type.setdefault(well_bc_type(cond), []).append(side)
            for bc_type, sides in by_type.items():
                grp = bcs.create_group(f"{AXIS_NAMES[a]}_{bc_type.lower()}")
                grp.attrs["bc_type"] = bc_type
                grp.attrs["associated_dims"] = str_array([AXIS_NAMES[a]])
                grp.attrs["associated_fields"] = str_array([])
                _set_varying(grp, sample=False, time=False)
                mask = np.zeros(g.resolution[a], dtype=bool)
                mask[sides] = True
                grp.create_dataset("mask", data=mask)

        sc = f.create_group("scalars")
        sc.attrs["field_names"] = str_array(list(self.parameters))
        for name, value in self.parameters.items():
            ds = sc.create_dataset(name, data=np.asarray(value, dtype=np.float64))
            _set_varying(ds, sample=False, time=False)

        groups = {i: f.create_group(f"t{i}_fields") for i in range(3)}
        for i in range(3):
            names = [n for n, k in self.kinds.items() if (k == "scalar") == (i == 0)] if i < 2 else []
            groups[i].attrs["field_names"] = str_array(names)
        for name, kind in self.kinds.items():
            if kind == "scalar":
                self._create(groups[0], name, g.resolution)
            else:
                self._create(groups[1], name, g.resolution + (d,))
        f.create_group("staggered")
        for name, kind in self.kinds.items():
            if kind == "staggered":
                self._create_staggered(name)

        ex = f.create_group("extras")
        ex.attrs["phisim_format"] = FORMAT_NAME
        ex.attrs["bounds"] = json.dumps([list(b) for b in g.bounds])
        ex.attrs["boundary"] = json.dumps(
            [[condition_to_json(c) for c in side] for side in self.boundary.sides]
        )
        ex.attrs["field_kinds"] = json.dumps(self.kinds)
        ex.create_dataset("config", data=config_json, dtype=h5py.string_dtype())

    def _create(self, group, name: str, frame_shape: tuple[int, ...]):
        kw = {}
        if self._level:
            kw = {"compression": _COMPRESSION, "compression_opts": self._level, "shuffle": True}
        ds = group.create_dataset(
            name,
            shape=(self.batch_size, 0, *frame_shape),
            maxshape=(self.batch_size, None, *frame_shape),
            chunks=(1, 1, *frame_shape),
            dtype=self.dtype,
            **kw,
        )
        _set_varying(ds, sample=True, time=True, dims=self.grid.rank)
        return ds

    def _create_staggered(self, name: str) -> None:
        for a in range(self.grid.rank):
            ds = self._create(self._file["staggered"], f"{name}_{AXIS_NAMES[a]}", self.grid.face_shape(a))
            ds.attrs["component"] = a
            ds.attrs["field"] = name
        self.kinds[name] = "staggered"
        if "extras" in self._file:
            self._file["extras"].attrs["field_kinds"] = json.dumps(self.kinds)

    # -- frames --
    @property
    def n_frames(self) -> int:
        """Number of frames written so far."""
        return self._n

    @property
    def file(self) -> h5py.File:
        """The open ``h5py.File`` (e.g. to give :class:`TrainingLog` a group of the same file)."""
        self._check_open()
        return self._file

    def _check_open(self) -> None:
        if self._file is None or not self._file.id.valid:
            raise ParameterError(f"SimulationWriter for {self.path} is closed")

    def _frame_arrays(self, name: str, value) -> tuple[np.ndarray, tuple[np.ndarray, ...] | None]:
        """(centre array in storage layout, staggered components or None) for one frame of one field."""
        kind, g, B, d = self.kinds[name], self.grid, self.batch_size, self.grid.rank
        if isinstance(value, (CenteredGrid, StaggeredGrid)) and value.grid != g:
            raise ShapeError(f"field {name!r} lives on {value.grid}, the file on {g}")
        if kind == "scalar":
            if isinstance(value, StaggeredGrid) or (isinstance(value, CenteredGrid) and value.is_vector):
                raise ShapeError(f"field {name!r} is declared 'scalar' but got a vector field")
            arr = _as_numpy(value.values if isinstance(value, CenteredGrid) else value, name)
            if arr.shape != (B, *g.resolution):
                raise ShapeError(
                    f"scalar field {name!r} must have shape {(B, *g.resolution)}, got {arr.shape}"
                )
            return arr, None
        stag = None
        if isinstance(value, StaggeredGrid):
            if kind == "vector":
                if self._n > 0:
                    raise ShapeError(
                        f"field {name!r} got a StaggeredGrid after centred frames; declare it 'staggered'"
                    )
                self._create_staggered(name)
                kind = "staggered"
            stag = tuple(_as_numpy(v, name) for v in value.values)
            centred = value.at_centers().values
        elif kind == "staggered":
            if isinstance(value, CenteredGrid) or not isinstance(value, (tuple, list)) or len(value) != d:
                raise ShapeError(
                    f"staggered field {name!r} needs a StaggeredGrid or a sequence of {d} face arrays"
                )
            stag = tuple(_as_numpy(v, f"{name}[{i}]") for i, v in enumerate(value))
            for i, s in enumerate(stag):
                if s.shape != (B, *g.face_shape(i)):
                    raise ShapeError(
                        f"staggered field {name!r} component {i} must have shape {(B, *g.face_shape(i))}, "
                        f"got {s.shape}"
                    )
            faces = StaggeredGrid(tuple(torch.as_tensor(s) for s in stag), g, self.boundary)
            centred = faces.at_centers().values
        else:
            centred = value.values if isinstance(value, CenteredGrid) else value
        arr = _as_numpy(centred, name)
        if arr.shape != (B, d, *g.resolution):
            raise ShapeError(
                f"vector field {name!r} must have shape {(B, d, *g.resolution)} (channel second), "
                f"got {arr.shape}"
            )
        return np.moveaxis(arr, 1, -1), stag

    def append(self, time: float, **fields) -> None:
        """Write one frame of every declared field, then flush the file.

        Args:
            time: The frame's simulation time (finite, larger than the previous frame's).
            **fields: One value per declared field: a :class:`CenteredGrid`, :class:`StaggeredGrid`, torch
                tensor or numpy array with the batch axis first (see the class docstring for shapes).

        Raises:
            ParameterError: For missing or unknown field names, a non-increasing time or a closed writer.
            ShapeError: For values whose shape, batch size or kind does not match the declaration.
        """
        self._check_open()
        missing = [n for n in self.kinds if n not in fields]
        unknown = [n for n in fields if n not in self.kinds]
        if missing or unknown:
            raise ParameterError(
                f"append needs exactly the declared fields {list(self.kinds)}; "
                f"missing {missing}, unknown {unknown}"
            )
        try:
            t = float(time)
        except (TypeError, ValueError) as exc:
            raise ParameterError(f"time must be a number, got {time!r}") from exc
        if not math.isfinite(t) or t <= self._last_time:
            raise ParameterError(f"time must be finite and increasing: got {t} after {self._last_time}")
        self._interval.check(t, self._last_time, self._file)
        frames = {name: self._frame_arrays(name, value) for name, value in fields.items()}
        frames = {name: (arr.astype(self.dtype, copy=False),
                         None if stag is None else tuple(c.astype(self.dtype, copy=False) for c in stag))
                  for name, (arr, stag) in frames.items()}
        raw = sum(a.nbytes + sum(c.nbytes for c in (st or ())) for a, st in frames.values())
        check_space(self.path, raw * (2 if self._journal is not None else 1))
        with uninterrupted():  # an interrupt waits for the frame: never half of one in the file
            if self._journal is not None:  # the commit record: complete in the journal before the HDF5 write
                keys, arrays = [], []
                for name, (arr, stag) in frames.items():
                    keys.append([f"c:{name}", list(arr.shape), arr.dtype.str])
                    arrays.append(arr)
                    for a, comp in enumerate(stag or ()):
                        keys.append([f"s:{name}:{a}", list(comp.shape), comp.dtype.str])
                        arrays.append(comp)
                self._journal.write_frame({"time": t, "kinds": self.kinds, "arrays": keys}, arrays)
            try:
                self._write_frame(frames, t)
            except (OSError, RuntimeError) as exc:
                raise write_failure(self.path, exc, f"write frame {self._n} to") from exc
            self._n += 1
            self._last_time = t

    def _write_frame(self, frames: dict, t: float) -> None:
        f, n = self._file, self._n
        for name, (arr, stag) in frames.items():
            ds = f["t0_fields" if self.kinds[name] == "scalar" else "t1_fields"][name]
            ds.resize(n + 1, axis=1)
            ds[:, n] = arr
            if stag is not None:
                for a, comp in enumerate(stag):
                    sds = f["staggered"][f"{name}_{AXIS_NAMES[a]}"]
                    sds.resize(n + 1, axis=1)
                    sds[:, n] = comp
        f.flush()  # the frame's data is on disk before the time axis grows over it
        tds = f["dimensions"]["time"]
        tds.resize((n + 1,))
        tds[n] = t
        f.flush()

    def training_log(self, method: str, attrs: Mapping[str, Any] | None = None, *,
                     planned_iterations: int | None = None, overwrite: bool = False,
                     resume: bool = False) -> TrainingLog:
        """A :class:`~phisim.io.TrainingLog` writing into ``/training/<method>`` of this file (same arguments)."""
        self._check_open()
        return TrainingLog(self._file, method, attrs=attrs, planned_iterations=planned_iterations,
                           overwrite=overwrite, resume=resume, journal=self._journal)

    def _abort(self) -> None:
        """Close after a failure: the partial HDF5 file and the journal are removed (nothing was committed)."""
        try:
            if self._file is not None and self._file.id.valid:
                self._file.close()
        except Exception:  # noqa: BLE001 - the original error is the one to report
            pass
        if self._journal is not None:
            self._journal.close(delete=True)
        self.path.unlink(missing_ok=True)

    def close(self) -> None:
        """Flush and close the file, then delete the journal (idempotent).

        Raises:
            FileFormatError: If the final flush fails (e.g. a full disk); the journal is kept, so
                :func:`read_simulation` still returns every appended frame.
        """
        with uninterrupted():
            if self._file is not None and self._file.id.valid:
                try:
                    self._file.flush()
                    self._file.close()
                except (OSError, RuntimeError) as exc:
                    if self._journal is not None:
                        self._journal.close(delete=False)
                    raise write_failure(self.path, exc, "flush and close") from exc
            if self._journal is not None and not self._journal.closed:
                self._journal.close(delete=True)

    def __enter__(self) -> SimulationWriter:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"SimulationWriter({str(self.path)!r}, {self.grid}, fields={self.kinds}, frames={self._n})"
