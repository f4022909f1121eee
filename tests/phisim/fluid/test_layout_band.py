"""A body layout is computed on the band of points near the surface only: the same numbers and gradients as on every
point (phisim.fluid.bodies: body_fraction, wall_stencil, extension_stencil)."""

import pytest
import torch

from phisim import Grid
from phisim.fluid import Body, Box, Sphere
from phisim.fluid.bodies import _arm, _cut_fraction, body_fraction, extension_stencil, wall_stencil
from phisim.fluid.geometry import SDF, RotatedBox, Union

G3 = Grid((24, 20, 22), bounds=[(-1.2, 1.2), (-1.0, 1.0), (-1.1, 1.1)])
G2 = Grid((40, 36), bounds=[(-1.0, 1.0), (-0.9, 0.9)])


def _points(grid, axis):
    return grid.cell_centers(torch.float64) if axis is None else grid.face_centers(axis, torch.float64)


def _scaled_disc(scale):
    return SDF(lambda x: scale * (x.norm(dim=-1) - 0.4), (0.0, 0.0), ((-0.4, -0.4), (0.4, 0.4)))


BODIES = [
    ("sphere", lambda: Body(Sphere((0.1, 0.05, -0.02), 0.5)), G3, 0.0),
    ("free-slip sphere", lambda: Body(Sphere((0.1, 0.05, -0.02), 0.5), no_slip=False), G3, 0.0),
    ("free-slip disc", lambda: Body(Sphere((0.1, 0.05), 0.5), no_slip=False), G2, 0.0),
    ("carried disc", lambda: Body(Sphere((0.1, 0.05), 0.5), velocity=(0.3, 0.1)), G2, 0.7),
    ("box", lambda: Body(Box((-0.3, -0.2, -0.4), (0.35, 0.3, 0.2))), G3, 0.0),
    ("rotated box", lambda: Body(RotatedBox((0.0, 0.1), (0.6, 0.3), 0.4)), G2, 0.0),
    ("union", lambda: Body(Union(Sphere((0.3, 0.0), 0.2), Box((-0.5, -0.3), (0.0, 0.3)))), G2, 0.0),
    # not distances: the band is a band of phi, like the cut's own exact 0 / 1 beyond it
    ("steep SDF", lambda: Body(_scaled_disc(2.0)), G2, 0.0),
    ("shallow SDF", lambda: Body(_scaled_disc(0.3)), G2, 0.0),
]


@pytest.mark.parametrize("name,make,grid,t", BODIES, ids=[b[0] for b in BODIES])
def test_body_fraction_on_the_band_equals_every_point(name, make, grid, t):
    body = make()
    h = min(grid.dx)
    for axis in [None, *range(grid.rank)]:
        x = _points(grid, axis)
        banded = body_fraction(body, x, t, h, axis)
        full = _cut_fraction(body, x, body.sdf(x, t), t, h, axis)
        assert torch.equal(banded, full), (name, axis)
        band = (body.sdf(x, t).abs() < h).sum().item()
        assert 0 < 4 * band < x[..., 0].numel()  # the band is a small part: the selecting path ran


def test_body_fraction_gradient_on_the_band_equals_every_point():
    r = torch.tensor(0.47, dtype=torch.float64, requires_grad=True)
    c = torch.tensor([0.1, 0.05, -0.02], dtype=torch.float64, requires_grad=True)
    h = min(G3.dx)
    x = G3.face_centers(1, torch.float64)
    w = torch.rand(x.shape[:-1], dtype=torch.float64, generator=torch.Generator().manual_seed(3))
    grads = []
    for banded in (True, False):
        body = Body(Sphere(c, r))
        theta = body_fraction(body, x, 0.0, h, 1) if banded else _cut_fraction(body, x, body.sdf(x, 0.0), 0.0, h, 1)
        grads.append(torch.autograd.grad((w * theta).sum(), (r, c)))
    assert grads[0][0] != 0
    for a, b in zip(*grads):  # the backward sums over ~1e4 points in another order: rounding of a few 1e-13
        torch.testing.assert_close(a, b, rtol=1e-12, atol=0)


