"""Tests of phisim.solvers.linalg: batched preconditioned CG, implicit gradients, float32 refinement, failures."""

from __future__ import annotations

import contextlib

import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as spla
import torch

from phisim.errors import NonFiniteError, ParameterError, ShapeError, SolveError
from phisim.solvers.linalg import Solve, SolveInfo, cg, remove_mean

# --------------------------------------------------------------------------------------------------
# local stencils (the grid/field modules are not used here on purpose)


def neg_laplace(x: torch.Tensor) -> torch.Tensor:
    """-Laplacian, 5-point, unit spacing, zero Dirichlet ghost cells, on (B, nx, ny)."""
    xp = torch.nn.functional.pad(x[:, None], (1, 1, 1, 1))[:, 0]
    return 4 * x - xp[:, 2:, 1:-1] - xp[:, :-2, 1:-1] - xp[:, 1:-1, 2:] - xp[:, 1:-1, :-2]


def neg_laplace_periodic(x: torch.Tensor) -> torch.Tensor:
    """-Laplacian, 5-point, periodic (singular: constant null space)."""
    return 4 * x - sum(torch.roll(x, s, d) for d in (1, 2) for s in (1, -1))


def diffusion_op(x: torch.Tensor, k: torch.Tensor) -> torch.Tensor:
    """x - div(k grad x) with face coefficients from the cell field k (B or 1, nx, ny), zero Dirichlet.

    Symmetric positive definite for k > 0; depends on k so gradients w.r.t. k can be checked.
    """
    kp = torch.nn.functional.pad(k[:, None], (1, 1, 1, 1), mode="replicate")[:, 0]
    xp = torch.nn.functional.pad(x[:, None], (1, 1, 1, 1))[:, 0]
    kc = kp[:, 1:-1, 1:-1]
    kxp = 0.5 * (kc + kp[:, 2:, 1:-1])
    kxm = 0.5 * (kc + kp[:, :-2, 1:-1])
    kyp = 0.5 * (kc + kp[:, 1:-1, 2:])
    kym = 0.5 * (kc + kp[:, 1:-1, :-2])
    flux = (kxp * (xp[:, 2:, 1:-1] - x) + kxm * (xp[:, :-2, 1:-1] - x)
            + kyp * (xp[:, 1:-1, 2:] - x) + kym * (xp[:, 1:-1, :-2] - x))
    return x - flux


def scipy_laplacian(nx: int, ny: int) -> sp.csr_matrix:
    """The same -Laplacian as neg_laplace as a sparse matrix (C order: index i*ny + j)."""
    def d2(n: int) -> sp.csr_matrix:
        return sp.diags([-np.ones(n - 1), 2 * np.ones(n), -np.ones(n - 1)], [-1, 0, 1])
    return sp.csr_matrix(sp.kron(d2(nx), sp.identity(ny)) + sp.kron(sp.identity(nx), d2(ny)))


def unrolled_cg(op, b: torch.Tensor, n_iter: int) -> torch.Tensor:
    """Textbook CG for a fixed number of iterations, differentiable through every operation."""
    x = torch.zeros_like(b)
    r = b.clone()
    p = r.clone()
    rr = (r * r).flatten(1).sum(1)
    for _ in range(n_iter):
        q = op(p)
        alpha = rr / (p * q).flatten(1).sum(1)
        x = x + alpha[:, None, None] * p
        r = r - alpha[:, None, None] * q
        rr_new = (r * r).flatten(1).sum(1)
        p = r + (rr_new / rr)[:, None, None] * p
        rr = rr_new
    return x


