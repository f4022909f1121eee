"""phisim.rollout: the trajectory of a stepper stacked in time, differentiable, with checkpointed segments."""

from __future__ import annotations

import pytest
import torch

import phisim
from phisim import CenteredGrid, Grid, StaggeredGrid
from phisim.errors import ParameterError
from phisim.fluid import BurgersStepper, FluidState, FluidStepper
from phisim.solvers.heat import HeatStepper

F64 = torch.float64


def _smoke(n=10, dtype=F64, integrator="split"):
    grid = Grid((n, n), bounds=[(0, 1), (0, 1)])
    stepper = FluidStepper(grid, "wall", viscosity=1e-2, buoyancy=0.5, dt=0.02, dtype=dtype, integrator=integrator)
    g = torch.Generator().manual_seed(0)
    v = StaggeredGrid.zeros(grid, stepper.boundary, dtype=dtype)
    v0 = tuple(0.1 * torch.randn(c.shape, generator=g, dtype=dtype) for c in v.values)
    m0 = torch.rand((1, n, n), generator=g, dtype=dtype)
    return grid, stepper, v, v0, m0


def _state(grid, stepper, v, v0, m0):
    return FluidState(v.with_values(v0), CenteredGrid(m0, grid, stepper.boundary.for_scalar()))


def test_trajectory_equals_a_python_loop_every_k():
    grid, stepper, v, v0, m0 = _smoke()
    s = _state(grid, stepper, v, v0, m0)
    tr = phisim.rollout(stepper, s, 7, every=3)
    assert len(tr) == 3  # the initial state, after 3 and after 6 steps
    assert tr.velocity[0].shape == (3, 1, 11, 10) and tr.velocity[1].shape == (3, 1, 10, 11)
    assert tr.marker.shape == tr.pressure.shape == (3, 1, 10, 10)
    torch.testing.assert_close(tr.times, torch.tensor([0.0, 0.06, 0.12], dtype=F64))
    loop = [s]
    for _ in range(7):
        loop.append(stepper(loop[-1]))
    for t, k in enumerate((0, 3, 6)):
        for i in range(2):
            assert torch.equal(tr.velocity[i][t], loop[k].velocity.values[i])
        assert torch.equal(tr.marker[t], loop[k].marker.values)
    assert not tr.pressure[0].any()  # the initial state had no pressure yet
    assert torch.equal(tr.pressure[2], loop[6].pressure.values)
    assert torch.equal(tr.final.velocity.values[0], loop[7].velocity.values[0])
    assert tr.final.time == loop[7].time


@pytest.mark.parametrize(("segment", "integrator"), [(1, "split"), (3, "split"), (5, "split"), (40, "split"),
                                                     (3, "split2")])
def test_checkpointed_gradients_equal_plain_backprop(segment, integrator):
    """'split2' keeps the velocity's rate and acceleration in the state: they carry gradients across segments."""
    grid, stepper, v, v0, m0 = _smoke(integrator=integrator)

    def grads(checkpoint):
        x = tuple(c.clone().requires_grad_() for c in v0)
        m = m0.clone().requires_grad_()
        tr = phisim.rollout(stepper, _state(grid, stepper, v, x, m), 9, every=2, checkpoint=checkpoint)
        loss = (sum((c[1:] ** 2).sum() for c in tr.velocity) + (tr.marker * tr.marker.detach()).sum()
                + tr.final.velocity.values[1].pow(3).sum() + tr.pressure[-1].pow(2).sum())
        return torch.autograd.grad(loss, (*x, m)), tr

    plain, tr0 = grads(None)
    ckpt, tr1 = grads(segment)
    for a, b in zip(tr0.velocity, tr1.velocity):
        assert torch.equal(a, b)
    torch.testing.assert_close(tr0.times, tr1.times)
    for a, b in zip(plain, ckpt):
        assert a.abs().max() > 0
        torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-14)


def test_gradient_matches_finite_differences():
    grid, stepper, v, v0, m0 = _smoke(n=8)
    direction = tuple(torch.randn(c.shape, generator=torch.Generator().manual_seed(7), dtype=F64) for c in v0)

    def loss(x):
        tr = phisim.rollout(stepper, _state(grid, stepper, v, x, m0), 4, every=4, checkpoint=2)
        return tr.velocity[0][-1].pow(2).sum() + tr.marker[-1].mul(tr.velocity[1][-1][..., :-1]).sum()

    x = tuple(c.clone().requires_grad_() for c in v0)
    g = torch.autograd.grad(loss(x), x)
    eps = 1e-6
    with torch.no_grad():
        plus = loss(tuple(c + eps * d for c, d in zip(v0, direction)))
        minus = loss(tuple(c - eps * d for c, d in zip(v0, direction)))
    fd = (plus - minus) / (2 * eps)
    ad = sum((a * d).sum() for a, d in zip(g, direction))
    torch.testing.assert_close(ad, fd, rtol=1e-5, atol=1e-8)


def test_field_steppers():
    grid = Grid((12, 12), bounds=[(0, 1), (0, 1)])
    heat = HeatStepper(grid, "dirichlet", diffusivity=0.05, dt=0.01, dtype=F64)
    u0 = CenteredGrid(torch.rand((2, 12, 12), generator=torch.Generator().manual_seed(1), dtype=F64), grid,
                      "dirichlet")
    tr = phisim.rollout(heat, u0, 5, every=2)
    assert tr.values.shape == (3, 2, 12, 12) and tr.velocity is None
    torch.testing.assert_close(tr.times, torch.tensor([0.0, 0.02, 0.04], dtype=F64))
    assert torch.equal(tr.values[2], heat(heat(heat(heat(u0)))).values)
    burgers = BurgersStepper(grid, viscosity=0.02, dt=0.02, dtype=F64)
    u = CenteredGrid(0.2 * torch.randn((1, 2, 12, 12), generator=torch.Generator().manual_seed(2), dtype=F64),
                     grid, "periodic")

    def grad(ck):
        x = u.values.clone().requires_grad_()
        tr = phisim.rollout(burgers, u.with_values(x), 6, every=3, checkpoint=ck)
        return torch.autograd.grad(tr.values.pow(2).sum(), x)[0]

    torch.testing.assert_close(grad(None), grad(2), rtol=1e-12, atol=1e-14)


def test_no_steps_and_bad_arguments():
    grid, stepper, v, v0, m0 = _smoke()
    s = _state(grid, stepper, v, v0, m0)
    tr = phisim.rollout(stepper, s, 0)
    assert len(tr) == 1 and tr.final is s and tr.pressure is None
    for kwargs in (dict(steps=-1), dict(steps=2, every=0), dict(steps=2, checkpoint=0), dict(steps=2.0)):
        with pytest.raises(ParameterError):
            phisim.rollout(stepper, s, **kwargs)
    with pytest.raises(ParameterError):
        phisim.rollout(stepper, v, 2)
