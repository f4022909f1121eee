"""Tests of inverse.physgrad: theorem 1, scale invariance, Newton steps of quadratic losses, the Function."""

from __future__ import annotations

import math

import pytest
import torch

from inverse.local_solvers import GradientStepSolver, NewtonSolver, SolverOperator
from inverse.nets import MLP
from inverse.operators import ScaleToy, Sine, SquareToy
from inverse.physgrad import (
    FourierTransform,
    QuadraticLoss,
    physgrad,
    physical_gradient_loss,
    physical_update,
)
from phisim.errors import NonFiniteError, ParameterError, ShapeError

F64 = torch.float64


def _nonlinear(x: torch.Tensor) -> torch.Tensor:
    """A nonlinear, coupled 2 -> 3 forward process (sample-independent)."""
    return torch.stack(
        [
            torch.sin(2 * x[:, 0]) * x[:, 1],
            x[:, 0] ** 2 - torch.exp(x[:, 1] / 2),
            torch.tanh(x[:, 0] * x[:, 1]),
        ],
        dim=-1,
    )


def _net_and_data(seed: int = 0):
    torch.manual_seed(seed)
    net = MLP([3, 8, 2], "tanh").to(F64)
    y_star = torch.randn(6, 3, dtype=F64)
    return net, y_star


def _grads(net, loss):
    net.zero_grad()
    loss.backward()
    return torch.cat([p.grad.reshape(-1) for p in net.parameters()])


# ------------------------------------------------------------------------------------------- theorem 1


@pytest.mark.parametrize("reduction", ["sum", "mean"])
def test_theorem1_gradient_step_inverse_equals_backprop(reduction):
    net, y_star = _net_and_data()
    op = SolverOperator(_nonlinear, GradientStepSolver(step_size=1.0))
    x = net(y_star)
    per_sample = 0.5 * ((_nonlinear(x) - y_star) ** 2).sum(dim=1)
    g_backprop = _grads(net, per_sample.sum() if reduction == "sum" else per_sample.mean())
    g_pg = _grads(net, physical_gradient_loss(net(y_star), y_star, op, eta=1.0, reduction=reduction))
    assert g_backprop.abs().max() > 1e-3  # a non-trivial gradient
    torch.testing.assert_close(g_pg, g_backprop, rtol=1e-12, atol=1e-14)


def test_theorem1_through_the_autograd_function():
    net, y_star = _net_and_data(1)
    op = SolverOperator(_nonlinear, GradientStepSolver(step_size=1.0))
    g_backprop = _grads(net, 0.5 * ((_nonlinear(net(y_star)) - y_star) ** 2).sum())
    g_fn = _grads(net, 0.5 * ((physgrad(op)(net(y_star)) - y_star) ** 2).sum())
    torch.testing.assert_close(g_fn, g_backprop, rtol=1e-12, atol=1e-14)
    # With a batch-mean loss and grad_scale = B the result is still the ordinary gradient.
    b = y_star.shape[0]
    g_backprop = _grads(net, 0.5 * ((_nonlinear(net(y_star)) - y_star) ** 2).sum(dim=1).mean())
    g_fn = _grads(net, 0.5 * ((physgrad(op, grad_scale=b)(net(y_star)) - y_star) ** 2).sum(dim=1).mean())
    torch.testing.assert_close(g_fn, g_backprop, rtol=1e-12, atol=1e-14)


def test_theorem1_does_not_hold_for_a_newton_inverse():
    """Control: a higher-order local inverse gives a different (physical) gradient."""
    net, y_star = _net_and_data()
    op = SolverOperator(_nonlinear, NewtonSolver(saddle_free=True))
    g_backprop = _grads(net, 0.5 * ((_nonlinear(net(y_star)) - y_star) ** 2).sum())
    g_pg = _grads(net, physical_gradient_loss(net(y_star), y_star, op))
    assert (g_pg - g_backprop).norm() > 1e-2 * g_backprop.norm()


# ------------------------------------------------------------------------------------------- scale invariance


