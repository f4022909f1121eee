"""The fluid stepper: one object per simulation set-up, settings checked and operators built once.

:class:`FluidStepper` is the way to advance an incompressible flow: its constructor validates every setting
(schemes, viscosity, buoyancy, pressure-solve settings, dtype and device) and builds what depends only on the
settings and the geometry (the static solids' layout and, at its first use, their masked pressure operator with
the direct solve and the viscous capacitance solves, kept on that layout); calling it advances a
:class:`~phisim.fluid.step.FluidState`. Every name has one meaning (see ``docs/SCHEMES.md``):

* ``advection``: the self-advection scheme of the split step, ``'maccormack'`` (default) or
  ``'semi_lagrangian'``; ``marker_advection`` the marker's scheme (default: ``advection``);
* ``viscosity_scheme``: the time discretisation of viscosity in the split step, ``'explicit'`` (default),
  ``'implicit'``, ``'crank_nicolson'`` or ``'spectral'``;
* ``integrator``: the time integrator of the whole step, ``'split'`` (default; first order), ``'rk2'``
  (Heun), ``'rk3'`` (SSP-RK3) or ``'imex2'`` (Crank-Nicolson viscosity, Heun convection).

:func:`step` and :func:`navier_stokes_step` are the same steps as pure functions (nothing is kept between
calls: solids are rasterised and their pressure operator built at every call, solved by PCG).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace

import torch

from phisim.allocator import keep_freed_memory
from phisim.boundary import Boundary, Inflow
from phisim.checks import check_dt, check_finite, check_finite_number, check_nonnegative
from phisim.compiled import compile_function
from phisim.errors import GridMismatchError, ParameterError
from phisim.field import CenteredGrid, StaggeredGrid
from phisim.fluid.bodies import Obstacle, as_solids, solid_layout
from phisim.fluid.extension import extend_into_bodies
from phisim.fluid.integrators import (
    INTEGRATORS,
    check_convection,
    check_viscous_number,
    navier_stokes_rk_step,
    rk_advance,
)
from phisim.fluid.periodic import PeriodicStep
from phisim.fluid.projection import check_balance, check_fits, check_velocity, project_box
from phisim.fluid.step import (
    FluidState,
    apply_buoyancy,
    buoyancy_args,
    finish_step,
    half_step_velocity,
    kinetic_energy,
    scalar_values,
    split2_advection,
    split2_memory,
    to_time,
)
from phisim.fluid.viscosity import VISCOSITY_SCHEMES
from phisim.grid import Grid
from phisim.ops.advection import SCALAR_SCHEMES, SCHEMES, advect, advect_trusted, validate_advection
from phisim.solvers.linalg import Solve

__all__ = ["FluidStepper", "step", "navier_stokes_step", "advance"]

#: The operator-split integrators (advection, forcing, viscosity, projection), as against the Runge-Kutta ones.
SPLIT = ("split", "split2")


def _check_schemes(advection: str, marker_advection: str | None, viscosity_scheme: str, integrator: str) -> str:
    """Validate the scheme settings of a fluid step; return the marker's scheme (default: ``advection``)."""
    if advection not in SCHEMES:
        raise ParameterError(f"unknown advection scheme {advection!r}; choose one of {SCHEMES}")
    marker_advection = advection if marker_advection is None else marker_advection
    if marker_advection not in SCALAR_SCHEMES:
        raise ParameterError(f"unknown marker advection scheme marker_advection={marker_advection!r}; choose one "
                             f"of {SCALAR_SCHEMES}")
    if viscosity_scheme not in VISCOSITY_SCHEMES:
        raise ParameterError(f"unknown viscosity_scheme {viscosity_scheme!r}; choose one of {VISCOSITY_SCHEMES}")
    if integrator not in INTEGRATORS:
        raise ParameterError(f"unknown integrator {integrator!r}; choose one of {tuple(INTEGRATORS)}")
    return marker_advection


