"""Diffusion: exact mode decay, conservation, first-order convergence of explicit/implicit, E4 operator."""

import math

import numpy as np
import pytest
import torch

from phisim.errors import ParameterError
from phisim.solvers.diffusion import (
    diffuse,
    diffuse_values,
    explicit_stability_limit,
    fourier_heat,
    fourier_k2,
    heat_decay_factors,
)
from phisim.solvers.linalg import Solve
from phisim.solvers.poisson import stencil_laplacian
from phisim.spectral import fft


@pytest.fixture(autouse=True)
def _fast_planning():
    with fft.fft_settings(planner_effort="FFTW_ESTIMATE"):
        yield


def _mode(n, kind, k):
    i = np.arange(n) + 0.5
    if kind == "periodic":
        return np.cos(2 * np.pi * k * i / n), -4 * np.sin(np.pi * k / n) ** 2
    if kind == "dirichlet":
        return np.sin(np.pi * (k + 1) * i / n), -4 * np.sin(np.pi * (k + 1) / (2 * n)) ** 2
    return np.cos(np.pi * k * i / n), -4 * np.sin(np.pi * k / (2 * n)) ** 2


@pytest.mark.parametrize(
    "kinds", [("periodic", "dirichlet"), ("neumann", "neumann"), ("dirichlet", "periodic")]
)
def test_spectral_decays_each_mode_exactly(kinds):
    n = (16, 12)
    dx = (0.5, 0.8)
    nu, dt = 0.3, 0.7
    for k in ((1, 2), (3, 0), (5, 7)):
        (m0, l0), (m1, l1) = _mode(n[0], kinds[0], k[0]), _mode(n[1], kinds[1], k[1])
        u0 = torch.from_numpy(np.outer(m0, m1))[None]
        lam = l0 / dx[0] ** 2 + l1 / dx[1] ** 2
        # it is an eigenvector of the stencil with this eigenvalue
        torch.testing.assert_close(stencil_laplacian(u0, dx, kinds), lam * u0)
        u = diffuse_values(u0, dt, viscosity=nu, dx=dx, kinds=kinds)
        torch.testing.assert_close(u, math.exp(nu * dt * lam) * u0, rtol=1e-12, atol=1e-13)


def test_continuous_spectrum_decays_sine_mode_like_the_pde():
    n, L = 32, 2.0
    x = (np.arange(n) + 0.5) * L / n
    u0 = torch.from_numpy(np.sin(3 * np.pi * x / L))[None]
    u = diffuse_values(u0, 0.1, viscosity=0.5, dx=L / n, kinds="dirichlet", spectrum="continuous")
    torch.testing.assert_close(u, u0 * math.exp(-0.5 * 0.1 * (3 * np.pi / L) ** 2), rtol=1e-12, atol=1e-13)


@pytest.mark.parametrize("kinds", ["periodic", "neumann", ("periodic", "neumann")])
@pytest.mark.parametrize("method", ["spectral", "implicit", "explicit"])
def test_mean_is_conserved(kinds, method):
    u0 = torch.rand(2, 16, 10, dtype=torch.float64)
    u = diffuse_values(u0, 0.2, viscosity=0.5, kinds=kinds, method=method, substeps=2)
    torch.testing.assert_close(u.mean(dim=(1, 2)), u0.mean(dim=(1, 2)), rtol=1e-12, atol=1e-13)
    assert u.std() < u0.std()


def test_boundary_values_steady_state_and_flux():
    # nonzero Dirichlet values: the long-time limit is the discrete harmonic solution
    kinds, values = "dirichlet", ((1.0, 3.0),)
    u0 = torch.zeros(1, 20, dtype=torch.float64)
    u = diffuse_values(u0, 1e4, viscosity=1.0, kinds=kinds, values=values)
    x = np.arange(20) + 0.5
    np.testing.assert_allclose(u[0].numpy(), 1.0 + 2.0 * x / 20, atol=1e-10)
    # Neumann influx: the mean grows by nu t (sum of fluxes) / length
    u = diffuse_values(u0, 2.0, viscosity=0.5, kinds="neumann", values=((0.25, 0.5),))
    assert abs(float(u.mean()) - 0.5 * 2.0 * 0.75 / 20) < 1e-13


