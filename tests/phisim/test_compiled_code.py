"""Compiled steps keep graphs of their own: many steppers compiled in one process do not exhaust
``torch.compile``'s per-code recompile limit (``phisim.compiled._own_code``); a CUDA-graph step's result is copied
out of the graph's memory (``phisim.compiled.own_memory``)."""

from __future__ import annotations

import torch

from phisim import CenteredGrid, Grid, StaggeredGrid
from phisim.compiled import _own_code, own_memory
from phisim.fluid import FluidState, FluidStepper

F64 = torch.float64


class _Scaled:
    def __init__(self, factor: float):
        self.factor = factor

    def advance(self, x):
        return x * self.factor + 1.0


def test_each_copy_has_its_own_code_and_the_same_behaviour():
    a, b = _Scaled(2.0), _Scaled(3.0)
    fa, fb = _own_code(a.advance), _own_code(b.advance)
    assert fa.__func__.__code__ is not fb.__func__.__code__
    assert fa.__self__ is a and fb.__self__ is b
    x = torch.arange(3.0)
    assert torch.equal(fa(x), a.advance(x)) and torch.equal(fb(x), b.advance(x))


def test_more_steppers_than_the_recompile_limit_compile_with_fullgraph():
    limit = torch._dynamo.config.recompile_limit
    for k in range(limit + 3):  # each guards on its own constants (spacing, dt): one graph per stepper
        n = 4 + k
        grid = Grid((n, n), bounds=[(0, 1), (0, 1)])
        st = FluidStepper(grid, "periodic", viscosity=1e-3, dt=0.01 * (k + 1), dtype=torch.float64)
        step = torch.compile(_own_code(st.advance), fullgraph=True, dynamic=False, backend="eager")
        state = FluidState(StaggeredGrid.zeros(grid, st.boundary, 1, dtype=torch.float64))
        out = step(state, st.dt)
        ref = st.advance(state, st.dt)
        for x, y in zip(out.velocity.values, ref.velocity.values):
            assert torch.equal(x, y)


def test_own_memory_copies_every_tensor_of_a_state():
    grid = Grid((6, 6), bounds=[(0, 1), (0, 1)])
    stepper = FluidStepper(grid, "wall", viscosity=1e-3, buoyancy=0.5, dt=0.02, dtype=F64)
    state = stepper(FluidState(StaggeredGrid.zeros(grid, stepper.boundary, dtype=F64),
                               CenteredGrid(torch.rand((1, 6, 6), dtype=F64), grid, stepper.boundary.for_scalar())))
    copy = own_memory(state)
    assert isinstance(copy, FluidState) and copy.time == state.time
    pairs = list(zip(copy.velocity.values, state.velocity.values))
    pairs += [(copy.marker.values, state.marker.values), (copy.pressure.values, state.pressure.values)]
    for x, y in pairs:
        assert torch.equal(x, y) and x.data_ptr() != y.data_ptr()
    assert own_memory((1, "a", None)) == (1, "a", None)
