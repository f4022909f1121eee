"""Selectable solvers of the E3 Poisson problem and the per-method HIG loss of E2."""

from __future__ import annotations

import pytest
import torch

from inverse.problems import get_problem
from inverse.train import batch_generator, train
from phisim.errors import ParameterError
from phisim.solvers.poisson import stencil_laplacian


def test_spectral_data_are_exact_and_agree_with_cg_data():
    """``y*`` from the DST solve satisfies ``∇²_h y* = x*`` to round-off; the CG-made ``y*`` agrees to its rtol."""
    settings = dict(resolution=(16, 16), dtype=torch.float64)
    spectral = get_problem("poisson", **settings).sample(3, batch_generator(0, 0))
    cg = get_problem("poisson", data_solver="cg", **settings).sample(3, batch_generator(0, 0))
    torch.testing.assert_close(spectral.x_true, cg.x_true, rtol=0, atol=0)  # same noise
    residual = stencil_laplacian(spectral.y_target, 1.0, "dirichlet") - spectral.x_true
    assert float(residual.norm() / spectral.x_true.norm()) < 1e-12
    rel = float((spectral.y_target - cg.y_target).norm() / spectral.y_target.norm())
    assert rel < 1e-4  # CG stops at rtol 1e-5 on the residual; the solution error is within a small factor


def test_training_solver_is_selectable_and_gives_the_same_physics():
    plain = get_problem("poisson", resolution=(16, 16), dtype=torch.float64)
    fast = get_problem("poisson", resolution=(16, 16), dtype=torch.float64, solver="spectral")
    assert plain.operator().preconditioner is None and fast.operator().preconditioner == "spectral"
    x = plain.sample(2, batch_generator(1, 0)).x_true
    y_plain, y_fast = plain.operator()(x), fast.operator()(x)
    assert float((y_plain - y_fast).norm() / y_fast.norm()) < 1e-4


@pytest.mark.parametrize("key", ["solver", "data_solver"])
def test_unknown_solver_is_rejected(key):
    with pytest.raises(ParameterError, match=key):
        get_problem("poisson", **{key: "multigrid"})


def test_hig_squared_differentiates_the_squared_loss():
    """E2's ``hig_squared`` logs the mean of ``½ (sin(a/x) + 1)²`` as its objective (the loss HIG steps on)."""
    problem = get_problem("sine", dtype=torch.float64)
    res = train(problem, "hig_squared", iterations=2, batch_size=16, seed=0)
    torch.manual_seed(0)
    net = problem.make_network().to(torch.float64)
    batch = problem.sample(16, batch_generator(0, 0))
    with torch.no_grad():
        h = problem.metric(problem.predict(net, batch), batch)
    assert res.curves["objective"][0] == pytest.approx(float((0.5 * h**2).mean()), rel=1e-12)
    assert problem.method("hig_squared").lr == 1.0
    assert problem.method("hig").loss is None  # the original HIG method keeps the problem's linear loss
