"""The split step's wall values moved by the previous tangential pressure gradient (``anticipate_pressure``): the
stencil, the steady state it gives, moving bodies, and gradients."""

from __future__ import annotations

import math

import pytest
import torch

from phisim import Grid, StaggeredGrid
from phisim.errors import GridMismatchError, ParameterError, ShapeError
from phisim.field import CenteredGrid
from phisim.fluid import (
    Body,
    FluidState,
    Sphere,
    anticipate_pressure,
    diffuse_velocity,
    impose_solids,
    make_incompressible,
    solid_layout,
    step,
)
from phisim.solvers import Solve

F64 = torch.float64
TIGHT = Solve(rtol=1e-12)


def _linear_pressure(grid, g) -> CenteredGrid:
    x = grid.cell_centers(F64, "cpu")
    return CenteredGrid((x @ torch.tensor(g, dtype=F64))[None], grid, "wall")


@pytest.mark.parametrize("rank", [2, 3])
def test_extra_source_is_the_tangential_gradient_times_the_wall_weight(rank):
    """For a linear pressure (gradient G everywhere) the source added to each face with a wall arm is
    ``(G - (G . n) n)_i`` times its wall weight, with ``n`` the sphere's normal there; other faces get nothing."""
    res, bounds = ((24, 20), [(0, 1.2), (0, 1)]) if rank == 2 else ((14, 12, 13), [(0, 1.1), (0, 1), (0, 1)])
    grid = Grid(res, bounds=bounds)
    centre, radius = (0.61, 0.48, 0.52)[:rank], 0.27
    body = Body(Sphere(centre, radius))
    v = StaggeredGrid.zeros(grid, "wall", dtype=F64)
    layout = solid_layout(body, grid, v.boundary, 0.0, F64)
    g = torch.tensor((0.7, -0.4, 0.25)[:rank], dtype=F64)
    out = anticipate_pressure(layout, _linear_pressure(grid, g.tolist()), v)
    assert out is not layout
    checked = 0
    for i in range(rank):
        index, weight, _, _ = layout.tangents[i]
        extra = out.walls[i][2][0].flatten()
        assert layout.walls[i][2] is None  # a resting body has no source of its own
        x = grid.face_centers(i, F64, "cpu").reshape(-1, rank)[index]
        n = (x - torch.tensor(centre, dtype=F64)) / (x - torch.tensor(centre, dtype=F64)).norm(dim=-1, keepdim=True)
        expected = g[i] - (n @ g) * n[:, i]  # per unit weight (the normal by differences of the distance: 1e-8)
        assert torch.allclose(extra[index] / weight, expected, rtol=0, atol=1e-7)
        rest = torch.ones_like(extra, dtype=torch.bool)
        rest[index] = False
        assert float(extra[rest].abs().max()) == 0.0
        checked += index.numel()
    assert checked > 40


def test_a_pressure_gradient_along_the_normal_adds_nothing():
    """``p = |x - c|^2 / 2`` about the disc's centre: its face gradient is ``x - c``, along the normal, and the other
    components at a face come from a diagonal pair of wetted faces around it (exact for this linear gradient), so
    the tangential correction vanishes to the normal's finite-difference error (measured 7e-9 of ``|x - c|``; the
    plain mean of the wetted neighbours left 1.8 % at D/8); an azimuthal gradient is kept."""
    grid = Grid((20, 20), bounds=[(0, 1), (0, 1)])
    centre = torch.tensor([0.52, 0.47], dtype=F64)
    body = Body(Sphere(tuple(centre.tolist()), 0.21))
    v = StaggeredGrid.zeros(grid, "wall", dtype=F64)
    layout = solid_layout(body, grid, v.boundary, 0.0, F64)
    r = grid.cell_centers(F64, "cpu") - centre
    radial = anticipate_pressure(layout, CenteredGrid((0.5 * (r**2).sum(-1))[None], grid, "wall"), v)
    swirl = anticipate_pressure(layout, CenteredGrid(torch.atan2(r[..., 1], r[..., 0])[None], grid, "wall"), v)
    for i in range(2):
        index, weight, _, _ = layout.tangents[i]
        x = grid.face_centers(i, F64, "cpu").reshape(-1, 2)[index]
        size = (x - centre).norm(dim=-1)
        assert float((radial.walls[i][2][0].flatten()[index] / weight / size).abs().max()) < 1e-6
        tangential = swirl.walls[i][2][0].flatten()[index] / weight  # |grad atan2| = 1 / r, along the surface
        assert float((tangential * size).abs().max()) > 0.9


