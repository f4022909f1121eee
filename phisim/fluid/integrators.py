"""Time integrators for incompressible flow that are second order (or better) in time.

The first-order step of :func:`phisim.fluid.navier_stokes_step` splits one step into advection, forcing,
viscosity and projection; the splitting error halves with ``dt`` (first order). The integrators here instead
treat the spatially discretised, projected equations

    ``du/dt = P F(u, t)``,   ``F(u, t) = -C(u) + ν L u + f(t)``

as an ordinary differential equation and apply an explicit strong-stability-preserving Runge-Kutta method,
projecting every stage (``P`` = :func:`phisim.fluid.make_incompressible`). Because ``P`` is linear and
leaves divergence-free fields unchanged, projecting each stage equals projecting the stage's right-hand
side, so the velocity inherits the Runge-Kutta order (Sanderse & Koren 2012, "Accuracy analysis of
explicit Runge-Kutta methods applied to the incompressible Navier-Stokes equations", J. Comput. Phys. 231).

* ``C(u)`` is the MAC convection term in divergence form, ``C_i = Σ_j ∂_j(u_j u_i)`` with second-order
  central differences (Harlow & Welch 1965; cell-centre products for ``j = i``, cell-edge products for
  ``j ≠ i``); boundary ghosts follow the velocity boundary (walls, moving lids, open sides, periodic).
  For a discretely divergence-free field it conserves momentum and kinetic energy in a periodic box
  (Morinishi et al. 1998, J. Comput. Phys. 143). ``convection='quick'`` carries the upwind-biased quadratic
  interpolation of Leonard (1979) instead of the average (conserves momentum; damps the grid-scale modes that
  central fluxes leave undamped where the cell Reynolds number is large; :func:`convection`).
* ``L`` is the (2d+1)-point Laplacian per component (:func:`phisim.fluid.viscosity.body_laplace`: sharp no-slip
  bodies enter at their true surface).
* ``f(t)`` is a body force (a StaggeredGrid, or a callable of time for time-dependent forcing).
* obstacles: faces touching solid cells are set to zero before every projection (resting no-slip bodies).

Orders in time (velocity; measured in ``tests/phisim/fluid/test_integrators.py``):

==================  ==================================================  ===========  ========================
integrator          stages                                              order        stability
==================  ==================================================  ===========  ========================
``'split'``         :func:`~phisim.fluid.navier_stokes_step`            1            unconditional (SL)
``'split2'``        the split step, advection to second order (below)   2            as ``'split'``
``'rk2'``           Heun / SSP-RK2, 2 projections, explicit viscosity   2            needs viscosity *
``'rk3'``           Shu-Osher SSP-RK3, 3 projections, explicit visc.    3 (≥ 2)      CFL ≲ 1.7 / π per axis
``'imex2'``         Crank-Nicolson viscosity, Heun convection,          2            any viscous number;
                    incremental pressure, 2 implicit solves + 2 proj.                CFL as ``'rk2'``
==================  ==================================================  ===========  ========================

(*) Heun's amplification for purely imaginary eigenvalues (central convection without viscosity) is
``|1 + z + z²/2| = (1 + y⁴/4)^{1/2} > 1``: a weak growth ``≈ (cfl π)⁴ / 8`` per step that viscosity must
damp; prefer ``'rk3'`` for nearly inviscid flow. Viscosity is explicit in ``'rk2'`` and ``'rk3'``:
``ν dt Σ 4/dx² ≤ 2`` (RK2) or ``≤ 2.5`` (RK3); larger viscous numbers raise :class:`ParameterError` and
call for ``'imex2'``.

``'split2'`` (:func:`~phisim.fluid.step`, :class:`~phisim.fluid.FluidStepper`; the state keeps what it needs) is the
split step with the two first-order errors of its advection removed: the advecting velocity is extrapolated to the
half step, ``u^n + dt/2 du/dt`` (``du/dt`` the change over the previous step, :attr:`FluidState.velocity_rate`), and
the previous step's acceleration by everything but the advection (pressure, viscosity, forces,
:attr:`FluidState.acceleration`) is transported with the velocity: ``u* = A(u^n + dt/2 f^{n-1}) - dt/2 f^{n-1}``
(:func:`~phisim.fluid.step.split2_advection`). Its first step is the split step. It keeps the split step's limited
MacCormack transport (no wiggles at large cell Reynolds numbers) and its cost; with ``'crank_nicolson'`` viscosity
every part is second order. Measured (Taylor-Green, dt = 0.5 dx): order 1.9-2.0 where the split step's is 0.9
(``docs/SCHEMES.md``). Next to sharp no-slip bodies the split step's wall treatment (:func:`~phisim.fluid.step.
anticipate_pressure`) was matched to ``'split'``; with ``'split2'`` a steady drag still depends on dt at first
order (``docs/VALIDATION.md``).

``'imex2'`` (a pressure-correction scheme, e.g. Guermond, Minev & Shen 2006, "An overview of projection
methods for incompressible flows", Comput. Methods Appl. Mech. Engrg. 195): with ``E(u, t) = -C(u) + f(t)``
and ``q`` the previous step's pressure potential (``pressure_guess``, in the ``dt * p`` convention),

    ``(I - ν dt/2 L) u* = u_n + dt E(u_n, t_n) + ν dt/2 L u_n - G q``,   ``u1 = P u*``,
    ``(I - ν dt/2 L) u** = u_n + dt/2 (E(u_n, t_n) + E(u1, t_n + dt)) + ν dt/2 L u_n - G q``,
    ``u_{n+1} = P u**``,  ``q_{n+1} = q + φ`` (``φ`` the potential of the last projection).

The implicit solves are :func:`phisim.solvers.diffusion.diffuse_staggered` (exact spectral box solves; with the
faces touching obstacles held at 0 a direct capacitance solve, or PCG on the first step with a new body
or dt). The incremental pressure ``-G q`` makes the splitting error of viscosity and projection at walls
second order: pass the returned pressure back as ``pressure_guess``
(``None`` on the first step is fine; without it on every step the scheme is first order at walls). Next to bodies
``-G q`` is the gradient the projection applies (:func:`~phisim.fluid.projection.applied_gradient`: the whole of it on
the faces a sharp body keeps), and the cells that the imposition closes to everything but faces held at the body's
velocity carry their neighbours' pressure instead of their own (:func:`carried_pressure`; there ``φ`` is a whole
pressure difference, not an increment, and ``q + φ`` grew without bound at a steady state).

The returned pressure is the potential of the last stage's correction rescaled to the convention of
:func:`phisim.fluid.make_incompressible` (``dt * p / rho``), so it is an approximation of the pressure at
the end of the step and a good warm start for the next step's CG solves.
"""