def _trajectory(alpha: float, method: str, steps: int = 12) -> torch.Tensor:
    x = torch.tensor([[3.0, 3.0]], dtype=F64, requires_grad=True)
    op = ScaleToy(alpha)
    target = torch.zeros(1, 2, dtype=F64)
    opt = torch.optim.SGD([x], lr=1.0 if method == "pg" else 1e-5)
    path = [x.detach().clone()]
    for _ in range(steps):
        opt.zero_grad()
        if method == "pg":
            loss = physical_gradient_loss(x, target, op, eta=0.3)
        else:
            loss = (op(x) ** 2).sum()  # L = |P(x)|^2
        loss.backward()
        opt.step()
        path.append(x.detach().clone())
    return torch.cat(path)


def test_pg_trajectory_is_scale_invariant_and_gd_is_not():
    pg = {a: _trajectory(a, "pg") for a in (1.0, 10.0, 100.0)}
    gd = {a: _trajectory(a, "gd") for a in (1.0, 10.0, 100.0)}
    for a in (10.0, 100.0):
        torch.testing.assert_close(pg[a], pg[1.0], rtol=1e-14, atol=1e-14)
        assert (gd[a] - gd[1.0]).abs().max() > 0.05
    # PG with eta: x_k = (1 - eta)^k x_0 exactly; GD's x2 shrinks by (1 - 2 lr alpha^2) per step.
    torch.testing.assert_close(pg[1.0][-1], 0.7**12 * torch.tensor([3.0, 3.0], dtype=F64))
    torch.testing.assert_close(gd[100.0][-1, 1], 3.0 * (1 - 2e-5 * 1e4) ** 12 * torch.ones((), dtype=F64))


# ------------------------------------------------------------------------------------- Newton steps in y


def test_l2_newton_step():
    y = torch.randn(4, 5, dtype=F64)
    t = torch.randn(4, 5, dtype=F64)
    torch.testing.assert_close(QuadraticLoss().newton_step(y, t, 0.3), 0.3 * (t - y))
    torch.testing.assert_close(QuadraticLoss().value(y, t), 0.5 * ((y - t) ** 2).sum(dim=1))


