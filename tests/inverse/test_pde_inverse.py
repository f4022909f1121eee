"""Spectral PDEs as physics for training (inverse.pde_inverse): the linear part's damped inverse, the full operator's
local inverse and gradient, the registered problem, the custom-physics route and bad input."""

from __future__ import annotations

import math

import pytest
import torch

from inverse import get_problem, make_problem, train
from inverse.local_solvers import InverseGradientSolver
from inverse.pde_inverse import ConvResNet, LinearPartSolver, PDEOperator, PDEProblem, pde_transfer, wiener_gain
from inverse.physgrad import physical_update
from phisim.errors import ParameterError, PhisimError, ShapeError
from phisim.pde import EQUATIONS, Diffusion, KuramotoSivashinsky, Wave, random_field

torch.set_num_threads(1)

KS = dict(domain=22.0, resolution=32, dt=0.25)


def _ks(steps=2, **kw):
    return PDEOperator("kuramoto_sivashinsky", steps, **{**KS, **kw})


def _power(g):
    return (g * g.conj()).real if g.is_complex() else g * g


# ------------------------------------------------------------------------------------------ the linear part


class TestLinearInverse:
    def test_wiener_gain_is_exact_above_eps_and_wiener_below(self):
        g = torch.tensor([2.0, 1.0, 0.5, 0.11, 0.09, 1e-3, 0.0], dtype=torch.float64)
        w = wiener_gain(g, 1e-2)
        exact = g[:4]
        assert torch.equal(w[:4], 1.0 / exact)
        damped = g[4:] / (g[4:] ** 2 + 1e-2)
        torch.testing.assert_close(w[4:], damped, rtol=0, atol=0)
        assert float(w[-1]) == 0.0  # an erased mode stays erased
        assert float(w.abs().max()) <= 1 / math.sqrt(1e-2) + 1e-12  # gain bounded by 1/sqrt(eps)

    def test_wiener_gain_complex(self):
        g = torch.polar(torch.tensor([1.5, 0.2, 0.01], dtype=torch.float64), torch.tensor([0.3, -1.0, 2.0],
                                                                                          dtype=torch.float64))
        w = wiener_gain(g, 1e-3)
        torch.testing.assert_close(w[:2], 1.0 / g[:2], rtol=1e-15, atol=0)
        torch.testing.assert_close(w[2], g[2].conj() / (abs(g[2]) ** 2 + 1e-3), rtol=1e-15, atol=0)

    @pytest.mark.parametrize("eps", [1e-2, 1e-8])
    def test_inverse_of_linear_forward_ks(self, eps):
        op = _ks(steps=4, eps=eps)
        x = random_field(op.stepper, batch=3, max_wavenumber=15, seed=1)
        back = op.linear_inverse(op.linear_forward(x))
        grid = op.grid
        xh, bh = grid.to_spectral(x), grid.to_spectral(back)
        stiff = op.stiff_modes()[0]
        assert bool(stiff.any()) and bool((~stiff).any())
        # round-off of the forward (float64 transforms) is amplified by the gain |W| and nothing else
        scale = float(xh.abs().max())
        tol = 64 * torch.finfo(torch.float64).eps * scale * (1 + op.gain[0].abs())
        # non-stiff modes: exact
        assert bool(((bh - xh).abs() <= tol)[..., ~stiff].all())
        # stiff modes: multiplied by the documented Wiener factor |g|^2 / (|g|^2 + eps)
        g = op.transfer[0]
        factor = _power(g) / (_power(g) + eps)
        assert bool(((bh - xh * factor).abs() <= tol)[..., stiff].all())
        assert float(factor[stiff].max()) < 0.5 + 1e-12  # damped: |g|^2 < eps  =>  factor < 1/2

    def test_transfer_is_the_order0_exponential(self):
        op = _ks(steps=3)
        lin = op.stepper.linear_symbol
        torch.testing.assert_close(op.transfer, torch.exp(3 * 0.25 * lin).to(op.transfer.dtype))
        torch.testing.assert_close(pde_transfer(op.stepper, 3), torch.exp(3 * 0.25 * lin))

    @pytest.mark.parametrize("boundaries", ["periodic", "dirichlet", "neumann"])
    def test_linear_equation_is_inverted_exactly(self, boundaries):
        # diffusion is its own linear part: forward == linear_forward, and eps = 0 inverts every mode
        op = PDEOperator("diffusion", 5, eps=0.0, diffusivity=0.002, resolution=24, dt=0.1, boundaries=boundaries)
        x = random_field(op.stepper, batch=2, max_wavenumber=6, seed=3)
        y = op.forward(x)
        torch.testing.assert_close(y, op.linear_forward(x), rtol=0, atol=1e-15)
        x_rec = op.local_inverse(y, torch.zeros_like(x))
        torch.testing.assert_close(x_rec, x, rtol=0, atol=1e-12)

    def test_complex_symbol_advection(self):
        op = PDEOperator("advection", 7, eps=1e-3, velocity=0.7, resolution=20, dt=0.05)
        assert op.transfer.is_complex()
        x = random_field(op.stepper, batch=2, max_wavenumber=8, seed=4)
        torch.testing.assert_close(op.linear_inverse(op.forward(x)), x, rtol=0, atol=1e-13)

    def test_wave_inverse_runs_the_propagator_backwards(self):
        stepper = Wave(1, speed=1.3, resolution=32, dt=0.05, dtype=torch.float64)
        op = PDEOperator(stepper, 6)
        x = random_field(stepper, batch=2, max_wavenumber=6, seed=5)
        y = op.forward(x)
        torch.testing.assert_close(y, stepper.repeat(x, 6), rtol=0, atol=1e-13)
        torch.testing.assert_close(op.linear_inverse(y), x, rtol=0, atol=1e-12)


