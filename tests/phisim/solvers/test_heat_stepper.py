"""HeatStepper: the exact decay of discrete eigenmodes, agreement with diffuse(), settings checked once."""

from __future__ import annotations

import math

import pytest
import torch

from phisim import CenteredGrid, Dirichlet, Grid
from phisim.errors import GridMismatchError, ParameterError
from phisim.solvers.diffusion import diffuse
from phisim.solvers.heat import HeatStepper

F64 = torch.float64


@pytest.mark.parametrize("method", ["spectral", "implicit", "explicit"])
def test_a_periodic_mode_decays_by_its_discrete_factor(method):
    n, nu, dt, k = 32, 0.05, 0.005, 3
    grid = Grid((n,), bounds=[(0, 1)])
    dx = 1.0 / n
    x = (torch.arange(n, dtype=F64) + 0.5) * dx
    u = CenteredGrid(torch.sin(2 * math.pi * k * x)[None], grid, "periodic")
    lam = -4 / dx**2 * math.sin(math.pi * k / n) ** 2  # eigenvalue of the 3-point stencil
    factor = {"spectral": math.exp(nu * dt * lam), "implicit": 1 / (1 - nu * dt * lam),
              "explicit": 1 + nu * dt * lam}[method]
    out = HeatStepper(grid, "periodic", diffusivity=nu, dt=dt, method=method, dtype=F64)(u)
    torch.testing.assert_close(out.values, factor * u.values, rtol=0, atol=1e-13)


@pytest.mark.parametrize("boundary", ["periodic", "dirichlet", "neumann", {"x": "dirichlet", "y": "neumann"}])
@pytest.mark.parametrize("method", ["spectral", "implicit"])
def test_equals_diffuse_in_2d(boundary, method):
    grid = Grid((12, 10), bounds=[(0, 1.2), (0, 1)])
    g = torch.Generator().manual_seed(0)
    u = CenteredGrid(torch.randn(3, 12, 10, generator=g, dtype=F64), grid, boundary)
    step = HeatStepper(grid, boundary, diffusivity=0.3, dt=0.02, method=method, dtype=F64)
    ref = diffuse(u, 0.02, viscosity=0.3, method=method)
    torch.testing.assert_close(step(u).values, ref.values, rtol=0, atol=1e-12)


def test_dirichlet_mode_and_heated_wall():
    n = 16
    grid = Grid((n,), bounds=[(0, 1)])
    x = (torch.arange(n, dtype=F64) + 0.5) / n
    u = CenteredGrid(torch.sin(math.pi * x)[None], grid, "dirichlet")
    lam = -4 * n**2 * math.sin(math.pi / (2 * n)) ** 2  # lowest Dirichlet mode of the face-boundary stencil
    out = HeatStepper(grid, "dirichlet", diffusivity=1.0, dt=0.01, dtype=F64)(u)
    torch.testing.assert_close(out.values, math.exp(0.01 * lam) * u.values, rtol=0, atol=1e-13)
    hot = CenteredGrid(torch.zeros(1, n, dtype=F64), grid, Dirichlet(1.0))  # a wall held at 1: diffuse's response
    step = HeatStepper(grid, Dirichlet(1.0), diffusivity=1.0, dt=0.01, dtype=F64)
    assert step.inhomogeneous
    torch.testing.assert_close(step(hot).values, diffuse(hot, 0.01, viscosity=1.0).values, rtol=0, atol=0)


def test_gradcheck():
    grid = Grid((6, 5), bounds=[(0, 1), (0, 1)])
    step = HeatStepper(grid, {"x": "periodic", "y": "dirichlet"}, diffusivity=0.1, dt=0.05, dtype=F64)
    u0 = torch.randn(2, 6, 5, dtype=F64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda v: step(CenteredGrid(v, grid, step.boundary)).values, (u0,))


@pytest.mark.parametrize("kwargs, match", [
    ({"diffusivity": -1.0, "dt": 0.1}, "diffusivity"),
    ({"diffusivity": 1.0, "dt": -0.1}, "dt"),
    ({"diffusivity": 1.0, "dt": 0.1, "method": "crank"}, "method"),
    ({"diffusivity": 1.0, "dt": 10.0, "method": "explicit"}, "unstable"),
    ({"diffusivity": 1.0, "dt": 0.1, "dtype": torch.int64}, "dtype"),
])
def test_bad_settings(kwargs, match):
    with pytest.raises(ParameterError, match=match):
        HeatStepper(Grid((8, 8)), "periodic", **kwargs)


def test_a_field_that_does_not_fit():
    grid = Grid((8, 8))
    step = HeatStepper(grid, "periodic", diffusivity=0.1, dt=0.1)
    with pytest.raises(GridMismatchError):
        step(CenteredGrid.zeros(Grid((8, 4)), "periodic"))
    with pytest.raises(GridMismatchError):
        step(CenteredGrid.zeros(grid, "dirichlet"))
    with pytest.raises(ParameterError, match="float32"):
        step(CenteredGrid.zeros(grid, "periodic", dtype=F64))
    with pytest.raises(ParameterError, match="scalar"):
        step(CenteredGrid.zeros(grid, "periodic", channels=2))
