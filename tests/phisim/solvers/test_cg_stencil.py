"""cg on the fused stencil operator (:func:`phisim.ops.stencil.negative_laplacian`): agreement with scipy's sparse
direct solve of the same matrix for every boundary kind, and the implicit gradient by gradcheck (float64)."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as spla
import torch

from phisim.ops.stencil import negative_laplacian
from phisim.solvers.linalg import Solve, cg, remove_mean

D = torch.float64


def _matrix(res, dx, kinds) -> sp.csr_matrix:
    """``-∇²_h`` with zero boundary values as a sparse matrix (C order), built from 1-D pieces."""
    def d2(n, h, kind):
        main = 2.0 * np.ones(n)
        off = -np.ones(n - 1)
        m = sp.lil_matrix(sp.diags([off, main, off], [-1, 0, 1], shape=(n, n)))
        if kind == "periodic":
            m[0, n - 1] += -1.0
            m[n - 1, 0] += -1.0
        else:
            m[0, 0] += 1.0 if kind == "dirichlet" else -1.0
            m[n - 1, n - 1] += 1.0 if kind == "dirichlet" else -1.0
        return sp.csr_matrix(m) / h**2

    out = 0
    for a, n in enumerate(res):
        pieces = [sp.identity(m) for m in res]
        pieces[a] = d2(n, dx[a], kinds)
        term = pieces[0]
        for p in pieces[1:]:
            term = sp.kron(term, p)
        out = out + term
    return sp.csr_matrix(out)


@pytest.mark.parametrize("res", [(40,), (12, 17), (6, 5, 7)], ids=lambda r: f"{len(r)}d")
@pytest.mark.parametrize("kinds", ["dirichlet", "neumann", "periodic"])
@pytest.mark.parametrize("batch", [1, 3])
def test_cg_on_the_fused_operator_matches_scipy(res, kinds, batch):
    dx = tuple(0.5 + 0.25 * a for a in range(len(res)))
    gen = torch.Generator().manual_seed(2)
    b = torch.randn(batch, *res, generator=gen, dtype=D)
    singular = kinds != "dirichlet"
    if singular:
        b = remove_mean(b)
    x, info = cg(lambda u: negative_laplacian(u, dx, kinds), b, solve=Solve(rtol=1e-11),
                 project=remove_mean if singular else None, return_info=True)
    assert info.all_converged
    A = _matrix(res, dx, kinds)
    n = int(np.prod(res))
    for s in range(batch):
        rhs = b[s].numpy().ravel()
        if singular:  # fix the constant: solve the bordered system [A 1; 1^T 0]
            K = sp.bmat([[A, np.ones((n, 1))], [np.ones((1, n)), None]]).tocsc()
            ref = spla.spsolve(K, np.append(rhs, 0.0))[:n]
        else:
            ref = spla.spsolve(A.tocsc(), rhs)
        err = np.linalg.norm(x[s].numpy().ravel() - ref) / np.linalg.norm(ref)
        assert err < 1e-8
        # the operator is the matrix
        u = torch.randn(res, generator=gen, dtype=D)
        torch.testing.assert_close(negative_laplacian(u[None], dx, kinds)[0].numpy().ravel(),
                                   A @ u.numpy().ravel(), rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("batch", [1, 2])
def test_implicit_gradient_through_the_fused_operator(batch):
    gen = torch.Generator().manual_seed(8)
    b = torch.randn(batch, 4, 5, generator=gen, dtype=D, requires_grad=True)

    def f(b):
        return cg(lambda u: negative_laplacian(u, (1.0, 0.5), "dirichlet"), b, solve=Solve(rtol=1e-13))

    assert torch.autograd.gradcheck(f, (b,))
    assert torch.autograd.gradgradcheck(f, (b,))