def rel_residual(op, x: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    b64 = b.double()
    return (torch.linalg.vector_norm((b64 - op(x.double())).flatten(1), dim=1)
            / torch.linalg.vector_norm(b64.flatten(1), dim=1))


def smooth_rhs(n: int, dtype=torch.float64) -> torch.Tensor:
    i = torch.arange(n, dtype=torch.float64)
    g = torch.exp(-((i[:, None] - n / 3) ** 2 + (i[None] - n / 2) ** 2) / (n / 8) ** 2)
    return g[None].to(dtype)


# --------------------------------------------------------------------------------------------------
# accuracy


def test_matches_scipy_spsolve_float64():
    nx, ny = 24, 17
    gen = torch.Generator().manual_seed(1)
    b = torch.randn(3, nx, ny, generator=gen, dtype=torch.float64)
    x, info = cg(neg_laplace, b, solve=Solve(rtol=1e-10), return_info=True)
    A = scipy_laplacian(nx, ny)
    for s in range(3):
        ref = spla.spsolve(A.tocsc(), b[s].numpy().ravel()).reshape(nx, ny)
        err = np.linalg.norm(x[s].numpy() - ref) / np.linalg.norm(ref)
        assert err < 1e-6
    assert info.all_converged and x.dtype == torch.float64
    assert torch.all(info.residual <= 1e-10 * torch.linalg.vector_norm(b.flatten(1), dim=1))
    # reported residual is the true one
    true = torch.linalg.vector_norm((b - neg_laplace(x)).flatten(1), dim=1)
    torch.testing.assert_close(info.residual, true, rtol=1e-6, atol=1e-14)


def test_batched_samples_converge_independently():
    n = 20
    i = torch.arange(1, n + 1, dtype=torch.float64)
    mode = (torch.sin(np.pi * i / (n + 1))[:, None] * torch.sin(2 * np.pi * i / (n + 1))[None])
    gen = torch.Generator().manual_seed(2)
    b = torch.stack([mode, torch.randn(n, n, generator=gen, dtype=torch.float64), 1e-3 * mode + 0 * mode])
    b[2] = smooth_rhs(n)[0]
    solve = Solve(rtol=1e-8)
    x, info = cg(neg_laplace, b, solve=solve, return_info=True)
    its = info.iterations.tolist()
    assert its[0] == 1  # an eigenvector converges in one step
    assert len(set(its)) == 3  # each sample stops on its own
    for s in range(3):
        xs, infos = cg(neg_laplace, b[s:s + 1], solve=solve, return_info=True)
        assert infos.iterations.item() == its[s]
        torch.testing.assert_close(x[s:s + 1], xs, rtol=1e-12, atol=1e-14)


def test_zero_rhs_and_warm_start_need_no_iterations():
    b = torch.zeros(2, 8, 8, dtype=torch.float64)
    b[1] = torch.randn(8, 8, dtype=torch.float64)
    x, info = cg(neg_laplace, b, solve=Solve(rtol=1e-10), return_info=True)
    assert info.iterations[0] == 0 and torch.all(x[0] == 0)
    x2, info2 = cg(neg_laplace, b, x0=x, solve=Solve(rtol=1e-8), return_info=True)
    assert info2.iterations.tolist() == [0, 0]
    torch.testing.assert_close(x2, x)


# --------------------------------------------------------------------------------------------------
# preconditioning


def test_jacobi_preconditioner_reduces_iterations():
    n = 32
    gen = torch.Generator().manual_seed(3)
    c = 10.0 ** (4 * torch.rand(1, n, n, generator=gen, dtype=torch.float64))  # 1 .. 1e4

    def op(x):
        return neg_laplace(x) + c * x

    b = torch.randn(2, n, n, generator=gen, dtype=torch.float64)
    _, plain = cg(op, b, solve=Solve(rtol=1e-8), return_info=True)
    x, jac = cg(op, b, solve=Solve(rtol=1e-8), preconditioner=lambda r: r / (4 + c), return_info=True)
    assert jac.all_converged
    assert torch.all(jac.iterations * 3 < plain.iterations)
    assert torch.all(rel_residual(op, x, b) <= 1e-8)


def test_exact_inverse_preconditioner_converges_in_one_iteration():
    nx, ny = 10, 7
    Ainv = torch.as_tensor(np.linalg.inv(scipy_laplacian(nx, ny).toarray()))

    def exact(r):
        return (r.flatten(1) @ Ainv.T).reshape(r.shape)

    b = torch.randn(3, nx, ny, dtype=torch.float64)
    x, info = cg(neg_laplace, b, solve=Solve(rtol=1e-10), preconditioner=exact, return_info=True)
    assert info.iterations.tolist() == [1, 1, 1]
    assert torch.all(rel_residual(neg_laplace, x, b) <= 1e-10)


# --------------------------------------------------------------------------------------------------
# implicit differentiation


def test_implicit_gradient_matches_unrolled_cg():
    n = 6
    gen = torch.Generator().manual_seed(4)
    b = torch.randn(2, n, n, generator=gen, dtype=torch.float64, requires_grad=True)
    k = (0.5 + torch.rand(1, n, n, generator=gen, dtype=torch.float64)).requires_grad_()
    w = torch.randn(2, n, n, generator=gen, dtype=torch.float64)

    x = cg(diffusion_op, b, solve=Solve(rtol=1e-13), operator_params=(k,))
    gb, gk = torch.autograd.grad((w * x).sum(), (b, k))

    # n*n iterations of exact-arithmetic CG solve the system; a few more absorb rounding.
    xu = unrolled_cg(lambda v: diffusion_op(v, k), b, n * n + 10)
    torch.testing.assert_close(x, xu, rtol=1e-10, atol=1e-12)
    gbu, gku = torch.autograd.grad((w * xu).sum(), (b, k))
    torch.testing.assert_close(gb, gbu, rtol=1e-8, atol=1e-10)
    torch.testing.assert_close(gk, gku, rtol=1e-8, atol=1e-10)


def test_gradcheck_rhs_and_operator_parameter():
    n = 4
    gen = torch.Generator().manual_seed(5)
    b = torch.randn(2, n, n + 1, generator=gen, dtype=torch.float64, requires_grad=True)
    k = (0.5 + torch.rand(1, n, n + 1, generator=gen, dtype=torch.float64)).requires_grad_()
    solve = Solve(rtol=1e-13)

    def f(b, k):
        return cg(diffusion_op, b, solve=solve, operator_params=(k,))

    assert torch.autograd.gradcheck(f, (b, k))
    assert torch.autograd.gradgradcheck(f, (b, k))


def test_gradient_wrt_x0_is_zero_and_rhs_gradient_is_adjoint_solution():
    n = 8
    b = torch.randn(1, n, n, dtype=torch.float64, requires_grad=True)
    x0 = torch.randn(1, n, n, dtype=torch.float64, requires_grad=True)
    g = torch.randn(1, n, n, dtype=torch.float64)
    x = cg(neg_laplace, b, x0, solve=Solve(rtol=1e-12))
    gb, gx0 = torch.autograd.grad((g * x).sum(), (b, x0), allow_unused=True)
    assert gx0 is None or torch.all(gx0 == 0)
    lam = cg(neg_laplace, g, solve=Solve(rtol=1e-12))
    torch.testing.assert_close(gb, lam, rtol=1e-10, atol=1e-12)


def _graph_stats(rtol: float) -> tuple[int, int, int]:
    """(iterations, saved tensors, graph nodes) of one differentiable solve."""
    n = 16
    b = torch.randn(1, n, n, dtype=torch.float64, generator=torch.Generator().manual_seed(6),
                    requires_grad=True)
    k = torch.ones(1, n, n, dtype=torch.float64, requires_grad=True)
    saved = []
    with torch.autograd.graph.saved_tensors_hooks(lambda t: saved.append(t) or t, lambda t: t):
        x, info = cg(diffusion_op, b, solve=Solve(rtol=rtol), operator_params=(k,), return_info=True)
    seen, stack = set(), [x.grad_fn]
    while stack:
        node = stack.pop()
        if node is None or node in seen:
            continue
        seen.add(node)
        stack.extend(f for f, _ in node.next_functions)
    return int(info.iterations), len(saved), len(seen)


def test_graph_and_saved_memory_do_not_grow_with_iterations():
    it_lo, saved_lo, nodes_lo = _graph_stats(1e-2)
    it_hi, saved_hi, nodes_hi = _graph_stats(1e-12)
    assert it_hi > 3 * it_lo
    assert saved_hi == saved_lo <= 4
    assert nodes_hi == nodes_lo <= 4


def test_operator_capturing_a_grad_tensor_is_rejected():
    k = torch.ones(1, 4, 4, dtype=torch.float64, requires_grad=True)
    with pytest.raises(ParameterError, match="operator_params"):
        cg(lambda x: diffusion_op(x, k), torch.ones(1, 4, 4, dtype=torch.float64))


# --------------------------------------------------------------------------------------------------
# failures and settings


def test_non_convergence_raises_with_residual_attached():
    b = torch.randn(2, 16, 16, dtype=torch.float64)
    with pytest.raises(SolveError, match="iteration limit") as e:
        cg(neg_laplace, b, solve=Solve(rtol=1e-10, max_iter=5))
    err = e.value
    assert err.iterations.tolist() == [5, 5]
    assert err.residual.shape == (2,) and torch.all(err.residual > 1e-10 * torch.linalg.vector_norm(b))
    x, info = cg(neg_laplace, b, solve=Solve(rtol=1e-10, max_iter=5, raise_on_failure=False),
                 return_info=True)
    assert not info.converged.any() and info.status == ("max_iter", "max_iter")
    assert torch.isfinite(x).all()


@pytest.mark.parametrize("kwargs", [
    dict(rtol=-1e-5), dict(atol=-1.0), dict(rtol=float("nan")), dict(rtol=0.0, atol=0.0),
    dict(max_iter=0), dict(max_iter=2.5), dict(stagnation_window=0), dict(refine_rtol=1.5),
    dict(max_refine=0), dict(check_every=0), dict(refine="yes"),
])
def test_bad_settings_raise_parameter_error(kwargs):
    with pytest.raises(ParameterError, match="Solve"):
        Solve(**kwargs)


def test_non_finite_inputs_and_operator_output():
    b = torch.ones(1, 4, 4, dtype=torch.float64)
    b[0, 1, 1] = float("nan")
    with pytest.raises(NonFiniteError, match="rhs"):
        cg(neg_laplace, b)
    with pytest.raises(NonFiniteError):
        cg(lambda x: neg_laplace(x) * float("inf"), torch.ones(1, 4, 4, dtype=torch.float64))


def test_bad_shapes():
    with pytest.raises(ShapeError):
        cg(lambda x: x[:, :-1], torch.ones(1, 4, 4, dtype=torch.float64))
    with pytest.raises(ShapeError):
        cg(neg_laplace, torch.ones(1, 4, 4, dtype=torch.float64), torch.ones(1, 4, 5, dtype=torch.float64))


def test_breakdown_on_indefinite_operator():
    b = torch.randn(1, 8, 8, dtype=torch.float64)
    with pytest.raises(SolveError, match="not symmetric positive definite"):
        cg(lambda x: -neg_laplace(x), b)


def test_singular_operator_with_projection_and_incompatible_rhs():
    n = 16
    gen = torch.Generator().manual_seed(7)
    b = torch.randn(2, n, n, generator=gen, dtype=torch.float64)
    x, info = cg(neg_laplace_periodic, b, solve=Solve(rtol=1e-8), project=remove_mean, return_info=True)
    assert info.all_converged
    torch.testing.assert_close(neg_laplace_periodic(x), remove_mean(b), rtol=0, atol=1e-6)
    assert torch.all(x.mean(dim=(1, 2)).abs() < 1e-12)
    with pytest.raises(SolveError, match="remove_mean") as e:
        cg(neg_laplace_periodic, b + 1.0, solve=Solve(rtol=1e-8, stagnation_window=50))
    assert int(e.value.iterations.max()) < 1000


def test_solve_info_repr():
    x, info = cg(neg_laplace, torch.ones(2, 5, 5, dtype=torch.float64), return_info=True)
    assert isinstance(info, SolveInfo)
    text = repr(info)
    for word in ("converged=2/2", "iterations=", "residual=", "rtol=1e-05", "atol=0"):
        assert word in text


# --------------------------------------------------------------------------------------------------
# float32


def test_float32_refinement_reaches_1e_5_where_plain_float32_fails():
    n = 128
    gen = torch.Generator().manual_seed(8)
    # White noise plus a smooth bump: reachable for a float32 vector (rounding the exact solution to
    # float32 gives a relative residual of about 7e-6), not for float32 CG arithmetic.
    b = (torch.randn(1, n, n, generator=gen, dtype=torch.float64) + smooth_rhs(n)).float()
    with pytest.raises(SolveError, match="float32 precision floor") as e:
        cg(neg_laplace, b, solve=Solve(rtol=1e-5, refine=False))
    assert int(e.value.iterations) < 2 * 400  # a few hundred, not thousands
    assert e.value.residual.item() > 1e-5 * torch.linalg.vector_norm(b.double())
    x, info = cg(neg_laplace, b, solve=Solve(rtol=1e-5), return_info=True)
    assert x.dtype == torch.float32 and info.refined and info.refinements >= 2
    assert rel_residual(neg_laplace, x, b).item() <= 1e-5  # true residual, computed in float64
    assert info.all_converged and info.iterations.item() < 500


def test_float32_smooth_solution_hits_representation_floor_float64_mixed_precision_does_not():
    n = 128
    b = smooth_rhs(n)
    # No float32 vector reaches 1e-5 here: rounding x alone adds ~eps32*||A||*||x||.
    with pytest.raises(SolveError, match="pass float64 input") as e:
        cg(neg_laplace, b.float(), solve=Solve(widen_tolerance=False))
    assert int(e.value.iterations) < 500
    # Default: the tolerance is widened by the measured rounding floor, reported, and met by the returned x.
    x32, info = cg(neg_laplace, b.float(), return_info=True)
    tol = 1e-5 * torch.linalg.vector_norm(b.float().double())
    floor = info.precision_floor
    assert x32.dtype == torch.float32 and info.all_converged and floor is not None
    assert float(floor[0]) > 0 and info.tolerance[0] == pytest.approx(float(tol) + float(floor[0]), rel=1e-6)
    true_res = torch.linalg.vector_norm(b.float().double() - neg_laplace(x32.double()))
    assert float(tol) < float(true_res) <= float(info.tolerance[0])
    # accepted, but the report says the requested tolerance was not met and what was
    assert info.status == ("precision_floor",) and not info.all_met_requested and not bool(info.met_requested[0])
    bn = torch.linalg.vector_norm(b.float().double())
    assert float(info.achieved_rtol[0]) == pytest.approx(float(true_res / bn), rel=1e-6)
    assert float(info.achieved_rtol[0]) > 1e-5
    assert float(info.requested_tolerance[0]) == pytest.approx(float(tol), rel=1e-6)
    x, info = cg(neg_laplace, b, solve=Solve(refine=True), return_info=True)
    assert x.dtype == torch.float64 and info.refined and info.all_converged
    assert rel_residual(neg_laplace, x, b).item() <= 1e-5


def test_float32_unreachable_tolerance_fails_fast():
    n = 128
    b = torch.randn(1, n, n, generator=torch.Generator().manual_seed(9))
    max_iter = Solve().resolved_max_iter(n * n)
    with pytest.raises(SolveError, match="float32 precision floor") as e:
        cg(neg_laplace, b, solve=Solve(rtol=1e-6, refine=False))
    assert int(e.value.iterations) < 0.03 * max_iter
    with pytest.raises(SolveError, match="float32 precision floor") as e:
        cg(neg_laplace, b, solve=Solve(rtol=1e-8, refine=False))
    assert int(e.value.iterations) == 0  # below float32's unit roundoff: refused at once


def test_refinement_falls_back_when_operator_rejects_float64():
    w = torch.tensor([[[[0.0, -1, 0], [-1, 4, -1], [0, -1, 0]]]])

    def conv_op(x):
        return torch.nn.functional.conv2d(x[:, None], w, padding=1)[:, 0]

    b = torch.randn(2, 16, 16)
    x, info = cg(conv_op, b, solve=Solve(rtol=1e-4), return_info=True)
    assert not info.refined and info.all_converged
    with pytest.raises(ParameterError, match="float64"):
        cg(conv_op, b, solve=Solve(refine=True))


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_cuda(dtype):
    b = torch.randn(3, 64, 64, device="cuda", dtype=dtype)
    x, info = cg(neg_laplace, b, solve=Solve(rtol=1e-5), return_info=True)
    assert x.device.type == "cuda" and x.dtype == dtype and info.all_converged
    assert torch.all(rel_residual(neg_laplace, x, b) <= 1e-5)


def test_public_names_have_docstrings():
    import phisim.solvers.linalg as m
    for name in m.__all__:
        assert getattr(m, name).__doc__, name


@contextlib.contextmanager
def _device_loop():
    from phisim.solvers import linalg

    linalg._CPU_LOOPS = False
    try:
        yield
    finally:
        linalg._CPU_LOOPS = True


@pytest.mark.parametrize("case", ["plain", "preconditioned", "projected", "breakdown", "stagnated", "max_iter",
                                  "float32"])
def test_single_sample_loop_equals_the_batched_loop(case):
    """One sample on the CPU runs a scalar loop: same iterations, statuses and solutions as the batched loop."""
    gen = torch.Generator().manual_seed(12)
    dtype = torch.float32 if case == "float32" else torch.float64
    b = torch.randn(1, 12, 10, dtype=torch.float64, generator=gen).to(dtype)
    op, kw = neg_laplace, {"solve": Solve(rtol=1e-9 if dtype == torch.float64 else 1e-5, raise_on_failure=False,
                                          refine=False)}
    if case == "preconditioned":
        kw["preconditioner"] = lambda r: r / 4.0
    if case == "projected":
        op, kw["project"] = neg_laplace_periodic, remove_mean
    if case == "breakdown":
        op = lambda x: -neg_laplace(x)  # noqa: E731
    if case == "stagnated":
        op, b = neg_laplace_periodic, b + 1.0
        kw["solve"] = Solve(rtol=1e-9, raise_on_failure=False, stagnation_window=20)
    if case == "max_iter":
        kw["solve"] = Solve(rtol=1e-12, max_iter=7, raise_on_failure=False)
    x1, i1 = cg(op, b, return_info=True, **kw)
    x2, i2 = cg(op, torch.cat([b, b]), return_info=True, **kw)
    assert i1.status[0] == i2.status[0] == i2.status[1]
    assert int(i1.iterations[0]) == int(i2.iterations[0])
    # the loop of other devices (no host reads; stopping reasons worked out after the loop), here on the CPU, with
    # a sample beside it that converges sooner (b / 1e6 of the same operator: the stopping rule is relative) and with
    # host checks every 1 and 7 iterations: the same iterations, statuses and solutions
    for every in (1, 7):
        solve = kw["solve"]
        dkw = dict(kw, solve=Solve(rtol=solve.rtol, atol=solve.atol, max_iter=solve.max_iter, raise_on_failure=False,
                                   refine=False, stagnation_window=solve.stagnation_window, check_every=every))
        other = torch.zeros_like(b)
        other.view(-1)[::3] = 1.0
        with _device_loop():
            x3, i3 = cg(op, torch.cat([b, other]), return_info=True, **dkw)
        x4, i4 = cg(op, torch.cat([b, other]), return_info=True, **dkw)
        assert i3.status == i4.status and i3.status[0] == i1.status[0]
        assert i3.iterations.tolist() == i4.iterations.tolist() and int(i3.iterations[0]) == int(i1.iterations[0])
        assert torch.equal(x3, x4)
        if case != "stagnated":  # (an incompatible right-hand side: where rounding ends it differs between loops)
            _, i5 = cg(op, other, return_info=True, **dkw)  # the scalar loop: the second sample on its own
            assert i3.status[1] == i5.status[0] and int(i3.iterations[1]) == int(i5.iterations[0])
    expected = {"breakdown": "breakdown", "max_iter": "max_iter"}.get(case)
    if expected:
        assert i1.status[0] == expected
    elif case != "stagnated":
        assert i1.status[0] == "converged"
    if case != "stagnated":  # a stagnated iterate is garbage in both loops
        scale = float(x2[0].abs().max())
        torch.testing.assert_close(x1[0], x2[0], rtol=0, atol=(1e-10 if dtype == torch.float64 else 1e-4) * scale)


@pytest.mark.parametrize("case", ["converged", "max_iter", "stagnated", "breakdown", "nonfinite"])
def test_the_device_loop_stops_like_the_scalar_loop(case):
    """The CG loop of other devices works out why each sample stopped after the loop, from what it stopped with;
    run on the CPU it gives the scalar loop's iterations and reasons, also beside a sample that keeps going."""
    from phisim.solvers import linalg

    gen = torch.Generator().manual_seed(3)
    b = torch.randn(1, 12, 10, dtype=torch.float64, generator=gen)
    op, window, budget, tol = neg_laplace, 50, 200, 1e-9 * float(torch.linalg.vector_norm(b))
    calls = [0]
    if case == "max_iter":
        budget = 9
    if case == "stagnated":
        op, window = neg_laplace_periodic, 4  # no projection: the residual's mean never goes
        b = b + 1.0
    if case == "breakdown":
        op = lambda x: -neg_laplace(x)  # noqa: E731
    if case == "nonfinite":
        def op(x):  # NaN from the sixth application on, in the first sample only
            calls[0] += 1
            y = neg_laplace(x)
            if calls[0] >= 6:
                y = y.clone()
                y[0, 0, 0] = float("nan")
            return y

    def run(loop, batch):
        calls[0] = 0
        rhs = b if batch == 1 else torch.cat([b, torch.randn(1, 12, 10, dtype=torch.float64, generator=gen)])
        n = rhs.shape[0]
        args = (op, None, None, torch.zeros_like(rhs), rhs.clone(), torch.full((n,), tol, dtype=torch.float64),
                torch.ones(n, dtype=torch.bool), torch.full((n,), budget, dtype=torch.int64), window, 3)
        linalg._CPU_LOOPS = loop
        try:
            x, iters, status = linalg._cg_core(*args)
        finally:
            linalg._CPU_LOOPS = True
        return x[:1], int(iters[0]), int(status[0])

    xs, ks, ss = run(True, 1)  # the scalar loop
    expected = {"converged": linalg._CONVERGED, "max_iter": linalg._MAX_ITER, "stagnated": linalg._STAGNATED,
                "breakdown": linalg._BREAKDOWN, "nonfinite": linalg._NONFINITE}[case]
    assert ss == expected
    for batch in (1, 2):
        x, k, s = run(False, batch)
        assert (k, s) == (ks, ss)
        if case in ("converged", "max_iter"):
            torch.testing.assert_close(x, xs, rtol=1e-12, atol=1e-12)