from __future__ import annotations

from collections.abc import Callable

import torch

from phisim.boundary import pad_staggered_component
from phisim.checks import check_dt, check_nonnegative
from phisim.errors import GridMismatchError, ParameterError
from phisim.field import CenteredGrid, StaggeredGrid
from phisim.fluid.bodies import solid_layout
from phisim.fluid.projection import applied_gradient, impose_solids, make_incompressible, project_trusted
from phisim.fluid.step import kinetic_energy, normalize_energy, pressure_in_body_frame, rescale_energy, to_time
from phisim.fluid.viscosity import body_laplace, held_faces
from phisim.ops.differential import gradient
from phisim.ops.tensors import sum_last, unravel
from phisim.solvers.diffusion import diffuse_staggered

__all__ = ["CONVECTION_SCHEMES", "INTEGRATORS", "carried_pressure", "check_convection", "convection",
           "navier_stokes_rk_step", "rk_advance"]

#: Time integrators of incompressible flow with their order in time for the velocity.
INTEGRATORS = {"split": 1, "split2": 2, "rk2": 2, "rk3": 3, "imex2": 2}

# (weight of u_n, weight of the previous stage after its Euler step, time offset of the stage) per stage
_SHU_OSHER = {
    "rk2": ((0.0, 1.0, 0.0), (0.5, 0.5, 1.0)),
    "rk3": ((0.0, 1.0, 0.0), (0.75, 0.25, 1.0), (1.0 / 3.0, 2.0 / 3.0, 0.5)),
}
_VISCOUS_LIMIT = {"rk2": 2.0, "rk3": 2.5}  # ν dt Σ 4/dx² on the negative real axis


