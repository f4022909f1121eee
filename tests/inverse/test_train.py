"""The training loop: same data stream for all methods, resume equivalence, theorem 1 through the harness, errors."""

from dataclasses import dataclass

import h5py
import numpy as np
import pytest
import torch
from torch import nn

from inverse.cli import main as cli_main
from inverse.local_solvers import GradientStepSolver
from inverse.operators import PhysicsOperator
from inverse.problems import Batch, Method, Problem, get_problem
from inverse.train import batch_generator, train
from phisim.errors import FileFormatError, ParameterError


class CubeOperator(PhysicsOperator):
    """y = x + 0.3 x^3 elementwise (nonlinear, invertible)."""

    def _forward(self, x):
        return x + 0.3 * x**3

    def _local_inverse(self, y_target, x0, y0):
        x = x0.clone()
        for _ in range(50):  # Newton on the scalar cubic
            x = x - (x + 0.3 * x**3 - y_target) / (1 + 0.9 * x**2)
        return x


@dataclass
class ToyProblem(Problem):
    """Inputs z ~ N(0, 1)^4, x* = tanh(A z), y* = P(x*); a linear network z -> x."""

    name: str = "toy"
    batch_size: int = 8
    reduction: str = "sum"
    dtype: torch.dtype = torch.float64

    def __post_init__(self):
        self.methods = {
            "sgd_physics": Method("sgd_physics", "physics", optimizer="sgd", lr=0.01),
            "sgd_pg_gradstep": Method("sgd_pg_gradstep", "physgrad", optimizer="sgd", lr=0.01,
                                      local_solver=GradientStepSolver(step_size=1.0)),
            "adam_pg": Method("adam_pg", "physgrad", lr=0.01),
        }
        self.A = torch.randn(4, 4, generator=torch.Generator().manual_seed(7), dtype=torch.float64)

    def make_network(self):
        return nn.Linear(4, 4, dtype=torch.float64)

    def sample(self, batch_size, generator, device=None):
        z = torch.randn(batch_size, 4, generator=generator, dtype=torch.float64)
        x = torch.tanh(z @ self.A.T)
        op = CubeOperator()
        return Batch(z, op.forward(x), x, op)

    def predict(self, model, batch):
        return model(batch.inputs)


def test_batch_stream_is_reproducible_and_method_independent():
    p = get_problem("sine")
    a = p.sample(16, batch_generator(3, 5))
    b = p.sample(16, batch_generator(3, 5))
    c = p.sample(16, batch_generator(3, 6))
    assert torch.equal(a.inputs, b.inputs)
    assert not torch.equal(a.inputs, c.inputs)


def test_theorem1_through_the_harness():
    """A one-gradient-step local inverse with eta = 1 trains exactly like backpropagation through P."""
    p = ToyProblem()
    r1 = train(p, "sgd_physics", iterations=5, seed=2)
    r2 = train(p, "sgd_pg_gradstep", iterations=5, seed=2)
    for a, b in zip(r1.model.parameters(), r2.model.parameters()):
        torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-13)
    np.testing.assert_allclose(r1.curves["loss"], r2.curves["loss"], rtol=1e-12)


def test_physical_gradients_with_exact_inverse_converge_faster_than_backprop():
    p = ToyProblem()
    adam = train(p, Method("adam", "physics", lr=0.01), iterations=150, seed=0)
    pg = train(p, "adam_pg", iterations=150, seed=0)
    assert pg.final("metric") < adam.final("metric")


def test_resume_continues_exactly(tmp_path):
    p = ToyProblem()
    full = train(p, "adam_pg", iterations=10, seed=1, out=tmp_path / "a.h5")
    # a run that is "killed" after 7 iterations with a checkpoint at 5, then resumed to 10
    train(p, "adam_pg", iterations=7, seed=1, out=tmp_path / "b.h5", checkpoint_every=5)
    resumed = train(p, "adam_pg", iterations=10, seed=1, out=tmp_path / "b.h5", checkpoint_every=5, resume=True)
    np.testing.assert_array_equal(resumed.curves["iteration"], np.arange(10))
    np.testing.assert_allclose(resumed.curves["metric"], full.curves["metric"], rtol=1e-12)
    for a, b in zip(full.model.parameters(), resumed.model.parameters()):
        torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-14)
    with h5py.File(tmp_path / "b.h5") as f:
        assert f["training/adam_pg/metric"].shape == (10,)
        assert f["training/adam_pg"].attrs["problem"] == "toy"


def test_training_errors(tmp_path):
    p = ToyProblem()
    with pytest.raises(ParameterError):
        train(p, "nope", iterations=1)
    with pytest.raises(ParameterError):
        train(p, "adam_pg", iterations=1, resume=True)
    with pytest.raises(ParameterError):
        train(p, "adam_pg", iterations=-1)
    out = tmp_path / "c.h5"
    (tmp_path / "c.h5.adam_pg.ckpt").write_bytes(b"not a checkpoint")
    with pytest.raises(FileFormatError):
        train(p, "adam_pg", iterations=2, out=out, resume=True)
    train(p, "adam_pg", iterations=2, seed=0, out=tmp_path / "d.h5", checkpoint_every=1)
    with pytest.raises(FileFormatError, match="seed"):
        train(p, "adam_pg", iterations=3, seed=5, out=tmp_path / "d.h5", resume=True)


