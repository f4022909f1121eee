"""One call for pictures: :func:`show` draws fields, states, trajectories and simulation files, inline in Jupyter
and as PNG / GIF / MP4 / HTML files.

``show(obj)`` returns a :class:`Picture`. A notebook displays it when it is the cell's last expression (its
``_repr_html_``: an ``<img>`` for a still picture, a player for an animation; ``_repr_png_`` for front ends
without HTML); ``show(obj, save="out/x.gif")`` also writes it. What is drawn:

==========================================  ===============================================================
``obj``                                     picture
==========================================  ===============================================================
1-D field or array                          a curve
2-D field or array                          an image, ``x`` right and ``y`` up
3-D field or array                          a slice normal to ``axis`` at ``index`` or a ``projection``
``FluidState``                              panels: the marker (if any) and the speed ``|u|``
``dict`` name -> field / array              one panel per entry, shared layout, no empty panels
``Trajectory`` (:func:`phisim.rollout`),    an animation (``animate=False``: panels of a few frames; 1-D:
list of fields / states / arrays,           the frames as curves in one axes)
simulation file (path or ``SimulationData``)
==========================================  ===============================================================

``y`` (axis 1) is up in every picture, as it is the default buoyancy direction of the fluid steps. Bodies
(``obstacles=``: ``Obstacle``, ``Body``, geometry, boolean mask, a list of them, or a ``FluidStepper``) are drawn
in grey with their outline; a simulation file's stored obstacle mask is drawn without being asked.
"""

from __future__ import annotations

import base64
import io
import os
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path

import numpy as np
import torch
from matplotlib.animation import FuncAnimation
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from phisim.errors import ParameterError, ShapeError
from phisim.field import CenteredGrid, StaggeredGrid
from phisim.fluid import FluidState, FluidStepper, obstacle_mask
from phisim.fluid.bodies import SolidLayout
from phisim.grid import Grid
from phisim.io import SimulationData, read_simulation
from phisim.rollout import Trajectory
from phisim.viz.plot import (
    animation_figure,
    ffmpeg_available,
    panel_layout,
    plane_grid,
    plot_field,
    save_animation,
    save_figure,
    view_label,
)
from phisim.viz.plotfile import default_field, field_frames, field_label, obstacle_of

__all__ = ["Picture", "show"]

_HTML_KINDS = ("jshtml", "video")