def _dense_newton_step(loss: QuadraticLoss, y: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """Reference: -H^+ grad with the Hessian of the loss from autograd (one sample, flattened)."""

    def f(v):
        return loss.value(v.reshape(y.shape), t).sum()

    v = y.reshape(-1)
    hess = torch.autograd.functional.hessian(f, v)
    grad = torch.autograd.functional.jacobian(f, v)
    return -(torch.linalg.pinv(hess, rtol=1e-10, hermitian=True) @ grad).reshape(y.shape)


def test_weighted_newton_step_matches_dense_newton():
    g = torch.Generator().manual_seed(4)
    y = torch.randn(1, 6, 5, dtype=F64, generator=g)
    t = torch.randn(1, 6, 5, dtype=F64, generator=g)
    # Elementwise weights with zeros: the Newton step leaves unweighted entries alone.
    w = torch.rand(6, 5, dtype=F64, generator=g) + 0.1
    w[0, :] = 0.0
    loss = QuadraticLoss(weights=w)
    step = loss.newton_step(y, t)
    torch.testing.assert_close(step, _dense_newton_step(loss, y, t), rtol=1e-9, atol=1e-10)
    assert torch.equal(step[0, 0], torch.zeros(5, dtype=F64))
    # Fourier weights w(|k|) with the highest frequencies ignored (as in E5's low-pass weighting).
    kx = torch.fft.fftfreq(6, dtype=F64)[:, None]
    ky = torch.fft.fftfreq(5, dtype=F64)[None, :]
    k2 = kx**2 + ky**2
    wk = torch.exp(-0.5 * k2 * 10.0) * (k2 < 0.2)
    loss = QuadraticLoss(weights=wk, transform=FourierTransform(2))
    step = loss.newton_step(y, t)
    torch.testing.assert_close(step, _dense_newton_step(loss, y, t), rtol=1e-9, atol=1e-10)
    assert not torch.allclose(step, t - y)
    # Positive weights everywhere: the full Newton step reaches the target, whatever the weights.
    loss = QuadraticLoss(weights=torch.exp(-0.5 * k2 * 10.0), transform=FourierTransform(2))
    torch.testing.assert_close(loss.newton_step(y, t), t - y, rtol=1e-12, atol=1e-12)
    # Damping shrinks the step mode by mode: w / (w + lambda).
    damped = QuadraticLoss(weights=w, damping=1.0).newton_step(y, t)
    torch.testing.assert_close(damped, (t - y) * w / (w + 1.0))


def test_fourier_transform_is_unitary():
    y = torch.randn(3, 8, 6, dtype=F64)
    ft = FourierTransform(2)
    torch.testing.assert_close(ft.inverse(ft(y)), y)
    torch.testing.assert_close((ft(y).abs() ** 2).sum(), (y**2).sum())


# ------------------------------------------------------------------------------------------- PG usage


def test_exact_inverse_with_eta_one_reaches_target_in_one_sgd_step():
    a = torch.tensor([1.0, 3.0, 8.0], dtype=F64)
    op = Sine(a)
    x = torch.tensor([[0.5], [0.9], [-2.0]], dtype=F64, requires_grad=True)
    target = torch.full((3, 1), -1.0, dtype=F64)
    opt = torch.optim.SGD([x], lr=1.0)
    loss = physical_gradient_loss(x, target, op, eta=1.0)
    loss.backward()
    opt.step()
    torch.testing.assert_close(op(x.detach()), target, rtol=0, atol=1e-12)
    x_tilde, y = physical_update(x.detach() * 1.01, target, op)
    torch.testing.assert_close(op(x_tilde), target, rtol=0, atol=1e-12)


def test_physgrad_function_with_exact_inverse():
    op = SquareToy()
    x = torch.tensor([[1.0, 2.0], [-0.5, -1.0]], dtype=F64, requires_grad=True)
    y_star = torch.tensor([[0.0, 1.0], [1.0, 4.0]], dtype=F64)
    y = physgrad(op, eta=1.0)(x)
    torch.testing.assert_close(y, op(x.detach()))
    (0.5 * ((y - y_star) ** 2).sum()).backward()
    # x - P^-1(y*; x): the closest preimage of y* on each sample's side.
    expected = x.detach() - torch.tensor([[0.0, 1.0], [1.0, -2.0]], dtype=F64)
    torch.testing.assert_close(x.grad, expected)


def test_reduction_mean_is_sum_over_batch():
    op = SquareToy()
    x = torch.tensor([[1.0, 2.0], [-0.5, -1.0]], dtype=F64)
    t = torch.zeros(2, 2, dtype=F64)
    s = physical_gradient_loss(x, t, op, eta=0.5, reduction="sum")
    m = physical_gradient_loss(x, t, op, eta=0.5, reduction="mean")
    torch.testing.assert_close(s, 2 * m)


# ------------------------------------------------------------------------------------------- errors


def test_errors():
    op = SquareToy()
    x = torch.zeros(2, 2, dtype=F64)
    t = torch.zeros(2, 2, dtype=F64)
    for eta in (0.0, -1.0, math.nan, math.inf, "a"):
        with pytest.raises(ParameterError):
            physical_gradient_loss(x, t, op, eta=eta)
        with pytest.raises(ParameterError):
            physgrad(op, eta=eta)
    with pytest.raises(ParameterError):
        physgrad(op, grad_scale=0.0)
    with pytest.raises(ParameterError):
        physgrad(op, grad_scale="b")
    with pytest.raises(ParameterError):
        physical_gradient_loss(x, t, op, reduction="max")
    with pytest.raises(ShapeError):
        physical_gradient_loss(x, torch.zeros(2, 3, dtype=F64), op)
    with pytest.raises(ShapeError):
        physical_gradient_loss(x, torch.zeros(3, 2, dtype=F64), op)
    with pytest.raises(NonFiniteError):
        physical_gradient_loss(torch.full((2, 2), math.nan, dtype=F64), t, op)
    with pytest.raises(NonFiniteError):
        physical_gradient_loss(x, torch.full((2, 2), math.inf, dtype=F64), op)
    with pytest.raises(ParameterError):
        QuadraticLoss(weights=-torch.ones(2))
    with pytest.raises(ParameterError):
        QuadraticLoss(transform=lambda v: v)  # no inverse
    with pytest.raises(ParameterError):
        QuadraticLoss().newton_step(x, t, eta=0.0)
