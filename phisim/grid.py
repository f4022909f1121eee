"""Uniform rectilinear grids: resolution, physical bounds, cell-centre and face coordinates.

Spatial axes are ordered ``(x, y[, z])`` and arrays use ``indexing='ij'``: ``values[b, i, j]`` sits at
``(x_i, y_j)``. Cell ``i`` along an axis with lower bound ``lo`` and spacing ``dx`` has its centre at
``lo + (i + 1/2) dx``; face ``i`` (``0 <= i <= n``) sits at ``lo + i dx``, so the two outermost faces lie
on the domain boundary.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch

from phisim.checks import check_device
from phisim.errors import ParameterError

__all__ = ["Grid", "AXIS_NAMES"]

AXIS_NAMES = ("x", "y", "z")
#: Largest number of cells along one axis (2**31 - 1): beyond it no array fits in memory, and an int beyond 2**63
#: overflows torch's indices.
MAX_CELLS_PER_AXIS = 2**31 - 1


def _as_bounds(resolution: tuple[int, ...], bounds) -> tuple[tuple[float, float], ...]:
    if bounds is None:
        return tuple((0.0, float(n)) for n in resolution)
    if isinstance(bounds, (str, bytes)) or not isinstance(bounds, (Sequence, np.ndarray)):
        raise ParameterError(
            f"bounds must be one (lower, upper) pair or one size per axis, e.g. [(0, 1)] * {len(resolution)}, "
            f"got {bounds!r}"
        )
    bounds = list(bounds)
    if len(bounds) != len(resolution):
        raise ParameterError(
            f"bounds has {len(bounds)} entries but the grid has {len(resolution)} axes; "
            "give one (lower, upper) pair or one size per axis"
        )
    out = []
    for axis, b in enumerate(bounds):
        if isinstance(b, (int, float, np.number)) and not isinstance(b, bool):
            lo, hi = 0.0, float(b)
        elif isinstance(b, (str, bytes, bool)):
            raise ParameterError(f"bounds[{axis}] = {b!r} is neither a size nor a (lower, upper) pair")
        else:
            try:
                lo, hi = (float(v) for v in b)
            except (TypeError, ValueError) as exc:
                raise ParameterError(f"bounds[{axis}] = {b!r} is neither a size nor a (lower, upper) pair") from exc
        if not (math.isfinite(lo) and math.isfinite(hi)) or hi <= lo:
            raise ParameterError(f"bounds[{axis}] = ({lo}, {hi}) must be finite with upper > lower")
        out.append((lo, hi))
    return tuple(out)


@dataclass(frozen=True, init=False)
class Grid:
    """A uniform grid of ``resolution`` cells covering the box ``bounds`` (1-D, 2-D or 3-D).

    Args:
        resolution: Cells per axis, e.g. ``(64, 64)``. An int means a 1-D grid.
        bounds: Per axis either a ``(lower, upper)`` pair or a size (lower bound 0). ``None`` gives
            ``dx = 1`` on every axis with the lower corner at the origin.

    Raises:
        ParameterError: For non-positive or too large (> 2**31 - 1) resolutions, more than three axes, or empty
            bounds.

    Example:
        >>> Grid((64, 32), bounds=[(0, 2), (0, 1)]).dx
        (0.03125, 0.03125)
    """

    resolution: tuple[int, ...]
    bounds: tuple[tuple[float, float], ...]

    def __init__(self, resolution: int | Sequence[int], bounds=None):
        if isinstance(resolution, (str, bytes, bool, float)):
            raise ParameterError(
                f"resolution must be an int or a sequence of ints, e.g. (64, 64), got {resolution!r}"
            )
        if isinstance(resolution, (int, np.integer)):
            resolution = (int(resolution),)
        try:
            if any(isinstance(n, (str, bytes, bool)) for n in resolution):
                raise TypeError("not an int")
            res = tuple(int(n) for n in resolution)
        except (TypeError, ValueError) as exc:
            raise ParameterError(f"resolution must be a sequence of ints, got {resolution!r}") from exc
        if any(float(n) != float(r) for n, r in zip(res, resolution)):
            raise ParameterError(f"resolution must be integers, got {resolution!r}")
        if not 1 <= len(res) <= 3:
            raise ParameterError(f"grids have 1, 2 or 3 axes, got resolution {res}")
        if any(n < 1 for n in res):
            raise ParameterError(f"every resolution entry must be >= 1, got {res}")
        if any(n > MAX_CELLS_PER_AXIS for n in res):
            raise ParameterError(f"every resolution entry must be <= {MAX_CELLS_PER_AXIS} (torch indexes arrays with "
                                 f"64-bit ints, and no array that long fits in memory), got {res}")
        object.__setattr__(self, "resolution", res)
        object.__setattr__(self, "bounds", _as_bounds(res, bounds))
        for axis, d in enumerate(self.dx):
            if not 1e-18 <= d <= 1e18:
                raise ParameterError(
                    f"cell size dx = {d:g} along axis {AXIS_NAMES[axis]} is out of range [1e-18, 1e18]: 1/dx^2 "
                    "would overflow float32 (derivatives give Inf/NaN); rescale the units of the domain"
                )

    # ---- basic geometry -------------------------------------------------------------------------
    @property
    def rank(self) -> int:
        """Number of spatial axes (1, 2 or 3)."""
        return len(self.resolution)

    @property
    def lower(self) -> tuple[float, ...]:
        """Lower corner of the domain."""
        return tuple(b[0] for b in self.bounds)

    @property
    def upper(self) -> tuple[float, ...]:
        """Upper corner of the domain."""
        return tuple(b[1] for b in self.bounds)

    @property
    def size(self) -> tuple[float, ...]:
        """Physical extent per axis (``upper - lower``)."""
        return tuple(hi - lo for lo, hi in self.bounds)

    @functools.cached_property
    def dx(self) -> tuple[float, ...]:
        """Cell spacing per axis."""
        return tuple(s / n for s, n in zip(self.size, self.resolution))

    @property
    def cell_volume(self) -> float:
        """Volume (area, length) of one cell."""
        return math.prod(self.dx)

    @property
    def num_cells(self) -> int:
        """Total number of cells."""
        return math.prod(self.resolution)

    def face_shape(self, axis: int) -> tuple[int, ...]:
        """Shape of the face array normal to ``axis`` (``resolution[axis] + 1`` faces along it)."""
        self._check_axis(axis)
        return tuple(n + 1 if a == axis else n for a, n in enumerate(self.resolution))

    # ---- coordinates ------------------------------------------------------------------------------
    def center_coords(self, axis: int, dtype: torch.dtype | None = None, device=None) -> torch.Tensor:
        """Cell-centre coordinates along ``axis``, shape ``(resolution[axis],)``."""
        self._check_axis(axis)
        n, lo, d = self.resolution[axis], self.bounds[axis][0], self.dx[axis]
        device = None if device is None else check_device(device)  # a missing GPU is a ParameterError
        return lo + (torch.arange(n, dtype=dtype or torch.get_default_dtype(), device=device) + 0.5) * d

    def face_coords(self, axis: int, dtype: torch.dtype | None = None, device=None) -> torch.Tensor:
        """Face coordinates along ``axis`` including both boundary faces, shape ``(resolution[axis] + 1,)``."""
        self._check_axis(axis)
        n, lo, d = self.resolution[axis], self.bounds[axis][0], self.dx[axis]
        device = None if device is None else check_device(device)
        return lo + torch.arange(n + 1, dtype=dtype or torch.get_default_dtype(), device=device) * d

    def cell_centers(self, dtype: torch.dtype | None = None, device=None) -> torch.Tensor:
        """All cell centres, shape ``(*resolution, rank)``, ``indexing='ij'``."""
        axes = [self.center_coords(a, dtype, device) for a in range(self.rank)]
        return torch.stack(torch.meshgrid(*axes, indexing="ij"), dim=-1)

    def face_centers(self, axis: int, dtype: torch.dtype | None = None, device=None) -> torch.Tensor:
        """Centres of the faces normal to ``axis``, shape ``(*face_shape(axis), rank)``."""
        axes = [
            self.face_coords(a, dtype, device) if a == axis else self.center_coords(a, dtype, device)
            for a in range(self.rank)
        ]
        return torch.stack(torch.meshgrid(*axes, indexing="ij"), dim=-1)

    def _check_axis(self, axis: int) -> None:
        if not 0 <= axis < self.rank:
            raise ParameterError(f"axis {axis} out of range for a {self.rank}-D grid")

    def __repr__(self) -> str:
        b = ", ".join(f"{AXIS_NAMES[a]}=[{lo:g}, {hi:g}]" for a, (lo, hi) in enumerate(self.bounds))
        return f"Grid(resolution={self.resolution}, {b})"
