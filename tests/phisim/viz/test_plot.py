"""Tests of phisim.viz.plot: files are written, images show x to the right and y up, bad input fails."""

from __future__ import annotations

import matplotlib.image as mpimg
import numpy as np
import pytest
import torch
from matplotlib.figure import Figure
from PIL import Image

from phisim import CenteredGrid, Grid, StaggeredGrid
from phisim.errors import ParameterError, ShapeError
from phisim.viz.plot import (
    animate,
    ffmpeg_available,
    new_figure,
    plot_curves,
    plot_field,
    plot_vector_field,
    save_figure,
)


def _ramp_x(grid: Grid) -> CenteredGrid:
    """A field equal to x (large at high x, constant in y)."""
    return CenteredGrid.from_function(lambda p: p[..., 0], grid, "periodic", batch_size=2)


def test_plot_field_orientation_image_data():
    g = Grid((8, 4), bounds=[(0.0, 2.0), (-1.0, 0.0)])
    f = CenteredGrid.from_function(lambda p: p[..., 0] + 10 * p[..., 1], g, "periodic")
    ax = plot_field(f, title="ramp")
    im = ax.images[-1]
    data = np.asarray(im.get_array())
    assert data.shape == (4, 8)  # rows are y, columns are x
    np.testing.assert_allclose(data, f.values[0].numpy().T)
    assert im.origin == "lower"
    assert tuple(im.get_extent()) == (0.0, 2.0, -1.0, 0.0)
    assert ax.get_title() == "ramp" and len(ax.figure.axes) == 2  # with colour bar