def test_nothing_to_anticipate_leaves_the_layout():
    grid = Grid((16, 16), bounds=[(0, 1), (0, 1)])
    v = StaggeredGrid.zeros(grid, "wall", dtype=F64)
    sharp = solid_layout(Body(Sphere((0.5, 0.5), 0.2)), grid, v.boundary, 0.0, F64)
    blended = solid_layout(Body(Sphere((0.5, 0.5), 0.2), sharp=False), grid, v.boundary, 0.0, F64)
    p = _linear_pressure(grid, (1.0, 0.0))
    assert anticipate_pressure(sharp, None, v) is sharp
    assert anticipate_pressure(blended, p, v) is blended
    assert anticipate_pressure(None, p, v) is None


def test_bad_pressure_is_refused():
    """A pressure on another grid, or a tensor of another resolution, is refused with a PhisimError."""
    grid = Grid((16, 16), bounds=[(0, 1), (0, 1)])
    v = StaggeredGrid.zeros(grid, "wall", dtype=F64)
    layout = solid_layout(Body(Sphere((0.5, 0.5), 0.2)), grid, v.boundary, 0.0, F64)
    other = Grid((16, 16), bounds=[(0, 2), (0, 1)])
    with pytest.raises(GridMismatchError, match="pressure grid"):
        anticipate_pressure(layout, CenteredGrid(torch.zeros((1, 16, 16), dtype=F64), other, "wall"), v)
    with pytest.raises(ShapeError):
        anticipate_pressure(layout, torch.zeros((1, 15, 16), dtype=F64), v)
    # a bare (*res) tensor is one sample, as the steps accept it
    with pytest.raises(ParameterError, match="viscosity_scheme"):
        anticipate_pressure(layout, _linear_pressure(grid, (0.3, 0.2)), v, viscosity_scheme="spectral")
    plain = anticipate_pressure(layout, _linear_pressure(grid, (0.3, 0.2)).values[0], v)
    ref = anticipate_pressure(layout, _linear_pressure(grid, (0.3, 0.2)), v)
    assert all(torch.equal(a[2], b[2]) for a, b in zip(plain.walls, ref.walls))


def _array_error(n: int, dt_cells: float, anticipate: bool, scheme: str = "implicit", weights: str | None = None,
                 steps: int = 2000) -> float:
    """The steady split-step drag of the periodic cylinder array (examples/cylinder_array.py's set-up, c = 0.05)
    relative to Sangani & Acrivos's 15.554; ``weights``: the scheme whose anticipation weights are used (default
    ``scheme``)."""
    radius = math.sqrt(0.05 / math.pi)
    grid = Grid((n, n), bounds=[(0.0, 1.0), (0.0, 1.0)])
    body = Body(Sphere((0.513, 0.479), radius))
    v = StaggeredGrid.zeros(grid, "periodic", dtype=F64)
    layout = solid_layout([body], grid, v.boundary, 0.0, F64)
    dt = dt_cells * grid.dx[0] ** 2
    p = None
    for _ in range(steps):
        w = impose_solids(v.with_values((v.values[0] + dt, v.values[1])), layout)
        walls = anticipate_pressure(layout, p, w, viscosity_scheme=weights or scheme) if anticipate else layout
        w = diffuse_velocity(w, dt, viscosity=1.0, scheme=scheme, solids=walls, solve=TIGHT)
        new, p = make_incompressible(w, layout, solve=TIGHT, pressure_guess=p)
        change = max(float((a - b).abs().max()) for a, b in zip(new.values, v.values))
        v = new
        if change < 1e-8 * float(v.values[0].abs().max()):
            break
    else:
        raise AssertionError("no steady state")
    flux = float(v.values[0][0, 0, :].sum()) * grid.dx[1]
    return 1.0 / flux / 15.554296312834756 - 1


def test_anticipated_gradient_removes_most_of_the_split_steps_slip():
    """Stokes flow pushed through a periodic array of discs, split steps with implicit viscosity at ``nu dt / dx^2 =
    5`` on 16^2 (D/4): the steady drag is 31.8 % low when the projection's change of the wall velocity is left in,
    10.5 % low with the anticipated tangential gradient (the steady state of the exact discrete equations: 2.6 %)."""
    without = _array_error(16, 5.0, anticipate=False)
    with_ = _array_error(16, 5.0, anticipate=True)
    assert -0.34 < without < -0.29
    assert -0.12 < with_ < -0.09


# long validations: explicit viscosity at nu dt / dx^2 = 0.2 takes about a minute to its steady state, Crank-Nicolson
# about 30 s (the default run keeps test_anticipated_gradient_removes_most_of_the_split_steps_slip)
@pytest.mark.parametrize("scheme, dt_cells, tol, whole_off", [
    pytest.param("explicit", 0.2, 0.002, 0.01, marks=pytest.mark.slow),
    pytest.param("crank_nicolson", 1.0, 0.012, 0.06, marks=pytest.mark.slow)])
