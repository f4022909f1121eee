"""The HIG examples run at tiny size and write sane HDF5 curves and PNG figures."""

from __future__ import annotations

import h5py
import numpy as np
import pytest
import torch


def test_hig_toy_tiny(tmp_path, load_example):
    toy = load_example("hig_toy")
    finals = toy.main(["--iterations", "40", "--records", "10", "--batch-size", "64", "--out", str(tmp_path),
                       "--device", "cpu"])
    assert set(finals) == {1.0, 0.01}
    for lam in ("1", "0.01"):
        assert (tmp_path / f"hig_toy_lambda{lam}.png").stat().st_size > 5_000
        with h5py.File(tmp_path / f"hig_toy_lambda{lam}.h5", "r") as f:
            assert float(f.attrs["lambda"]) == float(lam) and f.attrs["device"] == "cpu"
            for m in ("adam", "gn", "hig"):
                g = f[f"training/{m}"]
                loss, it = g["loss"][()], g["iteration"][()]
                assert it[0] == 0 and it[-1] == 40 and loss.shape == it.shape
                assert np.all(np.isfinite(loss))
                assert g["y_path"].shape == (it.size, 2)
                std = g["act_std"][()]
                assert np.all((std >= 0) & (std <= 1)) and np.all(np.abs(g["act_mean"][()]) <= 1)
            hig = f["training/hig/loss"][()]
            assert hig[-1] < hig[0]  # HIG makes progress in 40 steps
            np.testing.assert_allclose(f["extras/sample_target"][()], [np.sin(1.8), np.cos(2.7)], rtol=1e-12)


def test_hig_toy_target_and_net(load_example):
    toy = load_example("hig_toy")
    x = torch.tensor([[0.0], [0.5]], dtype=torch.float64)
    np.testing.assert_allclose(toy.target(x).numpy(), [[0.0, 1.0], [np.sin(3.0), np.cos(4.5)]], rtol=1e-14)
    assert sum(p.numel() for p in toy.make_net(0, torch.float32).parameters()) == 7 + 7 + 14 + 2


def test_oscillator_physics_is_exact_rk4_of_the_linear_system(load_example):
    osc = load_example("hig_oscillators")
    # free motion (u = 0) of the linear system s' = A s: RK4 multiplies by the degree-4 Taylor polynomial
    lap = osc.laplacian(2)
    torch.testing.assert_close(lap, torch.tensor([[-1.0, 1.0], [1.0, -1.0]], dtype=torch.float64))
    A = torch.zeros(4, 4, dtype=torch.float64)
    A[:2, 2:] = torch.eye(2)
    A[2:, :2] = -torch.eye(2) + 0.2 * lap
    h = osc.DT * A
    step = torch.eye(4, dtype=torch.float64) + h + h @ h / 2 + h @ h @ h / 6 + h @ h @ h @ h / 24
    s0 = torch.rand(3, 4, dtype=torch.float64)
    expected = s0 @ torch.linalg.matrix_power(step, osc.N_STEPS).mT
    torch.testing.assert_close(osc.simulate(torch.zeros(3, osc.N_STEPS, dtype=torch.float64), s0), expected)
    # the control enters as s' = A s + b u with b = e_last velocity; a pulse in the last step gives the
    # RK4 response DT (I + h/2 + h^2/6 + h^3/24) b
    du = torch.zeros(1, osc.N_STEPS, dtype=torch.float64)
    du[0, -1] = 1.0
    d = osc.simulate(du, torch.zeros(1, 4, dtype=torch.float64))[0]
    b = torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=torch.float64)
    resp = osc.DT * (torch.eye(4, dtype=torch.float64) + h / 2 + h @ h / 6 + h @ h @ h / 24) @ b
    torch.testing.assert_close(d, resp)