class Picture:
    """A picture made by :func:`show`: a still figure, or an animation of one.

    In Jupyter the picture displays itself (``_repr_html_``, ``_repr_png_``). :meth:`save` writes it.

    Attributes:
        figure: The matplotlib ``Figure`` (Agg canvas; not registered with pyplot).
        axes: The axes holding the panels (colour bars left out), in panel order.
        fps: Frames per second of the animation.
        saved: The file written by ``show(..., save=...)``, else None.
    """

    def __init__(self, figure: Figure, axes: Sequence, update: Callable[[int], object] | None = None, *,
                 n_frames: int = 1, fps: int = 10, html: str | None = None, dpi: int = 80):
        self.figure = figure
        self.axes = list(axes)
        self.fps = int(fps)
        self.saved: Path | None = None
        self._update = update
        self._n_frames = int(n_frames)
        self._animation: FuncAnimation | None = None
        self._html_kind = html
        self._dpi = dpi
        self._html: str | None = None

    @property
    def is_animation(self) -> bool:
        """Whether the picture is an animation."""
        return self._update is not None

    @property
    def animation(self) -> FuncAnimation | None:
        """The ``FuncAnimation`` (made when first needed), or None for a still picture."""
        if self._update is not None and self._animation is None:
            self._animation = FuncAnimation(self.figure, self._update, frames=self._n_frames,
                                            interval=1000.0 / self.fps, blit=False)
        return self._animation

    @property
    def n_frames(self) -> int:
        """Number of frames (1 for a still picture)."""
        return self._n_frames if self.is_animation else 1

    def __repr__(self) -> str:
        what = f"animation of {self.n_frames} frames" if self.is_animation else "still"
        return f"Picture({what}, {len(self.axes)} panel{'s' if len(self.axes) != 1 else ''})"

    def to_png(self) -> bytes:
        """The figure as PNG bytes (for an animation: the frame drawn last)."""
        buf = io.BytesIO()
        self.figure.savefig(buf, format="png", dpi=self._dpi, bbox_inches="tight")
        return buf.getvalue()

    def to_html(self) -> str:
        """HTML of the picture: an ``<img>`` of a still picture; an animation as a JavaScript player
        (``to_jshtml``) or an HTML5 ``<video>`` (needs ffmpeg), by ``show``'s ``html=`` (default: video where
        ffmpeg exists, else the JavaScript player)."""
        if self._html is None:
            if not self.is_animation:
                data = base64.b64encode(self.to_png()).decode("ascii")
                self._html = f'<img src="data:image/png;base64,{data}" alt="phisim picture"/>'
            elif self._kind() == "video":
                self._html = self.animation.to_html5_video()
            else:
                self._html = self.animation.to_jshtml(fps=self.fps)
        return self._html

    def _kind(self) -> str:
        if self._html_kind is None:
            return "video" if ffmpeg_available() else "jshtml"
        return self._html_kind

    def _repr_html_(self) -> str:
        return self.to_html()

    def _repr_png_(self) -> bytes:
        return self.to_png()

    def save(self, path: str | os.PathLike, *, fps: int | None = None, dpi: int | None = None) -> Path:
        """Write the picture: a still one as ``.png`` / ``.pdf`` / ``.svg`` / ... ; an animation as ``.gif``
        (Pillow), ``.mp4`` (ffmpeg) or ``.html`` (JavaScript player). Parent folders are created.

        Returns:
            The path written.

        Raises:
            ParameterError: For a format that does not fit (an animation as PNG, a still picture as GIF), an
                unknown format, or MP4 without ffmpeg.
        """
        p = Path(path)
        suffix = p.suffix.lower()
        if not self.is_animation:
            if suffix in (".gif", ".mp4", ".html"):
                raise ParameterError(f"cannot write {p.name}: this picture is still (one frame); animations come "
                                     "from trajectories, lists of frames or simulation files")
            return save_figure(self.figure, p, dpi=dpi or self._dpi)
        if suffix not in (".gif", ".mp4", ".html"):
            raise ParameterError(f"cannot write {p.name}: an animation is written as .gif, .mp4 or .html; for a "
                                 "picture of a few frames use show(..., animate=False)")
        if suffix == ".mp4" and not ffmpeg_available():  # checked before the animation is made
            raise ParameterError("writing MP4 needs ffmpeg on the PATH (matplotlib's animation.ffmpeg_path); "
                                 "install ffmpeg or write a .gif")
        fps = self.fps if fps is None else fps
        if isinstance(fps, bool) or not isinstance(fps, (int, np.integer)) or fps < 1:
            raise ParameterError(f"fps must be a positive int, got {fps!r}")
        return save_animation(self.animation, p, fps=fps, dpi=dpi or self._dpi)


# ---- what to draw -------------------------------------------------------------------------------------------


def _solid_mask(obstacles, grid: Grid, batch: int) -> np.ndarray | None:
    """The boolean cell mask ``(*res)`` of ``obstacles`` (sample ``batch``), or None."""
    if obstacles is None:
        return None
    if isinstance(obstacles, FluidStepper):
        if obstacles.grid.resolution != grid.resolution:
            raise ShapeError(f"the stepper's grid {obstacles.grid} does not fit the picture's {grid}")
        obstacles = obstacles.obstacles
        if obstacles is None:
            return None
    if isinstance(obstacles, SolidLayout):
        m = obstacles.cell_fraction.detach() < 0.5
    else:
        if isinstance(obstacles, np.ndarray):
            obstacles = torch.as_tensor(obstacles.astype(bool))
        elif isinstance(obstacles, list | tuple):
            obstacles = [torch.as_tensor(o.astype(bool)) if isinstance(o, np.ndarray) else o for o in obstacles]
        m = obstacle_mask(obstacles, grid)
        if m is None:
            return None
    m = m.detach().cpu().numpy().astype(bool)
    if m.ndim == grid.rank + 1:
        m = m[min(batch, m.shape[0] - 1)]
    if m.shape != tuple(grid.resolution):
        raise ShapeError(f"obstacle mask of shape {m.shape} does not fit {grid}")
    return m


