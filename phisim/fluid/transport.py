"""Steppers of transported fields: advection-diffusion of a scalar by a given flow, and Burgers' equation.

Both validate their settings once, in the constructor, and advance a :class:`~phisim.field.CenteredGrid` per
call: advection (:func:`~phisim.ops.advection.advect`) followed by diffusion (:func:`~phisim.solvers.diffusion.
diffuse`, exact spectral by default), first order in time (operator splitting), second order in space with
MacCormack advection.

A call validates its field (Python-level checks) and runs :meth:`advance`, which reads nothing back to the host
(the velocity's finiteness is not checked per step), so that it traces as one graph (``torch.compile(...,
fullgraph=True)``, see :func:`phisim.compile`); the ``'conservative'`` scheme chooses its number of sub-steps from
the velocity (a host read) and does not trace as one graph.
"""

from __future__ import annotations

import torch

from phisim.checks import check_dt, check_finite, check_nonnegative
from phisim.errors import GridMismatchError, ParameterError
from phisim.field import CenteredGrid, StaggeredGrid
from phisim.grid import Grid
from phisim.ops.advection import SCALAR_SCHEMES, SCHEMES, advect_trusted
from phisim.ops.differential import laplace
from phisim.ops.stencil import normalize_kinds
from phisim.solvers.box import apply_multiplier, eigenvalues_cached, transform_scale
from phisim.solvers.diffusion import DIFFUSION_METHODS, diffuse, explicit_stability_limit
from phisim.solvers.poisson import field_kinds_and_values

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
    dt, nu = check_dt(dt), check_nonnegative(diffusivity, name)
    if diffusion == "explicit" and nu != 0 and dt > explicit_stability_limit(grid.dx, nu) * (1 + 1e-12):
        raise ParameterError(f"explicit diffusion is unstable: dt = {dt:g} exceeds the limit "
                             f"1/(2 ν Σ 1/dx²) = {explicit_stability_limit(grid.dx, nu):g}; use diffusion='implicit' "
                             "or 'spectral'")
    return dt, nu


def _box_plan(u: CenteredGrid, nu_dt: float, method: str):
    """Per channel of ``u`` its solver kinds and the one-step multiplier of ``method`` (``exp(ν dt λ)``, or
    ``1 / (1 - ν dt λ)``, with the transforms' scale), kept on ``u``'s boundary; ``()`` for a boundary with
    non-zero values (then :func:`~phisim.solvers.diffusion.diffuse` steps it)."""
    grid, boundary = u.grid, u.boundary
    channels = u.values.shape[1] if u.is_vector else None
    device = u.values.device

    def make():
        plan = []
        for c in (range(channels) if channels is not None else (None,)):
            kinds, values = field_kinds_and_values(boundary, c if channels == grid.rank else None)
            if any(v is not None and not (isinstance(v, (int, float)) and v == 0) for pair in values for v in pair):
                return ()
            kinds = normalize_kinds(kinds, grid.rank)
            lam = eigenvalues_cached(grid.resolution, tuple(grid.dx), kinds, torch.float64, device, True)
            mult = torch.exp(nu_dt * lam) if method == "spectral" else 1.0 / (1.0 - nu_dt * lam)
            plan.append((kinds, (mult * transform_scale(grid.resolution, kinds)).to(u.dtype)))
        return tuple(plan)

    key = ("transport_diffusion", grid.resolution, tuple(grid.dx), nu_dt, method, u.dtype, device, channels)
    return boundary._memo(key, make)


def _diffuse_step(u: CenteredGrid, dt: float, nu: float, method: str) -> CenteredGrid:
    """One diffusion step of ``u`` without host reads: explicit ``u + ν dt ∇²u`` (boundary values included), or the
    exact box solve of ``'spectral'``/``'implicit'`` (zero boundary values; otherwise ``diffuse``)."""
    if method == "explicit":
        return u.with_values(u.values + (nu * dt) * laplace(u).values)
    plan = _box_plan(u, nu * dt, method)
    if not plan:
        return diffuse(u, dt, viscosity=nu, method=method)
    if not u.is_vector:
        kinds, mult = plan[0]
        return u.with_values(apply_multiplier(u.values, kinds, mult, None, prescaled=True))
    return u.with_values(torch.stack([apply_multiplier(u.values[:, c], kinds, mult, None, prescaled=True)
                                      for c, (kinds, mult) in enumerate(plan)], dim=1))


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
        diffusion: ``'spectral'`` (default, exact in time), ``'implicit'`` (backward Euler) or ``'explicit'``
            (forward Euler; a ``dt`` beyond its stability limit raises ParameterError). With zero boundary values
            the spectral and implicit steps are exact box solves (multipliers kept per boundary).
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
        for v in (self.velocity.values if isinstance(self.velocity, StaggeredGrid) else (self.velocity.values,)):
            check_finite(v, "velocity")  # once: the held velocity is not checked per step
        self._advance = self.advance

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
        if self.diffusivity != 0 and self.diffusion != "explicit":
            _box_plan(c, self.diffusivity * self.dt, self.diffusion)  # built here, found by a traced step
        if velocity is None:
            return self._advance(c, self.velocity)
        return self._advance(c, self._check_velocity(velocity))

    def advance(self, c: CenteredGrid, velocity) -> CenteredGrid:
        """The step on a validated field and velocity: no host read (what :func:`torch.compile` traces)."""
        c = advect_trusted(c, velocity, self.dt, scheme=self.advection)
        if self.diffusivity == 0:
            return c
        return _diffuse_step(c, self.dt, self.diffusivity, self.diffusion)


class BurgersStepper:
    """Viscous Burgers' equation ``∂u/∂t + (u·∇)u = ν ∇²u`` for a centred vector ``u``: self-advection, then
    diffusion (``u <- diffuse(advect(u, u))``), in 1-D, 2-D and 3-D with the field's boundary.

    Args:
        grid: The grid.
        viscosity: ``ν >= 0``.
        dt: Time step ``>= 0``.
        advection: ``'maccormack'`` (default) or ``'semi_lagrangian'``.
        diffusion: ``'spectral'`` (default, exact in time), ``'implicit'`` (backward Euler) or ``'explicit'``
            (forward Euler; a ``dt`` beyond its stability limit raises ParameterError). With zero boundary values
            the spectral and implicit steps are exact box solves (multipliers kept per boundary).
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
        self._advance = self.advance

    def __call__(self, u: CenteredGrid) -> CenteredGrid:
        """Advance ``u`` (a centred vector field ``(B, d, *res)``) by one step.

        Raises:
            ParameterError, GridMismatchError: For a field that does not fit the stepper.
        """
        _check_field(u, self.grid, self.dtype, "BurgersStepper", vector=True)
        if self.viscosity != 0 and self.diffusion != "explicit":
            _box_plan(u, self.viscosity * self.dt, self.diffusion)  # built here, found by a traced step
        return self._advance(u)

    def advance(self, u: CenteredGrid) -> CenteredGrid:
        """The step on a validated field: no host read (what :func:`torch.compile` traces)."""
        u = advect_trusted(u, u, self.dt, scheme=self.advection)
        if self.viscosity == 0:
            return u
        return _diffuse_step(u, self.dt, self.viscosity, self.diffusion)
