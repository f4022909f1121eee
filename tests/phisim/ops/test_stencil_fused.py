"""The fused Laplacian (ghost values folded into the stencil, no padded copy) against the padded reference.

``laplace(CenteredGrid)`` takes the fused kernel of :mod:`phisim.ops.stencil` when every side is periodic or has a
constant ghost rule, and the padded path otherwise; :func:`negative_laplacian` is ``-stencil_laplacian``. Both must
equal the padded second differences to rounding on random fields for every boundary, be exact on quadratic
polynomials (in the interior; everywhere for Neumann sides given the polynomial's own fluxes), differentiate
(gradcheck, float64) and trace as one graph.
"""

from __future__ import annotations

import warnings

import pytest
import torch

from phisim import CenteredGrid, Grid, laplace
from phisim.boundary import Dirichlet, Neumann, pad
from phisim.ops.stencil import negative_laplacian, normalize_dx, normalize_kinds, stencil_laplacian

D = torch.float64

BOUNDARIES = ["periodic", "dirichlet", "neumann", "wall", "open", "free_slip", Dirichlet(1.5), Neumann(-0.7)]
RESOLUTIONS = [(7,), (6, 9), (5, 4, 6)]


def _padded_reference(f: CenteredGrid) -> torch.Tensor:
    """Second differences of the ghost-padded array, ``(hi - 2 c + lo) / dx²`` per axis (the padded path)."""
    p = pad(f.values, f.boundary, f.grid.dx, 1)
    rank = f.grid.rank
    core = (slice(None),) + (slice(1, -1),) * rank
    out = 0
    for a in range(rank):
        lo, hi = list(core), list(core)
        lo[1 + a], hi[1 + a] = slice(0, -2), slice(2, None)
        out = out + (p[tuple(hi)] - 2 * p[core] + p[tuple(lo)]) / f.grid.dx[a] ** 2
    return out


def _grid(res):
    return Grid(res, bounds=[(0.0, 1.3 * (a + 1)) for a in range(len(res))])


def _mixed(rank):
    return [("dirichlet", Neumann(2.0))] + ["periodic"] * (rank - 1)


@pytest.mark.parametrize("res", RESOLUTIONS, ids=lambda r: f"{len(r)}d")
@pytest.mark.parametrize("boundary", BOUNDARIES + ["mixed"], ids=str)
@pytest.mark.parametrize("dtype", [torch.float32, D], ids=["f32", "f64"])
def test_fused_laplace_equals_padded_reference(res, boundary, dtype):
    gen = torch.Generator().manual_seed(3)
    bc = _mixed(len(res)) if boundary == "mixed" else boundary
    f = CenteredGrid(torch.randn(2, *res, generator=gen, dtype=D).to(dtype), _grid(res), bc)
    got, ref = laplace(f).values, _padded_reference(f)
    scale = float(ref.abs().max())
    eps = torch.finfo(dtype).eps
    torch.testing.assert_close(got, ref, rtol=0, atol=16 * eps * scale)


def test_multichannel_scalar_field_uses_every_channel_as_a_scalar():
    gen = torch.Generator().manual_seed(4)
    g = _grid((6, 5))
    v = torch.randn(2, 3, 6, 5, generator=gen, dtype=D)
    got = laplace(CenteredGrid(v, g, Dirichlet(0.5))).values
    for c in range(3):
        ref = _padded_reference(CenteredGrid(v[:, c], g, Dirichlet(0.5)))
        torch.testing.assert_close(got[:, c], ref, rtol=0, atol=1e-12)


def test_tensor_boundary_values_take_the_padded_path_and_agree():
    gen = torch.Generator().manual_seed(5)
    g = _grid((6, 5))
    value = torch.randn(1, 1, 5, generator=gen, dtype=D)
    f = CenteredGrid(torch.randn(1, 6, 5, generator=gen, dtype=D), g, [(Dirichlet(value), "neumann"), "periodic"])
    torch.testing.assert_close(laplace(f).values, _padded_reference(f), rtol=0, atol=1e-12)


@pytest.mark.parametrize("kinds", ["dirichlet", "neumann", "periodic", (("dirichlet", "neumann"), "periodic")],
                         ids=str)
@pytest.mark.parametrize("dtype", [torch.float32, D], ids=["f32", "f64"])
def test_negative_laplacian_is_the_negated_stencil_exactly(kinds, dtype):
    u = torch.randn(3, 8, 9, generator=torch.Generator().manual_seed(6), dtype=D).to(dtype)
    dx = (0.5, 0.25)
    assert torch.equal(negative_laplacian(u, dx, kinds), -stencil_laplacian(u, dx, kinds))


