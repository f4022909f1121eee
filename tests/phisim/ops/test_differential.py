"""Mathematics of the finite-difference operators: exactness, convergence orders, identities, gradients."""

import math

import numpy as np
import pytest
import torch

from phisim import (
    Boundary,
    CenteredGrid,
    Dirichlet,
    Grid,
    Neumann,
    NoSlipWall,
    ShapeError,
    StaggeredGrid,
    curl,
    divergence,
    gradient,
    laplace,
    velocity_from_stream_function,
)

D = torch.float64
PI = math.pi


def order(errors, sizes):
    """Least-squares slope of log(error) against log(dx): the measured convergence order."""
    return np.polyfit(np.log(sizes), np.log(errors), 1)[0]


# ---- exactness on polynomials ----------------------------------------------------------------------------


def quad(x):
    return 0.5 * x[..., 0] ** 2 + 3 * x[..., 0] * x[..., 1] - 2 * x[..., 1] ** 2 + x[..., 0]


def test_laplace_exact_on_quadratic_interior():
    g = Grid((9, 7), bounds=[(0, 2), (-1, 1)])
    f = CenteredGrid.from_function(quad, g, "neumann", dtype=D)
    lap = laplace(f).values[0, 1:-1, 1:-1]
    torch.testing.assert_close(lap, torch.full_like(lap, 1.0 - 4.0), rtol=0, atol=1e-11)


def test_gradient_exact_on_quadratic_interior_center_and_face():
    g = Grid((9, 7), bounds=[(0, 2), (-1, 1)])
    f = CenteredGrid.from_function(quad, g, "neumann", dtype=D)
    x = g.cell_centers(D)
    gc = gradient(f, "center").values[0]
    exact = torch.stack([x[..., 0] + 3 * x[..., 1] + 1, 3 * x[..., 0] - 4 * x[..., 1]])
    torch.testing.assert_close(gc[:, 1:-1, 1:-1], exact[:, 1:-1, 1:-1], rtol=0, atol=1e-11)
    gf = gradient(f, "face")
    xf = g.face_centers(0, D)
    torch.testing.assert_close(gf.values[0][0, 1:-1], (xf[..., 0] + 3 * xf[..., 1] + 1)[1:-1], rtol=0, atol=1e-11)
    yf = g.face_centers(1, D)
    torch.testing.assert_close(gf.values[1][0][:, 1:-1], (3 * yf[..., 0] - 4 * yf[..., 1])[:, 1:-1], rtol=0, atol=1e-11)


def test_mac_divergence_exact_on_quadratic_everywhere():
    g = Grid((6, 5), bounds=[(0, 1.5), (0, 1)])
    v = StaggeredGrid.from_function(lambda x: torch.stack([x[..., 0] ** 2 + x[..., 1], x[..., 1] ** 2 * 3], -1),
                                    g, "open", dtype=D)
    x = g.cell_centers(D)
    torch.testing.assert_close(divergence(v).values[0], 2 * x[..., 0] + 6 * x[..., 1], rtol=0, atol=1e-12)


def test_linear_function_with_exact_boundary_data_has_zero_laplacian_including_boundary_cells():
    # Dirichlet: u = 2 + 3x on [0, 1] with face values 2 and 5; the ghost 2v - u continues u exactly.
    g1 = Grid(10, bounds=[(0, 1)])
    f1 = CenteredGrid.from_function(lambda x: 2 + 3 * x[..., 0], g1, [(Dirichlet(2.0), Dirichlet(5.0))], dtype=D)
    torch.testing.assert_close(laplace(f1).values, torch.zeros(1, 10, dtype=D), rtol=0, atol=1e-10)
    # Neumann: u = 1 - y has outward derivative +1 at y = 0 and -1 at y = 1.
    g = Grid((6, 8), bounds=[(0, 1), (0, 1)])
    b = {"x": "periodic", "y": (Neumann(1.0), Neumann(-1.0))}
    f = CenteredGrid.from_function(lambda x: 1 - x[..., 1] + 0 * x[..., 0], g, b, dtype=D)
    torch.testing.assert_close(laplace(f).values, torch.zeros(1, 6, 8, dtype=D), rtol=0, atol=1e-10)
    torch.testing.assert_close(gradient(f).values[0, 1], -torch.ones(6, 8, dtype=D))


# ---- convergence orders per boundary type ---------------------------------------------------------------

