"""The direct viscous solve of a sharp no-slip surface with its correction on a window around the body.

Where the Green's function of the box operator ``I - a L₀`` decays fast (``a`` small against the cell size), the
capacitance solve of a persistent layout computes its correction by a box solve on a window around the body instead
of a second box solve of the whole component (:class:`phisim.solvers.mac_diffusion._SharpCapacitanceSolve`). These
tests check that the window path gives the step of the two-box-solve path and of PCG, that the decay bound it relies
on holds for the measured Green's function, and that the projection's shortcuts for sharp-only layouts give what the
general formulas give.
"""

from __future__ import annotations

import math

import pytest
import torch

from phisim import Grid, Inflow, Open, SlowPathWarning, StaggeredGrid
from phisim.fluid import Body, Sphere, diffuse_velocity, impose_solids, solid_layout
from phisim.fluid.projection import _blend, _flux, flux_correction
from phisim.solvers import Solve
from phisim.solvers import mac_diffusion as md

F64 = torch.float64


def _flow(closed: bool, n: int = 96, dtype=F64):
    """A random velocity past a disc of radius 4 cells (cell size 1), in a channel (inflow, open outlet) or a box."""
    grid = Grid((n, n), bounds=[(0.0, float(n)), (0.0, float(n))])
    spec = "wall" if closed else {"x": (Inflow((0.5, 0.0)), Open()), "y": "wall"}
    g = torch.Generator().manual_seed(3)
    values = tuple(torch.randn((1, *grid.face_shape(i)), generator=g, dtype=F64).to(dtype) for i in range(2))
    v = StaggeredGrid(values, grid, spec).with_boundary_faces()
    body = Body(Sphere((0.4 * n, 0.52 * n), 4.0), angular_velocity=0.2)
    layout = solid_layout(body, grid, v.boundary, 0.0, dtype)
    return impose_solids(v, layout), layout


def _solvers(layout, with_component: bool = False):
    """The sharp capacitance solves kept on a persistent layout (with their component's index)."""
    out = [(key[1][0], hit[3]) for key, hit in layout.solvers.items()
           if isinstance(key, tuple) and key[0] == "sharp-capacitance"]
    return out if with_component else [s for _, s in out]


@pytest.mark.parametrize("closed", [False, True])
@pytest.mark.parametrize("scheme", ["implicit", "crank_nicolson"])
def test_window_path_equals_two_box_solves_and_pcg(scheme, closed):
    w, layout = _flow(closed)
    nu = 0.08  # a = nu dt = 0.08 cell²: the Green's function falls by about 14 per cell
    cg = diffuse_velocity(w, 1.0, viscosity=nu, scheme=scheme, solids=layout, solve=Solve(rtol=1e-14))
    held = layout.persistent()
    windowed = diffuse_velocity(w, 1.0, viscosity=nu, scheme=scheme, solids=held)
    solvers = _solvers(held)
    assert len(solvers) == 2 and all(s.windows[F64] is not None for s in solvers)
    for s in solvers:  # the same solves without their windows: the correction by a second box solve
        s.windows = {dt: None for dt in s.windows}
    boxed = diffuse_velocity(w, 1.0, viscosity=nu, scheme=scheme, solids=held)
    for a, b, c in zip(windowed.values, boxed.values, cg.values):
        scale = float(b.abs().max())
        torch.testing.assert_close(a, b, rtol=0, atol=1e-12 * scale)
        torch.testing.assert_close(a, c, rtol=0, atol=1e-11 * scale)


