"""Tests of inverse.local_solvers: generic local inverses against the analytic ones, Jacobians, errors."""

from __future__ import annotations

import math

import pytest
import torch

from inverse.local_solvers import (
    GradientStepSolver,
    InverseGradientSolver,
    LBFGSBSolver,
    NewtonSolver,
    SolverOperator,
    batch_hessian,
    batch_jacobian,
)
from inverse.operators import ScaleToy, Sine, SquareToy
from phisim.errors import NonFiniteError, ParameterError, ShapeError

F64 = torch.float64


def _points() -> tuple[torch.Tensor, torch.Tensor]:
    x = torch.tensor([[1.0, 2.0], [0.5, -1.5], [-3.0, 0.7], [0.2, 4.0]], dtype=F64)
    x0 = x + torch.tensor([[0.1, -0.2], [-0.2, 0.15], [0.3, 0.1], [-0.1, -0.3]], dtype=F64)
    return x, x0


def _coupled(x: torch.Tensor) -> torch.Tensor:
    """A nonlinear, coupled 3 -> 2 test forward, sample-independent."""
    first = torch.sin(x[:, 0]) * x[:, 1] + x[:, 2] ** 3
    return torch.stack([first, x[:, 0] ** 2 + torch.exp(x[:, 1] / 3)], dim=-1)


# ------------------------------------------------------------------------------------------- Jacobians


def test_batch_jacobian_and_hessian_match_autograd_functional():
    x = torch.randn(3, 3, dtype=F64, generator=torch.Generator().manual_seed(0))
    t = torch.randn(3, 2, dtype=F64, generator=torch.Generator().manual_seed(1))
    jac = batch_jacobian(_coupled, x)
    g, hess = batch_hessian(_coupled, t, x)
    assert jac.shape == (3, 2, 3) and hess.shape == (3, 3, 3) and g.shape == (3, 3)
    for i in range(3):
        xi = x[i : i + 1]
        ref_j = torch.autograd.functional.jacobian(lambda z: _coupled(z)[0], xi)[:, 0, :]
        torch.testing.assert_close(jac[i], ref_j, rtol=1e-13, atol=1e-13)

        def li(z, i=i):
            return 0.5 * ((_coupled(z[None]) - t[i : i + 1]) ** 2).sum()

        ref_h = torch.autograd.functional.hessian(li, x[i])
        torch.testing.assert_close(hess[i], ref_h, rtol=1e-12, atol=1e-12)
        torch.testing.assert_close(g[i], torch.autograd.functional.jacobian(li, x[i]), rtol=1e-12, atol=1e-12)


class _OldStyleSquare(torch.autograd.Function):
    """An autograd Function without torch.func support (no setup_context): forces the loop fallback."""

    @staticmethod
    def forward(ctx, x):
        ctx.save_for_backward(x)
        return x**2

    @staticmethod
    def backward(ctx, g):
        (x,) = ctx.saved_tensors
        return 2 * x * g


def test_jacobian_falls_back_for_functions_without_torch_func_support():
    x = torch.tensor([[1.0, 2.0], [3.0, -1.0]], dtype=F64)
    jac = batch_jacobian(_OldStyleSquare.apply, x)
    torch.testing.assert_close(jac, torch.diag_embed(2 * x))
    # The inverse gradient (which needs only J) works through the fallback.
    got = InverseGradientSolver(max_iter=30)(_OldStyleSquare.apply, x**2, x + 0.1)
    torch.testing.assert_close(got, x, rtol=1e-12, atol=1e-12)


# ------------------------------------------------------------------------------------------- E1 agreement


@pytest.mark.parametrize(
    "solver",
    [NewtonSolver(max_iter=25), InverseGradientSolver(max_iter=25), LBFGSBSolver(max_iter=200)],
    ids=["newton", "inverse-gradient", "lbfgsb"],
)
@pytest.mark.parametrize("op", [SquareToy(), ScaleToy(10.0)], ids=["square", "scale"])
def test_generic_solvers_match_analytic_inverse_on_e1(solver, op):
    x, x0 = _points()
    target = op(x) * 0.7  # a target other than P(x), still reachable
    analytic = op.local_inverse(target, x0)
    got = solver(op, target, x0)
    tol = 1e-5 if isinstance(solver, LBFGSBSolver) else 1e-12
    torch.testing.assert_close(got, analytic, rtol=0, atol=tol)
    via_adapter = SolverOperator(op, solver).local_inverse(target, x0)
    torch.testing.assert_close(via_adapter, analytic, rtol=0, atol=tol)


def test_newton_and_inverse_gradient_are_exact_in_one_step_on_linear_toy():
    op = ScaleToy(100.0)
    x, x0 = _points()
    for solver in (NewtonSolver(), InverseGradientSolver()):
        torch.testing.assert_close(solver(op, op(x), x0), x, rtol=0, atol=1e-12)


def test_gradient_step_solver_formula():
    x0 = torch.tensor([[1.0, 2.0, 0.5]], dtype=F64)
    t = torch.tensor([[0.3, -0.2]], dtype=F64)
    jac = batch_jacobian(_coupled, x0)[0]
    expected = x0[0] - 0.25 * jac.T @ (_coupled(x0)[0] - t[0])
    got = GradientStepSolver(step_size=0.25)(_coupled, t, x0)
    torch.testing.assert_close(got[0], expected, rtol=1e-14, atol=1e-14)