def test_plot_field_orientation_in_png(tmp_path):
    """A field large at high x is bright on the right of the picture; one large at high y is bright on top."""
    g = Grid((32, 16), bounds=[(0.0, 2.0), (0.0, 1.0)])
    for axis in (0, 1):
        half = [1.0, 0.5][axis]
        f = CenteredGrid.from_function(lambda p, a=axis, h=half: (p[..., a] > h).to(p.dtype), g, "periodic")
        fig, ax = new_figure((4, 2))
        plot_field(f, ax, cmap="gray", colorbar=False)
        ax.set_axis_off()
        fig.subplots_adjust(0, 0, 1, 1)
        path = tmp_path / f"field{axis}.png"
        fig.savefig(path)  # no tight bounding box: the axes fill the picture exactly
        img = mpimg.imread(path)[..., :3].mean(axis=-1)  # rows top to bottom, columns left to right
        h, w = img.shape
        if axis == 0:
            left, right = img[:, : w // 4].mean(), img[:, -w // 4:].mean()
            assert right > 0.8 and left < 0.2
        else:
            top, bottom = img[: h // 4].mean(), img[-h // 4:].mean()
            assert top > 0.8 and bottom < 0.2


def test_plot_field_variants():
    g = Grid((6, 5))
    v = CenteredGrid(torch.stack([torch.ones(1, 6, 5), torch.zeros(1, 6, 5)], 1) * 3, g, "periodic")
    ax = plot_field(v)  # magnitude
    np.testing.assert_allclose(np.asarray(ax.images[-1].get_array()), 3.0)
    ax = plot_field(v, component=1, colorbar=False)
    np.testing.assert_allclose(np.asarray(ax.images[-1].get_array()), 0.0)
    ax = plot_field(np.arange(30.0).reshape(6, 5))
    np.testing.assert_allclose(np.asarray(ax.images[-1].get_array()), np.arange(30.0).reshape(6, 5).T)
    ax = plot_field(CenteredGrid(torch.arange(4.0)[None], Grid(4), "open"))  # 1-D: a line
    np.testing.assert_allclose(ax.lines[0].get_ydata(), [0, 1, 2, 3])
    f3 = CenteredGrid.from_function(lambda p: p[..., 2], Grid((3, 3, 4)), "periodic")
    ax = plot_field(f3, slice_index=1)
    np.testing.assert_allclose(np.asarray(ax.images[-1].get_array()), 1.5)
    s = StaggeredGrid.uniform((1.0, 2.0), g, "periodic")
    ax = plot_field(s)
    np.testing.assert_allclose(np.asarray(ax.images[-1].get_array()), np.sqrt(5.0), rtol=1e-6)


def test_plot_field_bad_input():
    g = Grid((6, 5))
    with pytest.raises(ShapeError):
        plot_field(np.zeros((2, 6, 5, 3, 2)))
    with pytest.raises(ShapeError):
        plot_field(np.zeros((6, 5)), grid=Grid((5, 6)))
    with pytest.raises(ParameterError):
        plot_field(_ramp_x(g), batch=5)
    with pytest.raises(ParameterError):
        plot_field(_ramp_x(g), component=0)  # scalar field
    with pytest.raises(ParameterError):
        plot_field(np.full((4, 4), np.nan))
    with pytest.raises(ParameterError):
        plot_field(np.zeros((4, 4)), ax="not axes")


def test_plot_vector_field_quiver_and_streamlines(tmp_path):
    g = Grid((16, 12), bounds=[(0, 1), (0, 1)])
    def vortex(p):
        return torch.stack([-p[..., 1] + 0.5, p[..., 0] - 0.5], -1)

    vel = StaggeredGrid.from_function(vortex, g, "wall")
    ax = plot_vector_field(vel, title="vortex", stride=2)
    q = [c for c in ax.collections if c.__class__.__name__ == "Quiver"][0]
    assert q.N == 8 * 6
    save_figure(ax.figure, tmp_path / "q.png")
    ax = plot_vector_field(vel.at_centers(), mode="streamlines", background=None)
    save_figure(ax.figure, tmp_path / "s.pdf")
    assert (tmp_path / "q.png").stat().st_size > 1000 and (tmp_path / "s.pdf").stat().st_size > 1000
    with pytest.raises(ShapeError):
        plot_vector_field(_ramp_x(g))  # scalar
    with pytest.raises(ShapeError):
        plot_vector_field(np.zeros((3, 4, 4)))
    with pytest.raises(ParameterError):
        plot_vector_field(vel, mode="arrows")
    with pytest.raises(ParameterError):
        plot_vector_field(vel, stride=0)


def test_plot_curves(tmp_path):
    it = np.arange(10)
    ax = plot_curves({"adam": (it, 1.0 / (it + 1)), "hig": (torch.arange(10), torch.full((10,), 0.01))},
                     title="loss")
    assert [line.get_label() for line in ax.lines] == ["adam", "hig"]
    assert ax.get_yscale() == "log"
    np.testing.assert_allclose(ax.lines[0].get_ydata(), 1.0 / (it + 1))
    ax = plot_curves({"m": (it, np.where(it % 2 == 0, it + 1.0, np.nan))}, logy=False)
    assert ax.get_yscale() == "linear" and len(ax.lines[0].get_xdata()) == 5  # NaN records skipped
    path = save_figure(ax.figure, tmp_path / "sub" / "curves.png")
    assert path.exists() and Image.open(path).format == "PNG"
    with pytest.raises(ParameterError):
        plot_curves({})
    with pytest.raises(ShapeError):
        plot_curves({"a": (it, it[:-1])})
    with pytest.raises(ParameterError):
        plot_curves({"a": it})


def test_save_figure_errors(tmp_path):
    fig, ax = new_figure()
    with pytest.raises(ParameterError, match="format"):
        save_figure(fig, tmp_path / "x.unknownfmt")
    with pytest.raises(ParameterError):
        save_figure(ax, tmp_path / "x.png")
    assert isinstance(fig, Figure)


def test_animate_gif(tmp_path):
    g = Grid((12, 8))
    frames = [CenteredGrid.from_function(lambda p, k=k: torch.sin(p[..., 0] + k), g, "periodic")
              for k in range(4)]
    path = animate(frames, tmp_path / "anim.gif", fps=5, title="t={t}")
    with Image.open(path) as im:
        assert im.format == "GIF" and im.n_frames == 4
    path2 = animate(torch.rand(3, 12, 8), tmp_path / "raw.gif", fps=2)
    with Image.open(path2) as im:
        assert im.n_frames == 3
    with pytest.raises(ParameterError):
        animate(frames, tmp_path / "anim.avi")
    with pytest.raises(ParameterError):
        animate([], tmp_path / "a.gif")
    with pytest.raises(ParameterError):
        animate(frames, tmp_path / "a.gif", fps=0)
    with pytest.raises(ShapeError):
        animate([np.zeros((4, 4)), np.zeros((5, 4))], tmp_path / "a.gif")


def test_animate_mp4(tmp_path):
    frames = np.random.default_rng(0).random((3, 16, 16))
    if not ffmpeg_available():
        with pytest.raises(ParameterError, match="ffmpeg"):
            animate(frames, tmp_path / "a.mp4")
        pytest.skip("ffmpeg not installed; MP4 output not exercised")
    path = animate(frames, tmp_path / "a.mp4", fps=4)
    assert path.stat().st_size > 0


@pytest.mark.parametrize("lo, hi, at_least", [(600.0, 800.0, 3), (190.0, 800.0, 3), (1.0, 3e4, 4), (1e-6, 1.0, 4)])
def test_log_axis_has_several_readable_labels(lo, hi, at_least):
    """A log axis labels at least three ticks inside the data range, as plain numbers (not only 10^k)."""
    it = np.arange(50)
    ax = plot_curves({"a": (it, np.geomspace(hi, lo, 50))}, logy=True)
    ax.figure.canvas.draw()
    y0, y1 = ax.get_ylim()
    labels = [t.get_text() for t in ax.get_yticklabels() if y0 <= t.get_position()[1] <= y1 and t.get_text()]
    assert len(labels) >= at_least, labels
    assert all("10^" not in s and "mathdefault" not in s for s in labels), labels
    values = sorted(float(s.replace("−", "-")) for s in labels)
    assert values[0] >= y0 * 0.999 and values[-1] <= y1 * 1.001


def test_training_curves_and_masks(tmp_path):
    from phisim.viz.plot import draw_mask, plot_training_curves

    curves = {"iteration": np.arange(6), "metric": np.array([800.0, 700, 650, 600, 640, 620]),
              "eval_metric": np.array([np.nan, 720, np.nan, 630, np.nan, 610])}
    ax = plot_training_curves({"adam": curves}, "x L1 per sample (sum over cells)")
    lines = ax.get_lines()
    np.testing.assert_array_equal(lines[1].get_xdata(), [1, 3, 5])  # held-out points only where evaluated
    assert ax.get_ylabel() == "x L1 per sample (sum over cells)"
    with pytest.raises(ParameterError):
        plot_training_curves({}, "m")
    g = Grid((4, 3))
    mask = np.zeros((4, 3), dtype=bool)
    mask[1, 2] = True
    ax2 = plot_field(np.arange(12.0).reshape(4, 3), grid=g, mask=mask)
    rgba = ax2.images[-1].get_array()
    assert rgba.shape == (3, 4, 4) and rgba[2, 1, 3] == 1.0 and rgba[..., 3].sum() == 1.0  # transposed, opaque
    with pytest.raises(ShapeError):
        draw_mask(ax2, np.zeros((3, 3), dtype=bool), g)
    gif = animate([np.zeros((4, 3)), np.ones((4, 3))], tmp_path / "a.gif", grid=g, times=[0.0, 0.5], mask=mask,
                  title="rho, t = {time:.1f}")
    assert gif.stat().st_size > 0
    with pytest.raises(ShapeError):
        animate([np.zeros((4, 3))], tmp_path / "b.gif", grid=g, times=[0.0, 1.0])