def test_hig_oscillators_tiny(tmp_path, load_example):
    osc = load_example("hig_oscillators")
    finals = osc.main(["--epochs", "3", "--n-train", "256", "--out", str(tmp_path), "--device", "cpu"])
    assert set(finals) == {"hig", "adam", "gn"}
    assert (tmp_path / "hig_oscillators.png").stat().st_size > 5_000
    with h5py.File(tmp_path / "hig_oscillators.h5", "r") as f:
        assert f.attrs["device"] == "cpu"
        for m in ("hig", "adam", "gn"):
            loss = f[f"training/{m}/loss"][()]
            assert f[f"training/{m}/epoch"][-1] >= 1
            assert np.all(np.diff(f[f"training/{m}/time"][()]) > 0)
            assert loss[0] > 0
        hig = f["training/hig/loss"][()]
        adam = f["training/adam/loss"][()]
        assert np.all(np.isfinite(hig)) and np.all(np.diff(hig) < 0)  # HIG decreases every epoch
        assert hig[-1] < 0.3 * hig[0]
        assert hig[-1] < adam[-1]


@pytest.mark.parametrize("bad", [["--iterations", "0"], ["--batch-size", "0"]])
def test_hig_toy_rejects_bad_options(bad, tmp_path, load_example):
    toy = load_example("hig_toy")
    with pytest.raises(SystemExit):
        toy.main(bad + ["--out", str(tmp_path)])


def test_cached_step_operators_equal_the_rk4_stages(load_example):
    osc = load_example("hig_oscillators")
    gen = torch.Generator().manual_seed(3)
    u = torch.randn(5, osc.N_STEPS, generator=gen, dtype=torch.float64)
    s0 = torch.rand(5, 4, generator=gen, dtype=torch.float64)
    torch.testing.assert_close(osc.simulate(u, s0), osc.simulate_stages(u, s0), rtol=1e-13, atol=1e-13)
    # float32 operators are the float64 ones rounded once: agreement at float32 precision
    torch.testing.assert_close(osc.simulate(u.float(), s0.float()), osc.simulate_stages(u, s0).float(),
                               rtol=2e-5, atol=2e-5)
    a = osc.rk4_step_operators(2, torch.float64)
    assert osc.rk4_step_operators(2, torch.float64) is a  # built once, then reused


# Headline regressions (E6): short seeded float64 runs with pinned ratios. A change that makes HIG lose its
# lead over Adam / Gauss-Newton, or halves it, fails; round-off does not: the runs are float64, a few hundred
# updates long, and the SVD truncation (rcond 1e-6 / 1e-10 relative) sits far from the kept spectrum's floor,
# so cross-machine round-off moves the ratios by far less than the 10% allowed.


def test_headline_hig_ahead_of_adam_and_gauss_newton_on_the_toy(load_example):
    """lambda = 0.01, 200 steps of batch 64: final validation losses Adam 0.458, GN 0.216, HIG 0.113."""
    toy = load_example("hig_toy")
    args = toy.parse_args(["--lambdas", "0.01", "--dtype", "float64", "--iterations", "200", "--batch-size", "64",
                           "--records", "4"])
    final = {m: float(toy.train(m, 0.01, args)["loss"][-1]) for m in ("adam", "gn", "hig")}
    assert final["hig"] < final["gn"] < final["adam"], final
    assert final["adam"] / final["hig"] == pytest.approx(0.4577285567753786 / 0.11313627615323509, rel=0.1)
    assert final["gn"] / final["hig"] == pytest.approx(0.21599331958009177 / 0.11313627615323509, rel=0.1)


def test_headline_hig_ahead_on_the_oscillators(load_example):
    """256 states, 2 epochs: loss per sample Adam 0.603, Gauss-Newton 0.141, HIG 0.0278."""
    osc = load_example("hig_oscillators")
    args = osc.parse_args(["--epochs", "2", "--n-train", "256", "--dtype", "float64"])
    data = torch.rand(256, 4, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    final = {m: float(osc.train(m, data, args)["loss"][-1]) for m in ("adam", "gn", "hig")}
    assert final["hig"] < final["gn"] < final["adam"], final
    assert final["adam"] / final["hig"] == pytest.approx(0.6029420275593753 / 0.02780711953500361, rel=0.1)
    assert final["gn"] / final["hig"] == pytest.approx(0.14134101031520158 / 0.02780711953500361, rel=0.1)