@pytest.mark.parametrize("method", ["explicit", "implicit"])
def test_first_order_convergence_to_spectral(method):
    n = 24
    kinds, values = ("dirichlet", "periodic"), ((0.5, -0.2), (None, None))
    u0 = torch.rand(1, n, 8, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    nu, T = 1.0, 0.5
    exact = diffuse_values(u0, T, viscosity=nu, kinds=kinds, values=values)
    limit = explicit_stability_limit((1.0, 1.0), nu)
    steps = [math.ceil(T / limit) * s for s in (2, 4, 8, 16)]
    errs = [
        float(
            (
                diffuse_values(
                    u0,
                    T,
                    viscosity=nu,
                    kinds=kinds,
                    values=values,
                    method=method,
                    substeps=s,
                    solve=Solve(rtol=1e-13),
                )
                - exact
            )
            .abs()
            .max()
        )
        for s in steps
    ]
    order = -np.polyfit(np.log(steps), np.log(errs), 1)[0]
    assert abs(order - 1) < 0.1, (order, errs)


def test_explicit_stability_check_and_bad_parameters():
    u = torch.rand(1, 8, 8, dtype=torch.float64)
    limit = explicit_stability_limit((1.0, 1.0), 1.0)
    assert limit == pytest.approx(0.25)
    diffuse_values(u, limit, viscosity=1.0, method="explicit")
    with pytest.raises(ParameterError, match="substeps >= 3"):
        diffuse_values(u, 2.5 * limit, viscosity=1.0, method="explicit")
    diffuse_values(u, 2.5 * limit, viscosity=1.0, method="explicit", substeps=3)
    for bad in (
        dict(dt=-1.0),
        dict(dt=float("nan")),
        dict(viscosity=-0.1),
        dict(viscosity=float("inf")),
        dict(method="crank"),
        dict(substeps=0),
    ):
        kw = dict(dt=0.1, viscosity=1.0) | bad
        with pytest.raises(ParameterError):
            diffuse_values(u, kw.pop("dt"), **kw)
    with pytest.raises(ParameterError):
        fourier_heat(u, -1.0)
    with pytest.raises(ParameterError):
        heat_decay_factors((8, 8), 1.0, viscosity=-1.0)


def test_spectral_diffusion_gradcheck():
    u = torch.rand(2, 6, 5, dtype=torch.float64, requires_grad=True)
    nu = torch.tensor(0.3, dtype=torch.float64, requires_grad=True)

    def f(u, nu):
        return diffuse_values(
            u, 0.5, viscosity=nu, kinds=("neumann", "dirichlet"), values=((None, None), (1.0, 0.0))
        )

    assert torch.autograd.gradcheck(f, (u, nu))
    assert torch.autograd.gradcheck(lambda u: fourier_heat(u, 0.05), (u,))


def test_fourier_heat_matches_e4_formula_and_numpy():
    x = np.random.default_rng(0).standard_normal((3, 64, 64))
    y = fourier_heat(torch.from_numpy(x), 8.0).numpy()
    kx = np.fft.fftfreq(64)[:, None]
    ky = np.fft.fftfreq(64)[None, :]
    ref = np.fft.ifft2(np.fft.fft2(x) * np.exp(-4 * np.pi**2 * (kx**2 + ky**2) * 8.0)).real
    np.testing.assert_allclose(y, ref, atol=1e-13)
    assert heat_decay_factors((64, 64), 8.0) is heat_decay_factors((64, 64), 8.0)  # cached
    assert fourier_k2((64, 64)).shape == (64, 33)
    for engine in fft.available_engines():
        np.testing.assert_allclose(
            fourier_heat(torch.from_numpy(x), 8.0, engine=engine).numpy(), ref, atol=1e-13
        )


def test_field_diffuse_scalar_and_vector():
    from phisim import Boundary, CenteredGrid, Dirichlet, Grid, NoSlipWall

    grid = Grid((16, 12), bounds=[(0, 2), (0, 1.5)])
    f = CenteredGrid(torch.rand(2, 16, 12, dtype=torch.float64), grid, [Dirichlet(1.0), "periodic"])
    g = diffuse(f, 0.01, viscosity=0.1)
    ref = diffuse_values(
        f.values,
        0.01,
        viscosity=0.1,
        dx=grid.dx,
        kinds=("dirichlet", "periodic"),
        values=((1.0, 1.0), (None, None)),
    )
    torch.testing.assert_close(g.values, ref)
    assert g.boundary == f.boundary
    lid = Boundary.create({"x": "wall", "y": ("wall", NoSlipWall(velocity=(1.0, 0.0)))}, 2)
    v = CenteredGrid(torch.zeros(1, 2, 16, 12, dtype=torch.float64), grid, lid)
    w = diffuse(v, 0.05, viscosity=0.1, method="implicit")
    assert float(w.values[0, 0, :, -1].mean()) > 0.01  # the moving lid drags u_x
    assert float(w.values[0, 1].abs().max()) == 0.0
    with pytest.raises(ParameterError):
        diffuse(f.values, 0.1, viscosity=0.1)