#: Convection schemes of the Runge-Kutta and IMEX integrators: the face value each momentum flux carries.
CONVECTION_SCHEMES = ("central", "quick")


def _face_values(p: torch.Tensor, dim: int, width: int, a: torch.Tensor | None) -> torch.Tensor:
    """The transported value at the points between the samples of ``p`` along ``dim``.

    ``p`` is padded with ``width`` ghost samples per side; point ``e`` lies between ``p[e + width - 1]`` and
    ``p[e + width]`` (``len - 2 width + 1`` points). ``a`` None: the central average; else QUICK (Leonard 1979, needs
    ``width >= 2``): the average less an eighth of the second difference centred on the upwind sample, ``a`` the
    advecting velocity at the points."""
    count = p.shape[dim] - 2 * width + 1
    left, right = p.narrow(dim, width - 1, count), p.narrow(dim, width, count)
    mean = 0.5 * (left + right)
    if a is None:
        return mean
    lo = p.narrow(dim, width - 2, count) - 2 * left + right  # a > 0: upwind sample is the left one
    hi = left - 2 * right + p.narrow(dim, width + 1, count)  # a < 0: the right one
    return mean - 0.125 * torch.where(a >= 0, lo, hi)


def convection(velocity: StaggeredGrid, scheme: str = "central") -> StaggeredGrid:
    """The MAC convection term ``C_i = Σ_j ∂_j (u_j u_i)`` (divergence form, second order).

    For component ``i`` on its faces: ``∂_i(u_i²)`` from fluxes at the cell centres (the advecting ``u_i`` the
    average of the two faces), and for ``j ≠ i`` ``∂_j(u_j u_i)`` from fluxes at the cell edges (``u_j`` averaged
    along ``i``). The transported ``u_i`` at those points is the average of its two neighbours (``'central'``,
    Harlow & Welch 1965: conserves momentum, and kinetic energy for a discretely divergence-free field in a periodic
    box, Morinishi et al. 1998) or the upwind-biased quadratic interpolation ``'quick'`` (Leonard 1979: third-order
    interpolation, second-order fluxes, a fourth-difference dissipation of size ``|a| dx^3`` that damps the grid-scale
    wiggles central fluxes make where the cell Reynolds number ``|u| dx / nu`` exceeds 2; conserves momentum).
    Ghost values come from the velocity boundary (:func:`phisim.boundary.pad_staggered_component`), so a no-slip
    wall contributes its wall velocity.

    Args:
        velocity: MAC velocity ``(B, *face_shape(i))`` per component, 1-3 axes.
        scheme: ``'central'`` (default) or ``'quick'``.

    Returns:
        ``C`` as a StaggeredGrid on the same grid and boundary (values on fixed boundary faces are
        computed but meaningless; a projection resets them). ``-C`` is the convective acceleration.

    Raises:
        GridMismatchError: If ``velocity`` is not a StaggeredGrid.
        ParameterError: For an unknown scheme.
    """
    if not isinstance(velocity, StaggeredGrid):
        raise GridMismatchError(f"convection needs a StaggeredGrid velocity, got {type(velocity).__name__}")
    quick = check_convection(scheme) == "quick"
    width = 2 if quick else 1  # ghost samples the interpolation reads per side
    grid, boundary = velocity.grid, velocity.boundary
    dx = grid.dx
    out = []
    for i, ui in enumerate(velocity.values):
        total = 0
        for j in range(grid.rank):
            dim_j = 1 + j
            if j == i:
                p = pad_staggered_component(ui, i, boundary, dx, width, axes=[i])
                a = _face_values(p, dim_j, width, None)  # the advecting velocity at the cell centres -1 .. n
                flux = a * (_face_values(p, dim_j, width, a) if quick else a)
                k = flux.shape[dim_j] - 1
                total = total + (flux.narrow(dim_j, 1, k) - flux.narrow(dim_j, 0, k)) / dx[j]
                continue
            uj = velocity.values[j]
            dim_i = 1 + i
            # u_j at the edges: average along i (u_j is cell-centred along i)
            pj = pad_staggered_component(uj, j, boundary, dx, 1, axes=[i])
            m = pj.shape[dim_i] - 1
            uj_edge = 0.5 * (pj.narrow(dim_i, 0, m) + pj.narrow(dim_i, 1, m))
            # u_i at the edges: between its samples along j (u_i is cell-centred along j)
            pi = pad_staggered_component(ui, i, boundary, dx, width, axes=[j])
            ui_edge = _face_values(pi, dim_j, width, uj_edge if quick else None)
            flux = ui_edge * uj_edge
            k = flux.shape[dim_j] - 1
            total = total + (flux.narrow(dim_j, 1, k) - flux.narrow(dim_j, 0, k)) / dx[j]
        out.append(total)
    return StaggeredGrid(tuple(out), grid, boundary)


