"""The small tensor helpers: ``unravel`` (torch.unravel_index without its sympy import) and ``sum_last``."""

from __future__ import annotations

import subprocess
import sys

import pytest
import torch

from phisim.errors import ParameterError
from phisim.ops.tensors import sum_last, unravel


@pytest.mark.parametrize("shape", [(7,), (7, 5), (7, 5, 3), (1, 4, 1, 6)])
def test_unravel_inverts_the_flat_index(shape):
    """Each flat index of a C-ordered array maps to the multi-index that ``ravel`` takes back to it."""
    n = 1
    for m in shape:
        n *= m
    index = torch.randperm(n, generator=torch.Generator().manual_seed(0))
    parts = unravel(index, shape)
    assert len(parts) == len(shape) and all(p.dtype == torch.int64 for p in parts)
    back = torch.zeros_like(index)
    for p, m in zip(parts, shape):
        assert int(p.min()) >= 0 and int(p.max()) < m
        back = back * m + p
    assert torch.equal(back, index)
    # a known one: index 1 * 5 * 3 + 2 * 3 + 1 = 22 of (7, 5, 3)
    if shape == (7, 5, 3):
        assert [int(p) for p in unravel(torch.tensor(22), shape)] == [1, 2, 1]


def test_unravel_rejects_float_indices():
    with pytest.raises(ParameterError, match="integer"):
        unravel(torch.tensor([1.0]), (3,))


@pytest.mark.parametrize("d", [1, 2, 3, 4])
def test_sum_last_is_the_sum_over_the_last_axis(d):
    """Bit-identical to ``x.sum(-1)`` for the short axes it is used on (a point's coordinates), and differentiable."""
    x = torch.randn(5, 7, 11, d, dtype=torch.float64, generator=torch.Generator().manual_seed(d))
    assert torch.equal(sum_last(x), x.sum(-1))
    y = torch.randn(3, d, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda t: sum_last(t * t), (y,))


def test_sum_last_rejects_an_empty_or_missing_axis():
    for bad in (torch.tensor(1.0), torch.zeros(3, 0)):
        with pytest.raises(ParameterError, match="last axis"):
            sum_last(bad)


def test_a_moving_body_step_does_not_import_sympy():
    """The first steps of a carried sphere do not pay for sympy's import (``torch.unravel_index`` imports it on its
    first call, half a second or more)."""
    code = (
        "import sys, torch\n"
        "from phisim import Grid, StaggeredGrid\n"
        "from phisim.fluid import Body, FluidState, FluidStepper, Sphere\n"
        "before = 'sympy' in sys.modules\n"
        "grid = Grid((12, 12, 12), bounds=[(0.0, 1.0)] * 3)\n"
        "body = Body(Sphere((0.4, 0.45, 0.5), 0.2), velocity=(0.5, 0.2, 0.0))\n"
        "st = FluidStepper(grid, 'wall', obstacles=body, viscosity=0.01, dt=0.01, dtype=torch.float64)\n"
        "s = FluidState(StaggeredGrid.zeros(grid, 'wall', dtype=torch.float64))\n"
        "for _ in range(2):\n"
        "    s = st(s)\n"
        "print(before, 'sympy' in sys.modules)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    before, after = out.stdout.split()
    if before == "True":
        pytest.skip("this torch imports sympy with phisim already")
    assert after == "False"
