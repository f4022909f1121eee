"""float32 fields with default settings: Poisson, masked Poisson and the fluid projection succeed from 64² to
512² (and 64³), and the returned solution's true residual (float64) meets the tolerance the solve reports."""

from __future__ import annotations

import math

import pytest
import torch

import phisim as ps
from phisim.fluid import Projection
from phisim.solvers.poisson import masked_laplacian, masked_poisson_solve_with_info, stencil_laplacian

SIZES = [pytest.param(n, marks=pytest.mark.slow) if n > 128 else n for n in (64, 128, 256, 512)]


def _smooth_rhs(res, dtype=torch.float32):
    """A smooth zero-mean rhs (the hard case for float32: a large, smooth solution)."""
    axes = [(torch.arange(n, dtype=torch.float64) + 0.5) / n for n in res]
    grids = torch.meshgrid(*axes, indexing="ij")
    f = math.prod(torch.cos((a + 1) * math.pi * g) for a, g in enumerate(grids))
    return f[None].to(dtype)


def _disc_mask(res):
    axes = [torch.arange(n, dtype=torch.float64) + 0.5 for n in res]
    grids = torch.meshgrid(*axes, indexing="ij")
    r2 = sum((g - 0.4 * n) ** 2 for g, n in zip(grids, res))
    return r2 > (0.12 * min(res)) ** 2  # True = fluid, one obstacle ball


def _masked_case(res):
    rhs = _smooth_rhs(res)
    mask = _disc_mask(res)
    u, info = masked_poisson_solve_with_info(rhs, mask, 1.0, "neumann", incompatible="project")
    return rhs, mask, u, info


def _check_masked(res):
    rhs, mask, u, info = _masked_case(res)
    assert u.dtype == torch.float32 and info.all_converged and info.refined
    # the true residual of the returned float32 solution, recomputed here in float64
    m = mask[None].double()
    f = rhs.double() * m
    f = f - (f.sum() / m.sum()) * m  # the solve's compatible rhs (mean over fluid cells removed)
    res64 = torch.linalg.vector_norm((masked_laplacian(u.double(), m, 1.0, "neumann") - f) * m)
    assert float(res64) <= float(info.tolerance[0]) * (1 + 1e-6)
    assert float(info.residual[0]) == pytest.approx(float(res64), rel=1e-3, abs=1e-12)
    # the reported tolerance is the requested one, widened at most by the measured float32 rounding floor
    requested = 1e-5 * float(torch.linalg.vector_norm(f))
    floor = 0.0 if info.precision_floor is None else float(info.precision_floor[0])
    assert float(info.tolerance[0]) <= requested * (1 + 1e-3) + floor
    # and float32 does not lose the solution: close to the float64 solve
    u64 = ps.masked_poisson_solve(rhs.double(), mask, 1.0, "neumann", incompatible="project")
    assert float((u.double() - u64).abs().max()) <= 1e-4 * float(u64.abs().max())


@pytest.mark.parametrize("n", SIZES)
def test_float32_masked_poisson_default_settings(n):
    _check_masked((n, n))


@pytest.mark.slow
def test_float32_masked_poisson_default_settings_3d():
    _check_masked((64, 64, 64))


@pytest.mark.parametrize("n", SIZES)
def test_float32_spectral_poisson_default_settings(n):
    rhs = _smooth_rhs((n, n))
    grid = ps.Grid((n, n))
    u = ps.solve_poisson(ps.CenteredGrid(rhs, grid, "dirichlet"))
    assert u.values.dtype == torch.float32
    r = stencil_laplacian(u.values.double(), 1.0, "dirichlet") - rhs.double()
    # direct solve: exact up to float32 rounding of the solution, eps32 * ||A|| * ||u|| (8 = ||A|| bound)
    assert float(torch.linalg.vector_norm(r)) <= 8 * 6e-8 * float(torch.linalg.vector_norm(u.values.double())) * 4


def _check_projection(res):
    grid = ps.Grid(res)
    g = torch.Generator().manual_seed(0)
    v = ps.StaggeredGrid(tuple(torch.randn(1, *grid.face_shape(a), generator=g) for a in range(len(res))), grid,
                         "wall")
    lo = tuple(0.3 * n for n in res)
    hi = tuple(0.5 * n for n in res)
    out, p, info = Projection(grid, v.boundary, ps.Obstacle.box(lo, hi))(v)
    assert out.values[0].dtype == torch.float32 and info is not None
    assert info.all_converged, info
    assert bool((info.residual <= info.tolerance).all())
    assert float(ps.relative_divergence(out).max()) < 1e-3


@pytest.mark.parametrize("n", SIZES)
def test_float32_projection_with_obstacle_default_settings(n):
    _check_projection((n, n))


@pytest.mark.slow
def test_float32_projection_with_obstacle_default_settings_3d():
    _check_projection((64, 64, 64))
