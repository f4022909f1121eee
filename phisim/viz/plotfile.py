"""Pictures of files without code (``phisim plot``): frames, GIF/MP4 of a field, learning curves.

For a simulation file (:func:`phisim.io.read_simulation`) any field can be shown, plus quantities derived
from a velocity: ``speed`` (``|u|``) and ``vorticity`` (``∂u_y/∂x − ∂u_x/∂y`` in 2-D, its magnitude
``|∇×u|`` in 3-D; central differences, periodic where the boundary is). ``y`` (axis 1) is up in every picture.
3-D fields show a slice normal to ``axis`` (default ``'z'``: an ``x``-``y`` picture, ``y`` up) at ``index``
(default the middle), or a projection of the whole volume along ``axis`` (``projection='max'`` / ``'mean'`` /
``'min'``); 1-D fields a line per frame. An obstacle mask stored with the simulation (a constant field, or a
field named ``obstacle_mask``/``mask``) is drawn as a grey overlay with its outline (its shadow in a
projection). Frames carry the simulation time; colour bars name the field and the view. For a training file
the learning curves of every method (loss and metric, with the held-out curves where present) go into one PNG.

Where pictures go (:func:`default_out_dir`): a file of a dataset, ``<root>/data/<split>/<name>.h5``, gets its
pictures in ``<root>/plots/<split>/`` (never inside the dataset's folders); any other file gets them beside it.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import h5py
import numpy as np
from matplotlib.animation import FuncAnimation
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from phisim.boundary import Periodic
from phisim.errors import FileFormatError, ParameterError
from phisim.io import read_simulation, read_training
from phisim.viz.plot import (
    AXIS_NAMES,
    PLANES,
    axis_index,
    draw_mask,
    ffmpeg_available,
    mask_view,
    new_figure,
    panel_layout,
    plane_grid,
    plot_curves,
    save_animation,
    save_figure,
    view_label,
    volume_view,
)

__all__ = ["DERIVED", "field_frames", "field_label", "obstacle_of", "plot_frames", "animate_file",
           "plot_training_file", "plot_file", "default_out_dir", "default_field", "file_animation"]

#: Quantities derived from a velocity field.
DERIVED = ("speed", "vorticity")
_MASK_NAMES = ("obstacle_mask", "mask", "obstacle", "solid")


def _velocity_name(data) -> str:
    vec = [n for n, k in data.kinds.items() if k in ("vector", "staggered")]
    if not vec:
        raise ParameterError(f"{data.path} has no vector field to derive speed/vorticity from")
    return "velocity" if "velocity" in vec else vec[0]


def _periodic_axes(data) -> list[bool]:

    return [isinstance(lo, Periodic) for lo, _ in data.boundary.sides]


def _diff(a: np.ndarray, axis: int, dx: float, periodic: bool) -> np.ndarray:
    if periodic:
        return (np.roll(a, -1, axis=axis) - np.roll(a, 1, axis=axis)) / (2 * dx)
    return np.gradient(a, dx, axis=axis)


def field_frames(data, name: str, sample: int = 0) -> np.ndarray:
    """The frames ``(T, *res)`` of a scalar field, a vector's magnitude or a derived quantity of one sample.

    Args:
        data: A :class:`~phisim.io.SimulationData`.
        name: A field name, or ``'speed'`` / ``'vorticity'``.
        sample: Trajectory index.

    Raises:
        ParameterError: Unknown field (the names are listed) or sample out of range.
    """
    if not 0 <= sample < data.batch_size:
        raise ParameterError(f"sample {sample} out of range: the file holds {data.batch_size} trajectories")
    if name in DERIVED and name not in data.fields:
        u = np.asarray(data.fields[_velocity_name(data)][sample], dtype=np.float64)  # (T, d, *res)
        if name == "speed":
            return np.sqrt((u**2).sum(axis=1))
        d = u.shape[1]
        dx = data.grid.dx
        per = _periodic_axes(data)

        def g(c, a):
            return _diff(u[:, c], a + 1, float(dx[a]), per[a])

        if d == 2:
            return g(1, 0) - g(0, 1)
        if d == 3:
            w = np.stack([g(2, 1) - g(1, 2), g(0, 2) - g(2, 0), g(1, 0) - g(0, 1)])
            return np.sqrt((w**2).sum(axis=0))
        raise ParameterError("vorticity needs a 2-D or 3-D velocity")
    if name not in data.fields:
        choices = list(data.fields) + [d for d in DERIVED if any(k != "scalar" for k in data.kinds.values())]
        raise ParameterError(f"no field {name!r} in {data.path}; choose from {choices}")
    v = np.asarray(data.fields[name][sample], dtype=np.float64)
    if data.kinds[name] != "scalar":
        v = v[:, 0] if v.shape[1] == 1 else np.sqrt((v**2).sum(axis=1))  # 1-D: the signed component
    return v


def obstacle_of(data, sample: int = 0) -> np.ndarray | None:
    """The boolean obstacle mask ``(*res)`` stored with a simulation, or None."""
    const = getattr(data, "constant_fields", None) or {}
    for n in _MASK_NAMES:
        if n in const:
            m = np.asarray(const[n])
            return (m[sample] if m.ndim == data.grid.rank + 1 else m) > 0.5
    for n in _MASK_NAMES:
        if n in data.fields and data.kinds.get(n) == "scalar":
            return np.asarray(data.fields[n][sample, 0]) > 0.5
    return None


def field_label(data, name: str) -> str:
    """The colour-bar label of a field: its name, and what a derived quantity is."""
    if name in DERIVED and name not in data.fields:
        if name == "speed":
            return "speed |u|"
        return "vorticity ∂u_y/∂x − ∂u_x/∂y" if data.grid.rank == 2 else "vorticity |∇×u|"
    return name


def _check_view(data, axis, index, projection) -> None:
    """3-D view options on a file's grid: valid on 3-D grids (checked by the first picture), refused elsewhere."""
    rank = data.grid.rank
    if rank == 3:
        a = 2 if axis is None else axis_index(axis, 3)
        view_label(data.grid, a, index, projection)  # checks index range and projection
    elif index is not None or projection is not None or axis not in (None, "z", 2):
        raise ParameterError(f"axis=, index= and projection= choose views of 3-D fields; {data.path} is {rank}-D")


