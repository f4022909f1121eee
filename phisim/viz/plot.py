"""Pictures of fields, vector fields, learning curves and animations (matplotlib, Agg canvas).

The library never touches pyplot's global state and never calls ``plt.show``: figures are created as
``matplotlib.figure.Figure`` objects with an Agg canvas, so the functions work on headless machines and in
tests. Pass an existing ``Axes`` (from pyplot or elsewhere) to draw into your own figure.

Orientation ("up" is ``y``, axis 1, everywhere: in pictures and as the default buoyancy direction of the
fluid steps): phisim arrays are indexed ``values[..., i, j]`` at ``(x_i, y_j)``; images are drawn transposed
with ``origin='lower'`` and the grid's physical extent, so ``x`` runs to the right and ``y`` upwards.

3-D fields are shown as a slice normal to ``axis`` (default ``'z'``: an ``x``-``y`` picture with ``y`` up, at the
middle ``index``) or as a projection of the whole volume along ``axis`` (``projection='max'``: maximum
intensity, ``'mean'``, ``'min'``). The picture's axes for each normal (:data:`PLANES`): ``z`` -> ``x`` right,
``y`` up; ``x`` -> ``z`` right, ``y`` up; ``y`` -> ``x`` right, ``z`` up (a view from above).
"""

from __future__ import annotations

import math
import os
import shutil
import warnings
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path

import matplotlib
import numpy as np
import torch
from matplotlib.animation import FFMpegWriter, FuncAnimation, PillowWriter
from matplotlib.axes import Axes
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.colors import to_rgb
from matplotlib.figure import Figure

from phisim.errors import ParameterError, ShapeError
from phisim.field import CenteredGrid, StaggeredGrid
from phisim.grid import Grid

__all__ = [
    "new_figure", "plot_field", "plot_vector_field", "plot_curves", "animate", "make_animation", "save_figure",
    "ffmpeg_available", "draw_mask", "plot_training_curves", "AXIS_NAMES", "PLANES", "PROJECTIONS", "axis_index",
    "volume_view", "mask_view", "plane_grid", "view_label", "panel_layout", "save_animation", "animation_figure",
]

PathLike = str | os.PathLike

#: Axis names by index (``y``, axis 1, is up).
AXIS_NAMES = ("x", "y", "z")
#: For each slice normal (axis index) of a 3-D field, the picture's (horizontal, vertical) axes: ``y`` is drawn
#: upwards whenever it is in the picture.
PLANES = {2: (0, 1), 0: (2, 1), 1: (0, 2)}
#: Projections of a whole volume along an axis (``None``: a slice).
PROJECTIONS = ("max", "mean", "min")


def new_figure(figsize: tuple[float, float] = (5.0, 4.0), dpi: int = 100) -> tuple[Figure, Axes]:
    """A new figure with one axes on an Agg canvas (independent of pyplot).

    Args:
        figsize: Width and height in inches.
        dpi: Dots per inch.

    Returns:
        ``(figure, axes)``.
    """
    fig = Figure(figsize=figsize, dpi=dpi)
    FigureCanvasAgg(fig)
    return fig, fig.add_subplot(1, 1, 1)


def axis_index(axis, rank: int = 3) -> int:
    """The index of an axis given as ``'x'`` / ``'y'`` / ``'z'`` or as an int (negative counts from the end).

    Raises:
        ParameterError: For an unknown name, an index out of range, or another type.
    """
    names = list(AXIS_NAMES[:rank])
    if isinstance(axis, str):
        key = axis.strip().lower()
        if key in names:
            return names.index(key)
        raise ParameterError(f"unknown axis {axis!r}: use one of {names} or an index 0..{rank - 1}")
    if isinstance(axis, (int, np.integer)) and not isinstance(axis, bool):
        if -rank <= int(axis) < rank:
            return int(axis) % rank
        raise ParameterError(f"axis {int(axis)} out of range for a {rank}-D field: use 0..{rank - 1} or {names}")
    raise ParameterError(f"axis must be one of {names} or an int, got {axis!r}")


def _view_args(axis, index, projection, n_along=None) -> tuple[int, int | None, str | None]:
    """Validated ``(normal axis, slice index or None for a projection, projection)`` of a 3-D view."""
    a = 2 if axis is None else axis_index(axis, 3)
    if projection is not None:
        if not isinstance(projection, str) or projection not in PROJECTIONS:
            raise ParameterError(f"unknown projection {projection!r}: use None (a slice), "
                                 + ", ".join(repr(p) for p in PROJECTIONS))
        if index is not None:
            raise ParameterError(f"index= picks a slice; projection={projection!r} uses the whole volume along "
                                 f"{AXIS_NAMES[a]} (pass one of them)")
        return a, None, projection
    if index is None:
        return a, None if n_along is None else n_along // 2, None
    if isinstance(index, bool) or not isinstance(index, (int, np.integer)):
        raise ParameterError(f"index must be an int (a slice along {AXIS_NAMES[a]}), got {index!r}")
    k = int(index)
    if n_along is not None:
        if not -n_along <= k < n_along:
            raise ParameterError(f"index {k} out of range: {n_along} cells along {AXIS_NAMES[a]} "
                                 f"(0..{n_along - 1}, negative counts from the end)")
        k %= n_along
    return a, k, None


