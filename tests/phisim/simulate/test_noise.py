"""Tests of phisim.simulate.noise: E3 spectral noise statistics and spectrum, E4 rectangles, E5 vortex, uniform flow."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from phisim import CenteredGrid, Grid, StaggeredGrid
from phisim.errors import ParameterError, ShapeError
from phisim.simulate.noise import gaussian_vortex, random_rectangles, rectangles, spectral_noise, uniform_velocity

F64 = torch.float64


# ---- spectral noise ------------------------------------------------------------------------------------


def test_e3_noise_zero_mean_unit_std_per_sample():
    x = spectral_noise(Grid((64, 64)), 8, seed=0, dtype=F64)
    assert isinstance(x, CenteredGrid) and x.values.shape == (8, 64, 64)
    torch.testing.assert_close(x.values.mean((1, 2)), torch.zeros(8, dtype=F64), rtol=0, atol=1e-12)
    torch.testing.assert_close(x.values.std((1, 2), unbiased=False), torch.ones(8, dtype=F64), rtol=0, atol=1e-12)
    assert x.boundary.periodic_axes == (True, True)


def test_e3_noise_modes_below_cutoff_are_zero():
    grid = Grid((64, 48))
    x = spectral_noise(grid, 4, seed=3, dtype=F64)
    spec = torch.fft.fftn(x.values, dim=(1, 2)).abs()
    k2 = sum(((torch.fft.fftfreq(n, 1.0 / n, dtype=F64) * 10 / n) ** 2).reshape(
        [n if a == b else 1 for b in range(2)]) for a, n in enumerate(grid.resolution))
    removed = k2 <= 0.1
    # k = m * 10 / n: the mean, (+-1, 0), (+-2, 0), (0, +-1) and (+-1, +-1) fall below the cutoff here
    assert int(removed.sum()) == 11
    assert float(spec[:, removed].max()) < 1e-9
    assert float(spec[:, ~removed].min()) > 0


@pytest.mark.parametrize("power", [2.0, 1.0])
def test_spectrum_falloff_slope_measured_by_fit(power):
    """The power spectrum |X(k)|^2 falls like |k|^(-2 power): fit the mean log-power against log|k|."""
    grid = Grid((64, 64))
    x = spectral_noise(grid, 16, power=power, seed=11, dtype=F64)
    power_k = (torch.fft.fftn(x.values, dim=(1, 2)).abs() ** 2).log().mean(0)  # (64, 64)
    k = torch.fft.fftfreq(64, 1.0 / 64, dtype=F64) * 10 / 64
    kk = (k[:, None] ** 2 + k[None, :] ** 2).sqrt()
    keep = kk ** 2 > 0.1
    slope = np.polyfit(kk[keep].log().numpy(), power_k[keep].numpy(), 1)[0]
    assert slope == pytest.approx(-2 * power, abs=0.08)


def test_seeds_reproducible_and_distinct_and_generator_stream():
    grid = Grid((32, 16))
    a = spectral_noise(grid, 3, seed=5).values
    b = spectral_noise(grid, 3, seed=5).values
    c = spectral_noise(grid, 3, seed=6).values
    torch.testing.assert_close(a, b, rtol=0, atol=0)
    assert float((a - c).abs().max()) > 0.1
    assert float((a[0] - a[1]).abs().max()) > 0.1  # samples differ within a batch
    g = torch.Generator().manual_seed(5)
    first = spectral_noise(grid, 3, generator=g).values
    second = spectral_noise(grid, 3, generator=g).values
    torch.testing.assert_close(first, a, rtol=0, atol=0)  # a seed is a fresh generator with that seed
    assert float((first - second).abs().max()) > 0.1  # the generator advances
    r1 = random_rectangles(grid, 2, seed=1).values
    torch.testing.assert_close(r1, random_rectangles(grid, 2, seed=1).values, rtol=0, atol=0)
    assert float((r1 - random_rectangles(grid, 2, seed=2).values).abs().max()) > 0


def test_vector_noise_channels_and_3d():
    x = spectral_noise(Grid((16, 8, 12)), 2, channels=3, seed=1, dtype=F64)
    assert x.values.shape == (2, 3, 16, 8, 12) and x.is_vector
    torch.testing.assert_close(x.values.std((2, 3, 4), unbiased=False), torch.ones(2, 3, dtype=F64), rtol=0,
                               atol=1e-12)
    assert float((x.values[:, 0] - x.values[:, 1]).abs().max()) > 0.1
    raw = spectral_noise(Grid(64), 1, normalize=False, seed=1, dtype=F64)
    assert abs(float(raw.values.std()) - 1) > 1e-3  # normalisation is optional


def test_noise_bad_input():
    grid = Grid((8, 8))
    with pytest.raises(ParameterError):
        spectral_noise(grid, 0)
    with pytest.raises(ParameterError):
        spectral_noise(grid, 2, scale=-1.0)
    with pytest.raises(ParameterError):
        spectral_noise(grid, 2, seed=1, generator=torch.Generator())
    with pytest.raises(ParameterError):
        spectral_noise(grid, 2, seed=1.5)
    with pytest.raises(ParameterError):
        spectral_noise(grid, 2, scale=1e-3)  # every mode below the cutoff
    with pytest.raises(ParameterError):
        spectral_noise((8, 8), 2)


# ---- rectangles ----------------------------------------------------------------------------------------


def test_rectangle_coverage_integrates_to_the_analytic_area():
    grid = Grid((20, 16), bounds=[(-1.0, 1.5), (0.0, 2.0)])
    lower = torch.tensor([[[-0.83, 0.31], [0.2, 1.1]]], dtype=F64)
    upper = torch.tensor([[[0.47, 0.94], [1.4, 2.6]]], dtype=F64)  # second box sticks out of the domain
    strength = torch.tensor([[0.7, 2.0]], dtype=F64)
    r = rectangles(grid, lower, upper, strength, dtype=F64)
    integral = float(r.values.sum()) * grid.cell_volume
    area1 = (0.47 + 0.83) * (0.94 - 0.31)
    area2 = (1.4 - 0.2) * (2.0 - 1.1)  # clipped to the domain
    assert integral == pytest.approx(0.7 * area1 + 2.0 * area2, rel=1e-13)
    # interior cells are full, partly covered edge cells get the covered fraction
    one = rectangles(grid, [-0.83, 0.31], [0.47, 0.94], dtype=F64).values[0]
    assert float(one.max()) == pytest.approx(1.0, abs=1e-14)
    assert 0 < float(one[1, 3]) < 1  # x cell [-0.875, -0.75] is covered from -0.83 on
    assert float(one[1, 3]) == pytest.approx((-0.75 + 0.83) / 0.125, rel=1e-12)


def test_rectangle_coverage_3d_and_bad_corners():
    grid = Grid((6, 5, 4))
    r = rectangles(grid, [0.5, 1.25, 0.1], [3.3, 4.0, 2.2], 1.5, dtype=F64)
    assert float(r.values.sum()) == pytest.approx(1.5 * 2.8 * 2.75 * 2.1, rel=1e-13)
    with pytest.raises(ParameterError):
        rectangles(grid, [1.0, 1.0, 1.0], [0.5, 2.0, 2.0])
    with pytest.raises(ShapeError):
        rectangles(grid, [1.0, 1.0], [2.0, 2.0])


def test_e4_random_rectangles_follow_the_recipe():
    grid = Grid((64, 64))
    r = random_rectangles(grid, 32, seed=4, dtype=F64)
    v = r.values
    assert v.shape == (32, 64, 64) and float(v.min()) >= 0
    # strengths < 1 and at most 10 overlapping boxes of at most (2 * 10)^2 cells each
    assert float(v.max()) < 10
    totals = v.sum((1, 2))
    assert float(totals.min()) > 0 and float(totals.max()) < 10 * 400
    # single boxes of strength 1: area at most 400 cells, full interior cells, fractional edges
    one = random_rectangles(grid, 200, count=(1, 1), strength=(1.0, 1.0), seed=9, dtype=F64).values
    areas = one.sum((1, 2))
    assert float(areas.max()) <= 400 + 1e-9  # (2 * 10)^2 cells at most
    assert float(one.max()) == pytest.approx(1.0)
    # soft edges: fractional values occur
    frac = (one > 1e-9) & (one < 1 - 1e-9)
    assert bool(frac.any())
    # centres in the middle 80 %: the box's centroid lies within [6.4, 57.6] (clamping only moves inward)
    x = grid.cell_centers(F64)
    cx = (one * x[..., 0]).sum((1, 2)) / areas.clamp_min(1e-12)
    cy = (one * x[..., 1]).sum((1, 2)) / areas.clamp_min(1e-12)
    ok = areas > 1e-9
    assert float(cx[ok].min()) >= 6.4 - 1e-9 and float(cx[ok].max()) <= 57.6 + 1e-9
    assert float(cy[ok].min()) >= 6.4 - 1e-9 and float(cy[ok].max()) <= 57.6 + 1e-9
    with pytest.raises(ParameterError):
        random_rectangles(grid, 2, count=(5, 3))
    with pytest.raises(ParameterError):
        random_rectangles(grid, 2, margin=0.6)


# ---- vortex and uniform velocity -------------------------------------------------------------------------


def _analytic_vortex(x, centre, s, sigma):
    d = x - torch.tensor(centre, dtype=x.dtype)
    w = s * torch.exp(-0.5 * (d ** 2).sum(-1) / sigma ** 2)
    return torch.stack([-w * d[..., 1], w * d[..., 0]], -1)


def test_vortex_matches_analytic_profile_and_is_divergence_free():
    grid = Grid((64, 64), bounds=[128, 128])
    s, sigma, centre = 1.5, 20.0, (64.0, 60.0)
    v = gaussian_vortex(grid, centre, s, sigma, dtype=F64)
    assert isinstance(v, StaggeredGrid)
    for i in range(2):
        exact = _analytic_vortex(grid.face_centers(i, F64), centre, s, sigma)[..., i]
        torch.testing.assert_close(v.values[i][0], exact, rtol=1e-12, atol=1e-12)
    c = gaussian_vortex(grid, centre, s, sigma, staggered=False, dtype=F64)
    torch.testing.assert_close(torch.movedim(c.values[0], 0, -1), _analytic_vortex(grid.cell_centers(F64), centre,
                                                                                   s, sigma), rtol=1e-12, atol=1e-12)
    # peak speed s * sigma * exp(-1/2) at radius sigma
    speed = torch.linalg.vector_norm(c.values[0], dim=0)
    assert float(speed.max()) == pytest.approx(s * sigma * math.exp(-0.5), rel=2e-3)
    # MAC divergence (face differences) is O(dx^2) relative to |v|/dx
    dx = grid.dx[0]
    div = (v.values[0][0, 1:] - v.values[0][0, :-1]) / dx + (v.values[1][0, :, 1:] - v.values[1][0, :, :-1]) / dx
    scale = float(speed.max()) / dx
    assert float(div.abs().max()) < 2e-3 * scale
    # centred divergence of the centred field is small too
    cv = c.values[0]
    cdiv = (cv[0, 2:, 1:-1] - cv[0, :-2, 1:-1]) / (2 * dx) + (cv[1, 1:-1, 2:] - cv[1, 1:-1, :-2]) / (2 * dx)
    assert float(cdiv.abs().max()) < 2e-3 * scale


def test_vortex_batched_strengths_several_centres_wrap_and_3d():
    grid = Grid((32, 32), bounds=[64, 64])
    s = torch.tensor([1.0, -2.0], dtype=F64)
    v = gaussian_vortex(grid, (32.0, 32.0), s, 8.0, dtype=F64)
    torch.testing.assert_close(v.values[0][1], -2.0 * v.values[0][0], rtol=1e-12, atol=1e-14)
    two = gaussian_vortex(grid, torch.tensor([[[20.0, 30.0], [44.0, 34.0]]], dtype=F64),
                          torch.tensor([[1.0, 0.5]], dtype=F64), 6.0, dtype=F64)
    a = gaussian_vortex(grid, (20.0, 30.0), 1.0, 6.0, dtype=F64)
    b = gaussian_vortex(grid, (44.0, 34.0), 0.5, 6.0, dtype=F64)
    for i in range(2):
        torch.testing.assert_close(two.values[i], a.values[i] + b.values[i], rtol=1e-12, atol=1e-14)
    # wrap: a vortex at the corner looks the same as one at the centre, shifted by half the domain
    corner = gaussian_vortex(grid, (0.0, 0.0), 1.0, 6.0, wrap=True, staggered=False, dtype=F64).values
    mid = gaussian_vortex(grid, (32.0, 32.0), 1.0, 6.0, wrap=True, staggered=False, dtype=F64).values
    torch.testing.assert_close(torch.roll(corner, (16, 16), dims=(2, 3)), mid, rtol=1e-12, atol=1e-12)
    g3 = Grid((8, 8, 8), bounds=[16, 16, 16])
    v3 = gaussian_vortex(g3, (8.0, 8.0, 8.0), 1.0, 4.0, axis=2, staggered=False, dtype=F64)
    assert float(v3.values[:, 2].abs().max()) == 0.0  # rotation about z has no z component
    with pytest.raises(ParameterError):
        gaussian_vortex(Grid(8), (4.0,), 1.0, 2.0)
    with pytest.raises(ParameterError):
        gaussian_vortex(grid, (1.0, 1.0), 1.0, 0.0)
    with pytest.raises(ShapeError):
        gaussian_vortex(grid, (1.0, 1.0, 1.0), 1.0, 2.0)


def test_uniform_velocity_per_sample():
    grid = Grid((5, 4))
    u = uniform_velocity(grid, [[1.0, 2.0], [-3.0, 0.5]], dtype=F64)
    assert isinstance(u, StaggeredGrid) and u.batch_size == 2
    assert float(u.values[0][1].min()) == float(u.values[0][1].max()) == -3.0
    assert float(u.values[1][0].min()) == 2.0
    c = uniform_velocity(grid, (1.0, 2.0), staggered=False, batch_size=3)
    assert c.values.shape == (3, 2, 5, 4) and float(c.values[:, 1].mean()) == 2.0
    with pytest.raises(ShapeError):
        uniform_velocity(grid, (1.0, 2.0, 3.0))
