"""Spectral grids: the DCT/DST/rfft transforms, their eigenfunctions and the grid checks."""

from __future__ import annotations

import math

import numpy as np
import pytest
import scipy.fft as sfft
import torch

from phisim.errors import BoundaryError, ParameterError, ShapeError
from phisim.pde import SpectralGrid, dct2, dst2, idct2, idst2


def test_dct_dst_match_scipy_and_invert():
    x = torch.randn(3, 17, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    np.testing.assert_allclose(dct2(x).numpy(), sfft.dct(x.numpy(), type=2) / 2, atol=1e-13)
    np.testing.assert_allclose(dst2(x).numpy(), sfft.dst(x.numpy(), type=2) / 2, atol=1e-13)
    assert torch.allclose(idct2(dct2(x)), x, atol=1e-14)
    assert torch.allclose(idst2(dst2(x)), x, atol=1e-14)


@pytest.mark.parametrize("boundaries", [("periodic", "dirichlet", "neumann"), ("dirichlet", "periodic", "neumann"),
                                        ("neumann", "dirichlet", "dirichlet"), ("periodic", "periodic", "periodic")])
def test_round_trip_and_laplacian_eigenfunctions(boundaries):
    grid = SpectralGrid(domain=(1.0, 2.0, 3.0), resolution=(6, 8, 5), boundaries=boundaries, dtype=torch.float64)
    u = torch.randn(2, 1, 6, 8, 5, dtype=torch.float64)
    u_hat = grid.to_spectral(u)
    assert tuple(u_hat.shape[2:]) == grid.spectral_shape
    assert u_hat.is_complex() == ("periodic" in boundaries)
    assert torch.allclose(grid.to_physical(u_hat), u, atol=1e-13)
    # a product of sines/cosines is an eigenfunction of the spectral Laplacian
    f = torch.ones(grid.resolution, dtype=torch.float64)
    k2 = 0.0
    for x, b, length in zip(grid.coordinates(), boundaries, grid.domain):
        k = (2 if b == "periodic" else 1) * math.pi * 2 / length
        f = f * (torch.sin(k * x) if b == "dirichlet" else torch.cos(k * x))
        k2 += k * k
    lap = grid.to_physical(grid.to_spectral(f) * grid.laplacian())
    assert torch.allclose(lap, -k2 * f, atol=1e-11)


def test_float32_transforms_and_mask():
    grid = SpectralGrid(domain=1.0, resolution=(16, 12), boundaries=("neumann", "periodic"))
    u = torch.randn(1, 2, 16, 12)
    assert grid.to_spectral(u).dtype == torch.complex64
    assert torch.allclose(grid.to_physical(grid.to_spectral(u)), u, atol=1e-5)
    mask = grid.dealias_mask()
    assert mask.shape == grid.spectral_shape and mask.dtype == torch.bool
    assert mask[:10].any() and not mask[11:].any()  # wall axis: modes m <= 2/3 * 16


def test_derivative_only_on_periodic_axes():
    grid = SpectralGrid(domain=(2 * math.pi, 1.0), resolution=(32, 8), boundaries=("periodic", "dirichlet"),
                        dtype=torch.float64)
    x, _ = grid.coordinates()
    f = torch.sin(3 * x).expand(32, 8)
    d = grid.to_physical(grid.derivative(0) * grid.to_spectral(f))
    assert torch.allclose(d, 3 * torch.cos(3 * x).expand(32, 8), atol=1e-12)
    with pytest.raises(BoundaryError, match="not diagonal"):
        grid.derivative(1)


@pytest.mark.parametrize("kwargs, error", [
    (dict(domain=-1.0), ParameterError), (dict(domain=0.0), ParameterError),
    (dict(domain=float("nan")), ParameterError),
    (dict(resolution=1), ParameterError), (dict(resolution=8.0), ParameterError), (dict(ndim=4), ParameterError),
    (dict(boundaries="robin"), BoundaryError), (dict(dtype=torch.float16), ParameterError),
    (dict(domain=(1.0, 2.0), ndim=3), ShapeError),
])
def test_grid_rejects_bad_settings(kwargs, error):
    with pytest.raises(error):
        SpectralGrid(**kwargs)


@pytest.mark.parametrize("resolution", [(12,), (12, 10), (9, 12), (6, 8, 10)])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_truncated_spectrum_inverts_like_the_masked_one(resolution, dtype):
    # the inverse transform of [..., :dealias_cut] equals that of the masked full spectrum (missing modes are zero)
    grid = SpectralGrid(domain=[2.0] * len(resolution), resolution=list(resolution), dtype=dtype)
    u = torch.randn((3, 2) + grid.resolution, dtype=dtype, generator=torch.Generator().manual_seed(1))
    u_hat = grid.to_spectral(u)
    cut = grid.dealias_cut()
    want = grid.to_physical(u_hat * grid.dealias_mask())
    got = grid.to_physical((u_hat * grid.dealias_mask())[..., :cut])
    assert got.shape == want.shape and got.is_contiguous()
    tol = 1e-5 if dtype == torch.float32 else 1e-13
    assert torch.allclose(got, want, rtol=0, atol=tol)
    assert bool((grid.dealias_mask()[..., cut:] == 0).all()) and bool(grid.dealias_mask()[..., cut - 1].any())
    if dtype == torch.float64:
        x = u_hat[..., :cut].detach().requires_grad_(True)
        assert torch.autograd.gradcheck(grid.to_physical, (x,), eps=1e-6, atol=1e-7)
