"""Linear equations against their exact solutions (the steppers integrate them exactly in time)."""

from __future__ import annotations

import math

import pytest
import torch

from phisim.pde import Advection, Diffusion, Dispersion, HyperDiffusion, Wave

F64 = torch.float64


def test_advection_1d_and_2d_exact():
    s = Advection(ndim=1, velocity=0.7, domain=2.0, resolution=64, dt=0.37, dtype=F64)
    (x,) = s.grid.coordinates()
    u0 = torch.sin(math.pi * x) + 0.5 * torch.cos(3 * math.pi * x)

    def exact(t):
        y = x - 0.7 * t
        return torch.sin(math.pi * y) + 0.5 * torch.cos(3 * math.pi * y)

    u = s.repeat(u0[None, None], 10)
    assert torch.allclose(u[0, 0], exact(3.7), atol=1e-12)
    s2 = Advection(ndim=2, velocity=(1.0, -0.5), domain=(1.0, 2.0), resolution=(32, 48), dt=0.1, dtype=F64)
    x, y = s2.grid.coordinates()
    u0 = torch.sin(2 * math.pi * x) * torch.cos(math.pi * y)
    u = s2.repeat(u0[None, None], 7)
    ue = torch.sin(2 * math.pi * (x - 0.7)) * torch.cos(math.pi * (y + 0.35))
    assert torch.allclose(u[0, 0], ue, atol=1e-12)


@pytest.mark.parametrize("boundary", ["periodic", "dirichlet", "neumann"])
def test_diffusion_exact_all_bases(boundary):
    nu, length = 0.05, 1.0
    s = Diffusion(ndim=2, diffusivity=(nu, 2 * nu), domain=length, resolution=(24, 20), dt=0.03,
                  boundaries=boundary, dtype=F64)
    x, y = s.grid.coordinates()
    if boundary == "periodic":
        kx, ky, fx, fy = 2 * math.pi * 2, 2 * math.pi, torch.sin, torch.cos
    elif boundary == "dirichlet":
        kx, ky, fx, fy = math.pi * 3, math.pi, torch.sin, torch.sin
    else:
        kx, ky, fx, fy = math.pi * 3, math.pi * 2, torch.cos, torch.cos
    u0 = fx(kx * x) * fy(ky * y)
    u = s.repeat(u0[None, None].expand(3, 1, 24, 20).contiguous(), 20)
    decay = math.exp(-(nu * kx ** 2 + 2 * nu * ky ** 2) * 0.6)
    assert torch.allclose(u, (decay * u0).expand_as(u), atol=1e-13)


def test_dispersion_exact():
    a = 0.01
    s = Dispersion(dispersivity=a, domain=1.0, resolution=64, dt=0.05, dtype=F64)
    (x,) = s.grid.coordinates()
    k = 2 * math.pi * 5
    u = s.repeat(torch.sin(k * x)[None, None], 40)
    # u_t = a u_xxx: sin(k x) -> sin(k (x - a k^2 t))
    assert torch.allclose(u[0, 0], torch.sin(k * (x - a * k * k * 2.0)), atol=1e-12)


@pytest.mark.parametrize("boundary", ["periodic", "dirichlet", "neumann"])
def test_hyperdiffusion_exact(boundary):
    nu = 1e-4
    s = HyperDiffusion(ndim=1, hyperdiffusivity=nu, resolution=32, dt=0.1, boundaries=boundary, dtype=F64)
    (x,) = s.grid.coordinates()
    k = 4 * math.pi
    u0 = torch.sin(k * x) if boundary == "dirichlet" else torch.cos(k * x)
    u = s.repeat(u0[None, None], 10)
    assert torch.allclose(u[0, 0], u0 * math.exp(-nu * k ** 4), atol=1e-13)


@pytest.mark.parametrize("boundary", ["periodic", "dirichlet"])
def test_wave_standing_mode_exact(boundary):
    c = 1.3
    s = Wave(ndim=1, speed=c, domain=2.0, resolution=32, dt=0.01, boundaries=boundary, dtype=F64)
    (x,) = s.grid.coordinates()
    k = math.pi * (2 if boundary == "dirichlet" else 1)
    u0 = torch.stack([torch.sin(k * x), torch.zeros_like(x)])[None]
    t = 0.01 * 123
    u = s.repeat(u0, 123)
    w = c * k
    assert torch.allclose(u[0, 0], math.cos(w * t) * torch.sin(k * x), atol=1e-12)
    assert torch.allclose(u[0, 1], -w * math.sin(w * t) * torch.sin(k * x), atol=1e-11)


def test_wave_mean_mode_moves_linearly():
    s = Wave(ndim=2, speed=1.0, resolution=8, dt=0.5, dtype=F64)
    u0 = torch.zeros(1, 2, 8, 8, dtype=F64)
    u0[:, 1] = 0.2
    u = s.repeat(u0, 4)
    assert torch.allclose(u[:, 0], torch.full_like(u[:, 0], 0.4), atol=1e-14)


def test_diffusion_3d_mixed_walls_exact():
    nu = 0.02
    s = Diffusion(ndim=3, diffusivity=nu, domain=(1.0, 2.0, 1.5), resolution=(12, 10, 8),
                  boundaries=("periodic", "dirichlet", "neumann"), dt=0.05, dtype=F64)
    x, y, z = s.grid.coordinates()
    kx, ky, kz = 2 * math.pi, math.pi * 3 / 2.0, math.pi * 2 / 1.5
    u0 = torch.cos(kx * x) * torch.sin(ky * y) * torch.cos(kz * z)
    u = s.repeat(u0[None, None], 10)
    assert torch.allclose(u[0, 0], u0 * math.exp(-nu * (kx ** 2 + ky ** 2 + kz ** 2) * 0.5), atol=1e-13)
