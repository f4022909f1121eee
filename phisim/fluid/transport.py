"""Steppers of transported fields: advection-diffusion of a scalar by a given flow, and Burgers' equation.

Both validate their settings once, in the constructor, and advance a :class:`~phisim.field.CenteredGrid` per
call: advection (:func:`~phisim.ops.advection.advect`) followed by diffusion (:func:`~phisim.solvers.diffusion.
diffuse`, exact spectral by default), first order in time (operator splitting), second order in space with
MacCormack advection.
"""

from __future__ import annotations

import torch

from phisim.checks import check_dt, check_nonnegative
from phisim.errors import GridMismatchError, ParameterError
from phisim.field import CenteredGrid, StaggeredGrid
from phisim.grid import Grid
from phisim.ops.advection import SCALAR_SCHEMES, SCHEMES, advect
from phisim.solvers.diffusion import DIFFUSION_METHODS, diffuse

__all__ = ["AdvectionDiffusionStepper", "BurgersStepper"]


def _check_common(grid, dt, diffusivity, name, advection, schemes, diffusion, dtype):
    if not isinstance(grid, Grid):
        raise ParameterError(f"grid must be a phisim.Grid, got {type(grid).__name__}")
    if advection not in schemes:
        raise ParameterError(f"unknown advection scheme {advection!r}; choose one of {schemes}")
    if diffusion not in DIFFUSION_METHODS:
        raise ParameterError(f"unknown diffusion method {diffusion!r}; choose one of {DIFFUSION_METHODS}")
    if dtype not in (torch.float32, torch.float64):
        raise ParameterError(f"dtype must be torch.float32 or torch.float64, got {dtype!r}")
    return check_dt(dt), check_nonnegative(diffusivity, name)


def _check_field(u, grid, dtype, what: str, vector: bool):
    if not isinstance(u, CenteredGrid) or u.is_vector != vector:
        kind = "vector" if vector else "scalar"
        raise ParameterError(f"a {what} advances a {kind} CenteredGrid, got {type(u).__name__}")
    if u.grid != grid:
        raise GridMismatchError(f"field grid {u.grid} differs from the {what}'s {grid}")
    if u.dtype != dtype:
        raise ParameterError(f"this {what} was built for {dtype}; got {u.dtype}")


class AdvectionDiffusionStepper:
    """``∂c/∂t + u·∇c = κ ∇²c`` for a scalar ``c`` in a given velocity ``u``: ``c <- diffuse(advect(c, u))``.

    Args:
        grid: The grid.
        velocity: The flow, a centred vector field or a :class:`~phisim.field.StaggeredGrid` on ``grid``
            (held; a call may pass another one of the same grid).
        diffusivity: ``κ >= 0`` (0: pure transport).
        dt: Time step ``>= 0``.
        advection: One of :data:`phisim.ops.advection.SCALAR_SCHEMES` (default ``'maccormack'``;
            ``'conservative'`` keeps the total to round-off).
        diffusion: ``'spectral'`` (default, exact in time), ``'implicit'`` or ``'explicit'``.
        dtype: Of the fields this stepper advances.

    Raises:
        ParameterError: For an unknown scheme, a negative dt or diffusivity, a velocity that is not a field.
        GridMismatchError: For a velocity on another grid.
    """

    def __init__(self, grid: Grid, velocity, *, diffusivity: float = 0.0, dt, advection: str = "maccormack",
                 diffusion: str = "spectral", dtype: torch.dtype = torch.float32):
        self.dt, self.diffusivity = _check_common(grid, dt, diffusivity, "diffusivity", advection, SCALAR_SCHEMES,
                                                  diffusion, dtype)
        self.grid, self.advection, self.diffusion, self.dtype = grid, advection, diffusion, dtype
        self.velocity = self._check_velocity(velocity)

    def _check_velocity(self, velocity):
        if not isinstance(velocity, (CenteredGrid, StaggeredGrid)):
            raise ParameterError(f"velocity must be a CenteredGrid or StaggeredGrid, got {type(velocity).__name__}")
        if velocity.grid != self.grid:
            raise GridMismatchError(f"velocity grid {velocity.grid} differs from the stepper's {self.grid}")
        return velocity

    def __call__(self, c: CenteredGrid, velocity=None) -> CenteredGrid:
        """Advance the scalar ``c`` by one step (in the held velocity, or ``velocity``).

        Raises:
            ParameterError, GridMismatchError: For a field or velocity that does not fit the stepper.
        """
        _check_field(c, self.grid, self.dtype, "AdvectionDiffusionStepper", vector=False)
        u = self.velocity if velocity is None else self._check_velocity(velocity)
        c = advect(c, u, self.dt, scheme=self.advection)
        if self.diffusivity == 0:
            return c
        return diffuse(c, self.dt, viscosity=self.diffusivity, method=self.diffusion)


class BurgersStepper:
    """Viscous Burgers' equation ``∂u/∂t + (u·∇)u = ν ∇²u`` for a centred vector ``u``: self-advection, then
    diffusion (``u <- diffuse(advect(u, u))``), in 1-D, 2-D and 3-D with the field's boundary.

    Args:
        grid: The grid.
        viscosity: ``ν >= 0``.
        dt: Time step ``>= 0``.
        advection: ``'maccormack'`` (default) or ``'semi_lagrangian'``.
        diffusion: ``'spectral'`` (default, exact in time), ``'implicit'`` or ``'explicit'``.
        dtype: Of the fields this stepper advances.

    Raises:
        ParameterError: For an unknown scheme or a negative dt or viscosity.

    For a spectral (ETDRK) Burgers solver with 2/3 dealiasing see :mod:`phisim.pde`.
    """

    def __init__(self, grid: Grid, *, viscosity: float, dt, advection: str = "maccormack",
                 diffusion: str = "spectral", dtype: torch.dtype = torch.float32):
        self.dt, self.viscosity = _check_common(grid, dt, viscosity, "viscosity", advection, SCHEMES, diffusion,
                                                dtype)
        self.grid, self.advection, self.diffusion, self.dtype = grid, advection, diffusion, dtype

    def __call__(self, u: CenteredGrid) -> CenteredGrid:
        """Advance ``u`` (a centred vector field ``(B, d, *res)``) by one step.

        Raises:
            ParameterError, GridMismatchError: For a field that does not fit the stepper.
        """
        _check_field(u, self.grid, self.dtype, "BurgersStepper", vector=True)
        u = advect(u, u, self.dt, scheme=self.advection)
        if self.viscosity == 0:
            return u
        return diffuse(u, self.dt, viscosity=self.viscosity, method=self.diffusion)