CASES = {
    # name: (boundary, u, laplace u, grad u) on [0,1]^2; each field continues across its faces the way the
    # ghost rule assumes (odd about Dirichlet values, even plus flux about Neumann faces) -> global order 2
    "periodic": (
        "periodic",
        lambda x: torch.sin(2 * PI * x[..., 0]) * torch.cos(2 * PI * x[..., 1]),
        lambda x: -8 * PI**2 * torch.sin(2 * PI * x[..., 0]) * torch.cos(2 * PI * x[..., 1]),
        lambda x: torch.stack([2 * PI * torch.cos(2 * PI * x[..., 0]) * torch.cos(2 * PI * x[..., 1]),
                               -2 * PI * torch.sin(2 * PI * x[..., 0]) * torch.sin(2 * PI * x[..., 1])]),
    ),
    "dirichlet_value": (
        Dirichlet(1.5),
        lambda x: 1.5 + torch.sin(PI * x[..., 0]) * torch.sin(2 * PI * x[..., 1]),
        lambda x: -5 * PI**2 * torch.sin(PI * x[..., 0]) * torch.sin(2 * PI * x[..., 1]),
        lambda x: torch.stack([PI * torch.cos(PI * x[..., 0]) * torch.sin(2 * PI * x[..., 1]),
                               2 * PI * torch.sin(PI * x[..., 0]) * torch.cos(2 * PI * x[..., 1])]),
    ),
    "neumann_flux": (
        {"x": (Neumann(-0.7), Neumann(0.7)), "y": "neumann"},
        lambda x: torch.cos(PI * x[..., 0]) * torch.cos(2 * PI * x[..., 1]) + 0.7 * x[..., 0],
        lambda x: -5 * PI**2 * torch.cos(PI * x[..., 0]) * torch.cos(2 * PI * x[..., 1]),
        lambda x: torch.stack([-PI * torch.sin(PI * x[..., 0]) * torch.cos(2 * PI * x[..., 1]) + 0.7,
                               -2 * PI * torch.cos(PI * x[..., 0]) * torch.sin(2 * PI * x[..., 1])]),
    ),
    "mixed": (
        {"x": "periodic", "y": "dirichlet"},
        lambda x: torch.cos(2 * PI * x[..., 0]) * torch.sin(PI * x[..., 1]),
        lambda x: -5 * PI**2 * torch.cos(2 * PI * x[..., 0]) * torch.sin(PI * x[..., 1]),
        lambda x: torch.stack([-2 * PI * torch.sin(2 * PI * x[..., 0]) * torch.sin(PI * x[..., 1]),
                               PI * torch.cos(2 * PI * x[..., 0]) * torch.cos(PI * x[..., 1])]),
    ),
}
SIZES = [16, 32, 64]


@pytest.mark.parametrize("name", list(CASES))
def test_laplace_and_gradient_second_order_per_boundary(name):
    bc, u, lap_u, grad_u = CASES[name]
    e_lap, e_grad, e_face = [], [], []
    for n in SIZES:
        g = Grid((n, n), bounds=[(0, 1), (0, 1)])
        f = CenteredGrid.from_function(u, g, bc, dtype=D)
        x = g.cell_centers(D)
        e_lap.append((laplace(f).values[0] - lap_u(x)).abs().max().item())
        e_grad.append((gradient(f, "center").values[0] - grad_u(x)).abs().max().item())
        gf = gradient(f, "face")
        e_face.append(max((gf.values[a][0] - grad_u(g.face_centers(a, D))[a]).abs().max().item() for a in range(2)))
    h = [1 / n for n in SIZES]
    assert order(e_lap, h) >= 1.9, e_lap
    assert order(e_grad, h) >= 1.9, e_grad
    assert order(e_face, h) >= 1.9, e_face


@pytest.mark.parametrize("bc", ["periodic", "free_slip", "wall"])
def test_centered_divergence_second_order(bc):
    # velocity tangential to the walls with zero normal component on them (sin in the normal direction)
    u = lambda x: torch.stack([torch.sin(2 * PI * x[..., 0]) * torch.cos(2 * PI * x[..., 1]),  # noqa: E731
                               torch.cos(2 * PI * x[..., 0]) * torch.sin(2 * PI * x[..., 1])], -1)
    div_u = lambda x: 4 * PI * torch.cos(2 * PI * x[..., 0]) * torch.cos(2 * PI * x[..., 1])  # noqa: E731
    errs = []
    for n in SIZES:
        g = Grid((n, n), bounds=[(0, 1), (0, 1)])
        f = CenteredGrid.from_function(u, g, bc, dtype=D)
        errs.append((divergence(f).values[0] - div_u(g.cell_centers(D))).abs().max().item())
    assert order(errs, [1 / n for n in SIZES]) >= 1.9, errs