def volume_view(values, axis="z", index: int | None = None, projection: str | None = None) -> np.ndarray:
    """A 2-D picture of one 3-D array: the slice normal to ``axis`` or a projection of the volume along it.

    Args:
        values: Array ``(nx, ny, nz)`` (numpy or torch).
        axis: The slice normal, ``'x'`` / ``'y'`` / ``'z'`` or 0 / 1 / 2 (default ``'z'``: an ``x``-``y`` picture).
        index: The slice's cell index along ``axis`` (default the middle; negative counts from the end).
        projection: ``None`` for a slice, or ``'max'`` (maximum intensity), ``'mean'``, ``'min'`` along ``axis``
            (NaN cells are left out).

    Returns:
        ``image`` with ``image[i, j]`` at the ``i``-th cell of the picture's horizontal axis and the ``j``-th of
        its vertical axis (:data:`PLANES`); draw ``image.T`` with ``origin='lower'``.

    Raises:
        ShapeError: For an array that is not 3-D.
        ParameterError: For an unknown axis or projection, an index out of range, or both index and projection.
    """
    v = _np(values)
    if v.ndim != 3:
        raise ShapeError(f"volume_view takes one 3-D array (nx, ny, nz), got shape {v.shape}")
    a = 2 if axis is None else axis_index(axis, 3)
    a, k, projection = _view_args(a, index, projection, v.shape[a])
    if projection is None:
        img = np.take(v, k, axis=a)
    else:
        reduce = {"max": np.nanmax, "mean": np.nanmean, "min": np.nanmin}[projection]
        with warnings.catch_warnings():  # columns of NaN only stay NaN
            warnings.simplefilter("ignore", RuntimeWarning)
            img = reduce(v, axis=a)
    h, vert = PLANES[a]
    return img.T if h > vert else img


def mask_view(mask, axis="z", index: int | None = None, projection: str | None = None) -> np.ndarray:
    """The 2-D picture of a boolean 3-D mask matching :func:`volume_view`: its slice, or for a projection its
    shadow (solid where any cell along ``axis`` is solid)."""
    m = _np(mask).astype(bool)
    if projection is not None:
        _view_args(axis, index, projection)
        return volume_view(m.astype(np.uint8), axis, None, "max").astype(bool)
    return volume_view(m, axis, index, None)


def plane_grid(grid: Grid, axis="z") -> Grid:
    """The 2-D grid of a picture of a 3-D grid (:data:`PLANES`); a 2-D grid is its own picture."""
    if grid.rank == 2:
        return grid
    if grid.rank != 3:
        raise ShapeError(f"plane_grid takes a 2-D or 3-D grid, got {grid}")
    h, v = PLANES[axis_index(axis, 3)]
    return Grid((grid.resolution[h], grid.resolution[v]), bounds=[grid.bounds[h], grid.bounds[v]])


def view_label(grid: Grid, axis="z", index: int | None = None, projection: str | None = None) -> str:
    """A short description of a 3-D view: ``'z = 0.47 (slice 8 of 16)'`` or ``'max along z'``."""
    a = axis_index("z" if axis is None else axis, 3)
    a, k, projection = _view_args(a, index, projection, grid.resolution[a])
    if projection is not None:
        return f"{projection} along {AXIS_NAMES[a]}"
    lo, hi = grid.bounds[a]
    coord = lo + (k + 0.5) * (hi - lo) / grid.resolution[a]
    return f"{AXIS_NAMES[a]} = {coord:.3g} (slice {k} of {grid.resolution[a]})"


def panel_layout(n: int, columns: int | None = None) -> tuple[int, int]:
    """``(rows, columns)`` of a grid of ``n`` panels with no empty row: one row up to six panels (or
    ``columns``), else rows as even as possible. The caller makes only ``n`` axes, so no panel stays empty.

    Raises:
        ParameterError: For ``n < 1`` or ``columns < 1``.
    """
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 1:
        raise ParameterError(f"a picture needs at least one panel, got {n!r}")
    if columns is not None and (isinstance(columns, bool) or not isinstance(columns, (int, np.integer))
                                or columns < 1):
        raise ParameterError(f"columns must be a positive int, got {columns!r}")
    most = 6 if columns is None else int(columns)
    rows = math.ceil(n / most)
    return rows, math.ceil(n / rows)


def _picture(v: np.ndarray, g: Grid, axis, index, projection, what: str) -> tuple[np.ndarray, Grid, str, str]:
    """``(image (nh, nv), picture grid, horizontal name, vertical name)`` of a 2-D or 3-D sample."""
    if g.rank == 2:
        if index is not None or projection is not None or axis not in (None, "z", 2):
            raise ParameterError(f"{what}: axis=, index= and projection= choose views of 3-D fields; "
                                 "this field is 2-D (x right, y up)")
        return v, g, "x", "y"
    a = 2 if axis is None else axis_index(axis, 3)
    h, vert = PLANES[a]
    return volume_view(v, a, index, projection), plane_grid(g, a), AXIS_NAMES[h], AXIS_NAMES[vert]