class FluidStepper:
    """An incompressible-flow time step with its settings and precomputed operators: ``state = stepper(state)``.

    Args:
        grid: The grid.
        boundary: The velocity boundary (a :class:`~phisim.boundary.Boundary` or any specification
            :class:`~phisim.field.StaggeredGrid` accepts, e.g. ``{"x": "wall", "y": "periodic"}``).
        obstacles: Solids (see :func:`~phisim.fluid.projection.make_incompressible`). Static ones are rasterised
            here, once, and their solvers kept; moving bodies are rasterised at each step's time.
        viscosity: Kinematic viscosity ``>= 0``.
        advection: ``'maccormack'`` (default) or ``'semi_lagrangian'`` self-advection (split integrator).
        marker_advection: Marker transport scheme (one of :data:`phisim.ops.advection.SCALAR_SCHEMES`);
            default ``advection``.
        viscosity_scheme: ``'explicit'`` (default), ``'implicit'``, ``'crank_nicolson'`` or ``'spectral'``.
        integrator: ``'split'`` (default), ``'split2'`` (the split step with second-order advection in time; the
            state keeps the velocity's rate and acceleration), ``'rk2'``, ``'rk3'`` or ``'imex2'``.
        buoyancy: Buoyancy per unit marker (acceleration); needs a marker in the state.
        buoyancy_direction: The "up" vector (default: y, axis 1).
        marker_source: Marker added per unit time, CenteredGrid or tensor ``(1 or B, *res)``.
        energy_normalization: Rescale the velocity to its kinetic energy at the start of each step.
        pressure: :class:`~phisim.solvers.linalg.Solve` settings of the masked pressure solve (and of viscous
            solves with bodies); default: :data:`~phisim.fluid.projection.PRESSURE_SOLVE` in float64, rtol
            1e-5 in float32.
        dt: Default time step of a call (a call may pass its own).
        dtype, device: Of the states this stepper advances.
        direct: ``'auto'`` (default): static solids get the direct solves that pay off when reused (pressure:
            :class:`~phisim.solvers.masked.MaskedPoisson` ``direct='auto'``; viscosity of ``'imex2'``: capacitance
            solves); ``False``: iterative solves only.
        check: Per-step finiteness check: ``None`` or 0 (default) never checks on the step's path; ``N > 0``
            checks the new state every ``N`` calls (one host read; raises
            :class:`~phisim.errors.NonFiniteError`).
        compile: ``True``: the step runs through ``torch.compile`` (see :func:`phisim.compile`; without a working
            C++ compiler a one-line warning and eager steps).
        fused: ``True`` (default): where the settings allow it (every axis periodic, no solids, ``'split'``
            integrator, semi-Lagrangian or MacCormack advection, explicit or no viscosity, no buoyancy, marker
            source or energy normalisation) states without a marker take the fused step of
            :class:`~phisim.fluid.periodic.PeriodicStep` (the same computation in a few array passes, equal to
            rounding); ``False``: always the general path.
        convection: The convection scheme of the ``'rk2'``, ``'rk3'`` and ``'imex2'`` integrators: ``'central'``
            (default) or ``'quick'`` (upwind-biased, for cell Reynolds numbers ``|u| dx / nu`` above about 2;
            :func:`~phisim.fluid.integrators.convection`). The split integrators' transport is ``advection``.

    The step of a call (:meth:`advance`) reads nothing back to the host and branches on no tensor value: the
    settings, the balance of the prescribed boundary fluxes and the solids' coverage are checked here, once,
    so that it traces as one graph (``torch.compile(stepper.advance, fullgraph=True)``; inside a traced step
    the transforms are ``torch.fft``). The pure function :func:`step` keeps its per-call checks.

    Raises:
        ParameterError: For an unknown scheme or integrator, a negative viscosity or dt, a non-finite
            buoyancy, ``pressure`` that is not a Solve, or solids that do not fit the domain.
        ShapeError, GridMismatchError: For a marker source that does not fit the grid.

    Example:
        >>> from phisim import Grid
        >>> from phisim.fluid import FluidStepper, FluidState, Body, Sphere
        >>> grid = Grid((64, 32), bounds=[(0, 2), (0, 1)])
        >>> stepper = FluidStepper(grid, {"x": "periodic", "y": "wall"}, obstacles=Body(Sphere((0.5, 0.5), 0.1)),
        ...                        viscosity=1e-3, dt=0.01)
        >>> state = FluidState(StaggeredGrid.zeros(grid, stepper.boundary))
        >>> state = stepper(state)   # doctest: +SKIP
    """

    def __init__(self, grid: Grid, boundary, *, obstacles=None, viscosity: float = 0.0,
                 advection: str = "maccormack", marker_advection: str | None = None,
                 viscosity_scheme: str = "explicit", integrator: str = "split", buoyancy: float = 0.0,
                 buoyancy_direction: Sequence[float] | None = None, marker_source=None,
                 energy_normalization: bool = False, pressure: Solve | None = None, dt=None,
                 dtype: torch.dtype = torch.float32, device=None, direct: bool | str = "auto", check: int | None = None,
                 compile: bool = False, fused: bool = True, convection: str = "central"):
        if not isinstance(grid, Grid):
            raise ParameterError(f"grid must be a phisim.Grid, got {type(grid).__name__}")
        if dtype not in (torch.float32, torch.float64):
            raise ParameterError(f"dtype must be torch.float32 or torch.float64, got {dtype!r}")
        template = StaggeredGrid.zeros(grid, boundary, 1, dtype=dtype, device=device)
        self.grid: Grid = grid
        self.boundary: Boundary = template.boundary
        self.dtype, self.device = dtype, template.device
        if self.device.type == "cpu":  # one step's freed arrays are reused by the next (phisim.allocator)
            keep_freed_memory()
        marker_advection = _check_schemes(advection, marker_advection, viscosity_scheme, integrator)
        if pressure is not None and not isinstance(pressure, Solve):
            raise ParameterError(f"pressure must be a phisim.solvers.Solve, got {type(pressure).__name__}")
        if not isinstance(energy_normalization, bool):
            raise ParameterError(f"energy_normalization must be True or False, got {energy_normalization!r}")
        self.viscosity = check_nonnegative(viscosity, "viscosity")
        self.buoyancy = check_finite_number(buoyancy, "buoyancy")
        self.buoyancy_direction = buoyancy_args(self.buoyancy, buoyancy_direction, grid.rank)[1]
        self.advection, self.marker_advection = advection, marker_advection
        self.viscosity_scheme, self.integrator = viscosity_scheme, integrator
        self.convection = check_convection(convection)
        self.energy_normalization, self.pressure = energy_normalization, pressure
        self.dt = None if dt is None else check_dt(dt)
        self.marker_source = None
        if marker_source is not None:
            src, _ = scalar_values(marker_source, grid)
            self.marker_source = src.to(dtype=dtype, device=self.device)
        solids = as_solids(obstacles) if obstacles is not None else []
        layout = solid_layout(obstacles, grid, self.boundary, 0.0, dtype, self.device)
        static = all(isinstance(s, Obstacle) or s.static for s in solids)
        #: The solids as passed to the step: the held (persistent) layout of static solids, the solids
        #: themselves when some move, None without solids.
        if direct not in ("auto", False):
            raise ParameterError(f"direct must be 'auto' or False, got {direct!r}")
        self.obstacles = None if layout is None else (layout.persistent(direct) if static else tuple(solids))
        if check is not None and (isinstance(check, bool) or not isinstance(check, int) or check < 0):
            raise ParameterError(f"check must be None or an int >= 0 (check every N steps), got {check!r}")
        #: Check the new state for NaN/Inf every ``check`` calls (0: never).
        self.check = int(check or 0)
        self._calls = 0
        if integrator not in SPLIT and self.dt is not None:
            check_viscous_number(integrator, self.viscosity, self.dt, grid.dx)
        # the checks the step's path does not repeat: fluxes that can balance, fluid left beside the solids
        faces = to_time(template, 0.0).with_boundary_faces()
        check_balance(faces)
        if layout is None:  # builds the spectral solve's multipliers, which a traced step then finds
            project_box(faces, check=False)
        if layout is not None and layout.bodies and bool((layout.cell_fraction.flatten(1).max(1).values <= 0).any()):
            raise ParameterError("obstacles cover every cell; there is no fluid to project")
        #: Whether the step depends on the time (moving bodies, time-dependent inflows).
        self.time_dependent = not static or any(isinstance(c, Inflow) and c.varying
                                                for pair in self.boundary.sides for c in pair)
        #: Whether the step reads the state's pressure (the warm start of CG solves, imex2's incremental pressure).
        self.uses_pressure = self.obstacles is not None or integrator == "imex2"
        if not isinstance(fused, bool):
            raise ParameterError(f"fused must be True or False, got {fused!r}")
        #: The fused step of an all-periodic set-up (:class:`~phisim.fluid.periodic.PeriodicStep`), or None.
        self.fused = None
        if fused and grid.rank in (2, 3) and PeriodicStep.applies(
                self.boundary, obstacles=self.obstacles, advection=advection, viscosity_scheme=viscosity_scheme,
                viscosity=self.viscosity, integrator=integrator, energy_normalization=energy_normalization,
                buoyancy=self.buoyancy, marker_source=self.marker_source):
            self.fused = PeriodicStep(grid, self.boundary, self.viscosity, advection, dtype, self.device)
        if self.dt is not None:  # one step at rest builds the caches a traced step then finds (no second graph)
            marker, rest = None, faces
            if self.buoyancy != 0 or self.marker_source is not None:
                batch = 1 if self.marker_source is None else self.marker_source.shape[0]  # a batch of sources
                marker = CenteredGrid.zeros(grid, self.boundary.for_scalar(), batch, dtype=dtype, device=self.device)
                rest = to_time(StaggeredGrid.zeros(grid, self.boundary, batch, dtype=dtype, device=self.device),
                               0.0).with_boundary_faces()
            with torch.no_grad():
                self.advance(FluidState(rest, marker), self.dt)
        self._advance = self.advance
        if compile:
            self._advance = compile_function(self.advance, device_type=self.device.type)

    def __call__(self, state: FluidState, dt=None) -> FluidState:
        """Advance ``state`` by ``dt`` (default: the stepper's ``dt``).

        Raises:
            GridMismatchError: For a state on another grid or with another boundary.
            ParameterError: For a state of another dtype or device, or no dt.
        """
        if not isinstance(state, FluidState):
            raise ParameterError(f"a FluidStepper advances a FluidState, got {type(state).__name__}")
        v = state.velocity
        check_fits(v, self.grid, self.dtype, self.device, "stepper")
        if state.marker is not None:
            scalar_values(state.marker, self.grid)
        elif self.buoyancy != 0:
            raise ParameterError("buoyancy needs a marker in the state")
        dt = self.dt if dt is None else dt
        if dt is None:
            raise ParameterError("no dt: pass one to the call or to the FluidStepper")
        if isinstance(dt, torch.Tensor):  # gradients w.r.t. dt: the validating pure step (reads dt for the time)
            new = step(state, dt, viscosity=self.viscosity, buoyancy_strength=self.buoyancy,
                       buoyancy_direction=self.buoyancy_direction, advection=self.advection,
                       viscosity_scheme=self.viscosity_scheme, marker_source=self.marker_source,
                       obstacles=self.obstacles, solve=self.pressure, energy_normalization=self.energy_normalization,
                       integrator=self.integrator, marker_advection=self.marker_advection,
                       convection=self.convection)
        else:
            dt = check_dt(dt)
            if dt != self.dt and self.integrator not in SPLIT:
                check_viscous_number(self.integrator, self.viscosity, dt, self.grid.dx)
            # the step sees only what it uses: a traced step then does not depend on the time or on whether a
            # pressure exists (no new graph per step); the time is advanced here
            inner = state
            if not self.time_dependent and state.time != 0.0:
                inner = replace(inner, time=0.0)
            if not self.uses_pressure and state.pressure is not None:
                inner = replace(inner, pressure=None)
            new = self._advance(inner, dt)
            if inner.time != state.time:
                new = replace(new, time=state.time + float(dt))
        if self.check:
            self._calls += 1
            if self._calls % self.check == 0:
                check_state(new)
        return new

    def advance(self, state: FluidState, dt: float) -> FluidState:
        """The step of a call on a validated state and ``dt`` (a number): no host read, no branch on tensor
        values; this is what :func:`torch.compile` traces (as one graph)."""
        if self.fused is not None and state.marker is None:
            v, p = self.fused(state.velocity, dt)
            return replace(state, velocity=v, pressure=p, time=state.time + float(dt))
        return advance(state, dt, viscosity=self.viscosity, buoyancy_strength=self.buoyancy,
                       buoyancy_direction=self.buoyancy_direction, advection=self.advection,
                       viscosity_scheme=self.viscosity_scheme, marker_source=self.marker_source,
                       obstacles=self.obstacles, solve=self.pressure, energy_normalization=self.energy_normalization,
                       integrator=self.integrator, marker_advection=self.marker_advection, trusted=True,
                       convection=self.convection)

    def __repr__(self) -> str:
        scheme = f", convection={self.convection!r}" if self.integrator not in SPLIT else ""
        return (f"FluidStepper({self.grid}, integrator={self.integrator!r}, advection={self.advection!r}{scheme}, "
                f"viscosity={self.viscosity}, viscosity_scheme={self.viscosity_scheme!r})")


