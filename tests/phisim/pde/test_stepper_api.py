"""The stepper's interface: custom equations, shapes, dtypes, errors, gradients, compilation, the registry."""

from __future__ import annotations

import math

import pytest
import torch

from phisim.errors import BoundaryError, NonFiniteError, ParameterError, PhisimError, ShapeError
from phisim.pde import (
    EQUATIONS,
    Advection,
    Burgers,
    Diffusion,
    ETDRKStepper,
    FisherKPP,
    GrayScott,
    KuramotoSivashinsky,
    SpectralGrid,
    make_stepper,
    phi_functions,
    random_field,
)

F64 = torch.float64


def test_phi_functions_accurate_near_zero_and_far():
    z = torch.tensor([0.0, 1e-10, -1e-6, -0.5, -5.0, -1e4, 3.0, 2j, -20 + 50j], dtype=torch.complex128)
    phi = phi_functions(z, 3)
    # Taylor series near zero: phi_k(0) = 1/k!
    assert torch.allclose(phi[1:, 0], torch.tensor([1.0, 0.5, 1 / 6], dtype=torch.complex128), atol=1e-15)
    assert torch.allclose(phi[3, 1].real, torch.tensor(1 / 6 + 1e-10 / 24, dtype=F64), rtol=1e-14)
    far = z[4:]
    e = torch.exp(far)
    p1 = (e - 1) / far
    p2 = (e - 1 - far) / far ** 2
    p3 = (e - 1 - far - far ** 2 / 2) / far ** 3
    for got, want in zip(phi[1:, 4:], (p1, p2, p3)):
        assert torch.allclose(got, want, rtol=1e-12, atol=0)


def test_custom_equation_in_a_few_lines_matches_builtin():
    # Fisher-KPP written by hand, both with a physical and a spectral nonlinear term
    grid = SpectralGrid(domain=1.0, resolution=64, dtype=F64)
    mine = ETDRKStepper(grid, dt=0.01, linear=lambda g: 1e-3 * g.laplacian() + 10.0,
                        nonlinear_physical=lambda u: -10.0 * u * u)
    spectral = ETDRKStepper(grid, dt=0.01, linear=lambda g: 1e-3 * g.laplacian() + 10.0,
                            nonlinear=lambda u_hat, g: g.to_spectral(-10.0 * g.to_physical(u_hat) ** 2))
    ref = FisherKPP(resolution=64, dt=0.01, dtype=F64)
    u0 = random_field(ref, 3, amplitude=0.1, mean=0.5, seed=0)
    a, b, c = mine.repeat(u0, 20), spectral.repeat(u0, 20), ref.repeat(u0, 20)
    assert torch.allclose(a, c, atol=1e-14) and torch.allclose(b, c, atol=1e-14)


@pytest.mark.parametrize("order", [1, 2, 3, 4])
@pytest.mark.parametrize("prefiltered", [False, True])
def test_nonlinear_factor_is_the_same_as_applying_it_in_the_nonlinear_term(order, prefiltered):
    # Burgers 1-D, N = -(1/2) i k F[u^2]: the factor folded into the coefficients vs applied on every evaluation
    grid = SpectralGrid(domain=2 * math.pi, resolution=64, dtype=F64)
    factor = -0.5 * grid.derivative(0)
    mask = grid.dealias_mask().to(torch.complex128)

    def square(u_hat, g):
        u = g.to_physical(u_hat * mask if prefiltered else u_hat)
        return g.to_spectral(u * u)

    folded = ETDRKStepper(grid, 0.01, lambda g: 0.05 * g.laplacian(), square, order=order,
                          prefiltered=prefiltered, nonlinear_factor=factor)
    inside = ETDRKStepper(grid, 0.01, lambda g: 0.05 * g.laplacian(), lambda u_hat, g: factor * square(u_hat, g),
                          order=order, prefiltered=prefiltered)
    u0 = random_field(inside, 2, seed=3)
    assert torch.allclose(folded.repeat(u0, 10), inside.repeat(u0, 10), rtol=0, atol=1e-13)
    assert torch.allclose(folded.nonlinear_spectral(folded.grid.to_spectral(u0)),
                          inside.nonlinear_spectral(inside.grid.to_spectral(u0)), rtol=0, atol=1e-12)
    with pytest.raises(ShapeError, match="nonlinear_factor"):
        ETDRKStepper(grid, 0.01, None, square, nonlinear_factor=torch.ones(5))


def test_batch_samples_are_independent_and_rollout_shapes():
    s = KuramotoSivashinsky(ndim=2, domain=20.0, resolution=16, dt=0.05, dtype=F64)
    u0 = random_field(s, 3, seed=1)
    u = s(u0)
    for i in range(3):
        assert torch.allclose(s(u0[i:i + 1]), u[i:i + 1], atol=1e-14)
    traj = s.rollout(u0, 6, every=2)
    assert traj.shape == (3, 4, 1, 16, 16)
    assert torch.allclose(traj[:, 0], u0) and torch.allclose(traj[:, 1], s(s(u0)), atol=1e-13)
    assert torch.allclose(s.repeat(u0, 6), traj[:, -1], atol=1e-13)