def _quadratic(x, rank):
    coef = [0.7, -1.3, 0.4][:rank]
    return 0.3 + sum(c * (x[..., a] - 0.2 * a) ** 2 + 0.5 * x[..., a] for a, c in enumerate(coef)), 2 * sum(coef)


@pytest.mark.parametrize("res", RESOLUTIONS, ids=lambda r: f"{len(r)}d")
@pytest.mark.parametrize("boundary", ["dirichlet", "neumann", "periodic", Dirichlet(1.5)], ids=str)
def test_exact_on_quadratics_in_the_interior(res, boundary):
    g = _grid(res)
    rank = len(res)
    u, lap = _quadratic(g.cell_centers(D), rank)
    got = laplace(CenteredGrid(u[None], g, boundary)).values[0]
    got2 = -negative_laplacian(u[None], g.dx, boundary if isinstance(boundary, str) else "dirichlet")[0]
    inner = (slice(1, -1),) * rank
    for out in (got, got2):
        torch.testing.assert_close(out[inner], torch.full_like(out[inner], lap), rtol=0, atol=1e-11)


@pytest.mark.parametrize("res", RESOLUTIONS, ids=lambda r: f"{len(r)}d")
def test_exact_on_quadratics_everywhere_with_their_neumann_fluxes(res):
    """Ghost ``u + g dx`` with ``g`` the outward derivative on the face is the polynomial's own value there."""
    g = _grid(res)
    rank = len(res)
    x = g.cell_centers(D)
    u, lap = _quadratic(x, rank)
    coef = [0.7, -1.3, 0.4][:rank]
    values = []
    for a in range(rank):
        lo_face, hi_face = 0.0, 1.3 * (a + 1)  # the bounds of _grid
        slab = [1] + list(res)
        slab[1 + a] = 1

        def deriv(face, a=a, slab=slab):
            xs = x.narrow(a, 0, 1).clone()
            xs[..., a] = face
            return (2 * coef[a] * (xs[..., a] - 0.2 * a) + 0.5).reshape(slab)

        values.append((-deriv(lo_face), deriv(hi_face)))  # outward normal derivatives
    got = stencil_laplacian(u[None], g.dx, "neumann", values)[0]
    torch.testing.assert_close(got, torch.full_like(got, lap), rtol=0, atol=1e-11)


@pytest.mark.parametrize("boundary", ["periodic", "dirichlet", Neumann(0.3)], ids=str)
def test_gradcheck_fused_laplace(boundary):
    gen = torch.Generator().manual_seed(7)
    g = _grid((4, 5))
    u = torch.randn(2, 4, 5, generator=gen, dtype=D, requires_grad=True)
    assert torch.autograd.gradcheck(lambda v: laplace(CenteredGrid(v, g, boundary)).values, (u,))
    assert torch.autograd.gradcheck(lambda v: negative_laplacian(v, g.dx, "dirichlet"), (u,))


def test_fused_laplace_traces_as_one_graph():
    g = _grid((6, 5))
    u = torch.randn(1, 6, 5, dtype=D)
    torch._dynamo.reset()
    try:
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", message=".*lru_cache.*")  # dynamo's note on cached helpers
            for boundary in ("periodic", Dirichlet(1.5), Neumann(-0.7)):
                def f(v, boundary=boundary):
                    return laplace(CenteredGrid(v, g, boundary)).values + negative_laplacian(v, g.dx, "neumann")

                traced = torch.compile(f, fullgraph=True, backend="eager", dynamic=False)
                torch.testing.assert_close(traced(u), f(u), rtol=0, atol=1e-12)
    finally:
        torch._dynamo.reset()


def test_normalisation_cache_answers_like_the_checks():
    assert normalize_kinds("dirichlet", 2) == (("dirichlet", "dirichlet"),) * 2
    assert normalize_kinds(["periodic", ("dirichlet", "neumann")], 2) == (("periodic", "periodic"),
                                                                          ("dirichlet", "neumann"))
    assert normalize_dx(0.5, 3) == (0.5, 0.5, 0.5) and normalize_dx((0.5, 2.0), 2) == (0.5, 2.0)
    assert normalize_dx(torch.tensor(0.5), 1) == (0.5,) and normalize_dx(1, 2) == (1.0, 1.0)
    for bad in (float("nan"), (1.0, -1.0), 0.0):
        with pytest.raises(Exception, match="dx"):
            normalize_dx(bad, 2)
    with pytest.raises(Exception, match="unknown boundary kind"):
        normalize_kinds("dirichet", 2)