def check_state(state: FluidState) -> None:
    """Raise :class:`~phisim.errors.NonFiniteError` if the state's velocity, marker or pressure holds NaN/Inf
    (a host read: the optional per-N-steps check of a stepper)."""
    for i, c in enumerate(state.velocity.values):
        check_finite(c, f"velocity component {i}")
    if state.marker is not None:
        check_finite(state.marker.values, "marker")
    if state.pressure is not None:
        check_finite(state.pressure.values, "pressure")


def navier_stokes_step(
    velocity: StaggeredGrid,
    dt,
    *,
    viscosity: float = 0.0,
    advection: str = "maccormack",
    viscosity_scheme: str = "explicit",
    force: StaggeredGrid | None = None,
    obstacles=None,
    solve: Solve | None = None,
    pressure_guess: CenteredGrid | torch.Tensor | None = None,
    energy_normalization: bool = False,
    time: float = 0.0,
    integrator: str = "split",
    convection: str = "central",
) -> tuple[StaggeredGrid, CenteredGrid]:
    """One incompressible Navier-Stokes step: advect, force, diffuse, project (and optionally renormalise).

    ``u* = A(u; u, dt) + dt f`` (the transported field extended into sharp no-slip bodies,
    :func:`~phisim.fluid.extension.extend_into_bodies`), the boundary (inflow profiles) and the bodies taken to time
    ``time + dt``,
    the bodies' velocity imposed on the faces they cover (:func:`impose_solids`, so that viscosity sees
    each body's velocity at its surface), ``u** = diffuse(u*)``, ``u_new, p = make_incompressible(u**)``; with
    ``energy_normalization`` the result is rescaled to the kinetic energy of ``u`` (E5 of the paper).
    First order in time (operator splitting); second order in space with MacCormack advection. With
    ``integrator`` other than ``'split'`` the step is :func:`~phisim.fluid.integrators.navier_stokes_rk_step`
    (second order in time; ``convection`` selects its convection scheme, ``advection`` and ``viscosity_scheme`` do
    not apply).

    Args:
        velocity: MAC velocity ``(B, *face_shape(i))`` per component.
        dt: Time step ``>= 0``.
        viscosity: Kinematic viscosity ``>= 0`` (0 skips diffusion).
        advection: ``'maccormack'`` (default) or ``'semi_lagrangian'`` self-advection.
        viscosity_scheme: ``'explicit'``, ``'implicit'``, ``'crank_nicolson'`` or ``'spectral'`` (see
            :func:`diffuse_velocity`; the implicit ones are exact spectral solves, about as cheap as explicit).
        force: Optional body force (acceleration) as a StaggeredGrid on the same grid.
        obstacles: Obstacles (see :func:`make_incompressible`).
        solve: CG settings of the masked pressure solve and of implicit viscosity.
        pressure_guess: Previous pressure, the warm start of the CG pressure solve.
        energy_normalization: Rescale the result to ``kinetic_energy(velocity)``.
        time: Simulation time at the start of the step (moving bodies, time-dependent inflows).
        integrator: ``'split'`` (this function's first-order step, default), ``'rk2'``, ``'rk3'`` or
            ``'imex2'`` (see :mod:`phisim.fluid.integrators`; ``'imex2'`` treats viscosity implicitly and
            needs the previous pressure as ``pressure_guess`` for second order at walls). ``'split2'`` keeps
            state between steps: :func:`step` or :class:`FluidStepper` take it.
        convection: The convection scheme of the other integrators, ``'central'`` (default) or ``'quick'``.

    Returns:
        ``(velocity, pressure)`` after the step.

    Raises:
        ParameterError: For invalid parameters or schemes.
        GridMismatchError: If ``velocity``/``force`` are not matching StaggeredGrids.
        SolveError: If a CG solve does not converge.
    """
    check_velocity(velocity)
    dt = check_dt(dt)
    if advection not in SCHEMES:
        raise ParameterError(f"unknown advection scheme {advection!r}; choose one of {SCHEMES}")
    if integrator == "split2":
        raise ParameterError("integrator='split2' keeps the velocity's rate and acceleration in the state: use step() "
                             "or FluidStepper")
    if integrator != "split":
        if force is not None:
            check_velocity(force, "force")
        return navier_stokes_rk_step(velocity, dt, viscosity=viscosity, integrator=integrator, force=force,
                                     time=time, obstacles=obstacles, solve=solve, pressure_guess=pressure_guess,
                                     energy_normalization=energy_normalization, convection=convection)
    e0 = kinetic_energy(velocity) if energy_normalization else None
    src = extend_into_bodies(velocity, obstacles, float(time))
    v = advect(src, src, dt, scheme=advection)
    v = to_time(v, float(time) + float(dt))
    if force is not None:
        check_velocity(force, "force")
        if force.grid != v.grid:
            raise GridMismatchError(f"force grid {force.grid} differs from the velocity grid {v.grid}")
        v = v + dt * force.with_boundary(v.boundary)
    return finish_step(v, dt, e0, viscosity, viscosity_scheme, obstacles, solve, pressure_guess,
                        float(time) + float(dt))