@pytest.mark.parametrize("ndim", [1, 2, 3])
def test_dims_and_float32(ndim):
    s = Burgers(ndim=ndim, viscosity=0.05, resolution=16, dt=0.01)
    s64 = Burgers(ndim=ndim, viscosity=0.05, resolution=16, dt=0.01, dtype=F64)
    u0 = random_field(s64, 2, amplitude=0.5, seed=0)
    u32 = s.repeat(u0.float(), 10)
    assert u32.dtype == torch.float32 and u32.shape == (2, ndim) + (16,) * ndim
    assert torch.allclose(u32.double(), s64.repeat(u0, 10), atol=1e-5)


def test_gray_scott_two_channels_stay_bounded():
    s = GrayScott(resolution=32, dt=1.0, dtype=F64)
    u0 = torch.cat([torch.ones(1, 1, 32, 32), torch.zeros(1, 1, 32, 32)], 1).double()
    u0[:, :, 12:20, 12:20] = torch.tensor([0.5, 0.25], dtype=F64)[:, None, None]
    u = s.repeat(u0, 200)
    assert torch.isfinite(u).all() and u.min() > -0.05 and u.max() < 1.05
    assert (u - u0).abs().max() > 0.05


def test_state_checks_raise_clear_errors():
    s = Burgers(resolution=32, dt=0.01)
    with pytest.raises(ShapeError, match=r"\(B, 1, 32\)"):
        s(torch.zeros(1, 32))
    with pytest.raises(ShapeError):
        s(torch.zeros(2, 1, 16))
    with pytest.raises(ShapeError):
        s(torch.zeros(2, 2, 32))
    with pytest.raises(ParameterError, match="dtype"):
        s(torch.zeros(2, 1, 32, dtype=F64))
    with pytest.raises(ShapeError):
        s([0.0] * 32)
    checked = ETDRKStepper(s.grid, 0.01, lambda g: g.laplacian(), check_finite=True)
    with pytest.raises(NonFiniteError):
        checked(torch.full((1, 1, 32), float("nan")))


@pytest.mark.parametrize("build, error", [
    (lambda: make_stepper("navier_stokes_3d"), ParameterError),
    (lambda: make_stepper("diffusion", order=4), ParameterError),
    (lambda: make_stepper("kolmogorov", viscosty=1e-3), ParameterError),
    (lambda: make_stepper("burgers", viscosity=0.0), ParameterError),
    (lambda: make_stepper("burgers", viscosity=-1.0), ParameterError),
    (lambda: make_stepper("burgers", viscosity=float("nan")), ParameterError),
    (lambda: make_stepper("diffusion", domain=-2.0), ParameterError),
    (lambda: make_stepper("diffusion", domain=0.0), ParameterError),
    (lambda: make_stepper("kdv", dt=float("nan")), ParameterError),
    (lambda: make_stepper("kdv", dt=0.0), ParameterError),
    (lambda: make_stepper("kdv", dt=-0.1), ParameterError),
    (lambda: make_stepper("burgers", order=5), ParameterError),
    (lambda: make_stepper("allen_cahn", reactivity=float("inf")), ParameterError),
    (lambda: make_stepper("advection", boundaries="dirichlet"), BoundaryError),
    (lambda: make_stepper("kdv", boundaries="neumann"), BoundaryError),
    (lambda: make_stepper("burgers", boundaries="dirichlet"), BoundaryError),
    (lambda: make_stepper("navier_stokes", boundaries=("periodic", "neumann")), BoundaryError),
    (lambda: make_stepper("diffusion", boundaries="robin"), BoundaryError),
    # a user-defined odd operator on a wall axis: not diagonal in the sine basis
    (lambda: ETDRKStepper(SpectralGrid(1.0, 16, boundaries="dirichlet"), 0.1, lambda g: g.wavenumbers[0] ** 3),
     BoundaryError),
    # growth so fast that exp(dt L) overflows float32 / the contour cannot be evaluated
    (lambda: FisherKPP(reactivity=1e3, dt=1.0), ParameterError),
    (lambda: FisherKPP(reactivity=1e3, dt=1.0, dtype=F64), ParameterError),
    (lambda: ETDRKStepper(SpectralGrid(1.0, 8), 0.1, lambda g: g.laplacian(), nonlinear_physical=lambda u: u,
                          order=0), ParameterError),
    (lambda: ETDRKStepper(SpectralGrid(1.0, 8), 0.1, torch.zeros(3, 5)), ShapeError),
    (lambda: ETDRKStepper(SpectralGrid(1.0, 8), 0.1, lambda g: g.laplacian() * float("nan")), ParameterError),
    (lambda: ETDRKStepper(SpectralGrid(1.0, 8), 0.1, None, contour_points=4), ParameterError),
    (lambda: ETDRKStepper(SpectralGrid(1.0, 8), 0.1, None, dealias=0.0), ParameterError),
])
def test_bad_settings_raise_phisim_errors(build, error):
    with pytest.raises(error) as info:
        build()
    assert isinstance(info.value, PhisimError)
    assert str(info.value)