def _axes(ax: Axes | None) -> Axes:
    if ax is None:
        return new_figure()[1]
    if not isinstance(ax, Axes):
        raise ParameterError(f"ax must be a matplotlib Axes or None, got {type(ax).__name__}")
    return ax


def _np(x) -> np.ndarray:
    if isinstance(x, torch.Tensor):
        x = x.detach().cpu()
        if x.is_complex():
            raise ShapeError("cannot plot complex values; plot .real, .imag or .abs()")
        return x.numpy()
    arr = np.asarray(x)
    if arr.dtype.kind not in "fiub":
        raise ShapeError(f"cannot plot an array of dtype {arr.dtype}")
    return arr


def _scalar_2d(field, batch: int, component: int | None, grid: Grid | None) -> tuple[np.ndarray, Grid]:
    """A ``(nx, ny)`` (or 1-D / 3-D) numpy array of one sample, and its grid."""
    if isinstance(field, StaggeredGrid):
        field = field.at_centers()
    if isinstance(field, CenteredGrid):
        grid = field.grid
        if not 0 <= batch < field.batch_size:
            raise ParameterError(f"batch index {batch} out of range for batch size {field.batch_size}")
        v = _np(field.values[batch])
        if field.is_vector:
            if component is None:
                v = np.sqrt((v.astype(np.float64) ** 2).sum(axis=0))
            elif not 0 <= component < v.shape[0]:
                raise ParameterError(f"component {component} out of range for {v.shape[0]} channels")
            else:
                v = v[component]
        elif component is not None:
            raise ParameterError("component= applies to vector fields only")
        return v, grid
    v = _np(field)
    if v.ndim not in (1, 2, 3):
        raise ShapeError(
            f"plot_field takes a field or a 1-D/2-D/3-D array of one sample, got shape {v.shape}; "
            "index the batch (values[0]) or pass a CenteredGrid"
        )
    if grid is None:
        grid = Grid(v.shape)
    elif tuple(v.shape) != grid.resolution:
        raise ShapeError(f"array of shape {v.shape} does not fit {grid}")
    return v, grid


def _extent(grid: Grid) -> tuple[float, float, float, float]:
    (x0, x1), (y0, y1) = grid.bounds[0], grid.bounds[1]
    return (x0, x1, y0, y1)


def _finite_check(v: np.ndarray, what: str) -> None:
    if v.size and not np.isfinite(v).any():
        raise ParameterError(f"{what}: every value is NaN or Inf; nothing to plot")


def _mask_2d(mask, grid: Grid, batch: int = 0, axis=None, index: int | None = None,
             projection: str | None = None) -> np.ndarray:
    """A 2-D boolean picture of a solid mask (one sample; for 3-D the view of :func:`mask_view`)."""
    m = _np(mask)
    if m.ndim == grid.rank + 1:
        m = m[min(batch, m.shape[0] - 1)]
    if tuple(m.shape) != grid.resolution:
        raise ShapeError(f"mask of shape {m.shape} does not fit {grid}")
    if grid.rank == 3:
        return mask_view(m, axis, index, projection)
    return m.astype(bool)