# ------------------------------------------------------------------------------------------ the full operator


class TestOperator:
    def test_forward_is_the_stepper(self):
        op = _ks(steps=3)
        x = random_field(op.stepper, batch=2, seed=0)
        torch.testing.assert_close(op.forward(x), op.stepper.repeat(x, 3), rtol=0, atol=0)
        y32 = op.forward(x.float())  # float32 in, float64 physics, float32 out
        assert y32.dtype == torch.float32
        torch.testing.assert_close(y32, op.forward(x).float())

    def test_gradcheck_float64(self):
        op = PDEOperator("kuramoto_sivashinsky", 2, domain=22.0, resolution=12, dt=0.25)
        x = (0.5 * random_field(op.stepper, batch=1, max_wavenumber=3, seed=2)).requires_grad_(True)
        assert torch.autograd.gradcheck(op.forward, (x,), eps=1e-6, atol=1e-7, rtol=1e-5)

    def _toy(self, op, seed=0):
        # a state of the dynamics and a guess a bit off it
        x_true = op.stepper.repeat(random_field(op.stepper, batch=4, max_wavenumber=4, seed=seed), 40)
        gen = torch.Generator().manual_seed(seed + 1)
        x0 = x_true + 0.3 * random_field(op.stepper, batch=4, max_wavenumber=6, seed=seed + 7) \
            + 0.05 * torch.randn(x_true.shape, generator=gen, dtype=torch.float64)
        return x_true, op.forward(x_true), x0

    def _loss(self, op, x, y_target):
        return float(0.5 * ((op.forward(x) - y_target) ** 2).sum())

    @pytest.mark.parametrize("variant", ["linear", "linear+inverse_gradient", "inverse_gradient"])
    def test_pg_update_reduces_the_y_loss(self, variant):
        solver = None if variant == "linear" else InverseGradientSolver(rcond=1e-2)
        op = _ks(steps=2, eps=1e-2, linear_iterations=0 if variant == "inverse_gradient" else 1, solver=solver)
        x_true, y_target, x0 = self._toy(op)
        x_tilde, y0 = physical_update(x0, y_target, op)  # eta = 1: the local inverse of y*
        before, after = self._loss(op, x0, y_target), self._loss(op, x_tilde, y_target)
        assert after < 0.5 * before, (before, after)
        torch.testing.assert_close(y0, op.forward(x0))
        # and it moves x towards x*
        assert float((x_tilde - x_true).abs().sum()) < float((x0 - x_true).abs().sum())

    def test_combined_inverse_beats_the_linear_one(self):
        lin = _ks(steps=2, eps=1e-2)
        both = _ks(steps=2, eps=1e-2, solver=InverseGradientSolver(rcond=1e-2))
        x_true, y_target, x0 = self._toy(lin, seed=3)
        a = self._loss(lin, lin.local_inverse(y_target, x0), y_target)
        b = self._loss(both, both.local_inverse(y_target, x0), y_target)
        assert b < a

    def test_linear_part_solver_equals_the_operator_picard_steps(self):
        op = _ks(steps=2, eps=1e-2, linear_iterations=2)
        x_true, y_target, x0 = self._toy(op, seed=5)
        a = op.local_inverse(y_target, x0)
        b = LinearPartSolver(2)(op, y_target, x0)
        torch.testing.assert_close(a, b, rtol=0, atol=0)