def _force_at(force, t, velocity: StaggeredGrid) -> StaggeredGrid | None:
    if force is None:
        return None
    f = force(t) if callable(force) and not isinstance(force, StaggeredGrid) else force
    if not isinstance(f, StaggeredGrid) or f.grid != velocity.grid:
        raise GridMismatchError("force must be a StaggeredGrid on the velocity's grid (or a callable returning one)")
    return f.with_boundary(velocity.boundary)


def navier_stokes_rk_step(
    velocity: StaggeredGrid,
    dt,
    *,
    viscosity: float = 0.0,
    integrator: str = "rk2",
    force: StaggeredGrid | Callable[[float], StaggeredGrid] | None = None,
    time: float = 0.0,
    obstacles=None,
    solve=None,
    pressure_guess: CenteredGrid | torch.Tensor | None = None,
    energy_normalization: bool = False,
    convection: str = "central",
) -> tuple[StaggeredGrid, CenteredGrid]:
    """One incompressible Navier-Stokes step of second (or third) order in time.

    ``'rk2'``/``'rk3'``: stage ``s`` (Shu-Osher form) is
    ``u^(s) = P[a_s u_n + b_s (u^(s-1) + dt F(u^(s-1), t_n + c_s dt))]`` with ``F = -C(u) + ν L u + f`` and
    ``P`` the projection with the solids imposed at the stage's time; ``'imex2'`` is the Crank-Nicolson /
    Heun pressure-correction scheme (see the module docstring). Inflow profiles and moving bodies are
    evaluated at the stage times.

    Args:
        velocity: Divergence-free MAC velocity at ``t_n`` (e.g. the output of a projection).
        dt: Time step ``>= 0``.
        viscosity: Kinematic viscosity ``>= 0`` (explicit in ``'rk2'``/``'rk3'``, see the stability limits
            in the module docstring; Crank-Nicolson in ``'imex2'``).
        integrator: ``'rk2'`` (Heun, second order), ``'rk3'`` (SSP-RK3, third order) or ``'imex2'``
            (Crank-Nicolson viscosity, Heun convection, incremental pressure; second order).
        force: Body force (acceleration): a StaggeredGrid, or ``force(t) -> StaggeredGrid`` evaluated at the
            stage times (needed for second order with time-dependent forcing).
        time: ``t_n``, for a callable force, moving bodies and time-dependent inflows.
        obstacles: Obstacles and bodies (see :func:`phisim.fluid.make_incompressible`).
        solve: CG settings of the pressure solves with solids (and of the viscous solve with solids).
        pressure_guess: The previous step's pressure (as returned): a warm start of the CG solves for
            ``'rk2'``/``'rk3'``, and the incremental pressure of ``'imex2'`` (see the module docstring).
        energy_normalization: Rescale the result to the kinetic energy of ``velocity``.
        convection: The convection scheme, ``'central'`` (default) or ``'quick'`` (upwind-biased; for cell Reynolds
            numbers ``|u| dx / nu`` above about 2, where central fluxes make wiggles; see :func:`convection`).

    Returns:
        ``(velocity, pressure)`` at ``t_n + dt``; the pressure in the convention of ``make_incompressible``.

    Raises:
        ParameterError: Unknown integrator, negative dt/viscosity, or (``'rk2'``, ``'rk3'``) a viscous
            number beyond the explicit stability limit.
        GridMismatchError: For a non-StaggeredGrid velocity or force.
        SolveError: If a CG solve does not converge.
    """
    if not isinstance(velocity, StaggeredGrid):
        raise GridMismatchError(f"velocity must be a StaggeredGrid, got {type(velocity).__name__}")
    if integrator not in (*_SHU_OSHER, "imex2"):
        raise ParameterError(f"integrator must be one of {(*_SHU_OSHER, 'imex2')}, got {integrator!r}")
    dt = check_dt(dt)
    nu = check_nonnegative(viscosity, "viscosity")
    check_viscous_number(integrator, nu, dt, velocity.grid.dx)
    scheme = check_convection(convection)
    return rk_advance(velocity, dt, nu, integrator, force, float(time), obstacles, solve, pressure_guess,
                      energy_normalization, scheme=scheme)


