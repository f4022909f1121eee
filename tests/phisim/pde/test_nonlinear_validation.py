"""Nonlinear equations against analytic results: Cole-Hopf, KdV solitons, Taylor-Green, conservation, orders."""

from __future__ import annotations

import math

import pytest
import torch

from phisim.pde import (
    AllenCahn,
    Burgers,
    CahnHilliard,
    FisherKPP,
    KortewegDeVries,
    NavierStokesVorticity,
    random_field,
)

from ._exact import burgers_cole_hopf, empirical_order, kdv_soliton, kdv_two_soliton

F64 = torch.float64


def test_burgers_matches_cole_hopf():
    nu = 0.1
    s = Burgers(viscosity=nu, resolution=256, dt=1e-3, order=4, dtype=F64)
    (x,) = s.grid.coordinates()
    u = s.repeat(torch.sin(x)[None, None], 1000)
    err = (u[0, 0] - burgers_cole_hopf(x, 1.0, nu)).abs().max().item()
    assert err < 1e-10, err


def test_burgers_2d_vector_reduces_to_1d():
    # u = (f(x), 0) stays a 1-D Burgers solution in 2-D
    nu = 0.1
    s2 = Burgers(ndim=2, viscosity=nu, resolution=(128, 8), dt=5e-3, dtype=F64)
    x, _ = s2.grid.coordinates()
    u0 = torch.zeros(1, 2, 128, 8, dtype=F64)
    u0[0, 0] = torch.sin(x)
    u = s2.repeat(u0, 200)
    ref = burgers_cole_hopf(x[:, 0], 1.0, nu)
    assert torch.allclose(u[0, 0], ref[:, None].expand(128, 8), atol=1e-7)
    assert u[0, 1].abs().max() < 1e-12


def test_kdv_soliton_keeps_speed_shape_and_invariants():
    length, kappa = 40.0, 1.0
    s = KortewegDeVries(domain=length, resolution=256, dt=2e-3, dtype=F64)
    (x,) = s.grid.coordinates()
    u0 = kdv_soliton(x, 0.0, kappa, 10.0, length)[None, None]
    t = 2.5  # travels 4 * kappa^2 * t = 10 length units
    u = s.repeat(u0, 1250)
    ue = kdv_soliton(x, t, kappa, 10.0, length)
    assert (u[0, 0] - ue).abs().max() < 1e-4
    dx = length / 256
    assert abs(float(u.sum() - u0.sum()) * dx) < 1e-11  # mass: exact (k = 0 mode untouched)
    momentum0 = float((u0 ** 2).sum()) * dx
    assert abs(float((u ** 2).sum()) * dx - momentum0) < 1e-6 * momentum0


def test_kdv_two_soliton_collision_phase_shifts():
    k1, k2, length, t_half, dt = 1.0, 0.6, 80.0, 5.0, 2e-3
    n = 512
    s = KortewegDeVries(domain=length, resolution=n, dt=dt, dtype=F64)
    (x,) = s.grid.coordinates()
    u0 = kdv_two_soliton(x, -t_half, k1, k2, 40.0, 40.0)
    u = s.repeat(u0[None, None], int(round(2 * t_half / dt)))[0, 0]
    assert (u - kdv_two_soliton(x, t_half, k1, k2, 40.0, 40.0)).abs().max() < 1e-5

    def peak(field, lo, hi, refine=64):
        fine = torch.fft.irfft(torch.fft.rfft(field), n=refine * n) * refine
        xf = torch.arange(refine * n, dtype=F64) * length / (refine * n)
        inside = (xf > lo) & (xf < hi)
        return float(xf[torch.argmax(torch.where(inside, fine, torch.full_like(fine, -1e9)))])

    fast_before, slow_before = peak(u0, 10, 30), peak(u0, 30, 40)
    fast_after, slow_after = peak(u, 52, 70), peak(u, 38, 50)
    shift_fast = fast_after - fast_before - 4 * k1 ** 2 * 2 * t_half
    shift_slow = slow_after - slow_before - 4 * k2 ** 2 * 2 * t_half
    log_ratio = math.log((k1 + k2) / (k1 - k2))
    assert shift_fast == pytest.approx(log_ratio / k1, abs=2e-3)  # +1.386
    assert shift_slow == pytest.approx(-log_ratio / k2, abs=2e-3)  # -2.310