# ------------------------------------------------------------------------------------------ problem and training

SMALL = dict(resolution=16, warmup_steps=20, width=4, blocks=1, kernel_size=3, batch_size=4, heldout_size=8)


class TestProblem:
    def test_registered_and_methods(self):
        p = get_problem("pde", **SMALL)
        assert isinstance(p, PDEProblem)
        assert {"adam", "pg", "pg_linear", "hig", "pg_inverse_gradient", "pg_lbfgsb", "supervised"} <= set(p.methods)
        b = p.sample(3, torch.Generator().manual_seed(0))
        assert b.inputs.shape == (3, 1, 16) and b.x_true.shape == (3, 1, 16)
        torch.testing.assert_close(b.y_target, p.operator().forward(b.x_true.double()).float())
        assert torch.equal(p.heldout().x_true, p.heldout().x_true)

    def test_network_starts_as_identity(self):
        net = ConvResNet(1, 1, width=4, blocks=2)
        x = torch.randn(2, 1, 16)
        assert torch.equal(net(x), x)
        with pytest.raises(ShapeError):
            net(torch.randn(2, 16))

    def test_each_method_trains(self):
        p = get_problem("pde", lr=1e-2, hig_lr=0.3, **SMALL)
        held = p.heldout()
        with torch.no_grad():  # the untrained network is the identity: x = y*
            start_loss = float(p.loss(held.operator(held.inputs), held.y_target).mean())
            start_metric = float(p.metric(held.inputs, held).mean())
        improved = []
        for method in ("adam", "pg", "hig"):
            r = train(p, method, iterations=8, seed=0, eval_every=0)
            assert r.curves["loss"].shape == (8,) and bool(torch.isfinite(torch.as_tensor(r.curves["loss"])).all())
            end_loss, end_metric = r.curves["eval_loss"][-1], r.curves["eval_metric"][-1]
            assert math.isfinite(end_loss) and math.isfinite(end_metric), method
            improved.append(end_loss < start_loss and end_metric < start_metric)
        assert any(improved), improved

    def test_burgers_settings(self):
        p = get_problem("pde", equation="Burgers", domain=2 * math.pi, dt=0.02, steps=3,
                        amplitude=0.3, equation_settings={"viscosity": 0.1}, **{**SMALL, "warmup_steps": 0})
        assert p.operator().stepper.viscosity == 0.1
        r = train(p, "pg_linear", iterations=2, seed=0, eval_every=0)
        assert math.isfinite(r.curves["eval_metric"][-1])

    def test_two_d_equation(self):
        p = get_problem("pde", equation="kolmogorov", resolution=16, domain=2 * math.pi, dt=0.01, warmup_steps=2,
                        heldout_size=2, batch_size=2, width=4, blocks=1)
        assert p.ndim == 2 and p.state_shape == (1, 16, 16)
        for method in ("pg", "hig"):
            r = train(p, method, iterations=1, seed=0, eval_every=0)
            assert math.isfinite(r.curves["eval_metric"][-1]), method
        with pytest.raises(ParameterError, match="2-D"):
            get_problem("pde", equation="kolmogorov", ndim=1)

    def test_custom_route(self):
        # a PDEOperator's simulate is a physics function and its local_inverse a local inverse for make_problem
        op = _ks(steps=2, eps=1e-2)
        stepper = op.stepper

        def data(batch_size, generator):
            noise = torch.randn((batch_size, 1, 32), generator=generator, dtype=torch.float64)
            return stepper.repeat(0.3 * noise, 10)

        # simulate: the forward without host reads, which HIG differentiates under torch.func
        problem = make_problem("ks_custom", data=data, physics=op.simulate, local_inverse=op.local_inverse,
                               network=lambda: ConvResNet(1, 1, width=4, blocks=1).double(), batch_size=4,
                               dtype=torch.float64)
        for method in ("pg", "hig"):
            r = train(problem, method, iterations=2, seed=0, eval_every=0)
            assert math.isfinite(r.curves["loss"][-1]), method