def draw_mask(ax: Axes, mask, grid: Grid, *, color: str = "0.55", outline: str | None = "k") -> None:
    """Draw solid cells (``True`` in a 2-D boolean ``(nx, ny)`` mask) as opaque grey over an image, outlined.

    Args:
        ax: The axes holding the image.
        mask: Boolean ``(nx, ny)`` array, ``True`` where the cell is solid.
        grid: The 2-D grid of the picture (for the extent; :func:`plane_grid` of a 3-D grid).
        color: Matplotlib colour of the solid cells.
        outline: Colour of the solids' outline (the 0.5 contour of the mask), or None for none.

    Raises:
        ShapeError: For a mask that does not fit the grid.
    """
    m = _np(mask).astype(bool)
    if m.shape != tuple(grid.resolution[:2]):
        raise ShapeError(f"mask of shape {m.shape} does not fit {grid}")
    g2 = Grid(grid.resolution[:2], bounds=grid.bounds[:2])
    rgba = np.zeros((*m.T.shape, 4))
    rgba[..., :3] = to_rgb(color)
    rgba[..., 3] = m.T.astype(float)
    ax.imshow(rgba, origin="lower", extent=_extent(g2), interpolation="nearest", aspect="equal")
    if outline is not None and m.any() and not m.all():
        # the 0.5 contour of the mask refined f times per cell follows the cells' edges (to 1/(2f) of a cell)
        f = max(1, min(4, 2048 // max(m.shape)))
        fine = np.kron(m, np.ones((f, f))).T
        (x0, x1), (y0, y1) = g2.bounds
        xc = x0 + (np.arange(fine.shape[1]) + 0.5) * (x1 - x0) / fine.shape[1]
        yc = y0 + (np.arange(fine.shape[0]) + 0.5) * (y1 - y0) / fine.shape[0]
        ax.contour(xc, yc, fine, levels=[0.5], colors=outline, linewidths=1.0)


def plot_field(
    field,
    ax: Axes | None = None,
    *,
    title: str | None = None,
    batch: int = 0,
    component: int | None = None,
    grid: Grid | None = None,
    cmap: str = "viridis",
    vmin: float | None = None,
    vmax: float | None = None,
    colorbar: bool = True,
    slice_index: int | None = None,
    mask=None,
    axis=None,
    index: int | None = None,
    projection: str | None = None,
    label: str | None = None,
) -> Axes:
    """Draw a scalar field: a line for 1-D, an image for 2-D (``x`` right, ``y`` up), a slice or a projection
    of the volume for 3-D.

    Args:
        field: A :class:`CenteredGrid` (scalar, or vector shown as its magnitude or one ``component``), a
            :class:`StaggeredGrid` (averaged to the centres), or one sample as an array of shape
            ``resolution`` (with ``grid`` for physical bounds; default ``dx = 1``).
        ax: Axes to draw into; a new figure is made when ``None``.
        title: Axes title.
        batch: Which sample of a batched field.
        component: For vector fields, the component to show (default: the magnitude).
        grid: The grid of a raw array.
        cmap: Colormap name.
        vmin: Lower colour limit (default: data minimum).
        vmax: Upper colour limit.
        colorbar: Add a colour bar.
        slice_index: The same as ``index`` (the ``z`` index of the default 3-D slice; kept for old callers).
        mask: Solid cells (e.g. an obstacle) drawn in grey and outlined over the image: a boolean array of the
            field's resolution (or ``(1 or B, *res)``, sample ``batch`` is used); 2-D and 3-D fields only. In a
            3-D projection the solids' shadow is drawn.
        axis: 3-D only: the slice normal, ``'x'`` / ``'y'`` / ``'z'`` or an int (default ``'z'``: an ``x``-``y``
            picture with ``y`` up); see :data:`PLANES`.
        index: 3-D only: the slice's cell index along ``axis`` (default the middle).
        projection: 3-D only: ``None`` (a slice), ``'max'`` (maximum intensity), ``'mean'`` or ``'min'`` along
            ``axis``.
        label: Label of the colour bar (1-D: of the y axis), e.g. the field's name and units.

    Returns:
        The axes. For 2-D and 3-D fields ``ax.images[0]`` is the ``AxesImage``; its data are ``image.T``
        (origin lower) of the 2-D field or of :func:`volume_view`, so the horizontal axis runs left to right and
        the vertical one (``y`` where it is in the picture) bottom to top.

    Raises:
        ShapeError: For arrays that are not one sample of a 1-D/2-D/3-D field or do not fit ``grid``.
        ParameterError: For bad indices, an unknown axis or projection, 3-D options on 1-D/2-D fields, or
            all-NaN data.
    """
    if slice_index is not None:
        if index is not None and index != slice_index:
            raise ParameterError(f"slice_index={slice_index} and index={index} disagree; pass index= only")
        index = slice_index
    v, g = _scalar_2d(field, batch, component, grid)
    _finite_check(v, "plot_field")
    if g.rank == 1 and (mask is not None or axis is not None or index is not None or projection is not None):
        raise ParameterError("plot_field: mask=, axis=, index= and projection= apply to 2-D and 3-D fields; "
                             "this field is 1-D")
    if g.rank > 1:
        img, pg, hname, vname = _picture(v, g, axis, index, projection, "plot_field")
    ax = _axes(ax)
    if g.rank == 1:
        ax.plot(_np(g.center_coords(0, torch.float64)), v)
        ax.set_xlabel("x")
        ax.set_xlim(*g.bounds[0])
        if label is not None:
            ax.set_ylabel(label)
        if vmin is not None or vmax is not None:
            ax.set_ylim(vmin, vmax)
    else:
        im = ax.imshow(img.T, origin="lower", extent=_extent(pg), cmap=cmap, vmin=vmin, vmax=vmax,
                       interpolation="nearest", aspect="equal")
        if mask is not None:
            draw_mask(ax, _mask_2d(mask, g, batch, axis, index, projection), pg)
        ax.set_xlabel(hname)
        ax.set_ylabel(vname)
        if colorbar:
            ax.figure.colorbar(im, ax=ax, label=label or "")
    if title is not None:
        ax.set_title(title)
    return ax


def plot_vector_field(
    field,
    ax: Axes | None = None,
    *,
    title: str | None = None,
    batch: int = 0,
    mode: str = "quiver",
    background: str | None = "magnitude",
    stride: int | None = None,
    grid: Grid | None = None,
    cmap: str = "viridis",
    color: str = "white",
) -> Axes:
    """Draw a 2-D vector field as arrows (``quiver``) or streamlines over an optional magnitude image.

    Args:
        field: A vector :class:`CenteredGrid` (``(B, 2, nx, ny)``), a :class:`StaggeredGrid` (averaged to
            the centres), or one sample as an array ``(2, nx, ny)`` (with ``grid``).
        ax: Axes to draw into; a new figure is made when ``None``.
        title: Axes title.
        batch: Which sample.
        mode: ``'quiver'`` or ``'streamlines'``.
        background: ``'magnitude'`` to draw the speed as an image below, or ``None``.
        stride: Draw every ``stride``-th arrow per axis (default: about 24 arrows per axis).
        grid: The grid of a raw array.
        cmap: Colormap of the background.
        color: Colour of arrows / streamlines.

    Returns:
        The axes.

    Raises:
        ShapeError: For fields that are not 2-D vector fields.
        ParameterError: For an unknown ``mode``/``background`` or a bad ``stride``.
    """
    if mode not in ("quiver", "streamlines"):
        raise ParameterError(f"mode must be 'quiver' or 'streamlines', got {mode!r}")
    if background not in ("magnitude", None):
        raise ParameterError(f"background must be 'magnitude' or None, got {background!r}")
    if isinstance(field, StaggeredGrid):
        field = field.at_centers()
    if isinstance(field, CenteredGrid):
        if not field.is_vector or field.values.shape[1] != 2 or field.grid.rank != 2:
            raise ShapeError(f"plot_vector_field needs a 2-D vector field with 2 components, got {field}")
        if not 0 <= batch < field.batch_size:
            raise ParameterError(f"batch index {batch} out of range for batch size {field.batch_size}")
        g, v = field.grid, _np(field.values[batch])
    else:
        v = _np(field)
        if v.ndim != 3 or v.shape[0] != 2:
            raise ShapeError(f"plot_vector_field takes one sample of shape (2, nx, ny), got {v.shape}")
        g = Grid(v.shape[1:]) if grid is None else grid
        if tuple(v.shape[1:]) != g.resolution:
            raise ShapeError(f"array of shape {v.shape} does not fit {g}")
    _finite_check(v, "plot_vector_field")
    ax = _axes(ax)
    if background == "magnitude":
        speed = np.sqrt((v.astype(np.float64) ** 2).sum(axis=0))
        im = ax.imshow(speed.T, origin="lower", extent=_extent(g), cmap=cmap, interpolation="nearest")
        ax.figure.colorbar(im, ax=ax, label="|v|")
    x = _np(g.center_coords(0, torch.float64))
    y = _np(g.center_coords(1, torch.float64))
    if mode == "quiver":
        if stride is None:
            stride = max(1, max(g.resolution) // 24)
        if not isinstance(stride, (int, np.integer)) or stride < 1:
            raise ParameterError(f"stride must be a positive int, got {stride!r}")
        X, Y = np.meshgrid(x[::stride], y[::stride], indexing="ij")
        ax.quiver(X.T, Y.T, v[0, ::stride, ::stride].T, v[1, ::stride, ::stride].T, color=color,
                  angles="xy")
    else:
        ax.streamplot(x, y, v[0].T, v[1].T, color=color, density=1.0)
    ax.set_xlim(*g.bounds[0])
    ax.set_ylim(*g.bounds[1])
    ax.set_aspect("equal")
    ax.set_xlabel("x")
    ax.set_ylabel("y")
    if title is not None:
        ax.set_title(title)
    return ax


def plot_curves(
    curves: Mapping[str, tuple],
    ax: Axes | None = None,
    *,
    logy: bool = True,
    title: str | None = None,
    xlabel: str = "iteration",
    ylabel: str = "loss",
) -> Axes:
    """Draw learning curves, one line per method.

    Args:
        curves: Name -> ``(iterations, values)``, two 1-D sequences of equal length. NaN entries (records
            where a curve was not logged) are skipped.
        ax: Axes to draw into; a new figure is made when ``None``.
        logy: Logarithmic y axis (non-positive values are left out of a log plot).
        title: Axes title.
        xlabel: x-axis label.
        ylabel: y-axis label.

    Returns:
        The axes, with a legend.

    Raises:
        ParameterError: For an empty mapping or entries that are not ``(iterations, values)`` pairs.
        ShapeError: For lengths that differ or arrays that are not 1-D.
    """
    if not isinstance(curves, Mapping) or not curves:
        raise ParameterError("curves must be a non-empty mapping name -> (iterations, values)")
    prepared = []
    for name, pair in curves.items():
        if not isinstance(pair, (tuple, list)) or len(pair) != 2:
            raise ParameterError(f"curve {name!r} must be an (iterations, values) pair")
        it, val = (_np(p).astype(np.float64) for p in pair)
        if it.ndim != 1 or val.ndim != 1 or len(it) != len(val):
            raise ShapeError(
                f"curve {name!r}: iterations {it.shape} and values {val.shape} must be 1-D, same length"
            )
        keep = np.isfinite(val) & np.isfinite(it)
        if logy:
            keep &= val > 0
        prepared.append((str(name), it[keep], val[keep]))
    ax = _axes(ax)
    for name, it, val in prepared:
        ax.plot(it, val, label=name)
    if logy:
        ax.set_yscale("log")
        _readable_log_ticks(ax, np.concatenate([val for _, _, val in prepared]))
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend()
    if title is not None:
        ax.set_title(title)
    return ax


def _readable_log_ticks(ax: Axes, values: np.ndarray) -> None:
    """Label a log y axis at 1-2-5 per decade (every integer multiple for data within one decade, only
    powers of ten beyond three decades), as plain numbers, so a curve spanning less than a decade still
    gets several labelled ticks."""
    from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter

    v = values[np.isfinite(values) & (values > 0)]
    if v.size == 0:
        return
    decades = float(np.log10(v.max() / v.min()))
    subs = tuple(range(1, 10)) if decades < 1 else (1.0, 2.0, 5.0) if decades < 3 else (1.0,)
    ax.yaxis.set_major_locator(LogLocator(base=10.0, subs=subs))
    ax.yaxis.set_major_formatter(FuncFormatter(lambda y, _pos: f"{y:g}"))
    ax.yaxis.set_minor_formatter(NullFormatter())


def plot_training_curves(
    runs: Mapping[str, Mapping[str, np.ndarray]],
    metric_name: str = "metric",
    ax: Axes | None = None,
    *,
    curve: str = "metric",
    title: str | None = None,
    logy: bool = True,
) -> Axes:
    """Learning curves of several runs: the training-batch curve (thin, faded) and the held-out curve
    (``eval_<curve>``, solid with markers) of each method in one colour.

    Args:
        runs: Method -> curves as written by :func:`inverse.train.train` (``iteration``, ``metric``,
            ``eval_metric``, ...).
        metric_name: The y-axis label (what the curve measures, with units).
        ax: Axes to draw into; a new figure is made when ``None``.
        curve: ``'metric'`` or ``'loss'``.
        title: Axes title.
        logy: Logarithmic y axis with readable tick labels.

    Returns:
        The axes, with a legend naming "train batch" and "held-out" for each method.

    Raises:
        ParameterError: For an empty mapping or runs without ``iteration`` and ``curve``.
    """
    if not isinstance(runs, Mapping) or not runs:
        raise ParameterError("runs must be a non-empty mapping method -> curves")
    ax = _axes(ax)
    everything = []
    for k, (name, c) in enumerate(runs.items()):
        if "iteration" not in c or curve not in c:
            raise ParameterError(f"run {name!r} has no 'iteration' and {curve!r} curves")
        color = f"C{k % 10}"
        it = _np(c["iteration"]).astype(np.float64)
        train = _np(c[curve]).astype(np.float64)
        keep = np.isfinite(train) & ((train > 0) if logy else True)
        ax.plot(it[keep], train[keep], color=color, alpha=0.35, lw=1.0, label=f"{name} (train batch)")
        everything.append(train[keep])
        if f"eval_{curve}" in c:
            held = _np(c[f"eval_{curve}"]).astype(np.float64)
            keep = np.isfinite(held) & ((held > 0) if logy else True)
            ax.plot(it[keep], held[keep], color=color, lw=1.8, marker="o", ms=3, label=f"{name} (held-out)")
            everything.append(held[keep])
    if logy:
        ax.set_yscale("log")
        _readable_log_ticks(ax, np.concatenate(everything) if everything else np.zeros(0))
    ax.set_xlabel("iteration")
    ax.set_ylabel(metric_name)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize="small")
    if title is not None:
        ax.set_title(title)
    return ax


def save_figure(fig: Figure, path: PathLike, *, dpi: int | None = None) -> Path:
    """Save a figure (format from the suffix: png, pdf, svg, ...), creating parent folders.

    Args:
        fig: The figure (e.g. ``ax.figure``).
        path: Output file.
        dpi: Resolution for raster formats (default: the figure's).

    Returns:
        The path written.

    Raises:
        ParameterError: If ``fig`` is not a figure or the suffix is not a format matplotlib writes.
    """
    if not isinstance(fig, Figure):
        raise ParameterError(
            f"save_figure needs a matplotlib Figure, got {type(fig).__name__} (use ax.figure)"
        )
    p = Path(path)
    fmt = p.suffix.lstrip(".").lower()
    supported = fig.canvas.get_supported_filetypes() if fig.canvas is not None else {}
    if fmt not in supported:
        raise ParameterError(f"cannot save {p}: unknown image format {fmt!r}; use one of {sorted(supported)}")
    p.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(p, dpi=dpi or fig.dpi, bbox_inches="tight")
    return p


def _frames_to_arrays(frames, grid: Grid | None, component: int | None, axis=None, index=None,
                      projection=None) -> tuple[list[np.ndarray], Grid, Grid, tuple[str, str]]:
    """The frames as 1-D arrays or 2-D pictures, the frames' grid, the picture's grid and axis names."""
    if isinstance(frames, (torch.Tensor, np.ndarray)):
        frames = list(frames)  # leading axis = time
    if not isinstance(frames, Sequence) or len(frames) == 0:
        raise ParameterError("frames must be a non-empty sequence of fields or arrays (or a (T, ...) array)")
    arrays, g0 = [], None
    for k, fr in enumerate(frames):
        v, g = _scalar_2d(fr, 0, component, grid)
        if g0 is None:
            g0 = g
            if g.rank == 1 and (axis is not None or index is not None or projection is not None):
                raise ParameterError("axis=, index= and projection= choose views of 3-D fields; the frames are 1-D")
        elif g.resolution != g0.resolution:
            raise ShapeError(f"frame {k} has resolution {g.resolution}, frame 0 {g0.resolution}")
        if g.rank == 1:
            arrays.append(v)
            pg, names = g, ("x", "")
        else:
            img, pg, hname, vname = _picture(v, g, axis, index, projection, "frames")
            arrays.append(img)
            names = (hname, vname)
    return arrays, g0, pg, names


def animation_figure(
    frames,
    *,
    grid: Grid | None = None,
    title: str | None = None,
    component: int | None = None,
    cmap: str = "viridis",
    vmin: float | None = None,
    vmax: float | None = None,
    dpi: int = 80,
    times: Sequence[float] | None = None,
    mask=None,
    axis=None,
    index: int | None = None,
    projection: str | None = None,
    label: str | None = None,
    figsize: tuple[float, float] | None = None,
) -> tuple[Figure, Callable[[int], tuple], int]:
    """The figure of an animation of 1-D, 2-D or 3-D scalar frames and the function that draws frame ``k``
    (:func:`make_animation` makes the ``FuncAnimation`` of them).

    The arguments are those of :func:`animate` without the path and ``fps``.

    Returns:
        ``(figure, update, n_frames)``; the figure shows frame 0, ``update(k)`` draws frame ``k``.

    Raises:
        ParameterError: For no frames, an unknown axis or projection, a slice index out of range.
        ShapeError: For frames of different resolutions or more than 3 dimensions.
    """
    arrays, g, pg, (hname, vname) = _frames_to_arrays(frames, grid, component, axis, index, projection)
    if times is not None:
        times = [float(t) for t in times]
        if len(times) != len(arrays):
            raise ShapeError(f"times has {len(times)} entries for {len(arrays)} frames")
        if title is None or "{time" not in title:
            title = (title + ", " if title else "") + "t = {time:.3g}"
    finite = [a[np.isfinite(a)] for a in arrays]
    lo = vmin if vmin is not None else min((float(a.min()) for a in finite if a.size), default=0.0)
    hi = vmax if vmax is not None else max((float(a.max()) for a in finite if a.size), default=1.0)
    if figsize is None:
        aspect = pg.size[0] / pg.size[1] if g.rank > 1 else 1.4
        figsize = (8.0, max(2.0, 7.0 / aspect + 0.8)) if aspect > 2 else (5.0, 4.0)
    fig, ax = new_figure(figsize, dpi)
    if g.rank == 1:
        (artist,) = ax.plot(_np(g.center_coords(0, torch.float64)), arrays[0])
        pad = 0.05 * (hi - lo) if hi > lo else 0.5
        ax.set_ylim(lo - pad, hi + pad)
        ax.set_xlim(*g.bounds[0])
        ax.set_xlabel("x")
        if label:
            ax.set_ylabel(label)
    else:
        artist = ax.imshow(arrays[0].T, origin="lower", extent=_extent(pg), cmap=cmap, vmin=lo, vmax=hi,
                           interpolation="nearest")
        fig.colorbar(artist, ax=ax, label=label or "")
        if mask is not None:
            draw_mask(ax, _mask_2d(mask, g, 0, axis, index, projection), pg)
        ax.set_xlabel(hname)
        ax.set_ylabel(vname)

    def text(k: int) -> str:
        return title.format(t=k, time=times[k] if times is not None else float(k)) if title else ""

    heading = ax.set_title(text(0))

    def update(k):
        if g.rank == 1:
            artist.set_ydata(arrays[k])
        else:
            artist.set_data(arrays[k].T)
        if title:
            heading.set_text(text(k))
        return (artist, heading)

    return fig, update, len(arrays)


def make_animation(frames, *, fps: int = 10, **kwargs) -> tuple[Figure, FuncAnimation]:
    """An animation of 1-D, 2-D or 3-D scalar frames (a line, an image, a slice or projection of the volume).

    The keyword arguments are those of :func:`animate` (without the path). Write the animation with
    :func:`save_animation` or ``anim.save``; show it in a notebook with :func:`phisim.viz.show` or
    ``anim.to_jshtml()``.

    Returns:
        ``(figure, animation)``: a ``matplotlib.animation.FuncAnimation`` of ``len(frames)`` frames, ``1000 / fps``
        ms apart. The image (``figure.axes[0].images[0]``) or line (``figure.axes[0].lines[0]``) holds the frame
        last drawn.

    Raises:
        ParameterError: For ``fps < 1`` and as :func:`animation_figure`.
        ShapeError: As :func:`animation_figure`.
    """
    if isinstance(fps, bool) or not isinstance(fps, (int, np.integer)) or fps < 1:
        raise ParameterError(f"fps must be a positive int, got {fps!r}")
    fig, update, n = animation_figure(frames, **kwargs)
    return fig, FuncAnimation(fig, update, frames=n, interval=1000.0 / int(fps), blit=False)


def animate(
    frames,
    path: PathLike,
    fps: int = 10,
    *,
    grid: Grid | None = None,
    title: str | None = None,
    component: int | None = None,
    cmap: str = "viridis",
    vmin: float | None = None,
    vmax: float | None = None,
    dpi: int = 80,
    times: Sequence[float] | None = None,
    mask=None,
    axis=None,
    index: int | None = None,
    projection: str | None = None,
    label: str | None = None,
) -> Path:
    """Write an animation of scalar frames as GIF (Pillow) or MP4 (ffmpeg): 2-D images, 3-D slices or
    projections (``axis``, ``index``, ``projection`` as in :func:`plot_field`), 1-D lines.

    Args:
        frames: A sequence of fields (the first sample of each is shown; vector fields as magnitude or
            ``component``) or of arrays of one sample (``(nx, ny)``, ``(nx, ny, nz)``, ``(nx,)``), or one
            ``(T, ...)`` array.
        path: Output file ending in ``.gif`` or ``.mp4``.
        fps: Frames per second.
        grid: Grid of raw arrays (for the axis extent).
        title: Title; ``{t}`` in it is replaced by the frame index and ``{time}`` by the frame's time
            (a number, so ``{time:.2f}`` works). With ``times`` and no ``{time}`` in the title (or no
            title), the time is appended as ``t = ...``.
        component: Component of vector frames to show.
        cmap: Colormap name.
        vmin: Lower colour limit (default: minimum over all frames, so colours are comparable).
        vmax: Upper colour limit (default: maximum over all frames).
        dpi: Resolution.
        times: The simulated time of each frame (shown in the title of every frame).
        mask: Solid cells drawn in grey and outlined on every frame (see :func:`plot_field`).
        axis: 3-D frames: the slice normal (default ``'z'``).
        index: 3-D frames: the slice index (default the middle).
        projection: 3-D frames: ``None``, ``'max'``, ``'mean'`` or ``'min'`` along ``axis``.
        label: Label of the colour bar (the field's name and units).

    Returns:
        The path written.

    Raises:
        ParameterError: For an unknown suffix, ``fps < 1``, no frames, or MP4 without ffmpeg installed.
        ShapeError: For frames of more than 3 dimensions or of different resolutions.
    """
    p = Path(path)
    suffix = p.suffix.lower()
    if suffix not in (".gif", ".mp4"):
        raise ParameterError(f"animate writes .gif or .mp4 files, got {p.name!r}")
    if suffix == ".mp4" and not ffmpeg_available():
        raise ParameterError("writing MP4 needs ffmpeg on the PATH (matplotlib's animation.ffmpeg_path); "
                             "install ffmpeg or write a .gif")
    _, anim = make_animation(frames, fps=fps, grid=grid, title=title, component=component, cmap=cmap, vmin=vmin,
                             vmax=vmax, dpi=dpi, times=times, mask=mask, axis=axis, index=index,
                             projection=projection, label=label)
    return save_animation(anim, p, fps=fps, dpi=dpi)


def save_animation(anim: FuncAnimation, path: PathLike, *, fps: int = 10, dpi: int = 80) -> Path:
    """Write an animation as ``.gif`` (Pillow), ``.mp4`` (ffmpeg) or ``.html`` (JavaScript player, no ffmpeg
    needed), creating parent folders.

    Raises:
        ParameterError: For another suffix, ``fps < 1``, or MP4 without ffmpeg.
    """
    p = Path(path)
    suffix = p.suffix.lower()
    if suffix not in (".gif", ".mp4", ".html"):
        raise ParameterError(f"an animation is written as .gif, .mp4 or .html, got {p.name!r}")
    if isinstance(fps, bool) or not isinstance(fps, (int, np.integer)) or fps < 1:
        raise ParameterError(f"fps must be a positive int, got {fps!r}")
    if suffix == ".mp4" and not ffmpeg_available():
        raise ParameterError("writing MP4 needs ffmpeg on the PATH (matplotlib's animation.ffmpeg_path); "
                             "install ffmpeg or write a .gif")
    p.parent.mkdir(parents=True, exist_ok=True)
    if suffix == ".html":
        p.write_text(anim.to_jshtml(fps=int(fps)))
        return p
    writer = PillowWriter(fps=int(fps)) if suffix == ".gif" else FFMpegWriter(fps=int(fps))
    anim.save(str(p), writer=writer, dpi=dpi)
    return p


def ffmpeg_available() -> bool:
    """Whether matplotlib can find an ffmpeg executable (needed for MP4)."""
    exe = matplotlib.rcParams.get("animation.ffmpeg_path", "ffmpeg")
    return shutil.which(exe) is not None or Path(exe).is_file()