def test_window_path_in_float32_and_with_gradients():
    w64, layout64 = _flow(True)
    ref = diffuse_velocity(w64, 1.0, viscosity=0.08, scheme="implicit", solids=layout64.persistent())
    w32, layout32 = _flow(True, dtype=torch.float32)
    held = layout32.persistent()
    out = diffuse_velocity(w32, 1.0, viscosity=0.08, scheme="implicit", solids=held)
    assert all(s.windows[torch.float32] is not None for s in _solvers(held))
    for a, b in zip(out.values, ref.values):
        torch.testing.assert_close(a.double(), b, rtol=0, atol=2e-6 * float(b.abs().max()))
    # with autograd the window is added out of place; the answer and the gradient are those of the two box solves
    held = layout64.persistent()
    grads = []
    for windows in (True, False):
        x = tuple(t.clone().requires_grad_(True) for t in w64.values)
        res = diffuse_velocity(w64.with_values(x), 1.0, viscosity=0.08, scheme="implicit", solids=held)
        if not windows:
            for s in _solvers(held):
                s.windows = {dt: None for dt in s.windows}
            res = diffuse_velocity(w64.with_values(x), 1.0, viscosity=0.08, scheme="implicit", solids=held)
        for a, b in zip(res.values, ref.values):
            torch.testing.assert_close(a.detach(), b, rtol=0, atol=1e-12 * float(b.abs().max()))
        loss = sum((r * torch.cos(torch.arange(r.numel(), dtype=F64).reshape(r.shape))).sum() for r in res.values)
        grads.append(torch.autograd.grad(loss, x))
    for a, b in zip(*grads):
        torch.testing.assert_close(a, b, rtol=0, atol=1e-12 * float(b.abs().max()))


@pytest.mark.parametrize("closed", [False, True])
def test_green_function_decays_within_its_bound(closed):
    """The row sums ``h = G 1_J`` of the box operator's inverse stay below ``H λ^(d - m)`` (the supersolution of the
    class docstring) at every distance ``d`` where they are measurable, for every anchor ``m``."""
    w, layout = _flow(closed)
    held = layout.persistent()
    diffuse_velocity(w, 1.0, viscosity=0.08, scheme="implicit", solids=held)
    for i, s in _solvers(held, with_component=True):
        comp = md._component(w.grid, w.boundary, i)
        shape = tuple(s.fixed.shape[1:])
        mult = comp.inverse_multiplier(0.08, F64, None)
        h = s._columns(comp, s.index, shape, mult, None).sum(0)
        hmax = float(h.max())
        assert float(h.min()) > -1e-15  # G >= 0 (an M-matrix), to round-off
        coords = torch.stack(torch.unravel_index(s.index, shape), 1)
        lo, hi = coords.min(0).values, coords.max(0).values
        grid = torch.stack(torch.meshgrid(*(torch.arange(n) for n in shape), indexing="ij"), -1)
        dist = torch.clamp(torch.maximum(lo - grid, grid - hi), min=0).max(-1).values.reshape(-1)
        at = [float(h[dist == d].max()) for d in range(int(dist.max()) + 1)]
        images = 4.0 if comp.odd is not None and not all(comp.odd) else 1.0  # mirror images of an open side
        lam = 0.08 / (1 + 0.08)
        measurable = [d for d, x in enumerate(at) if x > 1e-13 * hmax]
        assert len(measurable) >= 8
        for m in measurable:
            for d in measurable:
                if d > m:
                    assert at[d] <= images * at[m] * lam ** (d - m) * (1 + 1e-9) + 1e-14 * hmax, (m, d, at, lam)
        # the window reaches the distance where the bound from some reliable anchor is below the tolerance
        window = s.windows[F64][0]
        margin = max(max(int(lo[a]) - sl.start, sl.stop - 1 - int(hi[a])) for a, sl in enumerate(window))
        bound = min(images * (at[m] + 1e-13 * hmax) * lam ** (margin - m) for m in measurable
                    if m <= margin and (m == 0 or at[m] >= 1e-9 * hmax))
        assert bound <= md.WINDOW_TOLERANCE[F64] * hmax * (1 + 1e-9)