# ------------------------------------------------------------------------------------------ bad input


class TestBadInput:
    def test_unknown_equation(self):
        with pytest.raises(ParameterError, match="unknown equation"):
            PDEOperator("kuramoto", 2)
        with pytest.raises(ParameterError, match="unknown equation"):
            get_problem("pde", equation="navier-stokes-3d")
        with pytest.raises(ParameterError, match="equation"):
            PDEOperator(3.0, 2)

    @pytest.mark.parametrize("steps", [0, -1, 1.5, True])
    def test_bad_steps(self, steps):
        with pytest.raises(ParameterError, match="steps"):
            _ks(steps=steps)
        with pytest.raises(ParameterError, match="steps"):
            get_problem("pde", steps=steps)

    @pytest.mark.parametrize("dt", [0.0, -0.25, float("nan")])
    def test_bad_dt(self, dt):
        with pytest.raises(ParameterError, match="dt"):
            PDEOperator("kuramoto_sivashinsky", 2, dt=dt)
        with pytest.raises(ParameterError, match="dt"):
            get_problem("pde", dt=dt)

    def test_bad_settings(self):
        with pytest.raises(ParameterError, match="eps"):
            _ks(eps=-1.0)
        with pytest.raises(ParameterError, match="eps = 0"):
            _ks(steps=8, eps=0.0)  # the highest KS modes are erased to g = 0 over 8 steps
        with pytest.raises(ParameterError, match="linear_iterations"):
            _ks(linear_iterations=0)
        with pytest.raises(ParameterError, match="does not take"):
            PDEOperator("kuramoto_sivashinsky", 2, viscosity=0.1)
        with pytest.raises(ParameterError, match="overflows"):
            PDEOperator("allen_cahn", 10**6, dt=1.0, reactivity=10.0)
        with pytest.raises(ParameterError):
            get_problem("pde", nonlinear_solver="magic")
        with pytest.raises(ParameterError, match="linear_iterations"):
            get_problem("pde", linear_iterations=0, nonlinear_solver="none")
        with pytest.raises(ParameterError, match="viscosity"):
            get_problem("pde", equation="burgers", equation_settings={"viscosity": -1.0})
        with pytest.raises(ParameterError, match="resolution"):
            get_problem("pde", resolution=(16, 16))

    def test_mismatched_shapes(self):
        op = _ks(steps=2)
        x = random_field(op.stepper, batch=2, seed=0)
        with pytest.raises(ShapeError, match="resolution"):
            op.forward(torch.zeros(2, 1, 31, dtype=torch.float64))
        with pytest.raises(ShapeError):
            op.forward(torch.zeros(2, 32, dtype=torch.float64))  # no channel axis
        with pytest.raises(ShapeError):
            op.local_inverse(torch.zeros(2, 1, 16, dtype=torch.float64), x)
        with pytest.raises(ShapeError):
            op.linear_inverse(torch.zeros(2, 2, 32, dtype=torch.float64))
        with pytest.raises(ShapeError):
            op.local_inverse(op.forward(x), torch.zeros(3, 1, 32, dtype=torch.float64))  # batch 2 against 3

    def test_errors_are_phisim_errors(self):
        for make in (lambda: PDEOperator("nope", 1), lambda: _ks(steps=0), lambda: _ks(dt=-1.0)):
            with pytest.raises(PhisimError):
                make()

    def test_given_stepper_with_settings(self):
        stepper = KuramotoSivashinsky(1, domain=22.0, resolution=16, dtype=torch.float64)
        with pytest.raises(ParameterError, match="settings"):
            PDEOperator(stepper, 2, resolution=32)
        assert PDEOperator(stepper, 2).shape == (1, 16)
        assert PDEOperator(Diffusion(1, resolution=8, dtype=torch.float64), 1).transfer.dtype == torch.float64