def _view(a: np.ndarray, axis, index, projection) -> np.ndarray:
    return volume_view(a, axis, index, projection) if a.ndim == 3 else a


def _draw(ax, img: np.ndarray, grid, mask, vmin, vmax, cmap, axis=None, index=None, projection=None):
    """One picture of a 2-D field or a view of a 3-D field (``img`` already the view), mask drawn."""
    pg = plane_grid(grid, "z" if axis is None else axis)
    ext = (pg.bounds[0][0], pg.bounds[0][1], pg.bounds[1][0], pg.bounds[1][1])
    im = ax.imshow(img.T, origin="lower", extent=ext, vmin=vmin, vmax=vmax, cmap=cmap, interpolation="nearest")
    if mask is not None and mask.any():
        m = mask_view(mask, axis, index, projection) if mask.ndim == 3 else mask
        draw_mask(ax, m, pg)
    if grid.rank == 3:
        h, v = _plane_names(axis)
        ax.set_xlabel(h)
        ax.set_ylabel(v)
    else:
        ax.set_xlabel("x")
        ax.set_ylabel("y")
    return im


def _plane_names(axis) -> tuple[str, str]:
    h, v = PLANES[2 if axis is None else axis_index(axis, 3)]
    return AXIS_NAMES[h], AXIS_NAMES[v]


def _limits(frames: np.ndarray, name: str) -> tuple[float, float, str]:
    finite = frames[np.isfinite(frames)]
    lo, hi = (float(finite.min()), float(finite.max())) if finite.size else (0.0, 1.0)
    if name == "vorticity" and lo < 0 < hi:
        m = max(-lo, hi)
        return -m, m, "RdBu_r"
    return lo, hi, "viridis"


def _bar_label(data, name: str, axis, index, projection) -> str:
    label = field_label(data, name)
    if data.grid.rank == 3:
        label += f" ({view_label(data.grid, 'z' if axis is None else axis, index, projection)})"
    return label