def step(
    state: FluidState,
    dt,
    *,
    viscosity: float = 0.0,
    buoyancy_strength: float = 0.0,
    buoyancy_direction: Sequence[float] | None = None,
    advection: str = "maccormack",
    viscosity_scheme: str = "explicit",
    marker_source: CenteredGrid | torch.Tensor | None = None,
    obstacles=None,
    solve: Solve | None = None,
    energy_normalization: bool = False,
    integrator: str = "split",
    marker_advection: str | None = None,
    convection: str = "central",
) -> FluidState:
    """Advance a smoke simulation by ``dt``: marker transport, buoyancy, Navier-Stokes step.

    Order: ``marker <- A(marker; u) + dt * source`` (zeroed in cells entirely inside solids),
    ``u <- A(u; u)``, buoyancy from the new marker, the solids' velocity imposed (moving bodies at
    ``time + dt``), viscosity, projection (warm-started from ``state.pressure``), optional energy rescaling.

    Args:
        state: Current :class:`FluidState`.
        dt: Time step ``>= 0``.
        viscosity: Kinematic viscosity.
        buoyancy_strength: Buoyancy per unit marker (see :func:`buoyancy`); needs a marker.
        buoyancy_direction: "Up" vector (default: y, axis 1).
        advection: ``'semi_lagrangian'`` or ``'maccormack'`` (for the velocity of the split step, and for
            the marker unless ``marker_advection`` says otherwise).
        viscosity_scheme: ``'explicit'``, ``'implicit'``, ``'crank_nicolson'`` or ``'spectral'`` (split step).
        marker_source: Marker added per unit time (an inflow), CenteredGrid or tensor ``(B or 1, *res)``.
        obstacles: Obstacles (see :func:`make_incompressible`).
        solve: CG settings.
        energy_normalization: Rescale the velocity to its energy at the start of the step.
        integrator: ``'split'`` (first order, default), ``'split2'``, ``'rk2'``, ``'rk3'`` or ``'imex2'`` (second
            order in time for the velocity; see :mod:`phisim.fluid.integrators`). The buoyancy of the new marker is
            then a force held constant over the step (the Runge-Kutta integrators).
        marker_advection: Scheme of the marker transport: one of
            :data:`phisim.ops.advection.SCALAR_SCHEMES`; ``'conservative'`` keeps the total marker to round-off
            in closed boxes and periodic domains and never makes it negative. Default: ``advection``.
        convection: The convection scheme of the ``'rk2'``, ``'rk3'`` and ``'imex2'`` integrators, ``'central'``
            (default) or ``'quick'`` (:func:`~phisim.fluid.integrators.convection`).

    Returns:
        The new state (``time + dt``).

    Raises:
        ParameterError, ShapeError, GridMismatchError, SolveError: See the functions it composes.
    """
    dt = check_dt(dt)
    v0 = state.velocity
    check_velocity(v0)
    marker_advection = _check_schemes(advection, marker_advection, viscosity_scheme, integrator)
    marker = state.marker
    # validated once here (types, grids, dt, a finite velocity); the inner calls take the trusted paths
    if marker is not None:
        validate_advection(marker, v0, dt, marker_advection, "euler", "minmax")
    else:
        validate_advection(v0, v0, dt, advection, "euler", "minmax")
    if marker is None and buoyancy_strength != 0:
        raise ParameterError("buoyancy_strength needs a marker in the state")
    if marker is not None and buoyancy_strength != 0:
        buoyancy_args(buoyancy_strength, buoyancy_direction, v0.grid.rank)
        scalar_values(marker, v0.grid)  # a scalar CenteredGrid on the velocity's grid
    source = None
    if marker is not None and marker_source is not None:
        source, _ = scalar_values(marker_source, marker.grid)
        source = source.to(dtype=marker.dtype, device=marker.device)
    if integrator not in SPLIT:
        check_viscous_number(integrator, check_nonnegative(viscosity, "viscosity"), dt, v0.grid.dx)
    return advance(state, dt, viscosity=viscosity, buoyancy_strength=buoyancy_strength,
                   buoyancy_direction=buoyancy_direction, advection=advection, viscosity_scheme=viscosity_scheme,
                   marker_source=source, obstacles=obstacles, solve=solve,
                   energy_normalization=energy_normalization, integrator=integrator,
                   marker_advection=marker_advection, trusted=False, convection=check_convection(convection))


