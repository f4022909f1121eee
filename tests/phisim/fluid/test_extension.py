"""The fluid velocity extended into sharp no-slip bodies for self-advection (phisim.fluid.extension)."""

from __future__ import annotations

import math

import pytest
import torch

from phisim import Grid, StaggeredGrid
from phisim.fluid import Body, FluidStepper, RotatedBox, Sphere, solid_layout
from phisim.fluid.extension import BAND_CELLS, extend_into_bodies

F64 = torch.float64


def _plane_body(angle: float, velocity=None):
    # a large rotated box: near the grid's middle its surface is the plane through (0.5, 0.41) at ``angle``
    c = (0.5 - 5 * math.sin(angle), 0.41 + 5 * math.cos(angle))
    return Body(RotatedBox(c, (20.0, 10.0), angle), velocity=velocity)


def _wall_field(grid, body, g: float, us=(0.0, 0.0)):
    """``u = u_s + g phi (cos a, sin a)``-like linear field: each component ``u_s,i + g_i phi`` with the signed
    distance ``phi`` of the plane (linear in x), on the whole grid."""
    comps = []
    for i in range(grid.rank):
        x = grid.face_centers(i, F64)
        phi = body.sdf(x, 0.0)
        comps.append((us[i] + g * (i + 1) * phi)[None])
    return StaggeredGrid(tuple(comps), grid, "wall")


@pytest.mark.parametrize("moving", [False, True])
def test_extension_continues_a_linear_wall_profile_exactly(moving):
    """Near a planar surface a linear profile through the body's velocity is continued into the body exactly (the
    probe's multilinear interpolation is exact for linear fields), in the band of BAND_CELLS cells; faces deeper
    inside and all fluid faces keep their values."""
    grid = Grid((40, 40), bounds=[(0, 1), (0, 1)])
    us = (0.3, -0.2) if moving else (0.0, 0.0)
    body = _plane_body(0.3, velocity=us if moving else None)
    exact = _wall_field(grid, body, 1.7, us)
    h = grid.dx[0]
    stored = []
    for i, u in enumerate(exact.values):  # the step's stored field: u_s on the faces centred inside
        phi = body.sdf(grid.face_centers(i, F64), 0.0)
        stored.append(torch.where(phi[None] <= 0, torch.full_like(u, us[i]), u))
    out = extend_into_bodies(exact.with_values(tuple(stored)), body)
    for i in range(2):
        phi = body.sdf(grid.face_centers(i, F64), 0.0)[None]
        band = (phi <= 0) & (phi > -BAND_CELLS * h)
        assert int(band.sum()) > 50
        assert torch.allclose(out.values[i][band], exact.values[i][band], atol=1e-12, rtol=0)
        assert torch.equal(out.values[i][~band], stored[i][~band])


def test_extension_of_a_stepper_is_computed_once_and_kept_on_its_layout():
    grid = Grid((32, 16), bounds=[(0, 2), (0, 1)])
    stepper = FluidStepper(grid, "wall", obstacles=Body(Sphere((0.6, 0.5), 0.15)), viscosity=0.01, dt=0.01,
                           dtype=F64)
    layout = stepper.obstacles
    kept = [k for k in layout.solvers if isinstance(k, tuple) and k[0] == "inside_extension"]
    assert len(kept) == 1  # built by the stepper's first (warm-up) step
    first = layout.solvers[kept[0]]
    v = StaggeredGrid.from_function(lambda x: torch.stack([x[..., 1], -x[..., 0]], -1), grid, "wall", dtype=F64)
    extend_into_bodies(v, layout)
    assert layout.solvers[kept[0]] is first


def test_extension_leaves_fields_without_sharp_bodies_alone():
    grid = Grid((16, 16), bounds=[(0, 1), (0, 1)])
    v = StaggeredGrid.from_function(lambda x: torch.stack([x[..., 1], -x[..., 0]], -1), grid, "wall", dtype=F64)
    assert extend_into_bodies(v, None) is v
    blended = Body(Sphere((0.5, 0.5), 0.2), sharp=False)
    assert extend_into_bodies(v, blended) is v
    assert extend_into_bodies(v, solid_layout(blended, grid, v.boundary, 0.0, F64)) is v


def test_gradcheck_extension_wrt_radius_and_centre():
    grid = Grid((12, 12), bounds=[(0, 1), (0, 1)])
    v = StaggeredGrid.from_function(lambda x: torch.stack([torch.sin(3 * x[..., 1]), x[..., 0] ** 2], -1), grid,
                                    "wall", dtype=F64)
    r0 = torch.tensor(0.23, dtype=F64, requires_grad=True)
    c0 = torch.tensor([0.51, 0.47], dtype=F64, requires_grad=True)

    def f(r, c):
        out = extend_into_bodies(v, Body(Sphere(c, r)))
        return torch.cat([x.flatten() for x in out.values])

    assert torch.autograd.gradcheck(f, (r0, c0), eps=1e-6, atol=1e-6)


