"""Small tensor helpers that torch has, done faster or without heavy imports.

* :func:`unravel`: multi-indices of flat indices (``torch.unravel_index`` imports sympy on its first call, half a
  second or more of a process's first step with bodies).
* :func:`sum_last`: the sum over a point's 2-3 coordinates as a chain of additions: torch's reduction over an inner
  axis of length 2-3 costs 20-25 times more on the CPU, and the chain adds in the same order (bit-identical results
  on the CPU). From about 8 entries on (a stencil's corners) torch's vectorised reduction is the faster one, and it
  adds in another order.
"""

from __future__ import annotations

import torch

from phisim.errors import ParameterError

__all__ = ["unravel", "sum_last"]


def unravel(index: torch.Tensor, shape) -> tuple[torch.Tensor, ...]:
    """The multi-indices of the flat (C-order) ``index`` into an array of ``shape``, one tensor per axis: what
    ``torch.unravel_index`` returns, by integer division (whose first call imports sympy, half a second or more).

    Raises:
        ParameterError: For a non-integer ``index``.
    """
    if index.is_floating_point() or index.is_complex():
        raise ParameterError(f"unravel: index must be an integer tensor, got {index.dtype}")
    out = []
    rest = index
    for n in reversed(tuple(int(m) for m in shape)):
        out.append(torch.remainder(rest, n))
        rest = torch.div(rest, n, rounding_mode="floor")
    return tuple(reversed(out))


def sum_last(x: torch.Tensor) -> torch.Tensor:
    """``x.sum(-1)`` for a short last axis, added left to right (``((x0 + x1) + x2) + ...``).

    Raises:
        ParameterError: For a 0-d tensor or an empty last axis.
    """
    if x.ndim == 0 or x.shape[-1] == 0:
        raise ParameterError(f"sum_last: needs a non-empty last axis, got shape {tuple(x.shape)}")
    out = x[..., 0]
    for k in range(1, x.shape[-1]):
        out = out + x[..., k]
    return out
