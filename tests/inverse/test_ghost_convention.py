"""E3's alternative boundary convention: zero Dirichlet value in the ghost cells (the reference code's)."""

import numpy as np
import pytest
import scipy.sparse as sp
import torch

from inverse.operators import Poisson, ghost_dirichlet_laplacian, ghost_dirichlet_solve
from inverse.problems import PoissonProblem
from inverse.train import _identity_diff, _run_identity
from phisim.errors import ParameterError
from phisim.solvers.poisson import stencil_laplacian


def _ghost_matrix(n, m, dx, dy):
    def lap1(k, h):  # ghost 0: the boundary rows keep -2 on the diagonal
        return sp.diags([np.ones(k - 1), -2 * np.ones(k), np.ones(k - 1)], [-1, 0, 1]) / h**2

    return sp.kron(lap1(n, dx), sp.eye(m)) + sp.kron(sp.eye(n), lap1(m, dy))


def test_ghost_laplacian_matches_the_sparse_stencil_and_differs_from_the_face_one_at_the_boundary():
    n, m, dx = 7, 5, (0.5, 1.5)
    u = torch.randn(2, n, m, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    A = _ghost_matrix(n, m, *dx)
    ref = np.stack([A @ u[b].numpy().ravel() for b in range(2)]).reshape(2, n, m)
    got = ghost_dirichlet_laplacian(u, dx)
    np.testing.assert_allclose(got.numpy(), ref, rtol=1e-12, atol=1e-12)
    diff = got - stencil_laplacian(u, dx, "dirichlet")
    torch.testing.assert_close(diff[:, 1:-1, 1:-1], torch.zeros_like(diff[:, 1:-1, 1:-1]))  # interior: equal
    torch.testing.assert_close(diff[:, 0, 2], u[:, 0, 2] / dx[0] ** 2)  # one side: +u/dx^2


def test_ghost_solve_is_the_exact_inverse_and_gradcheck():
    x = torch.randn(3, 9, 6, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    y = ghost_dirichlet_solve(x, (1.0, 0.7))
    torch.testing.assert_close(ghost_dirichlet_laplacian(y, (1.0, 0.7)), x, rtol=1e-11, atol=1e-11)
    v = x[:1, :4, :3].clone().requires_grad_(True)
    assert torch.autograd.gradcheck(lambda t: ghost_dirichlet_solve(t, 1.0), (v,))


def test_poisson_operator_ghost_convention_forward_inverse_and_cg_agree():
    x = torch.randn(2, 12, 12, dtype=torch.float64, generator=torch.Generator().manual_seed(2))
    exact = ghost_dirichlet_solve(x)
    for pre in (None, "spectral"):
        op = Poisson(convention="ghost", preconditioner=pre)
        y = op.forward(x)
        assert float((y - exact).norm() / exact.norm()) < 1e-4  # CG to rtol 1e-5
        torch.testing.assert_close(op._local_inverse(exact, x, None), x, rtol=1e-10, atol=1e-10)
    torch.testing.assert_close(Poisson(convention="ghost").exact_solve(x), exact)
    with pytest.raises(ParameterError):
        Poisson(convention="edge")
    with pytest.raises(ParameterError):
        Poisson(kinds="neumann", convention="ghost")


def test_problem_boundary_option_and_old_checkpoints_resume():
    face, ghost = PoissonProblem(resolution=(16, 16)), PoissonProblem(resolution=(16, 16), boundary="ghost")
    gen = torch.Generator().manual_seed(3)
    b = ghost.sample(2, gen)
    torch.testing.assert_close(ghost_dirichlet_laplacian(b.y_target.double()).float(), b.x_true,
                               rtol=1e-4, atol=1e-4)
    with pytest.raises(ParameterError):
        PoissonProblem(boundary="edge")
    # a checkpoint written before the setting existed resumes a run that uses its default, not another value
    saved = _run_identity(face, 16)
    del saved["boundary"]
    assert _identity_diff(saved, _run_identity(face, 16), face) == {}
    assert set(_identity_diff(saved, _run_identity(ghost, 16), ghost)) == {"boundary"}
