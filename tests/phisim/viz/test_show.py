"""Tests of 3-D views (axis / index / projection), :func:`phisim.viz.show` and the file pictures: the data of each
picture is the slice or projection of the field, animations have one frame per state, panels are never empty,
dataset pictures go to their own folder, bad input is a PhisimError naming the problem."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

import phisim
from phisim import CenteredGrid, Grid, StaggeredGrid, rollout
from phisim.errors import FileFormatError, ParameterError, PhisimError, ShapeError
from phisim.fluid import Body, FluidState, FluidStepper, Sphere
from phisim.viz import (
    Picture,
    animate,
    default_out_dir,
    mask_view,
    panel_layout,
    plot_field,
    plot_file,
    plot_frames,
    show,
    volume_view,
)

G3 = Grid((6, 5, 4), bounds=[(0, 3), (0, 5), (0, 8)])


def _field3() -> CenteredGrid:
    gen = torch.Generator().manual_seed(0)
    return CenteredGrid(torch.rand(1, 6, 5, 4, generator=gen, dtype=torch.float64), G3, "open")


def _image(ax) -> np.ndarray:
    return np.asarray(ax.images[0].get_array())


# ---- 3-D views ----------------------------------------------------------------------------------------------


@pytest.mark.parametrize("axis, a", [("z", 2), ("y", 1), ("x", 0), (2, 2), (-3, 0), ("X", 0)])
def test_volume_view_slices_and_projections(axis, a):
    v = _field3().values[0].numpy()
    h, vert = phisim.viz.PLANES[a]
    img = volume_view(v, axis, 1)
    expected = np.take(v, 1, axis=a)
    np.testing.assert_array_equal(img, expected.T if h > vert else expected)
    assert img.shape == (v.shape[h], v.shape[vert])
    for name, fn in (("max", np.max), ("mean", np.mean), ("min", np.min)):
        expected = fn(v, axis=a)
        np.testing.assert_allclose(volume_view(v, axis, projection=name), expected.T if h > vert else expected)
    middle = np.take(v, v.shape[a] // 2, axis=a)
    np.testing.assert_array_equal(volume_view(v, axis), middle.T if h > vert else middle)


def test_y_is_up_in_every_view_that_shows_it():
    assert phisim.viz.PLANES == {2: (0, 1), 0: (2, 1), 1: (0, 2)}
    for normal in ("x", "z"):
        ax = plot_field(CenteredGrid.from_function(lambda x: x[..., 1], G3, "open"), axis=normal)
        assert ax.get_ylabel() == "y" and (np.diff(_image(ax), axis=0) > 0).all()  # upper rows: larger y
    ax = plot_field(_field3(), axis="y")
    assert (ax.get_xlabel(), ax.get_ylabel()) == ("x", "z")


@pytest.mark.parametrize("kwargs", [dict(axis="z"), dict(axis="x", index=-1), dict(axis="y", projection="max"),
                                    dict(axis=0, projection="mean")])
def test_plot_field_3d_image_is_the_view(kwargs):
    f = _field3()
    ax = plot_field(f, label="rho [kg/m^3]", **kwargs)
    view = volume_view(f.values[0], kwargs["axis"], kwargs.get("index"), kwargs.get("projection"))
    np.testing.assert_allclose(_image(ax), view.T)
    assert ax.images[0].origin == "lower"
    assert ax.figure.axes[1].get_ylabel() == "rho [kg/m^3]"  # colour bar label


def test_masks_in_views_slice_and_shadow():
    m = np.zeros((6, 5, 4), dtype=bool)
    m[2, 3, 0] = True
    assert mask_view(m, "z", 0)[2, 3] and not mask_view(m, "z", 1).any()
    shadow = mask_view(m, "z", projection="max")
    assert shadow.sum() == 1 and shadow[2, 3]
    ax = plot_field(_field3(), projection="max", mask=m)
    assert ax.images[-1].get_array()[3, 2, 3] == 1.0  # the mask image, transposed, opaque at (x=2, y=3)


@pytest.mark.parametrize("kwargs, error, match", [
    (dict(axis="w"), ParameterError, "unknown axis 'w'"),
    (dict(axis=3), ParameterError, "out of range"),
    (dict(axis=1.5), ParameterError, "axis must be"),
    (dict(index=4), ParameterError, "index 4 out of range: 4 cells along z"),
    (dict(index="1"), ParameterError, "index must be an int"),
    (dict(projection="median"), ParameterError, "unknown projection 'median'"),
    (dict(projection="max", index=1), ParameterError, "index= picks a slice"),
])
def test_view_errors(kwargs, error, match):
    with pytest.raises(error, match=match):
        plot_field(_field3(), **kwargs)
    with pytest.raises(error, match=match):
        show(_field3(), **kwargs)


def test_view_options_on_2d_and_1d_fields_fail():
    f2 = CenteredGrid.zeros(Grid((4, 4)), "open")
    for kwargs in (dict(projection="max"), dict(index=1), dict(axis="x")):
        with pytest.raises(ParameterError, match="3-D"):
            plot_field(f2, **kwargs)
    plot_field(f2, axis="z")  # the default view's axis is harmless
    with pytest.raises(ParameterError, match="1-D"):
        plot_field(CenteredGrid.zeros(Grid(8), "open"), projection="max")
    with pytest.raises(ShapeError, match="one 3-D array"):
        volume_view(np.zeros((3, 3)))


def test_animate_3d_and_1d_frames(tmp_path):
    frames = torch.rand(3, 6, 5, 4)
    path = animate(frames, tmp_path / "v.gif", grid=G3, projection="max", axis="x")
    with Image.open(path) as im:
        assert im.n_frames == 3
    path = animate(list(torch.rand(4, 16)), tmp_path / "line.gif")
    with Image.open(path) as im:
        assert im.n_frames == 4


def test_panel_layout_fills_rows():
    assert panel_layout(5) == (1, 5)
    assert panel_layout(7) == (2, 4) and panel_layout(12) == (2, 6) and panel_layout(5, columns=2) == (3, 2)
    with pytest.raises(ParameterError):
        panel_layout(0)
    with pytest.raises(ParameterError):
        panel_layout(3, columns=0)


# ---- show ---------------------------------------------------------------------------------------------------


def test_show_2d_field_still_and_displays():
    g = Grid((8, 6), bounds=[(0, 2), (0, 1)])
    f = CenteredGrid.from_function(lambda x: x[..., 0] + 10 * x[..., 1], g, "open")
    pic = show(f, title="ramp", label="T [K]")
    assert isinstance(pic, Picture) and not pic.is_animation and pic.animation is None and pic.n_frames == 1
    np.testing.assert_allclose(_image(pic.axes[0]), f.values[0].numpy().T)
    assert pic.axes[0].get_title() == "ramp" and pic.figure.axes[1].get_ylabel() == "T [K]"
    assert pic._repr_png_()[:8] == b"\x89PNG\r\n\x1a\n"
    assert pic._repr_html_().startswith('<img src="data:image/png;base64,')


def test_show_1d_3d_and_raw_arrays():
    pic = show(torch.arange(5.0))
    np.testing.assert_allclose(pic.axes[0].lines[0].get_ydata(), np.arange(5.0))
    f = _field3()
    pic = show(f, projection="max", axis="x")
    np.testing.assert_allclose(_image(pic.axes[0]), f.values[0].numpy().max(axis=0))  # (z, y).T = (y, z)
    assert "max along x" in pic.axes[0].get_title()
    pic = show(f.values[0], grid=G3, index=0)
    np.testing.assert_allclose(_image(pic.axes[0]), f.values[0, :, :, 0].numpy().T)
    assert tuple(pic.axes[0].images[0].get_extent()) == (0, 3, 0, 5)
    v = StaggeredGrid.uniform((3.0, 4.0), Grid((4, 4)), "periodic")
    np.testing.assert_allclose(_image(show(v).axes[0]), 5.0)
    np.testing.assert_allclose(_image(show(v, component=0).axes[0]), 3.0)


def test_show_dict_and_state_panels():
    g = Grid((6, 4))
    pic = show({"a": CenteredGrid.zeros(g, "open"), "b": np.ones((6, 4)), "c": np.full((6, 4), 2.0)})
    assert [ax.get_title() for ax in pic.axes] == ["a", "b", "c"]
    assert len(pic.figure.axes) == 6  # three panels, three colour bars, nothing empty
    state = FluidState(StaggeredGrid.uniform((1.0, 0.0), g, "periodic"), CenteredGrid.zeros(g, "periodic"), time=0.5)
    pic = show(state)
    assert [ax.get_title() for ax in pic.axes] == ["marker", "speed |u|"]
    np.testing.assert_allclose(_image(pic.axes[1]), 1.0)
    assert pic.figure.get_suptitle() == "t = 0.5"
    assert len(show(state, field="speed").axes) == 1
    with pytest.raises(ParameterError, match="choose from"):
        show(state, field="vorticity")


def _smoke():
    g = Grid((16, 24), bounds=[(0, 1), (0, 1.5)])
    body = Body(Sphere((0.5, 0.8), 0.15))
    src = CenteredGrid.from_function(lambda x: (((x[..., 0] - 0.5) ** 2 + (x[..., 1] - 0.25) ** 2) < 0.02).float(),
                                     g, "wall").values
    stepper = FluidStepper(g, "wall", obstacles=body, buoyancy=1.0, marker_source=src, dt=0.1)
    s0 = FluidState(StaggeredGrid.zeros(g, stepper.boundary), CenteredGrid.zeros(g, stepper.boundary.for_scalar()))
    return stepper, body, rollout(stepper, s0, 6, every=2)


def test_show_trajectory_animation_frames_and_files(tmp_path):
    stepper, body, traj = _smoke()
    pic = show(traj, obstacles=stepper, html="jshtml", save=tmp_path / "smoke.gif")
    assert pic.is_animation and pic.n_frames == len(traj) == 4
    with Image.open(pic.saved) as im:
        assert im.n_frames == 4
    html = pic._repr_html_()
    assert "<script" in html and html.count("frames[") >= 4  # the JavaScript player, one image per frame
    ax = pic.axes[0]
    np.testing.assert_allclose(_image(ax), traj.marker[-1, 0].numpy().T)  # the frame drawn last
    assert ax.images[-1].get_array().shape[-1] == 4  # the body, grey, over the image
    assert ax.collections, "the body's outline"
    assert ax.get_title().startswith("marker, t = ")
    assert pic.save(tmp_path / "smoke.html").read_text().count("frames[") >= 4
    with pytest.raises(ParameterError, match="animation is written as"):
        pic.save(tmp_path / "smoke.png")
    # a still picture of a few frames, one panel each, one colour bar; no empty panel
    pic = show(traj, animate=False, frames=[0, -1], obstacles=body, save=tmp_path / "frames.png")
    assert len(pic.axes) == 2 and len(pic.figure.axes) == 3
    np.testing.assert_allclose(_image(pic.axes[1]), traj.marker[-1, 0].numpy().T)
    assert Image.open(pic.saved).format == "PNG"
    with pytest.raises(ParameterError, match="still"):
        show(traj.final).save(tmp_path / "x.gif")
    speed = show(traj, field="speed", animate=False, frames=[1])
    assert "speed" in speed.figure.axes[-1].get_ylabel()


def test_show_list_of_frames_and_1d_frames():
    frames = [np.full((5, 4), float(k)) for k in range(3)]
    pic = show(frames, html="jshtml")
    assert pic.n_frames == 3
    curves = show([torch.sin(torch.linspace(0, 3, 20) + k) for k in range(4)], animate=False)
    assert len(curves.axes) == 1 and len(curves.axes[0].lines) == 4  # first, quarter, half (dup removed), last


def test_show_bad_input():
    with pytest.raises(ShapeError, match="not one field"):
        show(torch.zeros(2, 3, 4, 5))
    with pytest.raises(ParameterError, match="cannot draw a object"):
        show(object())
    with pytest.raises(ParameterError, match="html"):
        show(torch.zeros(3, 3), html="gif")
    with pytest.raises(ParameterError, match="batch index 3"):
        show(CenteredGrid.zeros(Grid((4, 4)), "open"), batch=3)
    with pytest.raises(ParameterError, match="animate=True needs frames"):
        show(torch.zeros(3, 3), animate=True)
    with pytest.raises(ShapeError):
        show([np.zeros((4, 4)), np.zeros((5, 4))])
    with pytest.raises(FileFormatError):
        show(Path("/nonexistent/file.h5"))
    assert issubclass(ShapeError, PhisimError)


def test_phisim_show_is_lazy():
    code = ("import sys, phisim; assert 'matplotlib' not in sys.modules; "
            "from phisim.viz import show; assert phisim.show is show; print('ok')")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0 and "ok" in out.stdout, out.stderr


# ---- pictures of files --------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def smoke3d(tmp_path_factory):
    from phisim.simulate import resolve_config, simulate_dataset

    cfg = resolve_config("smoke", dim=3, trajectories=1, trajectories_per_file=1, steps=3, resolution=12,
                         valid_fraction=0, test_fraction=0)
    root = simulate_dataset(tmp_path_factory.mktemp("sm3"), cfg, progress=False)["root"]
    return root, next((root / "data" / "train").glob("*.h5"))


def test_plot_file_views_and_default_folder(smoke3d, tmp_path):
    root, f = smoke3d
    assert default_out_dir(f) == root / "plots" / "train"
    assert default_out_dir(tmp_path / "run.h5") == tmp_path
    paths = plot_file(f, projection="max", animation=None)
    assert paths == [root / "plots" / "train" / f"{f.stem}_density_max_z.png"]
    assert not list((root / "data" / "train").glob("*.png"))  # nothing written among the dataset's files
    paths = plot_file(f, tmp_path, axis="x", index=2)
    assert [p.name for p in paths] == [f"{f.stem}_density_x2.png", f"{f.stem}_density_x2.gif"]
    with pytest.raises(ParameterError, match="index 12 out of range: 12 cells along z"):
        plot_file(f, tmp_path, index=12)
    with pytest.raises(ParameterError, match="unknown projection"):
        plot_file(f, tmp_path, projection="sum")


def test_plot_frames_data_and_no_empty_panels(smoke3d, tmp_path, monkeypatch):
    from phisim.io import read_simulation
    from phisim.viz import field_frames, plotfile

    _, f = smoke3d
    data = read_simulation(f)
    saved = {}
    real = plotfile.save_figure

    def keep(fig, p, **kw):  # the figure plot_frames writes
        saved["fig"] = fig
        return real(fig, p, **kw)

    monkeypatch.setattr(plotfile, "save_figure", keep)
    path = plot_frames(data, "density", tmp_path / "e.png", axis="y", projection="mean", frames=[0, 1, 2, 3],
                       columns=3)
    assert Image.open(path).format == "PNG"
    fig = saved["fig"]
    panels = [ax for ax in fig.axes if ax.images]
    assert len(panels) == 4 and len(fig.axes) == 5  # four frames, one colour bar, no empty axes
    arr = field_frames(data, "density")
    for k, ax in enumerate(panels):
        np.testing.assert_allclose(np.asarray(ax.images[0].get_array()), arr[k].mean(axis=1).T)
        assert (ax.get_xlabel(), ax.get_ylabel()) == ("x", "z")
    assert fig.axes[-1].get_ylabel() == "density (mean along y)"


def test_show_simulation_file(smoke3d):
    from phisim.io import read_simulation
    from phisim.viz import field_frames, obstacle_of

    _, f = smoke3d
    data = read_simulation(f)
    pic = show(f, projection="max", html="jshtml")  # a path: the file's first scalar field, every frame
    assert pic.is_animation and pic.n_frames == data.n_frames
    ax = pic.axes[0]
    np.testing.assert_allclose(_image(ax), field_frames(data, "density")[0].max(axis=2).T)  # frame 0 is drawn
    shadow = obstacle_of(data).any(axis=2).T
    assert shadow.any() and (ax.images[-1].get_array()[..., 3] == shadow).all()  # the stored obstacle, drawn
    assert pic.figure.axes[-1].get_ylabel() == "density"
    still = show(data, field="vorticity", animate=False, frames=[-1], axis="x")
    image = _image(still.axes[0])
    np.testing.assert_allclose(image, field_frames(data, "vorticity")[-1][data.grid.resolution[0] // 2])
    assert still.axes[0].images[0].get_cmap().name == "viridis"  # |curl u| in 3-D: not signed
    with pytest.raises(ParameterError, match="no field 'pressure'"):
        show(data, field="pressure")


def test_show_2d_vorticity_is_centred(tmp_path):
    from phisim.simulate import resolve_config, simulate_dataset

    cfg = resolve_config("taylor_green", trajectories=1, trajectories_per_file=1, steps=2, resolution=16,
                         valid_fraction=0, test_fraction=0)
    root = simulate_dataset(tmp_path / "tg", cfg, progress=False)["root"]
    pic = show(next((root / "data" / "train").glob("*.h5")), field="vorticity", animate=False, frames=[0])
    im = pic.axes[0].images[0]
    lo, hi = im.get_clim()
    assert im.get_cmap().name == "RdBu_r" and lo == pytest.approx(-hi) and hi > 0


def test_show_video_and_mp4_need_ffmpeg(tmp_path):
    from phisim.viz import ffmpeg_available

    frames = [np.full((6, 4), float(k)) for k in range(3)]
    if not ffmpeg_available():
        with pytest.raises(ParameterError, match="ffmpeg"):
            show(frames, html="video")
        with pytest.raises(ParameterError, match="ffmpeg"):
            show(frames, save=tmp_path / "a.mp4")
        assert "<script" in show(frames)._repr_html_()  # the default without ffmpeg: the JavaScript player
        pytest.skip("ffmpeg not installed; HTML5 video and MP4 not exercised")
    pic = show(frames, save=tmp_path / "a.mp4")
    assert pic.saved.stat().st_size > 0
    assert "<video" in pic._repr_html_()  # the default with ffmpeg
