"""Tests of inverse.hig: the HIG / Gauss-Newton direction against numpy, truncation, chunking, errors."""

from __future__ import annotations

import copy
import inspect

import numpy as np
import pytest
import torch

from inverse import hig as hig_mod
from inverse.hig import (
    HIG,
    GaussNewton,
    JacobianMemoryError,
    hig_update,
    per_sample_jacobian,
    squared_error,
    truncated_power_svd,
)
from phisim.errors import NonFiniteError, ParameterError, PhisimError, ShapeError


def _toy_net(dtype=torch.float64, seed=0, hidden=7):
    torch.manual_seed(seed)
    return torch.nn.Sequential(torch.nn.Linear(1, hidden), torch.nn.Tanh(), torch.nn.Linear(hidden, 2)).to(
        dtype
    )


def _toy_batch(B, dtype=torch.float64, seed=1):
    gen = torch.Generator().manual_seed(seed)
    x = torch.rand(B, 1, generator=gen, dtype=torch.float64) * 2 - 1
    t = torch.cat([torch.sin(6 * x), torch.cos(9 * x)], dim=1)
    return x.to(dtype), t.to(dtype)


def _vec(model):
    return torch.nn.utils.parameters_to_vector(model.parameters()).detach().clone()


def _numpy_direction(J, g, rcond, exponent):
    U, s, Vt = np.linalg.svd(J, full_matrices=False)
    keep = s >= rcond * s[0]
    inv = np.zeros_like(s)
    inv[keep] = s[keep] ** (-exponent)
    return Vt.T @ (inv * (U.T @ g))


# --- the pure function against numpy ----------------------------------------------------------------