def check_convection(scheme: str) -> str:
    """Return ``scheme`` if it is one of :data:`CONVECTION_SCHEMES`, else raise ParameterError."""
    if scheme not in CONVECTION_SCHEMES:
        raise ParameterError(f"convection scheme must be one of {CONVECTION_SCHEMES}, got {scheme!r}")
    return scheme


def check_viscous_number(integrator: str, nu: float, dt, dx) -> None:
    """Raise ParameterError where the explicit viscosity of ``'rk2'``/``'rk3'`` is unstable (``dt`` a number)."""
    if integrator not in _VISCOUS_LIMIT:
        return
    number = float(nu) * float(dt) * sum(4.0 / d**2 for d in dx)
    if number > _VISCOUS_LIMIT[integrator] * (1 + 1e-12):
        raise ParameterError(
            f"explicit viscosity in {integrator!r} is unstable: ν dt Σ 4/dx² = {number:.3g} > "
            f"{_VISCOUS_LIMIT[integrator]}; reduce dt or use integrator='imex2' (implicit viscosity)"
        )


def rk_advance(velocity: StaggeredGrid, dt, nu: float, integrator: str, force, time: float, obstacles, solve,
               pressure_guess, energy_normalization: bool, trusted: bool = False, scheme: str = "central"):
    """:func:`navier_stokes_rk_step` on validated arguments (``dt`` a number). ``trusted``: the step of a
    stepper, whose settings were validated when it was built: the projections read nothing back to the host.
    ``scheme``: the convection scheme (:data:`CONVECTION_SCHEMES`)."""
    def project(w, layout, guess, t):
        if trusted:
            return project_trusted(w, layout, solve=solve, pressure_guess=guess)
        return make_incompressible(w, layout, solve=solve, pressure_guess=guess, time=t)

    rescale = rescale_energy if trusted else normalize_energy
    if integrator == "imex2":
        return _imex2_step(velocity, dt, nu, force, time, obstacles, solve, pressure_guess, energy_normalization,
                           project, rescale, scheme)
    e0 = kinetic_energy(velocity) if energy_normalization else None
    u0 = velocity
    stage = velocity
    guess = pressure_guess
    pressure = None
    b_last = 1.0
    stages = _SHU_OSHER[integrator]
    layout = None  # the solids at the stage's time: their sharp no-slip surfaces enter the viscous term
    if float(nu) != 0 and obstacles is not None:
        layout = solid_layout(obstacles, u0.grid, u0.boundary, time, u0.dtype, u0.device)
    for k, (a, b, c) in enumerate(stages):
        rate = -convection(stage, scheme)
        if float(nu) != 0:
            rate = rate + nu * body_laplace(stage, layout)
        f = _force_at(force, time + c * float(dt), stage)
        if f is not None:
            rate = rate + f
        w = stage + dt * rate
        if b != 1.0:
            w = w * b
        if a != 0.0:
            w = w + a * u0.with_boundary(w.boundary)
        t_out = time + float(dt) * (stages[k + 1][2] if k + 1 < len(stages) else 1.0)
        w = to_time(w, t_out)
        layout = solid_layout(obstacles, w.grid, w.boundary, t_out, w.dtype, w.device)
        w = impose_solids(w, layout, moved=(time, t_out))
        stage, pressure = project(w, layout, guess, t_out)
        guess = pressure.values / b if b != 1.0 else pressure
        b_last = b
    pressure = pressure.with_values(pressure.values / b_last) if b_last != 1.0 else pressure
    if e0 is not None:
        stage = rescale(stage, e0)
    return stage, pressure