def advance(state: FluidState, dt, *, viscosity: float, buoyancy_strength: float, buoyancy_direction,
            advection: str, viscosity_scheme: str, marker_source: torch.Tensor | None, obstacles, solve,
            energy_normalization: bool, integrator: str, marker_advection: str, trusted: bool,
            convection: str = "central") -> FluidState:
    """:func:`step` on validated arguments (``marker_source`` a tensor of the marker's dtype and device, or None).

    ``trusted=True`` is the step of a :class:`FluidStepper`: nothing is read back to the host and nothing
    branches on tensor values (the balance of the boundary fluxes, the solids' coverage and the settings
    were checked when it was built), so that the step traces as one graph.
    """
    v0 = state.velocity
    marker = state.marker
    t_new = state.time + float(dt)
    # the solids at the new time, rasterised once for the marker's mask and the split step (a held layout as it is)
    layout = None
    if obstacles is not None and (marker is not None or integrator in SPLIT):
        layout = solid_layout(obstacles, v0.grid, v0.boundary, t_new, v0.dtype, v0.device)
    if marker is not None:
        carrier = half_step_velocity(v0, state.velocity_rate, dt) if integrator == "split2" else v0
        marker = advect_trusted(marker, carrier, dt, scheme=marker_advection)
        if marker_source is not None:
            marker = marker + dt * marker_source
        if layout is not None:  # no marker in cells entirely inside a solid
            marker = marker * (layout.cell_fraction > 0).to(marker.dtype)
    lift = marker is not None and buoyancy_strength != 0
    if integrator not in SPLIT:
        force = None
        if lift:
            force = apply_buoyancy(StaggeredGrid.zeros(v0.grid, v0.boundary, v0.batch_size, dtype=v0.dtype,
                                                       device=v0.device), marker.values, marker.boundary, 1.0,
                                   *buoyancy_args(buoyancy_strength, buoyancy_direction, v0.grid.rank))
        v, p = rk_advance(v0, dt, float(viscosity), integrator, force, float(state.time), obstacles, solve,
                          state.pressure, energy_normalization, trusted=trusted, scheme=convection)
        return replace(state, velocity=v, marker=marker, pressure=p, time=t_new)
    e0 = kinetic_energy(v0) if energy_normalization else None
    src = extend_into_bodies(v0, obstacles, state.time)
    if integrator == "split2":
        v = split2_advection(src, state, dt, advection)
    else:
        v = advect_trusted(src, src, dt, scheme=advection)
    v = to_time(v, t_new)
    advected = v
    if lift:  # sets the boundary faces
        strength, direction = buoyancy_args(buoyancy_strength, buoyancy_direction, v0.grid.rank)
        v = apply_buoyancy(v, marker.values, marker.boundary, dt, strength, direction)
    v, p = finish_step(v, dt, e0, viscosity, viscosity_scheme, obstacles if layout is None else layout, solve,
                       state.pressure, t_new, faces_set=lift, trusted=trusted)
    if integrator != "split2":
        return replace(state, velocity=v, marker=marker, pressure=p, time=t_new)
    rate, acc = split2_memory(v, v0, advected, dt, layout)
    return replace(state, velocity=v, marker=marker, pressure=p, time=t_new, velocity_rate=rate, acceleration=acc)