@pytest.mark.slow
def test_navier_stokes_couette_flow_converges_at_second_order_with_the_extension(load_example):
    """Circular Couette flow with MacCormack advection (Re 8): the velocity near the surfaces converges from 24^2 to
    48^2 at order >= 1.5 in the rms (measured 2.10) and >= 1.35 in the max (measured 1.42); without the extension
    at about 1.2 (the transported field reads the bodies' velocity inside them).

    The max-norm bound was 1.5 (measured 1.91) before the split step's wall values carried the previous tangential
    pressure gradient (``anticipate_pressure``): that removes the step's slip along the surface, which lowers the
    largest error on 24^2 by 20 % (9.4e-3 -> 7.5e-3) and raises it on 48^2 by 12 % (2.50e-3 -> 2.80e-3, where the
    slip had been cancelling part of the spatial error); the rms error is unchanged (7.0e-4 -> 7.0e-4). From 48^2
    to 96^2 the max-norm order is 1.66 with it (1.47 before; docs/VALIDATION.md)."""
    tc = load_example("taylor_couette")
    rows = tc.study([24, 48], advection="maccormack")
    orders = {k: math.log(rows[0][k] / rows[1][k]) / math.log(2) for k in ("near_max", "near_rms")}
    assert orders["near_rms"] >= 1.5 and orders["near_max"] >= 1.35, rows
    plain = tc.study([24, 48], advection="maccormack", extension=False)
    assert plain[1]["near_max"] > 1.2 * rows[1]["near_max"], (plain, rows)


def _ghost_error(n: int) -> float:
    """Largest error of the free-slip ghost values of a rigid rotation inside a free-slip outer cylinder."""
    from phisim.fluid import SDF, impose_solids
    from phisim.fluid.extension import free_slip_ghosts

    c = torch.tensor([0.013, -0.021], dtype=F64)
    grid = Grid((n, n), bounds=[(-1, 1), (-1, 1)])
    outer = Body(SDF(lambda x: 0.8 - (x - c.to(x.dtype)).norm(dim=-1), center=(0.013, -0.021),
                     bounds=((-1, -1), (1, 1))), no_slip=False)

    def rigid(x):
        r = x - c
        return torch.stack([-r[..., 1], r[..., 0]], -1)

    v = StaggeredGrid.from_function(rigid, grid, "wall", dtype=F64)
    layout = solid_layout(outer, grid, v.boundary, 0.0, F64)
    ghosts = free_slip_ghosts(impose_solids(v, layout), layout, closed_only=False)
    err = []
    for i in range(2):
        x = grid.face_centers(i, F64)
        phi = outer.sdf(x, 0.0)
        band = (phi <= 0) & (phi > -BAND_CELLS * grid.dx[0])
        err.append((ghosts.values[i][0] - rigid(x)[..., i])[band].abs().max())
    return float(max(err))


def test_free_slip_ghosts_continue_a_rigid_rotation_through_a_curved_surface():
    """A rigid rotation has no shear stress anywhere: the ghost values inside a free-slip cylinder (tangential part
    grown with the surface's curvature, normal part through 0) reproduce it, up to the finite-difference curvature
    of the signed distance (second order)."""
    e24, e48 = _ghost_error(24), _ghost_error(48)
    assert e48 < 1e-4, e48
    assert math.log2(e24 / e48) > 1.8, (e24, e48)


@pytest.mark.parametrize(("half", "periodic", "warns"), [(0.9, False, True), (0.98, False, False), (0.9, True, False)])
def test_free_slip_ghosts_warn_when_the_domain_edge_cuts_them(half, periodic, warns):
    """A free-slip outer sphere (radius 0.8) in the box ``[-half, half]^3`` on 16^3: with the walls 0.89 cells beyond
    it the edge passes within a cell inside the surface, where the ghost values would lie (a RuntimeWarning, once;
    that run's error is 35 %), with 1.47 cells nothing is said (its errors are those of a larger box); periodic sides
    are never an edge."""
    import warnings

    from phisim.fluid import SDF, diffuse_velocity, impose_solids
    from phisim.solvers import Solve

    outer = Body(SDF(lambda x: 0.8 - x.norm(dim=-1), center=(0.0, 0.0, 0.0), bounds=((-half,) * 3, (half,) * 3)),
                 no_slip=False)
    grid = Grid((16, 16, 16), bounds=[(-half, half)] * 3)
    v = StaggeredGrid.zeros(grid, "periodic" if periodic else "wall", dtype=torch.float64)
    layout = solid_layout([outer], grid, v.boundary, 0.0, torch.float64, v.device)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        diffuse_velocity(impose_solids(v, layout), 0.01, viscosity=1.0, scheme="implicit", solids=layout,
                         solve=Solve(rtol=1e-6))
    edge = [w for w in caught if issubclass(w.category, RuntimeWarning) and "domain's edge" in str(w.message)]
    assert len(edge) == (1 if warns else 0), [str(w.message) for w in caught]
    if warns:
        assert edge[0].filename == __file__  # pointed at the caller's line


def test_free_slip_edge_warning_points_at_the_users_line_through_a_stepper():
    """The warning of a domain edge inside a free-slip surface names the user's line (the stepper's construction,
    which builds the layout's ghost geometry, or its call), not a frame inside phisim."""
    import warnings

    from phisim.fluid import SDF, FluidState, FluidStepper

    half = 0.9
    outer = Body(SDF(lambda x: 0.8 - x.norm(dim=-1), center=(0.0, 0.0, 0.0), bounds=((-half,) * 3, (half,) * 3)),
                 no_slip=False)
    grid = Grid((12, 12, 12), bounds=[(-half, half)] * 3)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        stepper = FluidStepper(grid, "wall", obstacles=outer, viscosity=0.01, dt=0.01, dtype=torch.float64)
        stepper(FluidState(StaggeredGrid.zeros(grid, stepper.boundary, dtype=torch.float64)))
    edge = [w for w in caught if "domain's edge" in str(w.message)]
    assert edge and all(w.filename == __file__ for w in edge), [(w.filename, str(w.message)[:40]) for w in caught]