def test_unknown_equation_lists_the_known_ones():
    with pytest.raises(ParameterError, match="kuramoto_sivashinsky"):
        make_stepper("kuramoto")
    assert isinstance(make_stepper("Kuramoto-Sivashinsky", resolution=32), KuramotoSivashinsky)
    assert set(EQUATIONS) >= {"advection", "diffusion", "dispersion", "hyper_diffusion", "wave", "burgers", "kdv",
                              "kuramoto_sivashinsky", "allen_cahn", "cahn_hilliard", "fisher_kpp", "swift_hohenberg",
                              "gray_scott", "navier_stokes", "kolmogorov", "decaying_turbulence"}


@pytest.mark.parametrize("name, kwargs", [
    ("kuramoto_sivashinsky", dict(domain=22.0, resolution=16, dt=0.1)),
    ("burgers", dict(ndim=2, resolution=8, dt=0.01, viscosity=0.05)),
    ("allen_cahn", dict(resolution=12, dt=0.05, boundaries="neumann", diffusivity=0.01)),
    ("gray_scott", dict(ndim=1, resolution=8, dt=0.5, boundaries="dirichlet")),
    ("navier_stokes", dict(resolution=8, dt=0.01)),
    ("kuramoto_sivashinsky", dict(ndim=2, domain=10.0, resolution=8, dt=0.05)),
])
def test_gradcheck_one_step_float64(name, kwargs):
    s = make_stepper(name, dtype=F64, **kwargs)
    u0 = random_field(s, 1, amplitude=0.5, mean=0.3, seed=0).requires_grad_(True)
    assert torch.autograd.gradcheck(s, (u0,), eps=1e-6, atol=1e-7)


def test_fullgraph_trace_no_graph_breaks():
    s = KuramotoSivashinsky(domain=22.0, resolution=32, dt=0.25)
    u0 = random_field(s, 2, seed=0)
    compiled = torch.compile(s, fullgraph=True, backend="eager")
    assert torch.allclose(compiled(u0), s(u0), atol=1e-6)
    walls = Diffusion(ndim=2, resolution=8, boundaries=("neumann", "dirichlet"))
    compiled = torch.compile(walls, fullgraph=True, backend="eager")
    u1 = torch.randn(1, 1, 8, 8)
    assert torch.allclose(compiled(u1), walls(u1), atol=1e-6)


@pytest.mark.slow
def test_inductor_compile_matches_eager():
    s = FisherKPP(ndim=2, resolution=32, boundaries=("neumann", "periodic"))
    u0 = random_field(s, 2, amplitude=0.1, mean=0.5, seed=0)
    compiled = torch.compile(s, fullgraph=True)
    assert torch.allclose(compiled(u0), s(u0), atol=1e-5)


def test_advection_nyquist_and_mean_untouched():
    s = Advection(resolution=16, dt=0.1, dtype=F64)
    u0 = torch.ones(1, 1, 16, dtype=F64) * 2.0
    assert torch.allclose(s.repeat(u0, 5), u0)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
@pytest.mark.cuda
def test_cuda_matches_cpu():
    cpu = KuramotoSivashinsky(domain=22.0, resolution=64, dt=0.25, dtype=F64)
    gpu = KuramotoSivashinsky(domain=22.0, resolution=64, dt=0.25, dtype=F64, device="cuda")
    u0 = random_field(cpu, 2, seed=0)
    assert torch.allclose(gpu.repeat(u0.cuda(), 20).cpu(), cpu.repeat(u0, 20), atol=1e-10)
    with pytest.raises(ParameterError, match="device"):
        cpu(u0.cuda())


def test_random_field_statistics_and_checks():
    s = GrayScott(ndim=2, resolution=16)
    u = random_field(s, 4, amplitude=0.2, mean=[1.0, 0.0], seed=0)
    assert u.shape == (4, 2, 16, 16)
    assert torch.allclose(u.mean((2, 3)), torch.tensor([1.0, 0.0]).expand(4, 2), atol=1e-6)
    assert torch.allclose(u.std((2, 3)), torch.full((4, 2), 0.2), atol=1e-5)
    with pytest.raises(ParameterError):
        random_field(s, 0)
    with pytest.raises(ParameterError):
        random_field(s, 1, mean=[1.0, 2.0, 3.0])
    assert math.isfinite(float(random_field(Diffusion(boundaries="dirichlet"), 1, seed=1).sum()))
