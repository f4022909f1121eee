"""Tests of the foundation: Grid geometry, boundary conditions and padding, CenteredGrid/StaggeredGrid fields,
and the error family on bad input across the package."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

import phisim
from phisim import (
    Boundary,
    CenteredGrid,
    Dirichlet,
    FreeSlipWall,
    Grid,
    Neumann,
    NoSlipWall,
    Open,
    Periodic,
    StaggeredGrid,
    pad,
    pad_staggered_component,
    sample_padded,
    set_boundary_faces,
)
from phisim.errors import (
    BoundaryError,
    GridMismatchError,
    NonFiniteError,
    ParameterError,
    PhisimError,
    ShapeError,
)

F64 = torch.float64


# ---- grid ----------------------------------------------------------------------------------------------


def test_grid_coordinates_dx_and_shapes():
    g = Grid((8, 4), bounds=[(-1.0, 3.0), 2.0])
    assert g.rank == 2 and g.dx == (0.5, 0.5) and g.size == (4.0, 2.0)
    assert g.lower == (-1.0, 0.0) and g.upper == (3.0, 2.0)
    assert g.cell_volume == 0.25 and g.num_cells == 32
    torch.testing.assert_close(g.center_coords(0, F64), torch.arange(8, dtype=F64) * 0.5 - 0.75)
    torch.testing.assert_close(g.face_coords(0, F64), torch.arange(9, dtype=F64) * 0.5 - 1.0)
    assert g.face_coords(1).shape == (5,) and float(g.face_coords(1)[-1]) == 2.0
    assert g.face_shape(0) == (9, 4) and g.face_shape(1) == (8, 5)
    c = g.cell_centers(F64)
    assert c.shape == (8, 4, 2)
    assert tuple(c[3, 1].tolist()) == (0.75, 0.75)  # indexing='ij': values[i, j] sits at (x_i, y_j)
    f = g.face_centers(1, F64)
    assert f.shape == (8, 5, 2) and tuple(f[0, 0].tolist()) == (-0.75, 0.0)
    assert Grid(5).resolution == (5,) and Grid(5).dx == (1.0,)
    g3 = Grid((2, 3, 4))
    assert g3.face_shape(2) == (2, 3, 5) and g3.cell_centers().shape == (2, 3, 4, 3)
    assert Grid((4, 4)) == Grid((4, 4), bounds=[(0, 4), (0, 4)])  # dx = 1 by default
    assert "x=[-1, 3]" in repr(g)


# ---- boundary: construction ------------------------------------------------------------------------------


def test_boundary_create_forms():
    b = Boundary.create("periodic", 2)
    assert b.periodic_axes == (True, True)
    b = Boundary.create({"x": "periodic", "y": ("wall", NoSlipWall(velocity=(1.0, 0.0)))}, 2)
    assert b.periodic_axes == (True, False)
    assert isinstance(b.sides[1][0], NoSlipWall) and b.sides[1][1].velocity == (1.0, 0.0)
    b = Boundary.create([Dirichlet(1.0), ("open", "neumann")], 2)
    assert isinstance(b.sides[1][0], Open) and isinstance(b.sides[1][1], Neumann)
    assert Boundary.create("zero", 1).sides[0][0] == Dirichlet(0.0)
    assert Boundary.create("Free-Slip", 1).sides[0][0] == FreeSlipWall()
    p = Boundary.create({"x": "wall", "y": "open"}, 2).for_pressure()
    assert p.sides[0][0] == Neumann(0.0) and p.sides[1][0] == Dirichlet(0.0)
    s = Boundary.create({"x": "wall", "y": Dirichlet(2.0)}, 2).for_scalar()
    assert s.sides[0][0] == Neumann(0.0) and s.sides[1][0] == Dirichlet(2.0)


# ---- boundary: padding rules -----------------------------------------------------------------------------


def _row(values, dtype=F64):
    return torch.tensor([values], dtype=dtype)


def test_dirichlet_ghosts_put_the_value_on_the_face():
    u = _row([1.0, 4.0, 2.0, 7.0])
    p = pad(u, Boundary.create([(Dirichlet(3.0), Dirichlet(-1.0))], 1), (0.5,), width=2)
    # lower ghosts (outermost first): 2v - u_2, 2v - u_1; upper: 2v - u_n, 2v - u_{n-1}
    torch.testing.assert_close(p, _row([6 - 4.0, 6 - 1.0, 1, 4, 2, 7, -2 - 7.0, -2 - 2.0]))
    assert float(0.5 * (p[0, 1] + p[0, 2])) == 3.0  # the linear interpolant meets v on the face
    assert float(0.5 * (p[0, 5] + p[0, 6])) == -1.0


def test_neumann_ghosts_give_the_outward_flux():
    u = _row([1.0, 4.0, 2.0, 7.0])
    dx, f_lo, f_hi = 0.5, 0.8, -2.0
    p = pad(u, Boundary.create([(Neumann(f_lo), Neumann(f_hi))], 1), (dx,), width=2)
    # g_k = u_k + (2k - 1) dx f
    torch.testing.assert_close(p, _row([4 + 3 * dx * f_lo, 1 + dx * f_lo, 1, 4, 2, 7, 7 + dx * f_hi,
                                        2 + 3 * dx * f_hi]))
    assert float((p[0, 1] - p[0, 2]) / dx) == pytest.approx(f_lo)  # outward (-x) derivative at the lower face
    assert float((p[0, 6] - p[0, 5]) / dx) == pytest.approx(f_hi)


def test_periodic_padding_wraps_cells_and_faces():
    u = _row([1.0, 2.0, 3.0, 4.0])
    p = pad(u, Boundary.create("periodic", 1), (1.0,), width=2)
    torch.testing.assert_close(p, _row([3.0, 4, 1, 2, 3, 4, 1, 2]))
    faces = _row([10.0, 1, 2, 3, 10])  # face n repeats face 0
    pf = pad_staggered_component(faces, 0, Boundary.create("periodic", 1), (1.0,), width=1)
    torch.testing.assert_close(pf, _row([3.0, 10, 1, 2, 3, 10, 1]))


def test_staggered_normal_component_ghosts_odd_and_even_about_the_face():
    faces = _row([0.5, 1.0, 2.0, 4.0, -1.0])  # samples on faces 0..4, both boundary faces included
    b = Boundary.create([(Dirichlet(0.5), Neumann(0.25))], 1)
    p = pad_staggered_component(faces, 0, b, (2.0,), width=2)
    # lower (odd about face 0): 2v - u_k with u_k at k dx inside; upper (even): u_k + 2 k dx f
    torch.testing.assert_close(p, _row([1 - 2.0, 1 - 1.0, 0.5, 1, 2, 4, -1, 4 + 2 * 2.0 * 0.25,
                                        2 + 4 * 2.0 * 0.25]))


def test_walls_by_role_scalar_normal_tangential():
    grid = Grid((3, 4))
    dx = grid.dx
    torch.manual_seed(0)
    vec = torch.randn(1, 2, 3, 4, dtype=F64)
    for wall in (NoSlipWall(), FreeSlipWall(), Open()):
        b = Boundary.create(wall, 2)
        p = pad(vec, b, dx, 1, vector=True)
        ps = pad(vec[:, 0], b, dx, 1)
        # scalars see zero flux at every wall and open side
        torch.testing.assert_close(ps[:, 0, 1:-1], ps[:, 1, 1:-1])
        # normal component (component 0 at the x sides)
        normal_face = 0.5 * (p[:, 0, 0, 1:-1] + p[:, 0, 1, 1:-1])
        tangential_face = 0.5 * (p[:, 1, 0, 1:-1] + p[:, 1, 1, 1:-1])
        if isinstance(wall, Open):
            torch.testing.assert_close(p[:, 0, 0, 1:-1], p[:, 0, 1, 1:-1])  # zero flux
            torch.testing.assert_close(p[:, 1, 0, 1:-1], p[:, 1, 1, 1:-1])
        else:
            torch.testing.assert_close(normal_face, torch.zeros_like(normal_face))  # no flow through walls
        if isinstance(wall, NoSlipWall):
            torch.testing.assert_close(tangential_face, torch.zeros_like(tangential_face))  # no slip
        if isinstance(wall, FreeSlipWall):
            torch.testing.assert_close(p[:, 1, 0, 1:-1], p[:, 1, 1, 1:-1])  # tangential slips freely


def test_moving_lid_gives_the_lid_velocity_on_the_face():
    grid = Grid((4, 3))
    b = Boundary.create({"x": "wall", "y": ("wall", NoSlipWall(velocity=(1.0, 0.0)))}, 2)
    vec = torch.randn(2, 2, 4, 3, dtype=F64)
    p = pad(vec, b, grid.dx, 1, vector=True)
    top_u = 0.5 * (p[:, 0, 1:-1, -1] + p[:, 0, 1:-1, -2])
    torch.testing.assert_close(top_u, torch.ones_like(top_u))
    top_v = 0.5 * (p[:, 1, 1:-1, -1] + p[:, 1, 1:-1, -2])
    torch.testing.assert_close(top_v, torch.zeros_like(top_v))  # the lid's normal velocity is ignored
    bottom_u = 0.5 * (p[:, 0, 1:-1, 0] + p[:, 0, 1:-1, 1])
    torch.testing.assert_close(bottom_u, torch.zeros_like(bottom_u))
    # staggered: component 0 is tangential along y and meets the lid velocity on the top face
    stag = StaggeredGrid.zeros(grid, b, batch_size=2, dtype=F64)
    pc = stag.padded_component(0, 1)
    torch.testing.assert_close(0.5 * (pc[:, :, -1] + pc[:, :, -2]), torch.ones(2, 7, dtype=F64))
    # the centred-to-staggered conversion reads the lid velocity from the ghosts too
    c = CenteredGrid(torch.zeros(1, 2, 4, 3, dtype=F64), grid, b)
    s = c.to_staggered()
    torch.testing.assert_close(s.values[1][:, :, -1], torch.zeros(1, 4, dtype=F64))


def test_set_boundary_faces():
    b = Boundary.create({"x": "wall", "y": "periodic"}, 2)
    grid = Grid((3, 4))
    u = StaggeredGrid(tuple(torch.randn(1, *grid.face_shape(i), dtype=F64) for i in range(2)), grid, b)
    s = u.with_boundary_faces()
    assert float(s.values[0][:, 0].abs().max()) == 0 and float(s.values[0][:, -1].abs().max()) == 0
    torch.testing.assert_close(s.values[1][:, :, -1], u.values[1][:, :, 0])
    torch.testing.assert_close(s.values[0][:, 1:-1], u.values[0][:, 1:-1])
    o = set_boundary_faces(u.values[0], 0, Boundary.create("open", 2))
    torch.testing.assert_close(o, u.values[0])
    d = set_boundary_faces(u.values[0], 0, Boundary.create(Dirichlet((2.0, 5.0)), 2))
    assert float(d[:, 0].min()) == float(d[:, -1].max()) == 2.0


# ---- fields: sampling --------------------------------------------------------------------------------------


@pytest.mark.parametrize("rank", [1, 2, 3])
def test_sampling_is_exact_on_linear_functions_in_the_interior(rank):
    grid = Grid((7, 5, 6)[:rank], bounds=[(-1, 2.5), (0, 2), (1, 4)][:rank])
    coef = torch.tensor([0.7, -1.3, 2.1][:rank], dtype=F64)
    f = lambda x: 0.4 + (x * coef).sum(-1)  # noqa: E731
    q = CenteredGrid.from_function(f, grid, "open", batch_size=2, dtype=F64)
    g = torch.Generator().manual_seed(rank)
    lo = torch.tensor([c[0] for c in [grid.center_coords(a, F64) for a in range(rank)]], dtype=F64)
    hi = torch.tensor([c[-1] for c in [grid.center_coords(a, F64) for a in range(rank)]], dtype=F64)
    pts = lo + (hi - lo) * torch.rand(3, 4, rank, generator=g, dtype=F64)
    out = q.sample(pts)
    assert out.shape == (2, 3, 4)
    torch.testing.assert_close(out, f(pts).expand(2, 3, 4), rtol=1e-12, atol=1e-12)
    # staggered: each component linear in every coordinate, sampled inside the face box of every component
    v = StaggeredGrid.from_function(lambda x: torch.stack([f(x) * (a + 1) for a in range(rank)], -1), grid,
                                    "open", dtype=F64)
    sv = v.sample(pts)
    for a in range(rank):
        torch.testing.assert_close(sv[0, a], (a + 1) * f(pts), rtol=1e-12, atol=1e-12)
    # per-sample points
    per = torch.stack([pts, pts.flip(0)])
    torch.testing.assert_close(q.sample(per, per_sample=True)[1], f(pts.flip(0)), rtol=1e-12, atol=1e-12)


def test_sampling_meets_dirichlet_and_neumann_boundaries_of_a_linear_function():
    """Face-located values make linear functions exact right up to (and half a cell beyond) the boundary."""
    grid = Grid((6,), bounds=[(0.0, 3.0)])
    f = lambda x: 2.0 - 1.5 * x  # noqa: E731
    b = Boundary.create([(Dirichlet(f(0.0)), Neumann(-1.5))], 1)  # upper side: outward slope -1.5
    q = CenteredGrid.from_function(lambda x: f(x[..., 0]), grid, b, dtype=F64)
    pts = torch.tensor([[-0.25], [0.0], [0.1], [2.9], [3.0], [3.25]], dtype=F64)
    torch.testing.assert_close(q.sample(pts)[0], f(pts[:, 0]), rtol=1e-12, atol=1e-12)


def test_periodic_sampling_wraps():
    grid = Grid((8, 6), bounds=[(0, 4), (0, 3)])
    q = CenteredGrid(torch.randn(1, 8, 6, dtype=F64), grid, "periodic")
    p = torch.tensor([[0.3, 2.9], [3.9, 0.1]], dtype=F64)
    torch.testing.assert_close(q.sample(p + torch.tensor([4.0, -3.0], dtype=F64)), q.sample(p))
    torch.testing.assert_close(q.sample(grid.cell_centers(F64)), q.values)  # sampling at centres is the identity


def test_sample_padded_fast_path_matches_gather_path():
    arr = torch.randn(2, 3, 5, 7, dtype=F64)
    idx = torch.rand(2, 11, 2, dtype=F64) * torch.tensor([4.0, 6.0], dtype=F64)
    out = sample_padded(arr, idx)
    i0 = idx.floor().long()
    w = idx - i0
    i1 = (i0 + 1).clamp(max=torch.tensor([4, 6]))
    b = torch.arange(2)[:, None]
    ref = 0
    for cx, wx in ((i0[..., 0], 1 - w[..., 0]), (i1[..., 0], w[..., 0])):
        for cy, wy in ((i0[..., 1], 1 - w[..., 1]), (i1[..., 1], w[..., 1])):
            ref = ref + arr[b, :, cx, cy] * (wx * wy)[..., None]
    torch.testing.assert_close(out, ref.permute(0, 2, 1), rtol=1e-12, atol=1e-12)


# ---- fields: conversions -----------------------------------------------------------------------------------


@pytest.mark.parametrize("boundary", ["periodic", "open", "free_slip"])
def test_at_centers_to_staggered_round_trip(boundary):
    """u_x(y), u_y(x): each component is constant along its own axis, so it satisfies periodic, open and
    free-slip-tangential conditions, and averaging along its axis is exact in both directions."""
    grid = Grid((8, 6), bounds=[(0, 4), (0, 3)])
    if boundary == "free_slip":  # needs zero normal velocity on the walls and zero tangential flux
        fn = lambda x: torch.stack([0 * x[..., 0], 0 * x[..., 1]], -1)  # noqa: E731
    else:
        fn = lambda x: torch.stack([torch.sin(2 * math.pi * x[..., 1] / 3), torch.cos(2 * math.pi * x[..., 0] / 4)], -1)  # noqa: E731,E501
    s = StaggeredGrid.from_function(fn, grid, boundary, batch_size=2, dtype=F64)
    c = s.at_centers()
    assert isinstance(c, CenteredGrid) and c.values.shape == (2, 2, 8, 6)
    back = c.to_staggered()
    for a, b in zip(back.values, s.values):
        torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-12)


def test_to_staggered_of_a_linear_velocity_with_matching_dirichlet_faces():
    grid = Grid((5, 4), bounds=[(0, 5), (0, 4)])
    # u = (2, -1) constant with Dirichlet((2, -1)): every face, boundary included, gets it exactly
    c = CenteredGrid(torch.tensor([2.0, -1.0], dtype=F64).reshape(1, 2, 1, 1).expand(1, 2, 5, 4), grid,
                     Dirichlet((2.0, -1.0)))
    s = c.to_staggered()
    assert float(s.values[0].min()) == float(s.values[0].max()) == 2.0
    assert float(s.values[1].min()) == float(s.values[1].max()) == -1.0
    torch.testing.assert_close(s.at_centers().values, c.values)


# ---- fields: arithmetic and mismatches --------------------------------------------------------------------


def test_arithmetic_returns_new_fields():
    grid = Grid((4, 3))
    a = CenteredGrid(torch.full((1, 4, 3), 2.0), grid, "periodic")
    b = CenteredGrid(torch.full((1, 4, 3), 3.0), grid, "periodic")
    assert float((a + b).values.mean()) == 5.0 and float((a - b).values.mean()) == -1.0
    assert float((a * b).values.mean()) == 6.0 and float((b / a).values.mean()) == 1.5
    assert float((1 - a).values.mean()) == -1.0 and float((6 / a).values.mean()) == 3.0
    assert float((a ** 2).values.mean()) == 4.0 and float((-a).values.mean()) == -2.0
    assert float((2 * a + 1).values.mean()) == 5.0
    assert float((a + np.ones((1, 4, 3))).values.mean()) == 3.0
    vec = CenteredGrid(torch.ones(1, 2, 4, 3), grid, "periodic")
    assert (a * vec).values.shape == (1, 2, 4, 3)  # scalar x vector broadcasts over components
    assert float(a.values.mean()) == 2.0  # unchanged
    s = StaggeredGrid.uniform((1.0, 2.0), grid, "periodic")
    t = s * 2 + s
    assert float(t.values[1].mean()) == 6.0 and isinstance(t, StaggeredGrid)
    assert a.with_values(torch.zeros(1, 4, 3)).grid == grid
    assert a.detach().to(dtype=F64).dtype == F64
    assert isinstance(a.numpy(), np.ndarray) and len(s.numpy()) == 2


def test_mismatches_raise_grid_mismatch_error():
    grid = Grid((4, 3))
    a = CenteredGrid(torch.zeros(1, 4, 3), grid, "periodic")
    with pytest.raises(GridMismatchError):
        a + CenteredGrid(torch.zeros(1, 4, 3), Grid((4, 3), bounds=[1, 1]), "periodic")
    with pytest.raises(GridMismatchError):
        a + CenteredGrid(torch.zeros(1, 4, 3), grid, "open")
    with pytest.raises(GridMismatchError):
        a * StaggeredGrid.zeros(grid, "periodic")
    with pytest.raises(GridMismatchError):
        CenteredGrid(torch.zeros(1, 4, 3), (4, 3), "periodic")


# ---- bad input across the package ---------------------------------------------------------------------------


def _grid():
    return Grid((4, 3))


BAD_INPUTS = [
    ("resolution zero", lambda: Grid((0, 4)), ParameterError),
    ("resolution negative", lambda: Grid((-2,)), ParameterError),
    ("resolution not integer", lambda: Grid((2.5, 4)), ParameterError),
    ("four axes", lambda: Grid((2, 2, 2, 2)), ParameterError),
    ("empty bounds", lambda: Grid((4,), bounds=[(1.0, 1.0)]), ParameterError),
    ("non-finite bounds", lambda: Grid((4,), bounds=[(0.0, float("nan"))]), ParameterError),
    ("bounds count", lambda: Grid((4, 4), bounds=[4.0]), ParameterError),
    ("axis out of range", lambda: Grid((4, 4)).face_shape(2), ParameterError),
    ("unknown boundary name", lambda: Boundary.create("sticky", 2), BoundaryError),
    ("periodic on one side", lambda: Boundary.create([(Periodic(), Open())], 1), BoundaryError),
    ("boundary mapping misses an axis", lambda: Boundary.create({"x": "open"}, 2), BoundaryError),
    ("boundary mapping bad axis", lambda: Boundary.create({"z": "open", "x": "open"}, 2), BoundaryError),
    ("boundary sequence length", lambda: Boundary.create(["open"] * 3, 2), BoundaryError),
    ("boundary rank", lambda: CenteredGrid(torch.zeros(1, 4, 3), _grid(), Boundary.create("open", 1)),
     BoundaryError),
    ("boundary not a condition", lambda: Boundary.create(3.5, 1), BoundaryError),
    ("per-component value on a scalar", lambda: pad(torch.zeros(1, 4), Boundary.create(Dirichlet((1.0, 2.0)), 1),
                                                    (1.0,)), BoundaryError),
    ("centred values without batch axis", lambda: CenteredGrid(torch.zeros(4, 3), _grid(), "open"), ShapeError),
    ("centred values wrong size", lambda: CenteredGrid(torch.zeros(1, 4, 4), _grid(), "open"), ShapeError),
    ("staggered component count", lambda: StaggeredGrid((torch.zeros(1, 5, 3),), _grid(), "open"), ShapeError),
    ("staggered component shape", lambda: StaggeredGrid((torch.zeros(1, 4, 3), torch.zeros(1, 4, 4)), _grid(),
                                                        "open"), ShapeError),
    ("staggered from one tensor", lambda: StaggeredGrid(torch.zeros(2, 1, 4, 3), _grid(), "open"), ShapeError),
    ("staggered mixed dtypes", lambda: StaggeredGrid((torch.zeros(1, 5, 3), torch.zeros(1, 4, 4, dtype=F64)),
                                                     _grid(), "open"), ShapeError),
    ("uniform velocity length", lambda: StaggeredGrid.uniform((1.0,), _grid(), "open"), ShapeError),
    ("to_staggered of a scalar", lambda: CenteredGrid(torch.zeros(1, 4, 3), _grid(), "open").to_staggered(),
     ShapeError),
    ("sample points wrong width", lambda: CenteredGrid(torch.zeros(1, 4, 3), _grid(), "open").sample(
        torch.zeros(5, 3)), ShapeError),
    ("per-sample points wrong batch", lambda: CenteredGrid(torch.zeros(2, 4, 3), _grid(), "open").sample(
        torch.zeros(3, 5, 2), per_sample=True), ShapeError),
    ("pad wrong ndim", lambda: pad(torch.zeros(4, 3), Boundary.create("open", 2), (1.0, 1.0)), ShapeError),
    ("pad too wide", lambda: pad(torch.zeros(1, 2), Boundary.create("open", 1), (1.0,), width=3), ShapeError),
    ("pad vector components", lambda: pad(torch.zeros(1, 3, 4, 3), Boundary.create("open", 2), (1.0, 1.0),
                                          vector=True), ShapeError),
    ("sample_padded index width", lambda: sample_padded(torch.zeros(1, 1, 4, 3), torch.zeros(1, 2, 3)),
     ShapeError),
    ("grid is not a Grid", lambda: StaggeredGrid((torch.zeros(1, 5, 3), torch.zeros(1, 4, 4)), (4, 3), "open"),
     GridMismatchError),
    ("negative dt", lambda: phisim.check_dt(-1.0), ParameterError),
    ("infinite dt", lambda: phisim.check_dt(float("inf")), ParameterError),
    ("NaN dt tensor", lambda: phisim.check_dt(torch.tensor(float("nan"))), ParameterError),
    ("negative viscosity", lambda: phisim.check_nonnegative(-0.1, "viscosity"), ParameterError),
    ("zero where positive needed", lambda: phisim.check_positive(0.0, "rtol"), ParameterError),
    ("NaN state", lambda: phisim.check_finite(torch.tensor([1.0, float("nan")]), "state"), NonFiniteError),
]


@pytest.mark.parametrize("name,fn,error", BAD_INPUTS, ids=[b[0] for b in BAD_INPUTS])
def test_bad_input_raises_the_right_error(name, fn, error):
    with pytest.raises(error) as info:
        fn()
    assert isinstance(info.value, PhisimError)
    assert len(str(info.value)) > 10  # says what was wrong


def test_bad_input_cases_are_many_and_distinct():
    assert len({b[0] for b in BAD_INPUTS}) >= 15


def test_multichannel_fields_that_are_not_velocities_pad_and_sample_as_scalars():
    grid = Grid((4, 3))
    vals = torch.randn(2, 3, 4, 3, dtype=F64)
    c = CenteredGrid(vals, grid, Dirichlet(1.0))
    p = c.padded(1)
    assert p.shape == (2, 3, 6, 5)
    for ch in range(3):
        torch.testing.assert_close(p[:, ch], CenteredGrid(vals[:, ch], grid, Dirichlet(1.0)).padded(1))
    pts = torch.tensor([[0.2, 0.1], [3.9, 2.7]], dtype=F64)
    torch.testing.assert_close(c.sample(pts)[:, 1], CenteredGrid(vals[:, 1], grid, Dirichlet(1.0)).sample(pts))