def test_taylor_green_vortex_decays_exactly():
    nu = 0.02
    s = NavierStokesVorticity(viscosity=nu, resolution=32, dt=0.05, dtype=F64)
    x, y = s.grid.coordinates()
    w0 = (2 * torch.sin(x) * torch.sin(y))[None, None]
    w = s.repeat(w0, 20)
    assert torch.allclose(w, w0 * math.exp(-2 * nu * 1.0), atol=1e-12)
    vel = s.velocity(w0)
    assert torch.allclose(vel[0, 0], torch.sin(x) * torch.cos(y), atol=1e-12)
    assert torch.allclose(vel[0, 1], -torch.cos(x) * torch.sin(y), atol=1e-12)


def test_kolmogorov_laminar_state_is_steady():
    # the laminar Kolmogorov flow w = -A k_f cos(k_f y) / (nu k_f^2 + drag) is a steady state
    nu, drag, kf = 0.05, 0.1, 4
    s = NavierStokesVorticity(viscosity=nu, drag=drag, forcing="kolmogorov", forcing_wavenumber=kf, resolution=32,
                              dt=0.01, dtype=F64)
    _, y = s.grid.coordinates()
    w0 = (-kf * torch.cos(kf * y) / (nu * kf ** 2 + drag)).expand(32, 32)[None, None].contiguous()
    assert torch.allclose(s.repeat(w0, 50), w0, atol=1e-12)


@pytest.mark.parametrize("boundary", ["periodic", "neumann"])
def test_cahn_hilliard_conserves_mass(boundary):
    s = CahnHilliard(ndim=2, resolution=32, dt=2e-4, boundaries=boundary, dtype=F64)
    u0 = random_field(s, 2, amplitude=0.3, mean=0.1, max_wavenumber=8, seed=3)
    u = s.repeat(u0, 300)
    assert (u - u0).abs().max() > 0.05  # it did evolve
    assert torch.allclose(u.mean((2, 3)), u0.mean((2, 3)), atol=1e-13)


def _burgers(order, dt):
    return Burgers(viscosity=0.1, resolution=64, dt=dt, order=order, dtype=F64)


def _allen_cahn_neumann(order, dt):
    return AllenCahn(diffusivity=0.01, resolution=48, dt=dt, order=order, boundaries="neumann", dtype=F64)


def _fisher_dirichlet(order, dt):
    return FisherKPP(diffusivity=0.01, reactivity=2.0, resolution=48, dt=dt, order=order, boundaries="dirichlet",
                     dtype=F64)


def _initial(grid):
    """A smooth state compatible with the axis' boundary conditions (incompatible data reduce the order)."""
    (x,) = grid.coordinates()
    w = math.pi / grid.domain[0]
    if grid.boundaries[0] == "dirichlet":
        return (0.6 * torch.sin(w * x) + 0.2 * torch.sin(3 * w * x))[None, None]
    if grid.boundaries[0] == "neumann":
        return (0.5 + 0.3 * torch.cos(w * x) + 0.1 * torch.cos(3 * w * x))[None, None]
    return (0.5 + 0.3 * torch.sin(2 * w * x) + 0.1 * torch.cos(6 * w * x))[None, None]


@pytest.mark.parametrize("make, t_end, dts", [
    (_burgers, 1.0, [0.1, 0.05, 0.025, 0.0125]),
    (_allen_cahn_neumann, 2.0, [0.2, 0.1, 0.05, 0.025]),
    (_fisher_dirichlet, 1.0, [0.1, 0.05, 0.025, 0.0125]),
], ids=["burgers-periodic", "allen_cahn-neumann", "fisher-dirichlet"])
def test_temporal_convergence_orders(make, t_end, dts):
    ref = make(4, dts[-1] / 8)
    u0 = _initial(ref.grid)
    u_ref = ref.repeat(u0, int(round(t_end / ref.dt)))
    for order in (1, 2, 3, 4):
        errors = []
        for dt in dts:
            s = make(order, dt)
            errors.append(float((s.repeat(u0, int(round(t_end / dt))) - u_ref).abs().max()))
        p = empirical_order(dts, errors)
        assert abs(p - order) < 0.3, (order, p, errors)
