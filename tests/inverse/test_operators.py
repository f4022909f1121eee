"""Tests of inverse.operators: the E1 toys and the E2 sine pair (gradients, local inverses, errors)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from inverse.operators import Heat, PhysicsOperator, Poisson, ScaleToy, Sine, SquareToy
from phisim.errors import NonFiniteError, ParameterError, PhisimError, ShapeError
from phisim.solvers.linalg import Solve

F64 = torch.float64


def _gen(seed: int = 0) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


# ------------------------------------------------------------------------------------------- forward


@pytest.mark.parametrize("op", [ScaleToy(1.0), ScaleToy(10.0), SquareToy()])
def test_gradcheck_toys(op):
    x = torch.randn(3, 2, dtype=F64, generator=_gen(1), requires_grad=True)
    assert torch.autograd.gradcheck(op.forward, (x,))
    assert torch.autograd.gradgradcheck(op.forward, (x,))


def test_gradcheck_sine_per_sample_a():
    a = torch.tensor([0.5, 1.0, 7.3], dtype=F64)
    x = torch.tensor([[0.4], [-1.3], [2.2]], dtype=F64, requires_grad=True)
    op = Sine(a)
    assert torch.autograd.gradcheck(op.forward, (x,))
    assert torch.autograd.gradgradcheck(op.forward, (x,))
    np.testing.assert_allclose(op(x).detach().numpy()[:, 0], np.sin(a.numpy() / x.detach().numpy()[:, 0]))


def test_forward_values():
    x = torch.tensor([[3.0, -2.0]], dtype=F64)
    assert torch.equal(ScaleToy(10.0)(x), torch.tensor([[3.0, -20.0]], dtype=F64))
    assert torch.equal(SquareToy()(x), torch.tensor([[3.0, 4.0]], dtype=F64))


def test_forward_follows_dtype():
    x = torch.tensor([[0.3], [0.9]], dtype=torch.float32)
    assert Sine(torch.tensor([1.0, 2.0], dtype=F64))(x).dtype == torch.float32
    assert SquareToy()(torch.ones(2, 2, dtype=torch.float32)).dtype == torch.float32


# ------------------------------------------------------------------------------------------- E1 inverses


def test_scale_toy_inverse_exact():
    op = ScaleToy(100.0)
    x = torch.randn(5, 2, dtype=F64, generator=_gen(2))
    x0 = x + 0.1
    torch.testing.assert_close(op.local_inverse(op(x), x0), x, rtol=1e-15, atol=1e-15)


def test_square_toy_inverse_picks_the_side_of_x0():
    op = SquareToy()
    x = torch.tensor([[1.0, 2.0], [0.5, -1.5], [-3.0, 0.25]], dtype=F64)
    y = op(x)
    torch.testing.assert_close(op.local_inverse(y, x + 0.1), x, rtol=0, atol=1e-15)
    # Conditioned on a guess with the opposite sign of x2 the other preimage (x1, -x2) is returned.
    flipped = x * torch.tensor([1.0, -1.0], dtype=F64)
    torch.testing.assert_close(op.local_inverse(y, flipped + 0.01), flipped, rtol=0, atol=1e-15)
    # Both are preimages; the returned one is the closer to x0.
    x0 = torch.tensor([[0.0, -0.1]], dtype=F64)
    got = op.local_inverse(torch.tensor([[2.0, 4.0]], dtype=F64), x0)
    assert torch.equal(got, torch.tensor([[2.0, -2.0]], dtype=F64))


def test_square_toy_negative_target_gives_zero():
    x0 = torch.tensor([[0.0, 3.0]], dtype=F64)
    got = SquareToy().local_inverse(torch.tensor([[1.0, -4.0]], dtype=F64), x0)
    assert torch.equal(got, torch.tensor([[1.0, 0.0]], dtype=F64))


# ------------------------------------------------------------------------------------------- sine


def _all_solutions(a: float, t: float, x_lo: float, x_hi: float) -> np.ndarray:
    """All x in [x_lo, x_hi] with sin(a/x) = t, enumerated over phases (brute force)."""
    th1 = math.asin(t)
    sols = []
    for theta in (th1, math.pi - th1):
        for n in range(-4000, 4000):
            u = theta + 2 * math.pi * n
            if u != 0 and x_lo <= a / u <= x_hi:
                sols.append(a / u)
    return np.array(sols)


def test_sine_inverse_recovers_x_from_nearby_guess():
    a = torch.tensor([0.1, 1.0, 3.0, 10.0, 5.0], dtype=F64)
    x = torch.tensor([[0.05], [0.3], [-0.8], [4.0], [-20.0]], dtype=F64)
    op = Sine(a)
    y = op(x)
    got = op.local_inverse(y, x * (1 + 1e-3))
    torch.testing.assert_close(got, x, rtol=1e-12, atol=0)


def test_sine_inverse_is_the_closest_solution():
    g = np.random.default_rng(3)
    n = 300
    a = g.uniform(0.1, 10.1, n)
    x0 = g.choice([-1, 1], n) * np.exp(g.uniform(np.log(0.02), np.log(30.0), n))
    t = g.uniform(-1, 1, n)
    t[:100] = -1.0  # the E2 target
    op = Sine(torch.tensor(a))
    got = op.local_inverse(torch.tensor(t)[:, None], torch.tensor(x0)[:, None])[:, 0].numpy()
    np.testing.assert_allclose(np.sin(a / got), t, atol=1e-9)
    for i in range(n):
        sols = _all_solutions(a[i], t[i], -1e3, 1e3)
        best = sols[np.argmin(np.abs(sols - x0[i]))]
        assert abs(got[i] - x0[i]) <= abs(best - x0[i]) + 1e-12, (a[i], x0[i], t[i], got[i], best)


def test_sine_minimum_matches_paper_formula_and_outermost_minima():
    a = 1.0
    # Away from the outermost minima, with x0 at a minimum, the paper's rounding gives x0 itself.
    for n in (0, 1, 5, -2, -7):
        x_n = a / (1.5 * math.pi + 2 * math.pi * n)
        n_paper = round(a / (2 * math.pi * x_n) - 0.75)
        assert n_paper == n
        x0 = torch.tensor([[x_n * 1.01]], dtype=F64)
        got = Sine(a).local_inverse(torch.tensor([[-1.0]], dtype=F64), x0)
        assert got.item() == pytest.approx(x_n, rel=1e-13)
    # Far out on the positive side the closest minimum is the outermost positive one, n = 0 (rounding
    # alone would give n = -1, a negative x).
    for x0 in (2 * a / math.pi * 1.01, 10.0, 1e6):
        assert round(a / (2 * math.pi * x0) - 0.75) == -1
        got = Sine(a).local_inverse(torch.tensor([[-1.0]], dtype=F64), torch.tensor([[x0]], dtype=F64))
        assert got.item() == pytest.approx(a / (1.5 * math.pi), rel=1e-14)
    # Far out on the negative side: the outermost negative minimum x = -2a/pi (n = -1).
    got = Sine(a).local_inverse(torch.tensor([[-1.0]], dtype=F64), torch.tensor([[-1e6]], dtype=F64))
    assert got.item() == pytest.approx(-2 * a / math.pi, rel=1e-14)


def test_sine_inverse_edge_cases():
    op = Sine(2.0)
    # Targets beyond [-1, 1] are clamped: the result attains the closest reachable value.
    got = op.local_inverse(torch.tensor([[-1.5], [3.0]], dtype=F64), torch.tensor([[0.4], [0.4]], dtype=F64))
    np.testing.assert_allclose(torch.sin(2.0 / got).numpy()[:, 0], [-1.0, 1.0], atol=1e-12)
    # x0 = 0 returns a finite solution next to 0.
    got = op.local_inverse(torch.tensor([[0.3]], dtype=F64), torch.tensor([[0.0]], dtype=F64))
    assert torch.isfinite(got).all() and abs(got.item()) < 1e-6
    # float32 follows the input.
    got = op.local_inverse(torch.tensor([[-1.0]]), torch.tensor([[0.5]]))
    assert got.dtype == torch.float32


def test_sine_select():
    op = Sine(torch.tensor([1.0, 2.0, 3.0]))
    sub = op.select(slice(1, 2))
    assert torch.equal(sub.a, torch.tensor([2.0]))
    assert Sine(2.0).select(slice(0, 1)).a.item() == 2.0


# ------------------------------------------------------------------------------------------- errors


def test_errors_derive_from_phisim_error():
    op = SquareToy()
    x0 = torch.zeros(2, 2, dtype=F64)
    with pytest.raises(ShapeError, match="y_target has shape"):
        op.local_inverse(torch.zeros(2, 3, dtype=F64), x0)
    with pytest.raises(ShapeError, match="batch sizes"):
        op.local_inverse(torch.zeros(3, 2, dtype=F64), x0)
    with pytest.raises(ShapeError, match="y_target has shape"):
        op.local_inverse(torch.zeros(2, 3, dtype=F64), x0, y0=torch.zeros(2, 2, dtype=F64))
    with pytest.raises(NonFiniteError):
        op.local_inverse(torch.tensor([[0.0, math.nan], [0.0, 0.0]], dtype=F64), x0)
    with pytest.raises(NonFiniteError):
        op.local_inverse(torch.zeros(2, 2, dtype=F64), torch.tensor([[math.inf, 0.0], [0.0, 0.0]], dtype=F64))
    with pytest.raises(NonFiniteError):
        op.forward(torch.tensor([[math.nan, 0.0]], dtype=F64))
    with pytest.raises(ShapeError):
        op.forward(torch.zeros(2, 3, dtype=F64))
    with pytest.raises(ParameterError):
        ScaleToy(0.0)
    with pytest.raises(ParameterError):
        ScaleToy(math.inf)
    with pytest.raises(ParameterError):
        Sine(torch.tensor([1.0, 0.0]))
    with pytest.raises(ShapeError):
        Sine(torch.tensor([1.0, 2.0]))(torch.ones(3, 1))
    assert issubclass(ShapeError, PhisimError) and issubclass(NonFiniteError, PhisimError)


def test_check_inputs_can_be_disabled():
    op = SquareToy()
    op.check_inputs = False
    assert torch.isnan(op.forward(torch.tensor([[math.nan, 0.0]]))).any()


def test_base_class_is_abstract():
    with pytest.raises(NotImplementedError):
        PhysicsOperator().forward(torch.zeros(1, 2))


# ------------------------------------------------------------------------------------------- E3 Poisson


def _smooth_field(b: int, shape: tuple[int, int], seed: int) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return torch.randn(b, *shape, dtype=F64, generator=g)


def test_poisson_forward_solves_the_stencil_and_inverse_recovers_x():
    from phisim.solvers.poisson import spectral_poisson_solve, stencil_laplacian

    x = _smooth_field(3, (32, 24), 0)
    op = Poisson()  # E3: CG, rtol 1e-5, zero Dirichlet
    y = op(x)
    ref = spectral_poisson_solve(x, 1.0, "dirichlet")
    assert ((y - ref).norm() / ref.norm()) < 1e-4
    # The residual of the CG solve is within its tolerance: |lap y - x| <= 1e-5 |x| per sample.
    res = (stencil_laplacian(y, 1.0, "dirichlet") - x).flatten(1).norm(dim=1)
    assert (res <= 1e-5 * x.flatten(1).norm(dim=1) * (1 + 1e-9)).all()
    x0 = x + 0.3 * _smooth_field(3, (32, 24), 1)
    got = op.local_inverse(y, x0)
    # The inverse is exact for the discrete forward: recovery to the CG tolerance.
    assert ((got - x).flatten(1).norm(dim=1) <= 1e-5 * x.flatten(1).norm(dim=1) * (1 + 1e-9)).all()
    tight = Poisson(solve=Solve(rtol=1e-12), preconditioner="spectral")
    torch.testing.assert_close(tight.local_inverse(tight(x), x0), x, rtol=0, atol=1e-9)


def test_poisson_periodic_is_zero_mean():
    x = _smooth_field(2, (16, 16), 2)
    x = x - x.mean(dim=(1, 2), keepdim=True)
    op = Poisson(kinds="periodic", solve=Solve(rtol=1e-12))
    y = op(x)
    assert y.mean(dim=(1, 2)).abs().max() < 1e-12
    torch.testing.assert_close(op.local_inverse(y, torch.zeros_like(x)), x, rtol=0, atol=1e-9)


def test_poisson_gradcheck_implicit_gradient():
    op = Poisson(solve=Solve(rtol=1e-13))
    x = _smooth_field(2, (6, 5), 3).requires_grad_(True)
    assert torch.autograd.gradcheck(op.forward, (x,), atol=1e-7)


def test_poisson_and_heat_accept_float32_and_compute_in_float64():
    x = _smooth_field(2, (64, 64), 5)
    for op in (Poisson(), Heat()):
        y32 = op(x.float())  # a float32 CG could not reach rtol 1e-5 here (precision floor)
        assert y32.dtype == torch.float32
        torch.testing.assert_close(y32, op(x).float(), rtol=1e-5, atol=1e-5)
        got = op.local_inverse(y32, x.float() + 0.01)
        assert got.dtype == torch.float32 and torch.isfinite(got).all()
    with pytest.raises(ParameterError):
        Poisson(compute_dtype=torch.int64)


def test_poisson_settings_errors():
    with pytest.raises(ParameterError):
        Poisson(preconditioner="ilu")
    with pytest.raises(ParameterError):
        Poisson(solve={"rtol": 1e-5})
    with pytest.raises(ShapeError):
        Poisson()(torch.zeros(3, dtype=F64))


# ------------------------------------------------------------------------------------------- E4 heat


def _rectangles(b: int, seed: int) -> torch.Tensor:
    from phisim.grid import Grid
    from phisim.simulate.noise import random_rectangles

    return random_rectangles(Grid((64, 64)), b, seed=seed, dtype=F64).values


def test_heat_forward_matches_mode_decay_and_gradcheck():
    op = Heat()
    i = torch.arange(64, dtype=F64)
    mode = torch.cos(2 * math.pi * 3 * i / 64)[:, None] * torch.ones(1, 64, dtype=F64)
    y = op(mode[None])
    decay = math.exp(-4 * math.pi**2 * (3 / 64) ** 2 * 8)
    torch.testing.assert_close(y[0], mode * decay, rtol=1e-12, atol=1e-14)
    x = _smooth_field(2, (8, 6), 4).requires_grad_(True)
    assert torch.autograd.gradcheck(Heat(nu_t=0.05).forward, (x,))


def test_heat_inverse_recovers_smooth_perturbation_exactly():
    x = _rectangles(3, 0)
    op = Heat()
    i = torch.arange(64, dtype=F64)
    d = 0.1 * torch.sin(2 * math.pi * i / 64)[:, None] * torch.cos(2 * math.pi * 2 * i / 64)[None, :]
    got = op.local_inverse(op(x), x + d)
    assert (got - x).norm() < 1e-10 * d.norm()


def test_heat_inverse_accuracy_and_stability_under_noise():
    x = _rectangles(4, 0)
    x0 = x + 0.3 * (_rectangles(4, 5) - x)
    op = Heat()
    y = op(x)
    err0 = (x0 - x).norm()
    err = (op.local_inverse(y, x0) - x).norm()
    # Edges of the rectangles are lost to diffusion; the low modes of the error are removed.
    assert err < 0.3 * err0
    g = torch.Generator().manual_seed(7)
    # Noise at the level the inverse assumes (1e-6 of the residual): the result barely changes. Noise
    # modes with P >= 0.68 are partly inverted, each amplified at most to about the prior's size, which
    # shifts the error by about 1 % (0.4 % and 1.4 % for two seeds).
    r = y - op(x0)
    noise = torch.randn(y.shape, dtype=F64, generator=g)
    y_noisy = y + 1e-6 * r.norm(dim=(1, 2), keepdim=True) / 64 * noise
    assert abs((op.local_inverse(y_noisy, x0) - x).norm() - err) < 0.05 * err
    # Noise of 1e-6 relative to the observation: bounded with the default (the prior limits the
    # amplification) and accurate with a matching noise floor; the undamped inverse explodes.
    y_noisy = y + 1e-6 * y.norm(dim=(1, 2), keepdim=True) / 64 * noise
    damped = op.local_inverse(y_noisy, x0)
    assert torch.isfinite(damped).all() and (damped - x).norm() < 3 * err0
    floored = Heat(noise_floor=1e-6).local_inverse(y_noisy, x0)
    assert (floored - x).norm() < 0.3 * err0
    amp = torch.fft.fftn(y_noisy - op(x0), dim=(1, 2))
    naive = x0 + torch.fft.ifftn(amp * torch.exp(op.exponent((64, 64), F64, "cpu")), dim=(1, 2)).real
    assert (naive - x).norm() > 1e6 * err0


def test_heat_inverse_from_zero_and_settings():
    x = _rectangles(2, 3)
    op = Heat()
    got = op.local_inverse(op(x), torch.zeros_like(x))
    mae0 = x.abs().sum(dim=(1, 2)).mean()
    assert (got - x).abs().sum(dim=(1, 2)).mean() < 0.4 * mae0
    # The mean (k = 0) is always restored exactly.
    torch.testing.assert_close(got.mean(dim=(1, 2)), x.mean(dim=(1, 2)))
    for bad in (
        lambda: Heat(nu_t=0.0),
        lambda: Heat(noise_scale=-1.0),
        lambda: Heat(signal_scale=math.inf),
        lambda: Heat(threshold=0.4),
        lambda: Heat(noise_floor=-1.0),
    ):
        with pytest.raises(ParameterError):
            bad()
