"""Pictures of files without code (``phisim plot``): frames, GIF/MP4 of a field, learning curves.

For a simulation file (:func:`phisim.io.read_simulation`) any field can be shown, plus quantities derived
from a velocity: ``speed`` (``|u|``) and ``vorticity`` (``∂u_y/∂x − ∂u_x/∂y`` in 2-D, its magnitude
``|∇×u|`` in 3-D; central differences, periodic where the boundary is). 3-D fields show the middle ``z``
slice, 1-D fields a line per frame. An obstacle mask stored with the simulation (a constant field, or a field
named ``obstacle_mask``/``mask``) is drawn as a grey overlay with its outline. Frames carry the simulation
time. For a training file the learning curves of every method (loss and metric, with the held-out curves
where present) go into one PNG.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path

import h5py
import numpy as np

from phisim.boundary import Periodic
from phisim.errors import FileFormatError, ParameterError
from phisim.io import read_simulation, read_training
from phisim.viz.plot import ffmpeg_available, new_figure, plot_curves, save_figure

__all__ = ["DERIVED", "field_frames", "obstacle_of", "plot_frames", "animate_file", "plot_training_file",
           "plot_file"]

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


def _slice2d(a: np.ndarray) -> np.ndarray:
    return a[..., a.shape[-1] // 2] if a.ndim == 3 else a


def _draw(ax, img: np.ndarray, grid, mask, vmin, vmax, cmap):
    ext = (grid.bounds[0][0], grid.bounds[0][1], grid.bounds[1][0], grid.bounds[1][1])
    im = ax.imshow(img.T, origin="lower", extent=ext, vmin=vmin, vmax=vmax, cmap=cmap, interpolation="nearest")
    if mask is not None and mask.any():
        m = _slice2d(mask)
        overlay = np.ma.masked_where(~m.T, np.ones_like(m.T, dtype=float))
        ax.imshow(overlay, origin="lower", extent=ext, cmap="Greys", vmin=0, vmax=1.5, alpha=0.9,
                  interpolation="nearest")
        xs = np.linspace(ext[0], ext[1], m.shape[0] + 1)
        ys = np.linspace(ext[2], ext[3], m.shape[1] + 1)
        xc, yc = 0.5 * (xs[1:] + xs[:-1]), 0.5 * (ys[1:] + ys[:-1])
        ax.contour(xc, yc, m.T.astype(float), levels=[0.5], colors="k", linewidths=1.0)
    ax.set_xlabel("x")
    ax.set_ylabel("y")
    return im


def _limits(frames: np.ndarray, name: str) -> tuple[float, float, str]:
    finite = frames[np.isfinite(frames)]
    lo, hi = (float(finite.min()), float(finite.max())) if finite.size else (0.0, 1.0)
    if name == "vorticity" and lo < 0 < hi:
        m = max(-lo, hi)
        return -m, m, "RdBu_r"
    return lo, hi, "viridis"


def plot_frames(data, name: str, path: str | Path, *, sample: int = 0, frames: Sequence[int] | None = None,
                columns: int = 4) -> Path:
    """One PNG with a panel per frame (default: first, a quarter, half, three quarters, last).

    Returns:
        The path written.

    Raises:
        ParameterError: Unknown field or frame index out of range.
    """

    arr = field_frames(data, name, sample)
    T = arr.shape[0]
    if frames is None:
        frames = sorted({0, T // 4, T // 2, (3 * T) // 4, T - 1})
    frames = [int(f) + T if int(f) < 0 else int(f) for f in frames]
    bad = [f for f in frames if not 0 <= f < T]
    if bad:
        raise ParameterError(f"frame(s) {bad} out of range: the file has {T} frames")
    mask = obstacle_of(data, sample)
    lo, hi, cmap = _limits(arr[frames], name)
    if data.grid.rank == 1:
        fig, ax = new_figure((6.0, 4.0))
        x = np.asarray(data.grid.center_coords(0)) if hasattr(data.grid, "center_coords") else np.arange(arr.shape[1])
        for f in frames:
            ax.plot(x, arr[f], label=f"t = {data.times[f]:.4g}")
        ax.set_xlabel("x")
        ax.set_ylabel(name)
        ax.legend()
        ax.set_title(f"{name}, sample {sample}")
        return save_figure(fig, path)
    aspect = data.grid.size[0] / data.grid.size[1]
    wide = aspect > 2  # a channel: one panel per row
    cols = 1 if wide else min(columns, len(frames))
    rows = math.ceil(len(frames) / cols)
    pw, ph = (8.0, max(1.6, 8.0 / aspect + 0.7)) if wide else (3.2, 3.0)
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(rows, cols, figsize=(pw * cols + 0.8, ph * rows), squeeze=False, layout="constrained")
    im = None
    for k, ax in enumerate(axes.flat):
        if k >= len(frames):
            ax.axis("off")
            continue
        im = _draw(ax, _slice2d(arr[frames[k]]), data.grid, mask, lo, hi, cmap)
        ax.set_title(f"t = {data.times[frames[k]]:.4g}")
    fig.colorbar(im, ax=axes.ravel().tolist(), label=name + (" (middle z slice)" if data.grid.rank == 3 else ""))
    return save_figure(fig, path)


def animate_file(data, name: str, path: str | Path, *, sample: int = 0, fps: int = 10, dpi: int = 80) -> Path:
    """A GIF (Pillow) or MP4 (ffmpeg) of one field of one sample, time stamp in the title, obstacle drawn.

    Raises:
        ParameterError: Unknown suffix or field, MP4 without ffmpeg, a 1-D field.
    """
    from matplotlib.animation import FFMpegWriter, FuncAnimation, PillowWriter


    p = Path(path)
    suffix = p.suffix.lower()
    if suffix not in (".gif", ".mp4"):
        raise ParameterError(f"animations are .gif or .mp4 files, got {p.name!r}")
    if suffix == ".mp4" and not ffmpeg_available():
        raise ParameterError("writing MP4 needs ffmpeg on the PATH; install ffmpeg or write a .gif")
    if data.grid.rank == 1:
        raise ParameterError("animations show 2-D or 3-D fields; plot 1-D fields as frames")
    arr = field_frames(data, name, sample)
    mask = obstacle_of(data, sample)
    lo, hi, cmap = _limits(arr, name)
    aspect = data.grid.size[0] / data.grid.size[1]
    fig, ax = new_figure((8.0, max(2.0, 7.0 / aspect + 0.8)) if aspect > 2 else (5.0, 4.0), dpi)
    im = _draw(ax, _slice2d(arr[0]), data.grid, mask, lo, hi, cmap)
    fig.colorbar(im, ax=ax, label=name)
    title = ax.set_title("")

    def update(k):
        im.set_data(_slice2d(arr[k]).T)
        title.set_text(f"{name}   t = {data.times[k]:.4g}")
        return (im, title)

    update(0)
    anim = FuncAnimation(fig, update, frames=arr.shape[0], blit=False)
    writer = PillowWriter(fps=int(fps)) if suffix == ".gif" else FFMpegWriter(fps=int(fps))
    p.parent.mkdir(parents=True, exist_ok=True)
    anim.save(str(p), writer=writer, dpi=dpi)
    import matplotlib.pyplot as plt

    plt.close(fig)
    return p


def plot_training_file(path: str | Path, out: str | Path) -> Path:
    """Learning curves of every method in ``/training`` (loss and metric panels, log axes) as a PNG.

    Raises:
        FileFormatError: No training curves in the file.
    """

    curves = read_training(path)
    if not curves:
        raise FileFormatError(f"{path} holds no training curves (/training)")
    import matplotlib.pyplot as plt

    keys = [k for k in ("loss", "metric") if any(k in c for c in curves.values())]
    held = [k for k in curves[next(iter(curves))] if k.startswith(("eval_", "heldout_", "test_"))]
    fig, axes = plt.subplots(1, len(keys), figsize=(5.5 * len(keys), 4.0), squeeze=False, layout="constrained")
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


def plot_file(path: str | Path, out: str | Path | None = None, *, field: str | None = None, sample: int = 0,
              frames: Sequence[int] | None = None, animation: str | None = "gif", fps: int = 10) -> list[Path]:
    """Pictures of an HDF5 file: frames and an animation of a field for a simulation, curves for training.

    Args:
        path: The file.
        out: Output folder (default: beside the file). Names: ``<stem>_<field>.png``, ``<stem>_<field>.gif``,
            ``<stem>_training.png``.
        field: Field or derived quantity (default: the first scalar field other than a mask, else ``speed``).
        sample: Trajectory.
        frames: Frame indices of the PNG (negative counts from the end).
        animation: ``'gif'``, ``'mp4'`` or None.
        fps: Frames per second of the animation.

    Returns:
        The files written.

    Raises:
        FileFormatError: Not a readable HDF5 file, or neither simulation fields nor training curves.
        ParameterError: Unknown field, sample or frame.
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
    out_dir = path.parent if out is None else Path(out)
    written = []
    if has_training:
        written.append(plot_training_file(path, out_dir / f"{path.stem}_training.png"))
    if has_fields:
        data = read_simulation(path)
        if data.n_frames == 0 or not data.fields:
            if not written:
                raise FileFormatError(f"{path} holds no frames")
            return written
        if field is None:
            scal = [n for n, k in data.kinds.items() if k == "scalar" and n not in _MASK_NAMES]
            vec = [n for n, k in data.kinds.items() if k != "scalar"]
            field = scal[0] if scal else vec[0] if data.grid.rank == 1 else "speed"
        written.append(plot_frames(data, field, out_dir / f"{path.stem}_{field}.png", sample=sample, frames=frames))
        if animation and data.grid.rank > 1 and data.n_frames > 1:
            written.append(animate_file(data, field, out_dir / f"{path.stem}_{field}.{animation}", sample=sample,
                                        fps=fps))
    return written