def carried_pressure(q: torch.Tensor, layout) -> torch.Tensor:
    """The part of the previous pressure potential ``q`` that ``'imex2'``'s next pressure adds its increment to.

    ``q`` itself, except in the *enclosed cut cells*: cells centred inside a sharp no-slip body whose every open face
    (``theta > 0``) is centred inside it too. The imposition holds such faces at the body's velocity (they are no
    unknowns of the viscous step), so the predictor carries no ``-G q`` there and each projection rebuilds their
    velocity from its own potential ``phi``: ``phi`` in an enclosed cell is a whole pressure difference to its
    neighbours, not an increment, and ``q + phi`` would grow by it every step (a steady flow's cut-cell pressure
    drifted linearly while its velocity stood still). There the carried part is the mean of the neighbours' ``q``
    over those faces weighted with ``theta`` (enclosed neighbours left out; 0 where none is left), so that
    ``q + phi`` across them has the gradient ``G phi`` that built their velocity. ``q`` in an enclosed cell reaches
    no velocity (its faces' ``G q`` is imposed away), so this changes the pressure alone.

    A layout used again and again (a stepper's resting bodies, ``layout.solvers`` a dict) keeps the enclosed cells,
    their neighbours and weights, and the mean is taken on those cells alone (the same numbers as on every cell).
    """
    if layout is None or layout.walls is None:
        return q
    cache = getattr(layout, "solvers", None)
    if cache is None or layout.theta[0].shape[0] != 1:
        return _carried_dense(q, layout)
    key = ("carried_pressure", q.dtype, str(q.device), tuple(q.shape[1:]))
    plan = cache.get(key)
    if plan is None:
        if torch.compiler.is_compiling():  # built by an eager step first; a trace does no host reads
            return _carried_dense(q, layout)
        plan = cache[key] = _carried_plan(q, layout)
    index, neighbours, open_, weights, den = plan
    if index.numel() == 0:
        return q
    flat = q.reshape(q.shape[0], -1)
    near = torch.where(open_, flat[:, neighbours], torch.zeros((), dtype=q.dtype, device=q.device))
    mean = sum_last(weights * near) / den
    return flat.index_copy(1, index, mean).reshape(q.shape)