def test_sharp_only_blend_and_flux_shortcuts_match_the_general_formulas():
    w, layout = _flow(False)
    held = layout.persistent()
    values = tuple(t + 0.1 for t in w.values)
    for corrected in (None, tuple(2 * t for t in values)):
        fast, general = _blend(values, held, corrected), _blend(values, layout, corrected)
        assert any(isinstance(k, tuple) and k[0] == "sharp-keep" and v is not None for k, v in held.solvers.items())
        for a, b in zip(fast, general):
            assert torch.equal(a, b)
    corr = flux_correction(values, layout)
    assert layout.solid_velocity is not None  # a turning disc: the blend carries its velocity
    for f, u, th, us, c in zip(_flux(values, layout), values, layout.theta, layout.solid_velocity, corr):
        assert c is not None and bool((c != 0).any())
        assert torch.equal(f, th * u + (1 - th) * us + c)
    assert math.isfinite(float(sum(f.sum() for f in _flux(values, held))))


@pytest.mark.parametrize("rank, spec", [
    (2, "wall"),
    (2, {"x": (Inflow((0.5, 0.0)), Open()), "y": "wall"}),
    (2, {"x": "periodic", "y": "slip"}),
    (2, {"x": (Open(), "slip"), "y": "periodic"}),
    (3, {"x": (Inflow((0.5, 0.0, 0.0)), Open()), "y": "slip", "z": "wall"}),
    (3, {"x": "wall", "y": "periodic", "z": (Open(), "wall")}),
])
def test_green_rows_equal_the_box_solves_column_by_column(rank, spec):
    """The capacitance solves' block of ``(I - a L₀)⁻¹`` between surface faces, read from the component's separable
    decomposition (:meth:`_Component.green_factors`), equals the columns of box solves, for every own-axis rule
    (walls, open sides, free slip) and periodic axes."""
    res = (12, 10) if rank == 2 else (9, 8, 7)
    grid = Grid(res, bounds=[(0.0, 1.3 * n) for n in res])
    v = StaggeredGrid(tuple(torch.zeros((1, *grid.face_shape(i)), dtype=F64) for i in range(rank)), grid, spec)
    gen = torch.Generator().manual_seed(5)
    for i in range(rank):
        comp = md._Component(grid, v.boundary, i)
        shape = [comp.count if a == i else grid.face_shape(i)[a] for a in range(rank)]
        n_all = math.prod(shape)
        index = torch.randperm(n_all, generator=gen)[:9]
        coef = 0.7
        mult = comp.inverse_multiplier(coef, F64, "cpu")
        g = md._green_rows(comp, index, shape, coef, mult, "cpu", None)
        assert g is not None
        e = torch.zeros(index.numel(), n_all, dtype=F64)
        e[torch.arange(index.numel()), index] = 1.0
        cols = comp.apply(e.reshape(-1, *shape), mult, None, prescaled=True).reshape(index.numel(), n_all)[:, index]
        torch.testing.assert_close(g, cols, rtol=0, atol=1e-13 * float(cols.abs().max()))


def test_capacitance_rows_fall_back_to_box_solves(monkeypatch):
    """Where the separable block fails its check, the capacitance rows come from box solves column by column: the
    same block, and the windowed sharp solve gives the step it gives with the separable block."""
    w, layout = _flow(False)
    ref = diffuse_velocity(w, 1.0, viscosity=0.08, scheme="implicit", solids=layout.persistent())
    calls = []
    block = md.green_block

    def wrong_block(*args):  # a block that fails the check against the box solves
        calls.append(1)
        return 2.0 * block(*args)

    monkeypatch.setattr(md, "green_block", wrong_block)
    held = layout.persistent()
    with pytest.warns(SlowPathWarning, match="viscous capacitance solve.*box solves instead") as record:
        out = diffuse_velocity(w, 1.0, viscosity=0.08, scheme="implicit", solids=held)
    assert len(calls) == 2 and all(s.windows[F64] is not None for s in _solvers(held))
    assert sum(r.category is SlowPathWarning for r in record) == 2  # one per component
    assert all(r.filename == __file__ for r in record)  # pointed at the caller's line
    for a, b in zip(out.values, ref.values):
        torch.testing.assert_close(a, b, rtol=0, atol=1e-12 * float(b.abs().max()))
