"""AdvectionDiffusionStepper and BurgersStepper: the composed steps, conservation, settings checked once."""

from __future__ import annotations

import pytest
import torch

from phisim import CenteredGrid, Grid, StaggeredGrid
from phisim.errors import GridMismatchError, ParameterError
from phisim.fluid.transport import AdvectionDiffusionStepper, BurgersStepper
from phisim.ops.advection import advect
from phisim.solvers.diffusion import diffuse

F64 = torch.float64


def _fields():
    grid = Grid((16, 12), bounds=[(0, 1.6), (0, 1.2)])
    g = torch.Generator().manual_seed(1)
    c = CenteredGrid(torch.rand(2, 16, 12, generator=g, dtype=F64), grid, "periodic")
    v = StaggeredGrid.from_function(lambda x: torch.stack([torch.sin(x[..., 1] * 5.2), 0.3 + 0 * x[..., 0]], -1),
                                    grid, "periodic", dtype=F64)
    return grid, c, v


def test_advection_diffusion_is_advect_then_diffuse():
    grid, c, v = _fields()
    step = AdvectionDiffusionStepper(grid, v, diffusivity=0.01, dt=0.05, dtype=F64)
    ref = diffuse(advect(c, v, 0.05, scheme="maccormack"), 0.05, viscosity=0.01)
    torch.testing.assert_close(step(c).values, ref.values, rtol=0, atol=0)


def test_conservative_transport_keeps_the_total_and_the_sign():
    grid, c, v = _fields()
    step = AdvectionDiffusionStepper(grid, v, diffusivity=0.02, dt=0.05, advection="conservative", dtype=F64)
    out = c
    for _ in range(20):
        out = step(out)
    torch.testing.assert_close(out.values.sum((1, 2)), c.values.sum((1, 2)), rtol=1e-12, atol=0)
    assert float(out.values.min()) >= 0


def test_burgers_is_self_advection_then_diffusion_and_decays():
    grid = Grid((32,), bounds=[(0, 6.283185307179586)])
    x = grid.cell_centers(F64)[..., 0]
    u = CenteredGrid(torch.sin(x)[None, None], grid, "periodic")
    step = BurgersStepper(grid, viscosity=0.1, dt=0.05, dtype=F64)
    ref = diffuse(advect(u, u, 0.05, scheme="maccormack"), 0.05, viscosity=0.1)
    torch.testing.assert_close(step(u).values, ref.values, rtol=0, atol=0)
    energy = [float((u.values**2).sum())]
    for _ in range(20):
        u = step(u)
        energy.append(float((u.values**2).sum()))
    assert all(b < a for a, b in zip(energy, energy[1:]))  # viscous Burgers dissipates energy


@pytest.mark.parametrize("kwargs, match", [
    ({"dt": -1.0}, "dt"), ({"dt": 0.1, "advection": "upwind"}, "advection"),
    ({"dt": 0.1, "diffusion": "cn"}, "diffusion"), ({"dt": 0.1, "diffusivity": -0.1}, "diffusivity"),
])
def test_advection_diffusion_bad_settings(kwargs, match):
    grid, _, v = _fields()
    with pytest.raises(ParameterError, match=match):
        AdvectionDiffusionStepper(grid, v, **kwargs)


def test_fields_that_do_not_fit():
    grid, c, v = _fields()
    with pytest.raises(GridMismatchError):
        AdvectionDiffusionStepper(Grid((8, 8)), v, dt=0.1)
    step = AdvectionDiffusionStepper(grid, v, dt=0.1, dtype=F64)
    with pytest.raises(ParameterError, match="scalar"):
        step(CenteredGrid(torch.zeros(1, 2, 16, 12, dtype=F64), grid, "periodic"))
    with pytest.raises(ParameterError, match="BurgersStepper"):
        BurgersStepper(grid, viscosity=0.1, dt=0.1, dtype=F64)(c)
    with pytest.raises(ParameterError, match="viscosity"):
        BurgersStepper(grid, viscosity=-1.0, dt=0.1)