def _carried_terms(q: torch.Tensor, layout):
    """The enclosed cells of ``layout`` (see :func:`carried_pressure`) and per axis the weights ``theta`` of their
    held faces towards the lower and the upper neighbour, zero where that neighbour is enclosed or missing, as
    cell-shaped arrays ``(lo, hi)`` (None along an axis of one cell)."""
    rank = q.ndim - 1
    faces = []  # per axis: (theta on the held open faces, whether a face is open and not held), lower/upper per cell
    for a in range(rank):
        th = layout.theta[a].to(q.dtype)
        wall = layout.walls[a]
        held = (th > 0) & wall[0] if wall is not None else torch.zeros_like(th, dtype=torch.bool)
        free = (th > 0) & ~held
        w = torch.where(held, th, torch.zeros_like(th))
        n = q.shape[1 + a]
        faces.append((w.narrow(1 + a, 0, n), w.narrow(1 + a, 1, n), free.narrow(1 + a, 0, n), free.narrow(1 + a, 1, n)))
    has_held = sum((lo > 0) | (hi > 0) for lo, hi, _, _ in faces) > 0
    has_free = sum(flo | fhi for _, _, flo, fhi in faces) > 0
    enclosed = has_held & ~has_free
    weights = []
    for a, (lo, hi, _, _) in enumerate(faces):
        n = q.shape[1 + a]
        if n < 2:
            weights.append(None)
            continue
        dim = 1 + a
        lo, hi = lo.narrow(dim, 1, n - 1), hi.narrow(dim, 0, n - 1)  # the cells with a neighbour on that side
        ok_below = (~enclosed.narrow(dim, 0, n - 1)).to(q.dtype)
        ok_above = (~enclosed.narrow(dim, 1, n - 1)).to(q.dtype)
        pad_lo, pad_hi = _one_cell_pads(rank, a)
        weights.append((torch.nn.functional.pad(lo * ok_below, pad_lo), torch.nn.functional.pad(hi * ok_above, pad_hi)))
    return enclosed, weights


def _one_cell_pads(rank: int, a: int) -> tuple[list[int], list[int]]:
    """``F.pad`` widths of one cell before / after axis ``a`` of a ``rank``-D array (F.pad lists the last axis first:
    axis rank-1 low, high, ..., axis 0 low, high)."""
    lo, hi = [0] * (2 * rank), [0] * (2 * rank)
    lo[2 * (rank - 1 - a)] = 1
    hi[2 * (rank - 1 - a) + 1] = 1
    return lo, hi


def _carried_dense(q: torch.Tensor, layout) -> torch.Tensor:
    """:func:`carried_pressure` on every cell (no host reads)."""
    enclosed, weights = _carried_terms(q, layout)
    source = torch.where(enclosed, torch.zeros_like(q), q)
    num, den = torch.zeros_like(q), torch.zeros_like(q)
    rank = q.ndim - 1
    for a, w in enumerate(weights):
        if w is None:
            continue
        dim, n = 1 + a, q.shape[1 + a]
        pad_lo, pad_hi = _one_cell_pads(rank, a)
        below = torch.nn.functional.pad(source.narrow(dim, 0, n - 1), pad_lo)  # each cell's lower neighbour, 0 at 0
        above = torch.nn.functional.pad(source.narrow(dim, 1, n - 1), pad_hi)
        num = num + w[0] * below + w[1] * above
        den = den + w[0] + w[1]
    mean = num / torch.where(den > 0, den, torch.ones_like(den))
    return torch.where(enclosed, mean, q)


