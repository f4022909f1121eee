"""Ready-made forward simulations of the reference experiments (``EXPERIMENTS.md``).

:func:`e5_simulation` is the forward physics of E5 (incompressible Navier-Stokes with a passive marker,
paper section 3.4 and appendix B.4): 64x64 cells on a periodic 128x128 domain (``dx = 2``), 8 steps of
``dt = 0.25``. Each step:

1. ``E0 = mean(v^2)`` (:func:`phisim.fluid.kinetic_energy`, per sample);
2. MacCormack self-advection of the MAC velocity;
3. pressure projection, warm-started from the previous pressure (on the periodic box the projection is
   the exact direct FFT solve, so the warm start does not change the result);
4. rescale ``v`` to the energy ``E0`` (:func:`phisim.fluid.normalize_energy`);
5. MacCormack advection of the marker by the new velocity.

No viscosity. Batched and differentiable w.r.t. the initial marker and velocity.
"""

from __future__ import annotations

import torch

from phisim.errors import ShapeError
from phisim.field import CenteredGrid, StaggeredGrid
from phisim.fluid import kinetic_energy, make_incompressible, normalize_energy
from phisim.grid import Grid
from phisim.ops.advection import advect

__all__ = ["E5_RESOLUTION", "E5_BOUNDS", "E5_DT", "E5_STEPS", "e5_grid", "e5_step", "e5_simulation"]

#: Cells per axis of E5.
E5_RESOLUTION = (64, 64)
#: Domain size per axis of E5 (``dx = 2``).
E5_BOUNDS = (128.0, 128.0)
#: Time step of E5.
E5_DT = 0.25
#: Number of steps of E5 (``t = 2``).
E5_STEPS = 8


def e5_grid(resolution: tuple[int, int] = E5_RESOLUTION) -> Grid:
    """The E5 grid: ``resolution`` cells with ``dx = 2`` (the default is 64x64 cells on 128x128).

    Args:
        resolution: Cells per axis (other sizes keep ``dx = 2``; useful for small tests).

    Returns:
        The grid.
    """
    return Grid(resolution, bounds=[2.0 * n for n in resolution])


def e5_step(
    marker: CenteredGrid, velocity: StaggeredGrid, pressure: CenteredGrid | None, dt: float = E5_DT
) -> tuple[CenteredGrid, StaggeredGrid, CenteredGrid]:
    """One E5 step (see the module docstring for the order of operations).

    Args:
        marker: Scalar CenteredGrid ``(B, *res)``, periodic.
        velocity: Periodic MAC velocity on the same grid.
        pressure: Previous pressure (warm start) or None.
        dt: Time step.

    Returns:
        ``(marker, velocity, pressure)`` after the step.
    """
    e0 = kinetic_energy(velocity)
    v = advect(velocity, velocity, dt, scheme="maccormack")
    v, p = make_incompressible(v, pressure_guess=pressure)
    v = normalize_energy(v, e0)
    marker = advect(marker, v, dt, scheme="maccormack")
    return marker, v, p


def _as_velocity(velocity0, grid: Grid, batch: int) -> StaggeredGrid:
    if isinstance(velocity0, StaggeredGrid):
        if velocity0.grid != grid:
            raise ShapeError(f"velocity0 lives on {velocity0.grid}, the marker on {grid}")
        return velocity0.with_boundary("periodic")
    vals = velocity0.values if isinstance(velocity0, CenteredGrid) else torch.as_tensor(velocity0)
    if vals.ndim != 4 or vals.shape[1] != 2 or tuple(vals.shape[2:]) != grid.resolution:
        raise ShapeError(
            f"velocity0 must be centred (B, 2, {grid.resolution[0]}, {grid.resolution[1]}) or a "
            f"StaggeredGrid, got shape {tuple(vals.shape)}"
        )
    if vals.shape[0] not in (1, batch):
        raise ShapeError(f"velocity0 batch {vals.shape[0]} does not match the marker batch {batch}")
    return CenteredGrid(vals, grid, "periodic").to_staggered()


def e5_simulation(
    marker0, velocity0, steps: int = E5_STEPS, dt: float = E5_DT, *, return_velocity: bool = False
):
    """Run the E5 forward simulation: the marker after ``steps`` steps of ``dt``.

    Args:
        marker0: Initial marker ``(B, nx, ny)`` tensor or scalar CenteredGrid (64x64 in E5; other sizes use
            ``dx = 2`` too). A CenteredGrid's boundary is replaced by periodic.
        velocity0: Initial velocity: centred ``(B, 2, nx, ny)`` tensor or CenteredGrid (interpolated to the
            faces by averaging neighbouring cells), or a StaggeredGrid on the marker's grid.
        steps: Number of steps (8 in E5).
        dt: Time step (0.25 in E5).
        return_velocity: Also return the final MAC velocity.

    Returns:
        The final marker, a tensor ``(B, nx, ny)`` for tensor input or a CenteredGrid for CenteredGrid input;
        with ``return_velocity`` a pair ``(marker, velocity)``.

    Raises:
        ShapeError: For inputs of the wrong shape.
        ParameterError: For a negative ``dt`` (from the advection).
    """
    if isinstance(marker0, CenteredGrid):
        grid = marker0.grid
        marker = marker0.with_boundary("periodic")
    else:
        m = torch.as_tensor(marker0)
        if m.ndim != 3:
            raise ShapeError(f"marker0 must have shape (B, nx, ny), got {tuple(m.shape)}")
        grid = e5_grid(tuple(m.shape[1:]))
        marker = CenteredGrid(m, grid, "periodic")
    if isinstance(velocity0, StaggeredGrid) and not isinstance(marker0, CenteredGrid):
        grid = velocity0.grid
        marker = CenteredGrid(marker.values, grid, "periodic")
    velocity = _as_velocity(velocity0, grid, marker.batch_size)
    if int(steps) < 0:
        raise ShapeError(f"steps must be >= 0, got {steps}")
    pressure = None
    for _ in range(int(steps)):
        marker, velocity, pressure = e5_step(marker, velocity, pressure, dt)
    out = marker if isinstance(marker0, CenteredGrid) else marker.values
    return (out, velocity) if return_velocity else out