def test_body_fraction_gradcheck_with_the_band():
    grid = Grid((10, 9, 8), bounds=[(-1.0, 1.0), (-0.9, 0.9), (-0.8, 0.8)])
    x = grid.face_centers(0, torch.float64)
    h = min(grid.dx)

    def f(radius, center):
        return body_fraction(Body(Sphere(center, radius)), x, 0.0, h, 0)

    r = torch.tensor(0.55, dtype=torch.float64, requires_grad=True)
    c = torch.tensor([0.03, -0.02, 0.05], dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(f, (r, c))


def test_body_fraction_keeps_nan_distances():
    """A NaN distance gives a NaN fraction, as on every point; a point far from the surface whose gradient stencil
    reaches a NaN takes its 0 / 1 from its own distance (every point: NaN through the normal)."""

    def fn(x):
        phi = x.norm(dim=-1) - 0.4
        return torch.where(x[..., 0] > 0.8, torch.nan, phi)

    body = Body(SDF(fn, (0.0, 0.0), ((-0.4, -0.4), (0.4, 0.4))))
    x = G2.face_centers(0, torch.float64)
    phi = body.sdf(x, 0.0)
    theta = body_fraction(body, x, 0.0, min(G2.dx), 0)
    full = _cut_fraction(body, x, phi, 0.0, min(G2.dx), 0)
    assert torch.isnan(phi).any()
    assert torch.equal(torch.isnan(theta), torch.isnan(phi))
    assert not (torch.isnan(theta) & ~torch.isnan(full)).any()
    ok = ~torch.isnan(full)
    assert torch.equal(theta[ok], full[ok])


def _place(part, axis, side):
    """An arm's values (faces ``0..n-2`` for side +1, ``1..n-1`` for side -1) padded back to the full face shape."""
    shape = list(part.shape)
    shape[axis] = 1
    z = part.new_zeros(shape)
    return torch.cat([part, z] if side > 0 else [z, part], axis)


def _dense_wall_stencil(bodies, grid, i, t):
    """The sharp no-slip stencil's terms added over every face with zeros off the links (the formulas of
    wall_stencil, written densely)."""
    x = grid.face_centers(i, torch.float64)
    phis = torch.stack([b.sdf(x, t) for b in bodies], 0)
    phi = phis.min(0).values
    owner = phis.argmin(0)
    coef, weight, source = (torch.zeros_like(phi) for _ in range(3))
    for a in range(grid.rank):
        h2 = grid.dx[a] ** 2
        for side in (1, -1):
            pf, pn = _arm(phi, a, side)
            link = (pf > 0) & (pn <= 0)
            gap = torch.where(link, pf - pn, torch.ones_like(pf))
            s = torch.where(link, pf / gap, torch.ones_like(pf)).clamp(1e-5, 1.0)
            coef = coef + _place(torch.where(link, (1 / s - 1) / h2, torch.zeros_like(s)), a, side)
            weight = weight + _place(torch.where(link, 1 / (s * h2), torch.zeros_like(s)), a, side)
            xf = _arm(x, a, side)[0]
            step = torch.zeros(grid.rank, dtype=torch.float64)
            step[a] = side * grid.dx[a]
            xw = xf + s.unsqueeze(-1) * step
            vel = torch.stack([b.velocity_at(xw, t)[..., i] if not b.static else torch.zeros_like(s) for b in bodies])
            uw = vel.gather(0, _arm(owner, a, side)[1].unsqueeze(0))[0]
            source = source + _place(torch.where(link, uw / (s * h2), torch.zeros_like(s)), a, side)
    return phi <= 0, coef, source, weight


@pytest.mark.parametrize("grid", [G2, G3], ids=["2d", "3d"])
def test_wall_stencil_on_the_links_equals_the_dense_formula(grid):
    d = grid.rank
    bodies = [Body(Sphere((0.3,) + (0.0,) * (d - 1), 0.25), velocity=(0.2,) + (0.1,) * (d - 1)),
              Body(Box((-0.6,) + (-0.3,) * (d - 1), (-0.1,) + (0.3,) * (d - 1)))]
    for i in range(d):
        cut, coef, source, weight = wall_stencil(bodies, grid, i, 0.4, torch.float64, None)
        ref = _dense_wall_stencil(bodies, grid, i, 0.4)
        for got, want in zip((cut, coef, source, weight), ref):
            assert torch.equal(got, want), i
        assert (coef > 0).any() and (source != 0).any()


def test_extension_stencil_is_pointwise():
    """The probes of a subset of faces are the subset of the probes of all faces (distances taken at the selected
    faces alone)."""
    bodies = [Body(Sphere((0.3, 0.0), 0.25), velocity=(0.2, 0.1)), Body(Box((-0.6, -0.3), (-0.1, 0.3)))]
    x = G2.face_centers(1, torch.float64)
    phi = torch.minimum(bodies[0].sdf(x, 0.4), bodies[1].sdf(x, 0.4))
    wide = (phi > -2 * min(G2.dx)) & (phi < 0)
    narrow = wide & (torch.arange(wide.numel()).reshape(wide.shape) % 3 == 0)
    a = extension_stencil(bodies, G2, 1, 0.4, torch.float64, None, wide)
    b = extension_stencil(bodies, G2, 1, 0.4, torch.float64, None, narrow)
    keep = torch.isin(a[0], b[0])
    assert keep.sum() == b[0].numel() > 0
    for u, v in zip(a, b):
        assert torch.equal(u[keep], v)
    torch.testing.assert_close(a[3], phi.reshape(-1)[a[0]] / (2.0 * min(G2.dx)), rtol=0, atol=0)