def _union(a: np.ndarray | None, b: np.ndarray | None) -> np.ndarray | None:
    if a is None:
        return b
    return a if b is None else a | b


def _check_batch(batch, size: int) -> int:
    if isinstance(batch, bool) or not isinstance(batch, (int, np.integer)):
        raise ParameterError(f"batch must be an int (which sample), got {batch!r}")
    if not 0 <= int(batch) < size:
        raise ParameterError(f"batch index {batch} out of range for batch size {size}")
    return int(batch)


def _speed(components: Sequence[torch.Tensor], grid: Grid, boundary) -> np.ndarray:
    """|u| at the cell centres of one sample's MAC components (each ``(*face_shape(i))``)."""
    v = StaggeredGrid(tuple(c[None] for c in components), grid, boundary).at_centers().values[0]
    return torch.sqrt((v.detach().double() ** 2).sum(0)).cpu().numpy()


def _one(x, grid: Grid | None, batch: int, component: int | None) -> tuple[np.ndarray, Grid]:
    """One sample of a field or array as ``(values (*res), grid)`` for a picture."""
    if isinstance(x, StaggeredGrid):
        x = x.at_centers()
    if isinstance(x, CenteredGrid):
        b = _check_batch(batch, x.batch_size)
        v = x.values[b].detach().double().cpu()
        if x.is_vector:
            if component is None:
                v = torch.sqrt((v**2).sum(0))
            elif isinstance(component, bool) or not isinstance(component, int) or not 0 <= component < v.shape[0]:
                raise ParameterError(f"component {component!r} out of range for {v.shape[0]} channels")
            else:
                v = v[component]
        elif component is not None:
            raise ParameterError("component= applies to vector fields only")
        return v.numpy(), x.grid
    if isinstance(x, torch.Tensor):
        if x.is_complex():
            raise ShapeError("cannot show complex values; show .real, .imag or .abs()")
        x = x.detach().cpu().numpy()
    if isinstance(x, np.ndarray) or isinstance(x, (list, tuple)) and x and isinstance(x[0], (int, float)):
        v = np.asarray(x)
        if v.dtype.kind not in "fiub":
            raise ShapeError(f"cannot show an array of dtype {v.dtype}")
        if not 1 <= v.ndim <= 3:
            raise ShapeError(
                f"show takes one sample as a 1-D, 2-D or 3-D array; got shape {tuple(v.shape)}, which is not one "
                "field: pass a CenteredGrid (it knows its grid and batch), index one sample (values[0]), or pass "
                "a list of frames or a Trajectory to animate")
        if grid is None:
            grid = Grid(v.shape)
        elif tuple(v.shape) != grid.resolution:
            raise ShapeError(f"array of shape {tuple(v.shape)} does not fit {grid}")
        return v.astype(np.float64), grid
    raise ParameterError(
        f"show cannot draw a {type(x).__name__}: pass a CenteredGrid / StaggeredGrid, a FluidState, a Trajectory, "
        "an array of one sample, a dict of these, a list of frames, or a simulation file")