def plot_frames(data, name: str, path: str | Path, *, sample: int = 0, frames: Sequence[int] | None = None,
                columns: int | None = None, axis=None, index: int | None = None,
                projection: str | None = None) -> Path:
    """One PNG with a panel per frame (default: first, a quarter, half, three quarters, last); no empty panels.

    Args:
        data: A :class:`~phisim.io.SimulationData`.
        name: Field or derived quantity.
        path: The PNG (or any format :func:`~phisim.viz.plot.save_figure` writes).
        sample: Trajectory.
        frames: Frame indices (negative counts from the end).
        columns: Most panels per row (default: one row up to six panels); rows are filled evenly.
        axis: 3-D fields: the slice normal, ``'x'`` / ``'y'`` / ``'z'`` or an int (default ``'z'``).
        index: 3-D fields: the slice index along ``axis`` (default the middle).
        projection: 3-D fields: ``None`` (a slice), ``'max'``, ``'mean'`` or ``'min'`` along ``axis``.

    Returns:
        The path written.

    Raises:
        ParameterError: Unknown field, frame index out of range, bad view options.
    """
    _check_view(data, axis, index, projection)
    arr = field_frames(data, name, sample)
    T = arr.shape[0]
    if frames is None:
        frames = sorted({0, T // 4, T // 2, (3 * T) // 4, T - 1})
    frames = [int(f) + T if int(f) < 0 else int(f) for f in frames]
    bad = [f for f in frames if not 0 <= f < T]
    if bad:
        raise ParameterError(f"frame(s) {bad} out of range: the file has {T} frames")
    if not frames:
        raise ParameterError("frames is empty: name at least one frame index")
    mask = obstacle_of(data, sample)
    label = _bar_label(data, name, axis, index, projection)
    if data.grid.rank == 1:
        fig, ax = new_figure((6.0, 4.0))
        x = np.asarray(data.grid.center_coords(0)) if hasattr(data.grid, "center_coords") else np.arange(arr.shape[1])
        for f in frames:
            ax.plot(x, arr[f], label=f"t = {data.times[f]:.4g}")
        ax.set_xlabel("x")
        ax.set_ylabel(label)
        ax.legend()
        ax.set_title(f"{name}, sample {sample}")
        return save_figure(fig, path)
    views = np.stack([_view(arr[f], axis, index, projection) for f in frames])
    lo, hi, cmap = _limits(views, name)
    pg = plane_grid(data.grid, "z" if axis is None else axis)
    aspect = pg.size[0] / pg.size[1]
    wide = aspect > 2  # a channel: one panel per row
    rows, cols = (len(frames), 1) if wide else panel_layout(len(frames), columns)
    pw, ph = (8.0, max(1.6, 8.0 / aspect + 0.7)) if wide else (3.2, 3.0)
    fig = Figure(figsize=(pw * cols + 0.8, ph * rows), layout="constrained")
    FigureCanvasAgg(fig)
    axes, im = [], None
    for k, f in enumerate(frames):  # only as many axes as frames: no empty panel
        ax = fig.add_subplot(rows, cols, k + 1)
        im = _draw(ax, views[k], data.grid, mask, lo, hi, cmap, axis, index, projection)
        ax.set_title(f"t = {data.times[f]:.4g}")
        axes.append(ax)
    fig.colorbar(im, ax=axes, label=label)
    return save_figure(fig, path)


def file_animation(data, name: str, *, sample: int = 0, fps: int = 10, dpi: int = 80, axis=None,
                   index: int | None = None, projection: str | None = None) -> tuple[Figure, FuncAnimation]:
    """The animation of one field of one sample of a 2-D or 3-D simulation (see :func:`animate_file`).

    Returns:
        ``(figure, animation)``, one animation frame per stored frame.
    """
    if isinstance(fps, bool) or not isinstance(fps, (int, np.integer)) or fps < 1:
        raise ParameterError(f"fps must be a positive int, got {fps!r}")
    if data.grid.rank == 1:
        raise ParameterError("animations show 2-D or 3-D fields; plot 1-D fields as frames")
    _check_view(data, axis, index, projection)
    arr = field_frames(data, name, sample)
    views = np.stack([_view(a, axis, index, projection) for a in arr])
    mask = obstacle_of(data, sample)
    lo, hi, cmap = _limits(views, name)
    pg = plane_grid(data.grid, "z" if axis is None else axis)
    aspect = pg.size[0] / pg.size[1]
    fig, ax = new_figure((8.0, max(2.0, 7.0 / aspect + 0.8)) if aspect > 2 else (5.0, 4.0), dpi)
    im = _draw(ax, views[0], data.grid, mask, lo, hi, cmap, axis, index, projection)
    fig.colorbar(im, ax=ax, label=_bar_label(data, name, axis, index, projection))
    title = ax.set_title("")

    def update(k):
        im.set_data(views[k].T)
        title.set_text(f"{name}   t = {data.times[k]:.4g}")
        return (im, title)

    update(0)
    return fig, FuncAnimation(fig, update, frames=arr.shape[0], interval=1000.0 / int(fps), blit=False)


def animate_file(data, name: str, path: str | Path, *, sample: int = 0, fps: int = 10, dpi: int = 80, axis=None,
                 index: int | None = None, projection: str | None = None) -> Path:
    """A GIF (Pillow) or MP4 (ffmpeg) of one field of one sample, time stamp in the title, obstacle drawn
    (3-D: the view chosen by ``axis``, ``index``, ``projection`` as in :func:`plot_frames`).

    Raises:
        ParameterError: Unknown suffix or field, MP4 without ffmpeg, a 1-D field, bad view options.
    """
    p = Path(path)
    suffix = p.suffix.lower()
    if suffix not in (".gif", ".mp4"):
        raise ParameterError(f"animations are .gif or .mp4 files, got {p.name!r}")
    if suffix == ".mp4" and not ffmpeg_available():
        raise ParameterError("writing MP4 needs ffmpeg on the PATH; install ffmpeg or write a .gif")
    _, anim = file_animation(data, name, sample=sample, fps=fps, dpi=dpi, axis=axis, index=index,
                             projection=projection)
    return save_animation(anim, p, fps=fps, dpi=dpi)


def plot_training_file(path: str | Path, out: str | Path) -> Path:
    """Learning curves of every method in ``/training`` (loss and metric panels, log axes) as a PNG.

    Raises:
        FileFormatError: No training curves in the file.
    """

    curves = read_training(path)
    if not curves:
        raise FileFormatError(f"{path} holds no training curves (/training)")
    keys = [k for k in ("loss", "metric") if any(k in c for c in curves.values())]
    held = [k for k in curves[next(iter(curves))] if k.startswith(("eval_", "heldout_", "test_"))]
    fig = Figure(figsize=(5.5 * len(keys), 4.0), layout="constrained")
    FigureCanvasAgg(fig)
    axes = fig.subplots(1, len(keys), squeeze=False)
    with h5py.File(path, "r") as f:
        units = {m: dict(f[f"training/{m}"].attrs) for m in curves}
    for ax, key in zip(axes.flat, keys):
        lines = {m: (c["iteration"], c[key]) for m, c in curves.items() if key in c}
        for h in held:
            base = h.split("_", 1)[1]
            if base == key:
                for m, c in curves.items():
                    it = c.get(h.split("_", 1)[0] + "_iteration", c["iteration"])
                    tag = "held-out" if h.startswith(("eval_", "heldout_")) else h.split("_", 1)[0]
                    lines[f"{m} ({tag})"] = (it, c[h])
        label = key
        for m in curves:
            name = units[m].get(f"{key}_name") or units[m].get("metric_name" if key == "metric" else "loss_name")
            if name:
                label = str(name)
                break
        plot_curves(lines, ax, logy=True, title=f"{Path(path).name}: {key}", ylabel=label)
        colours = {ln.get_label(): ln.get_color() for ln in ax.get_lines()}
        for ln in ax.get_lines():  # a held-out curve: its method's colour, dashed
            name = ln.get_label()
            if name.endswith(")") and " (" in name and name.rsplit(" (", 1)[0] in colours:
                ln.set_color(colours[name.rsplit(" (", 1)[0]])
                ln.set_linestyle("--")
                ln.set_linewidth(2.0)
        ax.legend()
    return save_figure(fig, out)


def default_field(data) -> str:
    """The field a picture of a simulation shows when none is named: the first scalar field other than a mask,
    else the vector field of a 1-D file, else ``'speed'``."""
    scal = [n for n, k in data.kinds.items() if k == "scalar" and n not in _MASK_NAMES]
    vec = [n for n, k in data.kinds.items() if k != "scalar"]
    if scal:
        return scal[0]
    return vec[0] if data.grid.rank == 1 and vec else "speed"


def default_out_dir(path: str | Path) -> Path:
    """Where :func:`plot_file` puts the pictures of ``path`` when no folder is given: ``<root>/plots/<split>/``
    for a dataset file ``<root>/data/<split>/<name>.h5`` (pictures never land among the dataset's files),
    else the file's folder."""
    path = Path(path)
    if path.parent.parent.name == "data":
        return path.parent.parent.parent / "plots" / path.parent.name
    return path.parent


def _view_suffix(rank: int, axis, index, projection) -> str:
    """File-name part of a chosen 3-D view (empty for the default middle ``z`` slice)."""
    if rank != 3 or (axis in (None, "z", 2) and index is None and projection is None):
        return ""
    a = AXIS_NAMES[2 if axis is None else axis_index(axis, 3)]
    return f"_{projection}_{a}" if projection is not None else f"_{a}{'mid' if index is None else index}"


def plot_file(path: str | Path, out: str | Path | None = None, *, field: str | None = None, sample: int = 0,
              frames: Sequence[int] | None = None, animation: str | None = "gif", fps: int = 10, axis=None,
              index: int | None = None, projection: str | None = None) -> list[Path]:
    """Pictures of an HDF5 file: frames and an animation of a field for a simulation, curves for training.

    Args:
        path: The file.
        out: Output folder (default :func:`default_out_dir`: ``<root>/plots/<split>/`` for a dataset file
            ``<root>/data/<split>/*.h5``, else beside the file). Names: ``<stem>_<field>.png``,
            ``<stem>_<field>.gif``, ``<stem>_training.png``; a 3-D view other than the middle ``z`` slice adds
            ``_<axis><index>`` or ``_<projection>_<axis>`` (``smoke_00000_density_max_z.png``).
        field: Field or derived quantity (default: the first scalar field other than a mask, else ``speed``).
        sample: Trajectory.
        frames: Frame indices of the PNG (negative counts from the end).
        animation: ``'gif'``, ``'mp4'`` or None.
        fps: Frames per second of the animation.
        axis: 3-D fields: the slice normal, ``'x'`` / ``'y'`` / ``'z'`` or 0 / 1 / 2 (default ``'z'``: an
            ``x``-``y`` picture with ``y`` up).
        index: 3-D fields: the slice index along ``axis`` (default the middle).
        projection: 3-D fields: ``None`` (a slice), ``'max'`` (maximum intensity), ``'mean'`` or ``'min'`` along
            ``axis``.

    Returns:
        The files written.

    Raises:
        FileFormatError: Not a readable HDF5 file, or neither simulation fields nor training curves.
        ParameterError: Unknown field, sample or frame; bad view options (an unknown axis or projection, an
            index out of range, an index with a projection, view options for a 1-D or 2-D file).
    """

    path = Path(path)
    try:
        with h5py.File(path, "r") as f:
            has_fields = "t0_fields" in f or "t1_fields" in f
            has_training = "training" in f and len(f["training"]) > 0
    except OSError as exc:
        raise FileFormatError(f"{path}: not a readable HDF5 file ({exc})") from exc
    if not has_fields and not has_training:
        raise FileFormatError(f"{path} holds neither simulation fields nor training curves")
    if animation not in (None, "gif", "mp4"):
        raise ParameterError(f"animation must be 'gif', 'mp4' or None, got {animation!r}")
    if animation == "mp4":

        if not ffmpeg_available():
            raise ParameterError("writing MP4 needs ffmpeg on the PATH; install ffmpeg or write a .gif")
    out_dir = default_out_dir(path) if out is None else Path(out)
    written = []
    if has_training:
        written.append(plot_training_file(path, out_dir / f"{path.stem}_training.png"))
    if has_fields:
        data = read_simulation(path)
        if data.n_frames == 0 or not data.fields:
            if not written:
                raise FileFormatError(f"{path} holds no frames")
            return written
        _check_view(data, axis, index, projection)
        if field is None:
            field = default_field(data)
        stem = f"{path.stem}_{field}{_view_suffix(data.grid.rank, axis, index, projection)}"
        view = {"axis": axis, "index": index, "projection": projection}
        written.append(plot_frames(data, field, out_dir / f"{stem}.png", sample=sample, frames=frames, **view))
        if animation and data.grid.rank > 1 and data.n_frames > 1:
            written.append(animate_file(data, field, out_dir / f"{stem}.{animation}", sample=sample, fps=fps,
                                        **view))
    return written