def test_sine_supervised_learns_and_pg_analytic_runs():
    p = get_problem("sine", batch_size=100)
    sup = train(p, "supervised", iterations=150, seed=0)
    # the regression onto the closest-solution labels converges (the y-space metric only follows slowly)
    assert sup.final("objective", 20) < 0.5 * sup.curves["objective"][:5].mean()
    pg = train(p, "pg_analytic", iterations=3, seed=0)
    assert np.isfinite(pg.curves["metric"]).all()


def test_cli_train_and_errors(tmp_path, capsys):
    out = tmp_path / "s.h5"
    assert cli_main(["train", "sine", "adam", "--iterations", "3", "--batch-size", "10", "--out", str(out),
                     "--quiet"]) == 0
    assert '"final_metric"' in capsys.readouterr().out
    assert cli_main(["info", str(out)]) == 0
    assert "/training/adam/metric (3,)" in capsys.readouterr().out
    assert cli_main(["train", "sine", "nope", "--iterations", "1", "--quiet"]) == 2
    assert "no method 'nope'" in capsys.readouterr().err
    (tmp_path / "bad.h5").write_text("garbage")
    assert cli_main(["info", str(tmp_path / "bad.h5")]) == 2


# ---- no silent loss: a run over an earlier one needs resume or overwrite ---------------------------------


def test_a_second_run_of_a_method_is_refused_unless_resume_or_overwrite(tmp_path):
    p = ToyProblem()
    out = tmp_path / "o.h5"
    first = train(p, "adam_pg", iterations=4, seed=1, out=out, checkpoint_every=2)
    with h5py.File(out, "r") as f:
        g = f["training/adam_pg"]
        assert g.attrs["planned_iterations"] == 4 and bool(g.attrs["complete"])
    with pytest.raises(FileFormatError, match=r"already holds a run of 'adam_pg' \(complete \(4 iterations\)\)"):
        train(p, "adam_pg", iterations=4, seed=2, out=out)
    np.testing.assert_array_equal(h5py.File(out, "r")["training/adam_pg/metric"][()], first.curves["metric"])
    with pytest.raises(ParameterError, match="exclude"):
        train(p, "adam_pg", iterations=4, out=out, resume=True, overwrite=True)
    train(p, "sgd_physics", iterations=2, seed=1, out=out)  # another method in the same file is fine
    again = train(p, "adam_pg", iterations=3, seed=2, out=out, overwrite=True)
    assert not (tmp_path / "o.h5.adam_pg.ckpt").exists()  # the replaced run's checkpoint is gone
    with h5py.File(out, "r") as f:
        np.testing.assert_array_equal(f["training/adam_pg/metric"][()], again.curves["metric"])
        assert f["training/adam_pg"].attrs["seed"] == 2 and f["training/adam_pg/iteration"].shape == (3,)
        assert f["training/sgd_physics/iteration"].shape == (2,)
    with pytest.raises(FileFormatError, match="no checkpoint"):  # nothing to resume from: refused too
        train(p, "adam_pg", iterations=6, seed=2, out=out, resume=True)


def test_resume_continues_an_interrupted_run_and_marks_it_complete(tmp_path):
    p = ToyProblem()
    out = tmp_path / "i.h5"

    def stop_at_5(it, record):
        if it == 5:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        train(p, "adam_pg", iterations=8, seed=1, out=out, checkpoint_every=4, callback=stop_at_5)
    from phisim.errors import IncompleteFileWarning
    from phisim.io import read_training

    with pytest.warns(IncompleteFileWarning, match="stopped after 6 of 8"):
        run = read_training(out)["adam_pg"]
    assert run.complete is False and not (tmp_path / "i.h5.adam_pg.model.pt").exists()
    resumed = train(p, "adam_pg", iterations=8, seed=1, out=out, checkpoint_every=4, resume=True)
    full = train(p, "adam_pg", iterations=8, seed=1, out=tmp_path / "f.h5")
    np.testing.assert_array_equal(resumed.curves["metric"], full.curves["metric"])
    assert read_training(out)["adam_pg"].complete is True


def test_cli_overwrite_and_compare_checks_every_method_first(tmp_path, capsys):
    out = str(tmp_path / "c.h5")
    args = ["--iterations", "2", "--batch-size", "10", "--out", out, "--quiet"]
    assert cli_main(["train", "sine", "adam", *args]) == 0
    capsys.readouterr()
    assert cli_main(["compare", "sine", "supervised", "adam", *args]) == 2
    assert "already holds a run of 'adam'" in capsys.readouterr().err
    with h5py.File(out, "r") as f:
        assert sorted(f["training"]) == ["adam"]  # refused before the first method trained
    assert cli_main(["compare", "sine", "supervised", "adam", *args, "--overwrite"]) == 0
    with h5py.File(out, "r") as f:
        assert sorted(f["training"]) == ["adam", "supervised"]
    capsys.readouterr()
    assert cli_main(["info", out]) == 0
    text = capsys.readouterr().out
    assert "run adam: complete (2 iterations)" in text and "run supervised: complete (2 iterations)" in text