@pytest.mark.parametrize("shape", [(12, 7), (7, 12), (9, 9)])
def test_hig_update_matches_numpy_svd(shape):
    rng = np.random.default_rng(0)
    J = rng.standard_normal(shape)
    g = rng.standard_normal(shape[0])
    U, s, Vt = np.linalg.svd(J, full_matrices=False)
    expected = Vt.T @ np.diag(s**-0.5) @ U.T @ g  # V diag(s^-1/2) U^T g
    got = hig_update(torch.from_numpy(J), torch.from_numpy(g), rcond=1e-10, exponent=0.5).numpy()
    np.testing.assert_allclose(got, expected, rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("shape", [(12, 7), (7, 12)])
def test_exponent_one_is_pseudo_inverse_gauss_newton(shape):
    rng = np.random.default_rng(1)
    J = rng.standard_normal(shape)
    g = rng.standard_normal(shape[0])
    got = hig_update(torch.from_numpy(J), torch.from_numpy(g), rcond=1e-10, exponent=1.0).numpy()
    np.testing.assert_allclose(got, np.linalg.pinv(J) @ g, rtol=1e-9, atol=1e-12)


def test_exponent_one_rank_deficient_matches_pinv():
    rng = np.random.default_rng(2)
    J = rng.standard_normal((10, 3)) @ rng.standard_normal((3, 6))  # rank 3
    g = rng.standard_normal(10)
    direction, s, kept = truncated_power_svd(
        torch.from_numpy(J), torch.from_numpy(g), rcond=1e-8, exponent=1.0
    )
    assert int(kept.sum()) == 3
    np.testing.assert_allclose(direction.numpy(), np.linalg.pinv(J, rcond=1e-8) @ g, rtol=1e-8, atol=1e-10)


def test_exponent_minus_one_is_plain_gradient():
    rng = np.random.default_rng(3)
    J = rng.standard_normal((8, 5))
    g = rng.standard_normal(8)
    got = hig_update(torch.from_numpy(J), torch.from_numpy(g), rcond=0.0, exponent=-1.0).numpy()
    np.testing.assert_allclose(got, J.T @ g, rtol=1e-10, atol=1e-12)


def test_truncation_drops_exactly_the_small_directions():
    rng = np.random.default_rng(4)
    U, _ = np.linalg.qr(rng.standard_normal((8, 5)))
    V, _ = np.linalg.qr(rng.standard_normal((5, 5)))
    s = np.array([10.0, 3.0, 1.0, 1e-4, 1e-9])
    J = U @ np.diag(s) @ V.T
    g = rng.standard_normal(8)
    rcond = 1e-6  # cut-off 1e-5: drops 1e-9 only; 1e-4 stays
    d, s_t, kept = truncated_power_svd(torch.from_numpy(J), torch.from_numpy(g), rcond=rcond, exponent=0.5)
    d = d.numpy()
    assert kept.tolist() == [True, True, True, True, False]
    np.testing.assert_allclose(s_t.numpy(), s, rtol=1e-8, atol=1e-12)
    # no component at all along the dropped right singular vector (zeroed, not clamped)
    assert abs(V[:, 4] @ d) < 1e-10 * np.linalg.norm(d)
    # the kept directions carry exactly s_k^-1/2 (u_k . g)
    coeff = V.T @ d
    np.testing.assert_allclose(coeff[:4], s[:4] ** -0.5 * (U[:, :4].T @ g), rtol=1e-7)
    # a larger rcond also removes the 1e-4 direction, leaving the rest unchanged
    d2, _, kept2 = truncated_power_svd(torch.from_numpy(J), torch.from_numpy(g), rcond=1e-3, exponent=0.5)
    assert int(kept2.sum()) == 3
    assert abs(V[:, 3] @ d2.numpy()) < 1e-10 * np.linalg.norm(d2.numpy())
    np.testing.assert_allclose(V[:, :3].T @ d2.numpy(), coeff[:3], rtol=1e-7)
    # clamping instead of dropping would have produced a huge component: the truncation matters
    clamped = s[4] ** -0.5 * (U[:, 4] @ g)
    assert abs(clamped) > 100 * np.abs(coeff[:4]).max()


def test_numpy_reference_helper_agrees_with_truncation():
    rng = np.random.default_rng(5)
    J = rng.standard_normal((6, 4)) @ np.diag([1, 1e-3, 1e-7, 1e-12]) @ rng.standard_normal((4, 4))
    g = rng.standard_normal(6)
    for rcond in (1e-10, 1e-5, 1e-2):
        got = hig_update(torch.from_numpy(J), torch.from_numpy(g), rcond=rcond, exponent=0.5).numpy()
        np.testing.assert_allclose(got, _numpy_direction(J, g, rcond, 0.5), rtol=1e-6, atol=1e-9)


# --- the optimizer ----------------------------------------------------------------------------------


def test_per_sample_jacobian_matches_autograd():
    net = _toy_net()
    x, _ = _toy_batch(5)
    scale = torch.tensor([1.0, 0.3], dtype=torch.float64)
    J = per_sample_jacobian(net, x, lambda o: o * scale)
    names = [n for n, _ in net.named_parameters()]
    shapes = [p.shape for p in net.parameters()]

    def f(v):
        d, o = {}, 0
        for n, s in zip(names, shapes):
            d[n] = v[o : o + s.numel()].view(s)
            o += s.numel()
        return (torch.func.functional_call(net, d, (x,)) * scale).reshape(-1)

    Jref = torch.autograd.functional.jacobian(f, _vec(net))
    assert J.shape == (10, 30)
    torch.testing.assert_close(J, Jref, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("exponent", [0.5, 1.0])
@pytest.mark.parametrize("reduction", ["mean", "sum"])
def test_step_equals_numpy_update(exponent, reduction):
    net = _toy_net()
    x, t = _toy_batch(6)
    scale = torch.tensor([1.0, 0.01], dtype=torch.float64)
    physics = lambda o: o * scale  # noqa: E731
    J = per_sample_jacobian(net, x, physics).numpy()
    with torch.no_grad():
        r = (physics(net(x)) - t).numpy().reshape(-1)
    g = r / 6 if reduction == "mean" else r
    theta0 = _vec(net).numpy()
    rcond = 1e-5  # this J has a condition number ~1e9; keep the compared directions well conditioned
    opt = HIG(net, physics=physics, lr=0.3, rcond=rcond, exponent=exponent, reduction=reduction)
    info = opt.step(x, t)
    expected = theta0 - 0.3 * _numpy_direction(J, g, rcond, exponent)
    # two SVD implementations agree to about eps * (condition number of the kept part)
    sv = np.linalg.svd(J, compute_uv=False)
    kept = sv[sv >= rcond * sv[0]]
    assert info.n_kept == kept.size and 0 < info.n_dropped
    assert sv[kept.size] < 0.5 * kept[-1]  # a clear gap at the cut-off: both keep the same set
    rtol = 100 * np.finfo(np.float64).eps * kept[0] / kept[-1]
    assert rtol < 1e-8
    np.testing.assert_allclose(_vec(net).numpy(), expected, rtol=rtol, atol=rtol * np.abs(expected).max())
    assert info.loss == pytest.approx(0.5 * (r**2).sum() / 6, rel=1e-12)
    assert info.n_kept + info.n_dropped == min(12, 30)


def test_gauss_newton_solves_linear_least_squares_in_one_step():
    torch.manual_seed(3)
    net = torch.nn.Linear(4, 3).double()  # 15 parameters, 3 samples x 3 outputs = 9 equations
    x = torch.randn(3, 4, dtype=torch.float64)
    t = torch.randn(3, 3, dtype=torch.float64)
    opt = GaussNewton(net, lr=1.0, reduction="sum")
    info0 = opt.step(x, t)
    assert info0.loss > 0.1
    with torch.no_grad():
        assert float(squared_error(net(x), t).mean()) < 1e-20
    assert info0.n_dropped == 0


def test_hig_reduces_the_loss_on_the_toy():
    net = _toy_net()
    x, t = _toy_batch(64)
    opt = HIG(net, lr=1.0, rcond=1e-4)
    losses = [opt.step(x, t).loss for _ in range(80)]
    assert losses[-1] < 0.5 * losses[0]
    assert all(np.isfinite(losses))


def test_lr_scheduler_acts_on_step_size():
    net_a, net_b = _toy_net(), _toy_net()
    x, t = _toy_batch(8)
    opt_a, opt_b = HIG(net_a, lr=1e-3), HIG(net_b, lr=1e-3)
    sched = torch.optim.lr_scheduler.LambdaLR(opt_b, lambda epoch: 0.5)  # lr of opt_b becomes 0.5e-3
    assert opt_b.param_groups[0]["lr"] == pytest.approx(0.5e-3) and sched.get_last_lr() == [0.5e-3]
    a, b = opt_a.step(x, t), opt_b.step(x, t)
    assert b.update_norm == pytest.approx(0.5 * a.update_norm, rel=1e-10)


def test_output_scaling_hurts_hig_much_less_than_the_gradient():
    """Scale output 2 by lambda = 0.01 (physics ``diag(1, lambda)``, targets scaled alike, so the minimiser
    is unchanged) and measure, for the first step of each method, the share of the linearised
    network-output change ``J dtheta`` that falls into component 2, relative to lambda = 1.

    Measured (float64, 10 seeds, B = 32): plain gradient 0.58 -> 0.026 (ratio ~0.05, collapsed:
    the component-2 gradient is scaled by lambda^2); HIG 0.59 -> 0.33 (ratio ~0.57); Gauss-Newton
    0.695 -> 0.694 (ratio ~1); Adam's first step 0.69 -> 0.59 (ratio ~0.86). Adam's first step is the
    sign of the gradient, so it is nearly unchanged by this scaling; its trouble with lambda = 0.01
    shows over many steps (examples/hig_toy.py), not in the direction of one step.
    """
    ratios = {"gd": [], "adam": [], "hig": [], "gn": []}
    for seed in range(10):
        base = _toy_net(seed=seed)
        x, t = _toy_batch(32, seed=100 + seed)
        Jn = per_sample_jacobian(base, x)
        theta0 = _vec(base)
        for name in ratios:
            share = []
            for lam in (1.0, 0.01):
                D = torch.tensor([1.0, lam], dtype=torch.float64)
                net = copy.deepcopy(base)
                if name in ("hig", "gn"):
                    HIG(
                        net, physics=lambda o, D=D: o * D, lr=1e-3, exponent=0.5 if name == "hig" else 1.0
                    ).step(x, t * D)
                else:
                    cls = torch.optim.Adam if name == "adam" else torch.optim.SGD
                    opt = cls(net.parameters(), lr=1e-3)
                    squared_error(net(x) * D, t * D).mean().backward()
                    opt.step()
                dy = (Jn @ (_vec(net) - theta0)).view(32, 2)
                share.append(float(dy[:, 1].norm() / dy.norm()))
            ratios[name].append(share[1] / share[0])
    mean = {k: float(np.mean(v)) for k, v in ratios.items()}
    assert mean["gd"] < 0.1  # the gradient loses component 2
    assert mean["hig"] > 0.4  # HIG keeps most of it
    assert mean["hig"] > 5 * mean["gd"]
    assert 0.95 < mean["gn"] < 1.05  # Gauss-Newton is (nearly) invariant
    assert mean["adam"] > 0.7  # documented above: Adam's first step is sign-like


def test_chunked_jacobian_equals_unchunked():
    net = _toy_net(hidden=5)
    x, t = _toy_batch(7)
    J = per_sample_jacobian(net, x)
    for chunk in (1, 2, 3, 7, 100):
        torch.testing.assert_close(per_sample_jacobian(net, x, chunk_size=chunk), J, rtol=0, atol=0)


def test_memory_budget_forces_chunks_with_same_update():
    x, t = _toy_batch(16)
    net_a, net_b = _toy_net(), _toy_net()
    opt_a = HIG(net_a, lr=0.5)
    # Jacobian 32 x 30 float64: resident ~ (2*960 + 30*30*2) * 8 = 29 kB; per sample 2*2*30*8 = 960 B
    opt_b = HIG(net_b, lr=0.5, memory_budget=30_000 + 3 * 960)
    info_a, info_b = opt_a.step(x, t), opt_b.step(x, t)
    assert info_a.n_chunks == 1
    assert info_b.n_chunks > 1
    torch.testing.assert_close(_vec(net_a), _vec(net_b), rtol=1e-12, atol=1e-14)


def test_memory_error_when_even_one_sample_does_not_fit():
    x, t = _toy_batch(16)
    opt = HIG(_toy_net(), memory_budget=1000)
    with pytest.raises(JacobianMemoryError, match="memory budget") as exc:
        opt.step(x, t)
    assert isinstance(exc.value, PhisimError)
    assert exc.value.required > exc.value.budget == 1000


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_float32_and_float64(dtype):
    net = _toy_net(dtype=dtype)
    x, t = _toy_batch(8, dtype=dtype)
    ref = _toy_net(dtype=torch.float64)
    xr, tr = _toy_batch(8, dtype=torch.float64)
    # rcond 1e-3 keeps singular values >= 3.3e-3 of the largest (the next is 2.3e-4): their float32 rounding
    # (eps / 3.3e-3 ~ 2e-5 relative) stays below the tolerance; at rcond 1e-5 the kept 2.4e-5 would carry ~3e-3
    info = HIG(net, lr=0.1, rcond=1e-3).step(x, t)
    HIG(ref, lr=0.1, rcond=1e-3).step(xr, tr)
    assert info.singular_values.dtype == dtype
    assert all(p.dtype == dtype for p in net.parameters())
    tol = 1e-12 if dtype == torch.float64 else 2e-4
    torch.testing.assert_close(_vec(net).double(), _vec(ref), rtol=tol, atol=tol)


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_matches_cpu():
    x, t = _toy_batch(16)
    net_c, net_g = _toy_net(), _toy_net().cuda()
    # rcond 1e-5 keeps singular values >= 2.6e-5 of the largest (the next is 1.9e-6): the default 1e-10 keeps
    # 2.5e-10, whose rounding (eps / 2.5e-10 ~ 1e-6 relative) differs between LAPACK and cuSOLVER
    HIG(net_c, lr=0.5, rcond=1e-5).step(x, t)
    info = HIG(net_g, lr=0.5, rcond=1e-5, timing=True).step(x.cuda(), t.cuda())
    assert set(info.times) == {"jacobian", "svd", "apply"}
    torch.testing.assert_close(_vec(net_g).cpu(), _vec(net_c), rtol=1e-9, atol=1e-11)


# --- errors -----------------------------------------------------------------------------------------


def test_bad_input_to_hig_update():
    J = torch.randn(6, 4, dtype=torch.float64)
    g = torch.randn(6, dtype=torch.float64)
    with pytest.raises(ShapeError, match="2-D"):
        hig_update(J[0], g)
    with pytest.raises(ShapeError, match="one entry per row"):
        hig_update(J, g[:5])
    with pytest.raises(ShapeError):
        hig_update(J, g.view(2, 3))
    with pytest.raises(ParameterError, match="rcond"):
        hig_update(J, g, rcond=-1e-3)
    with pytest.raises(ParameterError, match="rcond"):
        hig_update(J, g, rcond=float("nan"))
    with pytest.raises(ParameterError, match="exponent"):
        hig_update(J, g, exponent=float("inf"))
    with pytest.raises(ParameterError, match="dtype"):
        hig_update(J, g.float())
    bad = J.clone()
    bad[0, 0] = float("nan")
    with pytest.raises(NonFiniteError, match="Jacobian"):
        hig_update(bad, g)
    with pytest.raises(NonFiniteError, match="gradient"):
        hig_update(J, g.clone().fill_(float("inf")))


def test_bad_optimizer_arguments():
    net = _toy_net()
    with pytest.raises(ParameterError, match="lr"):
        HIG(net, lr=0.0)
    with pytest.raises(ParameterError, match="rcond"):
        HIG(net, rcond=-1.0)
    with pytest.raises(ParameterError, match="reduction"):
        HIG(net, reduction="median")
    with pytest.raises(ParameterError, match="memory_budget"):
        HIG(net, memory_budget=0)
    with pytest.raises(ParameterError, match="chunk_size"):
        HIG(net, chunk_size=0)
    with pytest.raises(ParameterError, match="Module"):
        HIG(lambda x: x)
    frozen = _toy_net()
    for p in frozen.parameters():
        p.requires_grad_(False)
    with pytest.raises(ParameterError, match="trainable"):
        HIG(frozen)


def test_bad_step_input_leaves_parameters_untouched():
    net = _toy_net()
    x, t = _toy_batch(8)
    opt = HIG(net)
    theta0 = _vec(net)
    with pytest.raises(ParameterError, match="targets"):
        opt.step(x)
    bad_t = t.clone()
    bad_t[3, 1] = float("nan")
    with pytest.raises(NonFiniteError, match="loss"):
        opt.step(x, bad_t)
    with pytest.raises(ShapeError, match="same shape"):
        opt.step(x, t[:, :1])
    with pytest.raises(ShapeError, match=r"shape \(8,\)"):
        opt.step(x, t, loss_fn=lambda y, tt: ((y - tt) ** 2).sum())
    with pytest.raises(ShapeError, match="batch"):
        opt.step(x[:0], t[:0])
    phys = HIG(net, physics=lambda o, s: o * s)
    with pytest.raises(ShapeError, match=r"physics_args\[0\]"):
        phys.step(x, t, physics_args=(torch.ones(5, 2, dtype=torch.float64),))
    torch.testing.assert_close(_vec(net), theta0, rtol=0, atol=0)


def test_physics_args_are_passed_per_sample():
    net = _toy_net()
    x, t = _toy_batch(6)
    s = torch.linspace(0.5, 2.0, 6, dtype=torch.float64)[:, None].expand(6, 2).contiguous()
    J = per_sample_jacobian(net, x, lambda o, sc: o * sc, (s,))
    J0 = per_sample_jacobian(net, x)
    torch.testing.assert_close(J, J0 * s.reshape(-1, 1))


def test_public_names_have_docstrings():
    for name in hig_mod.__all__:
        obj = getattr(hig_mod, name)
        assert inspect.getdoc(obj), name
        if inspect.isclass(obj):
            for meth in ("step", "plan_chunks"):
                if hasattr(obj, meth) and obj is not JacobianMemoryError:
                    assert inspect.getdoc(getattr(obj, meth)), f"{name}.{meth}"


def test_wide_jacobian_factorised_on_the_tall_orientation_gives_the_same_factors():
    """``J`` with fewer rows than columns is decomposed as ``J^T``; the thin factors still satisfy ``J = U s Vh``."""
    from inverse.hig import _thin_svd

    rng = np.random.default_rng(4)
    for shape in [(6, 40), (40, 6)]:
        J = torch.from_numpy(rng.standard_normal(shape))
        U, s, Vh = _thin_svd(J)
        k = min(shape)
        assert U.shape == (shape[0], k) and Vh.shape == (k, shape[1])
        np.testing.assert_allclose(s.numpy(), np.linalg.svd(J.numpy(), compute_uv=False), rtol=1e-12)
        torch.testing.assert_close(U @ torch.diag(s) @ Vh, J, rtol=1e-12, atol=1e-12)
        torch.testing.assert_close(U.mT @ U, torch.eye(k, dtype=J.dtype), rtol=0, atol=1e-12)
        torch.testing.assert_close(Vh @ Vh.mT, torch.eye(k, dtype=J.dtype), rtol=0, atol=1e-12)