def _state_panels(state: FluidState, field: str | None, batch: int, component) -> dict[str, tuple]:
    v = state.velocity
    grid = v.grid
    b = _check_batch(batch, v.batch_size)
    names = ["marker", "speed"] if state.marker is not None else ["speed"]
    if field is not None:
        names = [_state_field(field, state.marker is not None, state.pressure is not None)]
    out = {}
    for n in names:
        if n == "marker":
            out["marker"] = _one(state.marker, None, min(b, state.marker.batch_size - 1), None)
        elif n == "pressure":
            out["pressure"] = _one(state.pressure, None, min(b, state.pressure.batch_size - 1), None)
        elif n == "velocity" and component is not None:
            out[f"velocity[{component}]"] = _one(v, None, b, component)
        else:
            out["speed |u|"] = (_speed([c[b] for c in v.values], grid, v.boundary), grid)
    return out


def _state_field(field: str, has_marker: bool, has_pressure: bool) -> str:
    choices = ["speed", "velocity"] + (["marker"] if has_marker else []) + (["pressure"] if has_pressure else [])
    if field not in choices:
        raise ParameterError(f"field {field!r} is not in this state; choose from {choices}")
    return field


def _trajectory_frames(traj: Trajectory, field: str | None, batch: int, component) -> tuple[list, Grid, str]:
    """The frames of one sample of a trajectory, its grid and the name of the quantity."""
    final = traj.final
    if traj.values is not None:
        if not isinstance(final, CenteredGrid):
            raise ParameterError(f"cannot show a trajectory of {type(final).__name__} states")
        if field not in (None, "values"):
            raise ParameterError(f"field {field!r} is not in this trajectory of field values; leave field= out")
        template = final
        b = _check_batch(batch, traj.values.shape[1])
        return [_one(template.with_values(traj.values[t, b][None]), None, 0, component)[0]
                for t in range(len(traj))], template.grid, "values"
    v = final.velocity
    grid = v.grid
    b = _check_batch(batch, traj.velocity[0].shape[1])
    name = field or ("marker" if traj.marker is not None else "speed")
    name = _state_field(name, traj.marker is not None, traj.pressure is not None)
    T = len(traj)
    if name == "marker":
        return [traj.marker[t, min(b, traj.marker.shape[1] - 1)].detach().double().cpu().numpy()
                for t in range(T)], grid, "marker"
    if name == "pressure":
        return [traj.pressure[t, min(b, traj.pressure.shape[1] - 1)].detach().double().cpu().numpy()
                for t in range(T)], grid, "pressure"
    if name == "velocity" and component is not None:
        frames = []
        for t in range(T):
            s = StaggeredGrid(tuple(c[t, b][None] for c in traj.velocity), grid, v.boundary)
            frames.append(_one(s, None, 0, component)[0])
        return frames, grid, f"velocity[{component}]"
    return [_speed([c[t, b] for c in traj.velocity], grid, v.boundary) for t in range(T)], grid, "speed |u|"