# ------------------------------------------------------------------------------------------ the example


def test_example_tiny(tmp_path):
    import importlib.util
    from pathlib import Path

    import h5py

    path = Path(__file__).resolve().parents[2] / "examples" / "pde_inverse.py"
    spec = importlib.util.spec_from_file_location("pde_inverse_example", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    out = tmp_path / "run"
    summary = mod.main(["--iterations", "4", "--max-iterations", "hig=2", "--seeds", "0", "1", "--heldout-size", "4",
                        "--eval-every", "2", "--reference-iterations", "2", "--width", "4", "--blocks", "1",
                        "--out", str(out), "--device", "cpu"])
    assert summary["settings"]["device"] == "cpu" and summary["settings"]["common_iteration"] == 2
    table = summary["table"]
    assert set(table) == {"adam", "pg", "pg_linear", "pg_inverse_gradient", "hig"}
    assert all(row["seeds"] == 2 and math.isfinite(row["mean_final"]) for row in table.values())
    assert table["hig"]["iterations"] == 2 and table["adam"]["iterations"] == 4
    assert summary["references"]["local_inverse_2"] < summary["references"]["identity"]
    assert (out / "pde_inverse.png").stat().st_size > 0 and (out / "pde_inverse_modes.png").stat().st_size > 0
    modes = summary["mode_errors"]
    assert len(modes["hig"]) == len(modes["signal"]) == 64 // 2 + 1
    again = mod.main(["--iterations", "4", "--max-iterations", "hig=2", "--seeds", "0", "1", "--heldout-size", "4",
                      "--eval-every", "2", "--reference-iterations", "2", "--width", "4", "--blocks", "1",
                      "--out", str(out), "--plot-only"])
    assert again["table"] == table and again["runs"] == summary["runs"]
    with h5py.File(out / "pde_inverse.h5", "r") as f:
        assert "adam_s1" in f["training"] and "json" in f["summary"].attrs


# ------------------------------------------------------------------------------------------ every equation

_TWO_D = {"navier_stokes", "kolmogorov", "decaying_turbulence"}


@pytest.mark.parametrize("name", sorted(EQUATIONS))
def test_every_equation_has_the_linear_inverse(name):
    grid = {"resolution": 16} if name in _TWO_D or name == "kdv" else {"ndim": 1, "resolution": 16}
    op = PDEOperator(name, 2, eps=1e-6, **grid)
    x = random_field(op.stepper, batch=2, max_wavenumber=3, seed=0)
    if op.transfer is not None:  # the non-stiff modes come back exactly (round-off amplified by the gain only)
        grid_ = op.grid
        xh = grid_.to_spectral(x)
        bh = grid_.to_spectral(op.linear_inverse(op.linear_forward(x)))
        tol = 64 * torch.finfo(torch.float64).eps * float(xh.abs().max()) * (1 + op.gain.abs())
        assert bool((((bh - xh).abs() <= tol) | op.stiff_modes()).all())  # per channel and mode
    else:
        torch.testing.assert_close(op.linear_inverse(op.forward(x)), x, rtol=0, atol=1e-12)
    y = op.forward(x)
    x_rec = op.local_inverse(y, x + 0.01 * random_field(op.stepper, batch=2, max_wavenumber=3, seed=1))
    assert bool(torch.isfinite(x_rec).all()) and x_rec.shape == x.shape