def _carried_plan(q: torch.Tensor, layout):
    """What :func:`carried_pressure` keeps for a persistent layout: the enclosed cells' flat indices ``(K,)``, their
    neighbours' flat indices ``(K, 2 d)`` (lower and upper per axis), whether each neighbour exists and is not
    enclosed, the weights ``(K, 2 d)`` and their sums (1 where they are 0)."""
    enclosed, weights = _carried_terms(q, layout)
    shape = tuple(q.shape[1:])
    index = enclosed[0].reshape(-1).nonzero().squeeze(1)
    nbrs, opens, ws = [], [], []
    strides = [1] * len(shape)
    for a in range(len(shape) - 2, -1, -1):
        strides[a] = strides[a + 1] * shape[a + 1]
    coords = unravel(index, shape)
    for a, w in enumerate(weights):
        for side, wk in ((-1, None if w is None else w[0]), (1, None if w is None else w[1])):
            c = coords[a] + side
            inside = (c >= 0) & (c < shape[a])
            nb = torch.where(inside, index + side * strides[a], index)
            if wk is None:
                ws.append(torch.zeros(index.shape, dtype=q.dtype, device=q.device))
            else:
                ws.append(wk[0].reshape(-1)[index])
            nbrs.append(nb)
            opens.append(inside & ~enclosed[0].reshape(-1)[nb])
    weights_k = torch.stack(ws, -1)
    den = sum_last(weights_k)
    den = torch.where(den > 0, den, torch.ones_like(den))
    return index, torch.stack(nbrs, -1), torch.stack(opens, -1), weights_k, den


def _imex2_step(velocity, dt, nu, force, time, obstacles, solve, pressure, energy_normalization, project, rescale,
                scheme="central"):
    """Crank-Nicolson viscosity, Heun convection and forcing, incremental pressure correction."""
    grid = velocity.grid
    t_new = time + float(dt)
    e0 = kinetic_energy(velocity) if energy_normalization else None
    layout = solid_layout(obstacles, grid, velocity.boundary, t_new, velocity.dtype, velocity.device)
    # faces entirely inside solids keep the solids' velocity in the viscous solve: the layout's own masks (computed
    # once for a stepper's layout), so that a resting body's direct viscous solve is found again in a traced step
    fixed = None if layout is None else held_faces(layout, beyond_cut=layout.walls is not None)
    u0 = velocity
    half_lap = 0.5 * dt * nu * body_laplace(u0, layout) if float(nu) != 0 else None
    explicit0 = -convection(u0, scheme)
    f0 = _force_at(force, time, u0)
    if f0 is not None:
        explicit0 = explicit0 + f0
    grad_q = None
    if pressure is not None:
        q = pressure.values if isinstance(pressure, CenteredGrid) else torch.as_tensor(pressure)
        q = q.to(dtype=velocity.dtype, device=velocity.device)
        q = CenteredGrid(q if q.ndim == grid.rank + 1 else q[None], grid, velocity.boundary.for_pressure())
        # moving bodies carry their pressure field along: read it where each cell was relative to the body a step
        # earlier, from the cells that held fluid then (a freshly uncovered cell holds none)
        q = pressure_in_body_frame(q, layout, velocity, t_new, float(dt))
        # the gradient the projection applies: the whole of it on the faces a sharp body keeps, theta times it on
        # a blended body's cut faces
        grad_q = (q, applied_gradient(gradient(q, at="face").values, layout))

    def stage(explicit):
        y = u0 + dt * explicit
        if grad_q is not None:
            y = y.with_values(tuple(c - x for c, x in zip(y.values, grad_q[1])))
        if half_lap is not None:
            y = y + half_lap
        y = impose_solids(to_time(y, t_new), layout, moved=(time, t_new))
        if float(nu) != 0:
            y = diffuse_staggered(y, 0.5 * dt, viscosity=nu, method="implicit", fixed=fixed, solve=solve,
                                  capacitance=layout.solvers if layout is not None and layout.direct else None,
                                  walls=None if layout is None else layout.walls)
        return project(y, layout, None if grad_q is None else torch.zeros_like(grad_q[0].values), t_new)

    u1, _ = stage(explicit0)
    explicit1 = -convection(u1, scheme)
    f1 = _force_at(force, t_new, u1)
    if f1 is not None:
        explicit1 = explicit1 + f1
    explicit1 = explicit1.with_boundary(u0.boundary)  # time-dependent inflows: u1 carries the new time
    u2, phi = stage(0.5 * (explicit0 + explicit1))
    p = phi if grad_q is None else phi.with_values(phi.values + carried_pressure(grad_q[0].values, layout))
    if e0 is not None:
        u2 = rescale(u2, e0)
    return u2, p