def test_staggered_divergence_and_laplace_second_order():
    u = lambda x: torch.stack([torch.sin(2 * PI * x[..., 0]) * torch.cos(4 * PI * x[..., 1]),  # noqa: E731
                               torch.cos(2 * PI * x[..., 0]) * torch.sin(2 * PI * x[..., 1])], -1)
    e_div, e_lap = [], []
    for n in SIZES:
        g = Grid((n, n), bounds=[(0, 1), (0, 1)])
        v = StaggeredGrid.from_function(u, g, "periodic", dtype=D)
        x = g.cell_centers(D)
        cx, cy2, cy4 = torch.cos(2 * PI * x[..., 0]), torch.cos(2 * PI * x[..., 1]), torch.cos(4 * PI * x[..., 1])
        exact_div = 2 * PI * cx * (cy4 + cy2)
        e_div.append((divergence(v).values[0] - exact_div).abs().max().item())
        lap = laplace(v).values[0][0]
        xf = g.face_centers(0, D)
        exact_lap = -20 * PI**2 * torch.sin(2 * PI * xf[..., 0]) * torch.cos(4 * PI * xf[..., 1])
        e_lap.append((lap - exact_lap).abs().max().item())
    h = [1 / n for n in SIZES]
    assert order(e_div, h) >= 1.9 and order(e_lap, h) >= 1.9, (e_div, e_lap)


