"""One convention for "up" (issue 26, item 3): y, axis 1, in 2-D and 3-D.

Buoyancy pushes a hot blob along +y by default (the pure ``buoyancy`` / ``step`` functions and the
``FluidStepper``), and pictures draw y upwards (``origin='lower'``), so a rising plume rises on screen.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from phisim import CenteredGrid, Grid, StaggeredGrid, buoyancy, step
from phisim.fluid import FluidState, FluidStepper
from phisim.fluid.step import buoyancy_args


def _blob(grid: Grid) -> CenteredGrid:
    centre = [0.5 * s for s in grid.size]
    return CenteredGrid.from_function(
        lambda x: (((x - torch.tensor(centre, dtype=x.dtype)) ** 2).sum(-1) < (0.2 * grid.size[0]) ** 2).to(x.dtype),
        grid, "wall")


@pytest.mark.parametrize("rank, expected", [(1, (1.0,)), (2, (0.0, 1.0)), (3, (0.0, 1.0, 0.0))])
def test_default_up_is_axis_1(rank, expected):
    assert buoyancy_args(1.0, None, rank)[1] == expected


def test_3d_buoyancy_default_pushes_along_y():
    grid = Grid((8, 8, 8))
    v = StaggeredGrid.zeros(grid, "wall")
    out = buoyancy(v, _blob(grid), 0.5, strength=2.0)
    vx, vy, vz = (c.abs().max().item() for c in out.values)
    assert vy > 0.5 and vx == 0.0 and vz == 0.0
    assert out.values[1].min().item() >= 0.0  # upwards, not down


@pytest.mark.parametrize("how", ["step", "stepper"])
def test_3d_hot_blob_rises_along_plus_y(how):
    """After a few steps of the default 3-D step the blob's centre of mass has moved up in y only."""
    grid = Grid((10, 10, 10))
    state = FluidState(StaggeredGrid.zeros(grid, "wall"), _blob(grid))
    if how == "stepper":
        stepper = FluidStepper(grid, "wall", buoyancy=1.0, dt=0.5)
        for _ in range(4):
            state = stepper(state)
    else:
        for _ in range(4):
            state = step(state, 0.5, buoyancy_strength=1.0)
    m = state.marker.values[0].double()
    x = grid.cell_centers(torch.float64)
    com = [(m * x[..., a]).sum().item() / m.sum().item() for a in range(3)]
    assert com[1] > 5.0 + 0.3  # rose along +y
    assert abs(com[0] - 5.0) < 0.05 and abs(com[2] - 5.0) < 0.05  # not sideways, not along z
    v = state.velocity.values
    up = v[1][0, 5, :, 5]  # y-velocity on the vertical line through the blob's centre
    assert up[5].item() > 0.1 and up[5].item() == pytest.approx(v[1].max().item(), rel=0.3)


def test_2d_default_unchanged():
    grid = Grid((6, 8))
    v = StaggeredGrid.zeros(grid, "wall")
    out = buoyancy(v, _blob(grid), 1.0)
    assert out.values[0].abs().max().item() == 0.0 and out.values[1].max().item() > 0.0


def test_pictures_draw_y_upwards():
    """plot_field and show put y on the vertical axis with the origin at the lower left: a field that grows
    with y has its largest values in the top rows of the picture (3-D: the default slice is an x-y picture)."""
    from phisim.viz import plot_field, show

    grid = Grid((6, 8, 4), bounds=[(0, 6), (0, 8), (0, 4)])
    f = CenteredGrid.from_function(lambda x: x[..., 1], grid, "open")
    for ax in (plot_field(f), show(f).axes[0]):
        im = ax.images[0]
        assert im.origin == "lower" and ax.get_ylabel().startswith("y") and ax.get_xlabel().startswith("x")
        data = np.asarray(im.get_array())
        assert data.shape == (8, 6)  # rows are y
        assert (np.diff(data, axis=0) > 0).all()  # row index (upwards with origin lower) follows y
        assert tuple(im.get_extent()) == (0, 6, 0, 8)