def _frame_indices(n: int, frames) -> list[int]:
    if frames is None:
        return sorted({0, n // 4, n // 2, (3 * n) // 4, n - 1})
    if isinstance(frames, (int, np.integer)) and not isinstance(frames, bool):
        frames = [frames]
    out = []
    for f in frames:
        if isinstance(f, bool) or not isinstance(f, (int, np.integer)):
            raise ParameterError(f"frames must be frame indices (ints), got {f!r}")
        if not -n <= int(f) < n:
            raise ParameterError(f"frame {int(f)} out of range: there are {n} frames")
        out.append(int(f) % n)
    if not out:
        raise ParameterError("frames is empty: name at least one frame index")
    return out


# ---- drawing ------------------------------------------------------------------------------------------------


def _figure(n_panels: int, grid: Grid, columns, axis, dpi: int) -> tuple[Figure, list]:
    rows, cols = panel_layout(n_panels, columns)
    if grid.rank == 1:
        pw, ph = 5.5, 3.6
    else:
        pg = plane_grid(grid, "z" if axis is None else axis)
        aspect = pg.size[0] / pg.size[1]
        pw = 6.5 if aspect > 2 else 4.2 if cols <= 3 else 3.4
        ph = max(1.6, min(5.5, (pw - 0.9) / aspect + 0.7))
    fig = Figure(figsize=(pw * cols, ph * rows), dpi=dpi, layout="constrained")
    FigureCanvasAgg(fig)
    return fig, [fig.add_subplot(rows, cols, k + 1) for k in range(n_panels)]


def _stills(panels: Mapping[str, tuple], *, mask, batch, view, title, label, cmap, vmin, vmax, columns, dpi,
            shared: bool, suptitle: str | None = None) -> tuple[Figure, list]:
    """One panel per entry ``name -> (values, grid)``; with ``shared`` one colour scale and one colour bar."""
    items = list(panels.items())
    grid0 = items[0][1][1]
    fig, axes = _figure(len(items), grid0, columns, view["axis"], dpi)
    lo, hi = vmin, vmax
    if shared and (lo is None or hi is None):
        finite = np.concatenate([v[np.isfinite(v)].ravel() for v, _ in panels.values()])
        lo = float(finite.min()) if lo is None and finite.size else lo
        hi = float(finite.max()) if hi is None and finite.size else hi
    for ax, (name, (values, grid)) in zip(axes, items):
        m = mask if (mask is not None and grid.rank > 1 and mask.shape == tuple(grid.resolution)) else None
        heading = name if title is None or len(items) > 1 else title
        if grid.rank == 3:  # say which view of the volume this is
            where = view_label(grid, "z" if view["axis"] is None else view["axis"], view["index"], view["projection"])
            heading = f"{heading}: {where}" if heading else where
        plot_field(values, ax, grid=grid, cmap=cmap, vmin=lo, vmax=hi, colorbar=not shared, mask=m,
                   label=label or name, title=heading, **view)
    if shared and grid0.rank > 1:
        fig.colorbar(axes[-1].images[0], ax=axes, label=label or "")
    if suptitle:
        fig.suptitle(suptitle)
    return fig, axes


def show(
    obj,
    *,
    save: str | os.PathLike | None = None,
    field: str | None = None,
    batch: int = 0,
    component: int | None = None,
    axis=None,
    index: int | None = None,
    projection: str | None = None,
    obstacles=None,
    grid: Grid | None = None,
    title: str | None = None,
    label: str | None = None,
    cmap: str | None = None,
    vmin: float | None = None,
    vmax: float | None = None,
    animate: bool | None = None,
    frames: Sequence[int] | None = None,
    fps: int = 10,
    columns: int | None = None,
    html: str | None = None,
    dpi: int = 80,
) -> Picture:
    """Draw a field, a state, a trajectory or a simulation file in one call; inline in Jupyter, or to a file.

    Args:
        obj: What to draw (see the module's table): a ``CenteredGrid`` / ``StaggeredGrid`` (vectors as their
            magnitude or ``component``), an array of one sample (1-D, 2-D or 3-D; with ``grid`` for its bounds),
            a ``FluidState``, a ``dict`` name -> field/array, a :class:`~phisim.rollout.Trajectory`, a list of
            fields / states / arrays (frames), a ``SimulationData`` or the path of a simulation file.
        save: Also write the picture here (``.png`` / ``.pdf`` / ``.svg`` for a still picture; ``.gif``, ``.mp4``
            or ``.html`` for an animation); see :meth:`Picture.save`.
        field: Which quantity of a state, trajectory or file: ``'marker'``, ``'speed'``, ``'pressure'``,
            ``'velocity'`` (with ``component``) for fluid states; a field name, ``'speed'`` or ``'vorticity'`` for
            a file (default: the marker, else the speed; a file's first scalar field).
        batch: Which sample (trajectory of a file).
        component: For vector fields, one component instead of the magnitude.
        axis: 3-D: the slice normal, ``'x'`` / ``'y'`` / ``'z'`` or an int (default ``'z'``: an ``x``-``y`` picture,
            ``y`` up).
        index: 3-D: the slice index along ``axis`` (default the middle).
        projection: 3-D: ``None`` (a slice), ``'max'`` (maximum intensity), ``'mean'`` or ``'min'`` along ``axis``.
        obstacles: Solids drawn in grey and outlined: an ``Obstacle``, ``Body``, geometry, boolean mask, a list
            of them, or a ``FluidStepper`` (its bodies). A file's stored obstacle mask is drawn as well.
        grid: The grid of raw arrays (physical bounds).
        title: Title (of a single panel; of an animation, where ``{time}`` and ``{t}`` are replaced as in
            :func:`~phisim.viz.plot.animate`).
        label: Colour-bar label (default: the quantity's name).
        cmap: Colormap (default ``'viridis'``; a file's vorticity: ``'RdBu_r'``, centred on zero).
        vmin: Lower colour limit (animations and frame panels: default the minimum over all frames).
        vmax: Upper colour limit.
        animate: For frames (trajectory, list, file): ``True`` / ``None`` an animation, ``False`` a still picture of
            a few ``frames`` (1-D: curves in one axes, else one panel each).
        frames: The frames of a still picture of frames (default: first, a quarter, half, three quarters, last).
        fps: Frames per second of an animation.
        columns: Most panels per row (default: one row up to six panels; rows filled evenly, no empty panel).
        html: How a notebook shows an animation: ``'jshtml'`` (JavaScript player), ``'video'`` (HTML5 video,
            needs ffmpeg); default ``'video'`` where ffmpeg exists, else ``'jshtml'``.
        dpi: Resolution.

    Returns:
        A :class:`Picture`; a notebook displays it when it is the cell's value.

    Raises:
        ShapeError: For arrays that are not one sample of a 1-D/2-D/3-D field (e.g. a 4-D tensor), or that do not
            fit ``grid`` or each other.
        ParameterError: For an unknown object, quantity, axis or projection, indices out of range, a ``save``
            format that does not fit, or ``html='video'`` without ffmpeg.
        FileFormatError: For a path that is not a simulation file.
    """
    if html is not None and html not in _HTML_KINDS:
        raise ParameterError(f"html must be None, 'jshtml' or 'video', got {html!r}")
    if html == "video" and not ffmpeg_available():
        raise ParameterError("html='video' needs ffmpeg on the PATH; use html='jshtml' (no ffmpeg needed)")
    if animate not in (None, True, False):
        raise ParameterError(f"animate must be None, True or False, got {animate!r}")
    if isinstance(obj, (str, os.PathLike)):
        obj = read_simulation(obj)
    view = {"axis": axis, "index": index, "projection": projection}

    times = None
    file_mask = None
    if isinstance(obj, SimulationData):
        name = field or default_field(obj)
        b = _check_batch(batch, obj.batch_size)
        seq = list(field_frames(obj, name, b))
        g = obj.grid
        times = [float(t) for t in obj.times]
        file_mask = obstacle_of(obj, b)
        qty = field_label(obj, name)
        if obj.grid.rank == 1 and (axis is not None or index is not None or projection is not None):
            raise ParameterError("axis=, index= and projection= choose views of 3-D fields; this file is 1-D")
        finite = np.stack(seq)[np.isfinite(np.stack(seq))]
        if name == "vorticity" and cmap is None and finite.size and finite.min() < 0 < finite.max():
            top = float(np.abs(finite).max())  # signed (2-D): a diverging map centred on zero
            cmap = "RdBu_r"
            vmin, vmax = (-top if vmin is None else vmin), (top if vmax is None else vmax)
    elif isinstance(obj, Trajectory):
        seq, g, qty = _trajectory_frames(obj, field, batch, component)
        times = [float(t) for t in obj.times]
    elif isinstance(obj, (list, tuple)) and obj and not isinstance(obj[0], (int, float)):
        if all(isinstance(s, FluidState) for s in obj):
            stacked = [_state_panels(s, field, batch, component) for s in obj]
            qty = next(iter(stacked[0]))
            seq, g = [p[qty][0] for p in stacked], stacked[0][qty][1]
            times = [float(s.time) for s in obj]
        else:
            pairs = [_one(x, grid, batch, component) for x in obj]
            g = pairs[0][1]
            for k, (_, gk) in enumerate(pairs):
                if gk.resolution != g.resolution:
                    raise ShapeError(f"frame {k} has resolution {gk.resolution}, frame 0 {g.resolution}")
            seq, qty = [v for v, _ in pairs], label or ""
    else:
        seq = None
    cmap = "viridis" if cmap is None else cmap
    common = {"cmap": cmap, "vmin": vmin, "vmax": vmax, "columns": columns, "dpi": dpi}
    if seq is not None:  # frames: an animation, or a still picture of a few of them
        mask = _union(file_mask, _solid_mask(obstacles, g, batch))
        if len(seq) == 0:
            raise ParameterError("no frames to show")
        if animate is False or len(seq) == 1:
            picks = _frame_indices(len(seq), frames)
            stamp = (lambda k: f"t = {times[k]:.4g}") if times is not None else (lambda k: f"frame {k}")
            if g.rank == 1:
                fig, axes = _figure(1, g, None, None, dpi)
                x = g.center_coords(0, torch.float64).numpy()
                for k in picks:
                    axes[0].plot(x, seq[k], label=stamp(k))
                axes[0].set_xlabel("x")
                axes[0].set_ylabel(label or qty)
                axes[0].legend(fontsize="small")
                if title:
                    axes[0].set_title(title)
            else:
                panels = {stamp(k): (seq[k], g) for k in picks}
                fig, axes = _stills(panels, mask=mask, batch=0, view=view, title=None, label=label or qty,
                                    shared=True, suptitle=title, **common)
            pic = Picture(fig, axes, fps=fps, html=html, dpi=dpi)
        else:
            if frames is not None:
                raise ParameterError("frames= picks the frames of a still picture; pass animate=False with it")
            heading = title if title is not None else (f"{qty}, t = {{time:.4g}}" if qty else None)
            if isinstance(fps, bool) or not isinstance(fps, (int, np.integer)) or fps < 1:
                raise ParameterError(f"fps must be a positive int, got {fps!r}")
            fig, update, n = animation_figure(seq, grid=g, title=heading, cmap=cmap, vmin=vmin, vmax=vmax, dpi=dpi,
                                              times=times, mask=mask, label=label or qty, **view)
            pic = Picture(fig, [fig.axes[0]], update, n_frames=n, fps=fps, html=html, dpi=dpi)
    else:
        if animate is True:
            raise ParameterError("animate=True needs frames: a Trajectory, a list of fields or a simulation file")
        if frames is not None:
            raise ParameterError("frames= applies to trajectories, lists of frames and simulation files")
        if isinstance(obj, FluidState):
            panels = _state_panels(obj, field, batch, component)
            suptitle = title or f"t = {float(obj.time):.4g}"
            title = None
        elif isinstance(obj, Mapping):
            if not obj:
                raise ParameterError("show got an empty dict; pass name -> field entries")
            panels = {str(k): _one(v, grid, batch, component) for k, v in obj.items()}
            suptitle, title = title, None
        else:
            if field is not None:
                raise ParameterError("field= picks a quantity of a state, trajectory or file; this is one field")
            panels = {"": _one(obj, grid, batch, component)}
            suptitle = None
        g = next(iter(panels.values()))[1]
        mask = _solid_mask(obstacles, g, batch)
        fig, axes = _stills(panels, mask=mask, batch=batch, view=view, title=title, label=label, shared=False,
                            suptitle=suptitle, **common)
        pic = Picture(fig, axes, fps=fps, html=html, dpi=dpi)
    if save is not None:
        pic.saved = pic.save(save)
    return pic