def test_generic_smooth_field_interior_order_and_boundary_cell_consistency():
    # u = sin(pi x) + x (1 - x) is 0 on both faces but not odd about them (u'' = -2 there). Interior: second
    # order; boundary cells: the local truncation error stays O(1) (a quarter of u'' at the face), the
    # documented behaviour of the compact stencil with face-located values.
    errs_int, errs_bnd = [], []
    for n in SIZES:
        g = Grid(n, bounds=[(0, 1)])
        u = lambda x: torch.sin(PI * x[..., 0]) + x[..., 0] * (1 - x[..., 0])  # noqa: E731
        f = CenteredGrid.from_function(u, g, "dirichlet", dtype=D)
        x = g.center_coords(0, D)
        exact = -PI**2 * torch.sin(PI * x) - 2
        err = (laplace(f).values[0] - exact).abs()
        errs_int.append(err[n // 4: 3 * n // 4].max().item())
        errs_bnd.append(err[0].item())
    assert order(errs_int, [1 / n for n in SIZES]) >= 1.9
    np.testing.assert_allclose(errs_bnd, 0.5, rtol=0.05)  # |0.75 u'' - u''| = 0.5 at the boundary cell


def test_laplace_1d_and_3d_second_order():
    e1, e3 = [], []
    sizes = [12, 24, 48]  # the 3-D field has a full period on 12 cells: asymptotic from here on
    for n in sizes:
        g1 = Grid(n, bounds=[(0, 1)])
        f1 = CenteredGrid.from_function(lambda x: torch.cos(3 * PI * x[..., 0]), g1, "neumann", dtype=D)
        e1.append((laplace(f1).values[0] + 9 * PI**2 * torch.cos(3 * PI * g1.center_coords(0, D))).abs().max().item())
        g3 = Grid((n, n, n), bounds=[(0, 1)] * 3)
        fn = lambda x: torch.sin(PI * x[..., 0]) * torch.cos(2 * PI * x[..., 1]) * torch.sin(2 * PI * x[..., 2])  # noqa: E731
        f3 = CenteredGrid.from_function(fn, g3, {"x": "dirichlet", "y": "periodic", "z": "dirichlet"}, dtype=D)
        e3.append((laplace(f3).values[0] + 9 * PI**2 * fn(g3.cell_centers(D))).abs().max().item())
    h = [1 / n for n in sizes]
    assert order(e1, h) >= 1.9 and order(e3, h) >= 1.9, (e1, e3)


# ---- discrete identities ----------------------------------------------------------------------------------


def test_div_of_stream_function_velocity_is_zero():
    g = Grid((12, 10), bounds=[(0, 1.2), (0, 2)])
    psi = torch.randn(3, 13, 11, dtype=D, generator=torch.Generator().manual_seed(0))
    v = velocity_from_stream_function(psi, g, "wall")
    assert divergence(v).values.abs().max() < 1e-12


def test_curl_of_face_gradient_vanishes():
    g = Grid((12, 10), bounds=[(0, 1.2), (0, 2)])
    gen = torch.Generator().manual_seed(1)
    p = CenteredGrid(torch.randn(2, 12, 10, dtype=D, generator=gen), g, "periodic")
    assert curl(gradient(p, "face"), at="node").abs().max() < 1e-11
    p = CenteredGrid(torch.randn(2, 12, 10, dtype=D, generator=gen), g, "neumann")
    w = curl(gradient(p, "face", boundary="wall"), at="node")
    assert w.shape == (2, 13, 11)
    assert w[:, 1:-1, 1:-1].abs().max() < 1e-11  # exact at interior corners; boundary corners see the wall


def test_3d_div_curl_zero_periodic():
    g = Grid((6, 7, 8), bounds=[(0, 1), (0, 2), (0, 3)])
    f = CenteredGrid(torch.randn(2, 3, 6, 7, 8, dtype=D, generator=torch.Generator().manual_seed(2)), g, "periodic")
    assert divergence(curl(f)).values.abs().max() < 1e-11


def test_curl_2d_rotation_and_stream_function():
    g = Grid((16, 16), bounds=[(-1, 1), (-1, 1)])
    v = StaggeredGrid.from_function(lambda x: torch.stack([-x[..., 1], x[..., 0]], -1), g, "open", dtype=D)
    w = curl(v)  # solid-body rotation: vorticity 2
    torch.testing.assert_close(w.values[0, 1:-1, 1:-1], torch.full((14, 14), 2.0, dtype=D))
    psi = CenteredGrid.from_function(lambda x: x[..., 0] * x[..., 1], g, "neumann", dtype=D)
    u = curl(psi).values[0]  # (dpsi/dy, -dpsi/dx) = (x, -y)
    x = g.cell_centers(D)
    torch.testing.assert_close(u[:, 1:-1, 1:-1], torch.stack([x[..., 0], -x[..., 1]])[:, 1:-1, 1:-1])


def test_moving_lid_enters_laplacian_through_ghost():
    g = Grid((4, 5), bounds=[(0, 4), (0, 5)])
    b = Boundary.create({"x": "wall", "y": ("wall", NoSlipWall(velocity=(2.0, 0.0)))}, 2)
    v = StaggeredGrid.zeros(g, b, dtype=D)
    lap_u = laplace(v).values[0][0]
    torch.testing.assert_close(lap_u[1:-1, -1], torch.full((3,), 2 * 2.0, dtype=D))  # (2U - 0)/dy^2, dy = 1
    assert lap_u[1:-1, :-1].abs().max() == 0


# ---- gradients and errors ---------------------------------------------------------------------------------


def test_gradcheck_all_operators():
    g = Grid((4, 3), bounds=[(0, 1), (0, 2)])
    b = Boundary.create({"x": (Dirichlet(0.3), Neumann(0.2)), "y": ("wall", NoSlipWall((1.0, 0.0)))}, 2)
    s = torch.randn(2, 4, 3, dtype=D, requires_grad=True)
    vc = torch.randn(2, 2, 4, 3, dtype=D, requires_grad=True)
    u = torch.randn(2, 5, 3, dtype=D, requires_grad=True)
    w = torch.randn(2, 4, 4, dtype=D, requires_grad=True)
    checks = [
        (lambda s: gradient(CenteredGrid(s, g, b), "center").values, (s,)),
        (lambda s: gradient(CenteredGrid(s, g, b), "face").values, (s,)),
        (lambda s: laplace(CenteredGrid(s, g, b)).values, (s,)),
        (lambda v: laplace(CenteredGrid(v, g, b)).values, (vc,)),
        (lambda v: divergence(CenteredGrid(v, g, b)).values, (vc,)),
        (lambda v: curl(CenteredGrid(v, g, b)).values, (vc,)),
        (lambda u, w: divergence(StaggeredGrid((u, w), g, b)).values, (u, w)),
        (lambda u, w: laplace(StaggeredGrid((u, w), g, b)).values, (u, w)),
        (lambda u, w: curl(StaggeredGrid((u, w), g, b), at="node"), (u, w)),
    ]
    for fn, args in checks:
        assert torch.autograd.gradcheck(fn, args)


def test_operator_errors():
    g = Grid((4, 4))
    vec = CenteredGrid(torch.zeros(1, 2, 4, 4), g, "periodic")
    sca = CenteredGrid(torch.zeros(1, 4, 4), g, "periodic")
    with pytest.raises(ShapeError):
        gradient(vec)
    with pytest.raises(ShapeError):
        gradient(sca, at="edge")
    with pytest.raises(ShapeError):
        divergence(sca)
    with pytest.raises(ShapeError):
        curl(CenteredGrid(torch.zeros(1, 4), Grid(4), "periodic"))
    with pytest.raises(ShapeError):
        velocity_from_stream_function(torch.zeros(1, 4, 4), g, "wall")