def test_gradient_descent_converges_slowly_to_the_inverse():
    x, x0 = _points()
    got = GradientStepSolver(step_size=0.02, max_iter=2000)(SquareToy(), SquareToy()(x), x0)
    torch.testing.assert_close(got, x, rtol=0, atol=1e-6)


# ------------------------------------------------------------------------------------------- Newton variants


def test_saddle_free_newton_descends_where_plain_newton_ascends():
    def sq(x):
        return x**2

    x0 = torch.tensor([[0.1]], dtype=F64)
    t = torch.tensor([[1.0]], dtype=F64)
    g = 2 * x0 * (x0**2 - t)  # dL/dx of L = 1/2 (x^2 - t)^2
    h = 6 * x0**2 - 2 * t  # d2L/dx2, negative here: the loss is concave near x = 0
    plain = NewtonSolver()(sq, t, x0)
    free = NewtonSolver(saddle_free=True)(sq, t, x0)
    torch.testing.assert_close(plain, x0 - g / h)
    torch.testing.assert_close(free, x0 - g / h.abs())

    def loss(x):
        return 0.5 * (x**2 - t) ** 2

    assert loss(plain) > loss(x0) > loss(free)
    # Iterated, saddle-free Newton reaches the nearby root x = 1.
    iterated = NewtonSolver(max_iter=30, saddle_free=True)(sq, t, x0)
    torch.testing.assert_close(iterated, torch.ones(1, 1, dtype=F64))


def test_clipped_steps_are_bounded():
    op = Sine(torch.tensor([1.0, 1.0]))
    x0 = torch.tensor([[0.05], [0.9]], dtype=F64)
    t = torch.full((2, 1), -1.0, dtype=F64)
    for solver in (NewtonSolver(saddle_free=True, clip=0.01), InverseGradientSolver(clip=0.01)):
        step = solver(op, t, x0) - x0
        assert step.abs().max() <= 0.01 + 1e-15


def test_sine_generic_solvers_recover_nearby_solution():
    a = torch.tensor([0.5, 2.0, 7.0], dtype=F64)
    x = torch.tensor([[0.2], [-1.1], [3.0]], dtype=F64)
    op = Sine(a)
    y = op(x)
    x0 = x * (1 + 2e-3)
    for solver in (NewtonSolver(max_iter=20), InverseGradientSolver(max_iter=20), LBFGSBSolver(max_iter=100)):
        torch.testing.assert_close(solver(op, y, x0), x, rtol=1e-6, atol=0)
        # Through the adapter and its per-sample selection.
        torch.testing.assert_close(SolverOperator(op, solver).local_inverse(y, x0), x, rtol=1e-6, atol=0)


# ------------------------------------------------------------------------------------------- L-BFGS-B details


def test_lbfgsb_float32_and_per_sample_results():
    op = SquareToy()
    x, x0 = _points()
    solver = LBFGSBSolver(max_iter=100)
    got = solver(op, op(x).float(), x0.float())
    assert got.dtype == torch.float32
    torch.testing.assert_close(got, x.float(), rtol=0, atol=1e-5)
    assert len(solver.last_results) == x.shape[0]
    assert all(r.nit <= 100 for r in solver.last_results)


def test_lbfgsb_iteration_budget_and_bounds():
    op = SquareToy()
    x0 = torch.tensor([[3.0, 3.0]], dtype=F64)
    t = torch.zeros(1, 2, dtype=F64)
    solver = LBFGSBSolver(max_iter=2)
    solver(op, t, x0)
    assert solver.last_results[0].nit <= 2
    got = LBFGSBSolver(max_iter=100, bounds=(1.0, None))(op, t, x0)
    torch.testing.assert_close(got, torch.ones(1, 2, dtype=F64), rtol=0, atol=1e-8)


# ------------------------------------------------------------------------------------------- errors


def test_solver_errors():
    op = SquareToy()
    x0 = torch.zeros(2, 2, dtype=F64)
    for solver in (GradientStepSolver(), NewtonSolver(), InverseGradientSolver(), LBFGSBSolver()):
        with pytest.raises(ShapeError):
            solver(op, torch.zeros(2, 3, dtype=F64), x0)
        with pytest.raises(NonFiniteError):
            solver(op, torch.full((2, 2), math.nan, dtype=F64), x0)
        with pytest.raises(NonFiniteError):
            solver(op, torch.zeros(2, 2, dtype=F64), torch.full((2, 2), math.inf, dtype=F64))
    with pytest.raises(NonFiniteError, match="forward"):
        GradientStepSolver()(lambda z: torch.log(z), torch.zeros(1, 1), -torch.ones(1, 1))
    for bad in (
        lambda: GradientStepSolver(step_size=0.0),
        lambda: GradientStepSolver(max_iter=0),
        lambda: NewtonSolver(step_size=math.nan),
        lambda: NewtonSolver(clip=-1.0),
        lambda: InverseGradientSolver(max_iter=1.5),
        lambda: LBFGSBSolver(bounds=(1.0, 0.0)),
        lambda: NewtonSolver(rcond=-1.0),
    ):
        with pytest.raises(ParameterError):
            bad()
    with pytest.raises(TypeError):
        SolverOperator(3, NewtonSolver())


def test_solver_operator_for_plain_callable_checks_shapes():
    op = SolverOperator(_coupled, NewtonSolver())
    x0 = torch.zeros(2, 3, dtype=F64)
    assert op.output_shape(x0.shape) is None
    with pytest.raises(ShapeError):
        op.local_inverse(torch.zeros(2, 3, dtype=F64), x0)
    assert op(x0).shape == (2, 2)