def test_the_anticipated_part_follows_the_viscosity_scheme(scheme, dt_cells, tol, whole_off):
    """The same array on 16^2 (the exact discrete steady state: -2.633 %) with explicit viscosity at ``nu dt / dx^2 =
    0.2`` and Crank-Nicolson at 1: only the part of the stencil that reads the intermediate velocity gets the
    correction (the explicit step's point-implicit diagonal ``coef``, half the wall weight for Crank-Nicolson).
    Measured: explicit -2.757 % (the whole wall weight: -1.360 %), Crank-Nicolson -3.619 % (whole: +4.227 %)."""
    exact = -0.02633
    matched = _array_error(16, dt_cells, True, scheme)
    whole = _array_error(16, dt_cells, True, scheme, weights="implicit")
    assert abs(matched - exact) < tol and abs(whole - exact) > whole_off


def test_moving_body_reads_the_pressure_in_its_own_frame():
    """A disc moving exactly one cell per step, with a previous pressure that moves with it: the anticipated source
    equals that of a resting disc at the new position with the pressure at the new position (the body-frame reading
    is exact for whole-cell shifts)."""
    n = 24
    grid = Grid((n, n), bounds=[(0, 1), (0, 1)])
    h, dt, speed = 1.0 / n, 0.5, 2.0 / n  # one cell per step
    c0, c1 = (0.41, 0.52), (0.41 + h, 0.52)
    v = StaggeredGrid.zeros(grid, "periodic", dtype=F64)
    moving = Body(Sphere(c0, 0.17), velocity=(speed, 0.0))
    resting = Body(Sphere(c1, 0.17))

    def pressure(c):
        x = grid.cell_centers(F64, "cpu")
        r = x - torch.tensor(c, dtype=F64)
        return CenteredGrid((r[..., 0] ** 2 - 0.5 * r[..., 0] * r[..., 1] + 0.3 * r[..., 1])[None], grid, "periodic")

    lay_m = solid_layout(moving, grid, v.boundary, dt, F64)
    lay_r = solid_layout(resting, grid, v.boundary, 0.0, F64)
    out_m = anticipate_pressure(lay_m, pressure(c0), v, time=dt, dt=dt)
    out_r = anticipate_pressure(lay_r, pressure(c1), v)
    for i in range(2):
        index = lay_r.tangents[i][0]
        assert torch.equal(index, lay_m.tangents[i][0])
        src_m = (out_m.walls[i][2] - lay_m.walls[i][2])[0].flatten()[index]
        src_r = out_r.walls[i][2][0].flatten()[index]
        assert torch.allclose(src_m, src_r, rtol=1e-9, atol=1e-9)
        assert float(src_r.abs().max()) > 1.0


@pytest.mark.parametrize("moving", [False, True])
def test_gradcheck_split_step_with_a_previous_pressure(moving):
    """A split step past a sharp disc whose wall values carry the anticipated gradient is differentiable in the
    disc's radius, centre (and velocity) and in the previous pressure."""
    grid = Grid((10, 8), bounds=[(0, 1.25), (0, 1)])
    gen = torch.Generator().manual_seed(5)
    u0 = StaggeredGrid.zeros(grid, "periodic", dtype=F64)
    u0 = u0.with_values(tuple(0.3 * torch.randn(c.shape, generator=gen, dtype=F64) + (0.5 if k == 0 else 0.0)
                              for k, c in enumerate(u0.values)))
    p0 = 0.01 * torch.randn((1, 10, 8), generator=gen, dtype=F64)

    def f(radius, centre, velocity, pscale):
        body = Body(Sphere(centre, radius), velocity=velocity if moving else None)
        state = FluidState(u0, pressure=CenteredGrid(p0 * pscale, grid, "periodic"), time=0.1)
        out = step(state, 0.05, viscosity=0.05, obstacles=body, advection="semi_lagrangian", solve=TIGHT)
        return out.velocity.values[0].sum() + (out.velocity.values[1] ** 2).sum()

    args = (torch.tensor(0.26, dtype=F64, requires_grad=True),
            torch.tensor([0.6, 0.47], dtype=F64, requires_grad=True),
            torch.tensor([0.2, -0.05], dtype=F64, requires_grad=moving),
            torch.tensor(1.0, dtype=F64, requires_grad=True))
    assert torch.autograd.gradcheck(f, args, eps=1e-6, atol=1e-6, rtol=1e-5)
