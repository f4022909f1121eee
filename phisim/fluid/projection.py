"""Pressure projection of MAC velocities with walls, inflows, outflows, periodic sides and bodies.

Discretisation. Velocities live on the faces (:class:`~phisim.field.StaggeredGrid`), the pressure at cell
centres. Without bodies the projection makes ``u`` discretely divergence-free,

    ``u_new = u - G p``   with   ``D G p = D u``,

where ``D`` is the MAC divergence and ``G`` the face gradient ``(p_k - p_{k-1}) / dx``. With bodies each
face carries its fluid fraction ``theta`` and the solids' velocity ``u_s`` (:mod:`phisim.fluid.bodies`);
the projection solves the weighted (variational, cut-cell) problem

    ``D(theta G p) = D(theta u + (1 - theta) u_s)``

and stores ``u - G p`` on faces with ``theta > 0`` and ``u_s`` on closed faces (free-slip bodies and sharp no-slip
bodies; the divergence of the flux :func:`solid_flux` is zero; sharp bodies add to the flux the wall profile that
``theta u`` misses, :func:`flux_correction`) or ``theta (u - G p) + (1 - theta) u_s`` (blended no-slip solids and
staircase obstacles; its MAC divergence is zero). A staircase :class:`~phisim.fluid.bodies.Obstacle` is the special
case of 0/1 fractions. The returned "pressure" ``p`` is the potential of the correction (``p = dt * p_phys / rho``).

Boundary conditions per side (from the velocity boundary, :meth:`~phisim.boundary.Boundary.for_pressure`):

* sides with prescribed normal velocity (walls, :class:`~phisim.boundary.Dirichlet`,
  :class:`~phisim.boundary.Inflow`): the boundary faces keep their value and the pressure has zero flux
  there, so every cell, the first column included, ends divergence-free;
* :class:`~phisim.boundary.Open` sides (the outflow): pressure 0 on the face; the boundary face is
  corrected like an interior face, so the outflow carries exactly the mass the inflow brings;
* periodic axes: face ``n`` is face ``0``.

A domain without an open side must balance its prescribed fluxes (net inflow 0); otherwise no divergence-
free field exists and :class:`~phisim.errors.ParameterError` says so.

Solvers: without bodies the spectral solver of :mod:`phisim.solvers.poisson` (exact, ``O(N log N)``); with bodies
conjugate gradients on :class:`~phisim.solvers.masked.MaskedPoisson` (kept per body layout) with the
spectral preconditioner, warm-started from ``pressure_guess``; gradients by the implicit adjoint solve.

References: Harlow & Welch (1965), Phys. Fluids 8 (the MAC grid); Chorin (1968), Math. Comp. 22
(projection); Batty, Bertails & Bridson (2007), ACM TOG 26 (fractional face weights).
"""

from __future__ import annotations

import math
from dataclasses import replace
from typing import NamedTuple

import torch

from phisim.boundary import NORMAL, Boundary
from phisim.checks import all_finite, check_batch_compatible
from phisim.errors import GridMismatchError, NonFiniteError, ParameterError, ShapeError, SolveError
from phisim.field import CenteredGrid, StaggeredGrid
from phisim.fluid.bodies import (
    Obstacle,
    SolidLayout,
    as_solids,
    set_from_probes,
    sharp_no_slip,
    solid_layout,
    uncovered_stencil,
)
from phisim.fluid.extension import free_slip_flux
from phisim.ops.differential import divergence
from phisim.ops.stencil import face_divergence, face_gradient, normalize_kinds
from phisim.solvers.box import apply_multiplier, is_singular, solve_multiplier
from phisim.solvers.linalg import Solve, SolveInfo
from phisim.solvers.masked import MaskedPoisson
from phisim.solvers.poisson import field_kinds_and_values

__all__ = ["PRESSURE_SOLVE", "Projection", "ProjectionResult", "check_velocity", "check_fits", "project_box",
           "make_incompressible", "project_trusted", "check_balance", "relative_divergence", "impose_solids",
           "net_boundary_flux", "solid_flux", "applied_gradient", "pressure_values"]

#: Default CG settings of the masked pressure solve in float64: a relative residual of 1e-6 keeps the
#: relative divergence after the projection below 1e-5 with a margin. Float32 input uses rtol 1e-5, and
#: with these defaults a solve that stops at float32's precision floor is accepted (the pressure is then as
#: accurate as float32 can represent it); any other failure raises SolveError.
PRESSURE_SOLVE = Solve(rtol=1e-6)
_PRESSURE_SOLVE_LOW = Solve(rtol=1e-5)


def check_velocity(velocity, what: str = "velocity") -> None:
    if not isinstance(velocity, StaggeredGrid):
        raise GridMismatchError(
            f"{what} must be a StaggeredGrid (MAC velocity), got {type(velocity).__name__}; convert a centred "
            "velocity with CenteredGrid.to_staggered()"
        )


def pressure_values(pressure, velocity: StaggeredGrid) -> torch.Tensor:
    """The values of the pressure a step or projection returned, checked against ``velocity``'s grid.

    Raises:
        ParameterError: For anything but a scalar :class:`CenteredGrid`.
        ShapeError: For a pressure on another grid.
    """
    if not isinstance(pressure, CenteredGrid) or pressure.is_vector:
        raise ParameterError("pressure must be the scalar CenteredGrid returned by the step / projection")
    if pressure.grid != velocity.grid:
        raise ShapeError(f"pressure grid {pressure.grid} differs from the velocity grid {velocity.grid}")
    return pressure.values


def _guess_tensor(pressure_guess, velocity: StaggeredGrid) -> torch.Tensor | None:
    if pressure_guess is None:
        return None
    g = pressure_guess.values if isinstance(pressure_guess, CenteredGrid) else torch.as_tensor(pressure_guess)
    shape = (velocity.batch_size, *velocity.grid.resolution)
    if g.ndim == velocity.rank:
        g = g[None]
    if tuple(g.shape) != shape:
        if g.shape[0] == 1 and tuple(g.shape[1:]) == shape[1:]:
            g = g.expand(shape)
        else:
            raise ShapeError(f"pressure_guess must have shape {shape}, got {tuple(g.shape)}")
    return g.detach().to(dtype=velocity.dtype, device=velocity.device)


def net_boundary_flux(velocity: StaggeredGrid) -> torch.Tensor:
    """Per sample, the net volume flux into the domain through its non-periodic sides ``(B,)``.

    Args:
        velocity: MAC velocity (boundary faces as stored).

    Returns:
        ``sum over sides of (inward normal velocity x face area)``.
    """
    grid = velocity.grid
    total = torch.zeros(velocity.batch_size, dtype=velocity.dtype, device=velocity.device)
    for a, c in enumerate(velocity.values):
        if velocity.boundary.is_periodic(a):
            continue
        area = 1.0
        for b, d in enumerate(grid.dx):
            if b != a:
                area *= d
        n = grid.resolution[a]
        total = total + (c.narrow(1 + a, 0, 1).flatten(1).sum(1) - c.narrow(1 + a, n, 1).flatten(1).sum(1)) * area
    return total


def check_balance(v: StaggeredGrid) -> None:
    """A domain without an open side must have zero net inflow (one host read; a stepper checks it once, when
    it is built).

    Raises:
        ParameterError: If the prescribed boundary fluxes of ``v`` (boundary faces as stored) do not balance.
    """
    if _box_constants(v.boundary)[2]:
        return  # an open side, or every prescribed normal velocity is 0 (walls): nothing to balance
    net = net_boundary_flux(v).detach()
    scale = 0.0
    grid = v.grid
    for a, c in enumerate(v.values):
        if v.boundary.is_periodic(a):
            continue
        n = grid.resolution[a]
        area = 1.0
        for b, d in enumerate(grid.dx):
            if b != a:
                area *= d
        ends = c.narrow(1 + a, 0, 1).abs().flatten(1).sum(1) + c.narrow(1 + a, n, 1).abs().flatten(1).sum(1)
        scale = scale + ends * area
    if not isinstance(scale, torch.Tensor):
        return
    tol = (1e-5 if v.dtype == torch.float32 else 1e-9) * scale.detach() + torch.finfo(v.dtype).tiny
    bad = net.abs() > tol
    if bool(bad.any()):
        b = int(torch.nonzero(bad).flatten()[0])
        raise ParameterError(
            f"the prescribed boundary velocities cannot balance: net inflow {float(net[b]):.4g} (sample {b}) "
            "into a domain without an open side, so no divergence-free velocity exists. Add an outflow side "
            "(Open()) or make the inflows and outflows through walls/Dirichlet/Inflow sides sum to zero."
        )


def _zero_normal(condition, axis: int) -> bool:
    """Whether a side prescribes the normal velocity 0 (a wall, or a zero Dirichlet value)."""
    rule = condition.rule(NORMAL, axis)
    return rule[0] == "odd" and isinstance(rule[1], (int, float)) and rule[1] == 0


def _pressure_kinds(boundary: Boundary):
    kinds, _ = field_kinds_and_values(boundary.for_pressure())
    return kinds


def check_fits(velocity: StaggeredGrid, grid, dtype: torch.dtype, device: torch.device, owner: str) -> None:
    """Check that ``velocity`` is a MAC velocity on ``grid`` of the ``dtype`` and device an object was built for.

    Raises:
        GridMismatchError: For a velocity that is not a StaggeredGrid or lives on another grid.
        ParameterError: For another dtype or device.
    """
    check_velocity(velocity)
    if velocity.grid != grid:
        raise GridMismatchError(f"velocity grid {velocity.grid} differs from the {owner}'s {grid}")
    if velocity.dtype != dtype or velocity.device.type != device.type:
        raise ParameterError(f"this {owner} was built for {dtype} on {device}; got a velocity of {velocity.dtype} "
                             f"on {velocity.device}")


def _operator(layout: SolidLayout, kinds, dx) -> MaskedPoisson:
    """The pressure operator of ``layout``: kept on a persistent layout (with the direct solve where it applies
    and the layout's policy allows it), built anew for a one-off layout (PCG)."""
    cache = layout.solvers
    if cache is None:
        return MaskedPoisson(layout.theta, dx, kinds, direct=False)
    direct = layout.direct
    key = ("pressure", kinds, tuple(dx), direct)
    op = cache.get(key)
    if op is None:
        op = cache[key] = MaskedPoisson(layout.theta, dx, kinds, direct=direct)
    return op


class ProjectionResult(NamedTuple):
    """The result of a :class:`Projection`."""

    #: The divergence-free MAC velocity.
    velocity: StaggeredGrid
    #: The pressure potential, a scalar CenteredGrid.
    pressure: CenteredGrid
    #: The :class:`~phisim.solvers.linalg.SolveInfo` of the CG pressure solve; None for the exact spectral solve.
    info: SolveInfo | None


class Projection:
    """The pressure projection of one domain, built once: ``Projection(grid, boundary, obstacles)(velocity)``.

    The constructor validates the settings and rasterises static solids once; their masked pressure operator
    (labels, null space, preconditioner, and the direct capacitance solve where it applies) is built at the
    first call and kept. Moving bodies are rasterised at each call's ``time`` (PCG solves). Without solids the
    projection is the exact spectral solve. :func:`make_incompressible` is the same projection as a pure
    function (nothing kept between calls).

    Args:
        grid: The grid.
        boundary: The velocity boundary.
        obstacles: Solids, as for :func:`make_incompressible` (None: none).
        solve: CG settings of the masked solve (default as :func:`make_incompressible`).
        method: ``'auto'``, ``'spectral'`` or ``'cg'`` (see :func:`make_incompressible`).
        dtype, device: Of the velocities this projection will be called with.
        direct: The direct pressure solve of static solids (see :class:`~phisim.solvers.masked.MaskedPoisson`):
            ``'auto'`` (default: where it applies and pays) or ``False`` (PCG).

    Raises:
        ParameterError: For an unknown method, ``'spectral'`` with solids, or solids outside the domain.
    """

    def __init__(self, grid, boundary: Boundary, obstacles=None, *, solve: Solve | None = None,
                 method: str = "auto", dtype: torch.dtype = torch.float32, device=None, direct="auto"):
        if method not in ("auto", "spectral", "cg"):
            raise ParameterError(f"method must be 'auto', 'spectral' or 'cg', got {method!r}")
        if solve is not None and not isinstance(solve, Solve):
            raise ParameterError(f"solve must be a phisim.solvers.Solve, got {type(solve).__name__}")
        if direct not in ("auto", False):
            raise ParameterError(f"direct must be 'auto' or False, got {direct!r}")
        self.grid, self.boundary, self.solve, self.method, self.direct = grid, boundary, solve, method, direct
        self.dtype, self.device = dtype, torch.device(device or "cpu")
        self.solids = tuple(as_solids(obstacles)) if not isinstance(obstacles, SolidLayout) else obstacles
        self.static = isinstance(obstacles, SolidLayout) or all(
            isinstance(s, Obstacle) or s.static for s in self.solids)
        layout = solid_layout(obstacles, grid, boundary, 0.0, dtype, self.device)
        if layout is not None and method == "spectral":
            raise ParameterError("the direct spectral pressure solve cannot handle obstacles; use method='auto' "
                                 "or 'cg'")
        self.has_solids = layout is not None
        self._layout = layout.persistent(direct) if (layout is not None and self.static) else None

    def layout(self, time: float = 0.0) -> SolidLayout | None:
        """The solids at ``time`` (the held layout of static solids)."""
        if not self.has_solids:
            return None
        if self._layout is not None:
            return self._layout
        return solid_layout(self.solids, self.grid, self.boundary, time, self.dtype, self.device)

    def __call__(self, velocity: StaggeredGrid, *, pressure_guess=None, time: float = 0.0) -> ProjectionResult:
        """Project ``velocity`` (its boundary faces set first); see :func:`make_incompressible`.

        Raises:
            GridMismatchError: For a velocity on another grid or with another boundary.
            ParameterError: For a velocity of another dtype or device than the projection was built for.
        """
        check_fits(velocity, self.grid, self.dtype, self.device, "projection")
        return self._apply(velocity, self.layout(time), pressure_guess, time)

    def _apply(self, velocity, layout, pressure_guess, time) -> ProjectionResult:
        if layout is None and self.method != "cg":
            out, pressure = project_box(velocity.with_boundary_faces(), check=True)
            return ProjectionResult(out, pressure, None)
        return _project(velocity.with_boundary_faces(), layout, self.solve, pressure_guess)


def impose_solids(velocity: StaggeredGrid, layout: SolidLayout | None, moved: tuple[float, float] | None = None
                  ) -> StaggeredGrid:
    """Impose the solids' velocity ``u_s`` before a viscous step and a projection.

    Blended no-slip solids store ``theta u + (1 - theta) u_s``; free-slip bodies and sharp no-slip bodies keep the
    fluid velocity on faces with ``theta > 0`` (a sharp body: on faces whose centre lies in the fluid) and take
    ``u_s`` on the others. With ``moved``, the faces whose centre a moving sharp no-slip body left since the
    previous time (freshly uncovered faces, which still hold the body's velocity) take the linear wall profile
    between the body's velocity at the surface and the fluid's velocity at a probe two cells out along the normal
    (:func:`~phisim.fluid.bodies.uncovered_stencil`).

    Args:
        velocity: MAC velocity.
        layout: The rasterised solids (None: returned with boundary faces set).
        moved: ``(t_old, t_new)``: the time of the previous position of the bodies and the time of ``layout``
            (None: no face is treated as uncovered).

    Returns:
        The velocity with boundary faces re-imposed.
    """
    v = velocity.with_boundary_faces()
    if layout is None:
        return v
    values = _blend(v.values, layout)
    if moved is not None:
        values = uncover_faces(values, layout, v.grid, *moved)
    return v.with_values(values).with_boundary_faces()


def applied_gradient(gradient: tuple, layout: SolidLayout | None) -> tuple:
    """Per component, what a projection whose potential has the face gradient ``gradient`` subtracts from the
    stored velocity (``stored(u) - stored(u - gradient)`` of :func:`_blend`): the whole gradient on the faces a
    sharp or free-slip body keeps (``theta > 0``), ``theta`` times it on the cut faces of a blended body, nothing
    inside solids. An incremental pressure ``-G q`` taken off in these terms is the gradient the next projection
    would have applied (the pressure-correction step of ``'imex2'``)."""
    if layout is None:
        return tuple(gradient)
    zero = tuple(torch.zeros_like(g) for g in gradient)
    full = _blend(zero, layout, tuple(gradient))
    none = _blend(zero, layout, zero)
    return tuple(a - b for a, b in zip(full, none))


def _solid(layout: SolidLayout, i: int, like: torch.Tensor):
    return 0.0 if layout.solid_velocity is None else layout.solid_velocity[i].to(like.dtype)


def flux_correction(values, layout: SolidLayout):
    """Per component, the flux that the blend ``theta u + (1 - theta) u_s`` misses on the faces cut by sharp no-slip
    bodies (:attr:`~phisim.fluid.bodies.SolidLayout.extension`; zero elsewhere), or None without such bodies."""
    parts = _correction_values(values, layout)
    if parts is None:
        return None
    return tuple(None if part is None else torch.zeros_like(u.reshape(u.shape[0], -1)).index_copy(
        1, part[0], part[1]).reshape(u.shape) for u, part in zip(values, parts))


def _correction_values(values, layout: SolidLayout):
    """:func:`flux_correction` as ``(index, value)`` per component (the flat faces and their extra flux), or None."""
    if layout.extension is None:
        return None
    out = []
    for u, ext in zip(values, layout.extension):
        if ext is None:
            out.append(None)
            continue
        index, corners, weights, kappa, base = ext
        flat = u.reshape(u.shape[0], -1)
        probe = flat.index_select(1, corners.reshape(-1)).view(flat.shape[0], *corners.shape)
        value = base.to(u.dtype) + kappa.to(u.dtype) * (probe * weights.to(u.dtype)).sum(-1)
        out.append((index, value))
    return out


def _blend(values, layout: SolidLayout, corrected=None):
    """The stored velocity: ``values`` imposed (``corrected`` None) or the projection's ``corrected`` velocity.

    Blended no-slip solids store ``theta c + (1 - theta) u_s``; free-slip and sharp no-slip bodies keep ``c`` on the
    faces with ``theta > 0`` (imposing, a sharp body gives the faces centred inside it its velocity) and ``u_s`` on
    the others."""
    out = []
    for i, u in enumerate(values):
        c = u if corrected is None else corrected[i]
        keep = _sharp_keep(layout, i, corrected is None)
        if keep is not None:  # sharp no-slip bodies alone on this component: (1 - sl) noslip + sl free is free
            if layout.solid_velocity is None:  # resting bodies: c on the kept faces, 0 on the others
                weight = keep.get(c.dtype)
                if weight is None:
                    weight = keep["mask"].to(c.dtype)
                    if not torch.compiler.is_compiling():  # what a trace computes is not kept
                        keep[c.dtype] = weight
                out.append(c * weight)
            else:
                out.append(torch.where(keep["mask"], c, _solid(layout, i, u)))
            continue
        th = layout.theta[i].to(u.dtype)
        s = _solid(layout, i, u)
        noslip = th * c if layout.solid_velocity is None else th * c + (1 - th) * s
        share = [x[i].to(u.dtype) for x in (layout.slip, layout.sharp) if x is not None]
        if not share:
            out.append(noslip)
            continue
        sl = share[0] if len(share) == 1 else share[0] + share[1]
        keep = th > 0
        if corrected is None and layout.walls is not None and layout.walls[i] is not None:
            keep = keep & ~layout.walls[i][0]
        free = torch.where(keep, c, torch.zeros_like(c) + s)
        out.append((1 - sl) * noslip + sl * free)
    return tuple(out)


def _sharp_keep(layout: SolidLayout, i: int, imposing: bool):
    """For a persistent layout whose component ``i`` is closed by sharp no-slip bodies alone (the share ``sl`` of
    :func:`_blend` is 1 on every face), the faces that keep the fluid velocity (``theta > 0``, imposing: and not cut),
    found once (``{'mask': bool mask, dtype: the mask as 0/1 in that dtype}``); None otherwise (the general
    blend)."""
    cache = layout.solvers
    if cache is None or layout.sharp is None:
        return None
    key = ("sharp-keep", i, imposing)
    if key not in cache:
        if torch.compiler.is_compiling():  # found by the eager steps only (it reads the share back)
            return None
        share = [x[i] for x in (layout.slip, layout.sharp) if x is not None]
        sl = share[0] if len(share) == 1 else share[0] + share[1]
        keep = None
        if not sl.requires_grad and bool((sl == 1).all()):
            mask = layout.theta[i].detach() > 0
            if imposing and layout.walls is not None and layout.walls[i] is not None:
                mask = mask & ~layout.walls[i][0]
            keep = {"mask": mask}
        cache[key] = keep
    return cache[key]


def _flux(values, layout: SolidLayout, probes=None, grid=None):
    """The volume flux per face of imposed velocities (the projection's right-hand side): ``theta u + (1 - theta)
    u_s``, plus the :func:`flux_correction` of sharp no-slip bodies (from ``probes``, default ``values``)."""
    out = []
    corr = _correction_values(values if probes is None else probes, layout)
    slip = None if grid is None else free_slip_flux(values if probes is None else probes, layout, grid)
    if slip is not None:
        corr = slip if corr is None else [a if b is None else b if a is None else
                                          (torch.cat([a[0], b[0]]), torch.cat([a[1], b[1]], -1))
                                          for a, b in zip(corr, slip)]
    for i, u in enumerate(values):
        th = layout.theta[i].to(u.dtype)
        s = _solid(layout, i, u)
        f = th * u if layout.solid_velocity is None else th * u + (1 - th) * s
        if corr is not None and corr[i] is not None:  # the flux correction added on the cut faces alone
            index, value = corr[i]
            flat = f.reshape(f.shape[0], -1)
            if f.is_contiguous() and flat.shape[0] == value.shape[0]:  # f: new here, saved by no backward
                flat.index_add_(1, index, value)
            else:
                batch = max(flat.shape[0], value.shape[0])
                f = flat.expand(batch, -1).index_add(1, index, value.expand(batch, -1)).reshape(batch, *f.shape[1:])
        out.append(f)
    return tuple(out)


def solid_flux(velocity: StaggeredGrid, layout: SolidLayout | None, before: StaggeredGrid | None = None
               ) -> StaggeredGrid:
    """The volume flux through each face of a projected velocity: its MAC divergence is the discrete continuity
    residual of the flow past the solids, zero after a projection (to the solve's tolerance).

    Faces of blended solids store the flux itself; faces of free-slip and sharp no-slip bodies store the fluid
    velocity ``u``, whose flux is ``theta u + (1 - theta) u_s``, plus, on the faces sharp bodies cut, the
    :func:`flux_correction`. The projection takes that correction from the velocity it is given (the probes two
    cells out, which the projection changes by the pressure gradient there): pass that velocity as ``before`` for the
    exact residual; without it the correction of ``velocity`` itself is used (a residual of the order of the
    projection's change at the probes).

    Args:
        velocity: MAC velocity (e.g. a projection's output).
        layout: The rasterised solids (:func:`~phisim.fluid.bodies.solid_layout`), or None (the velocity itself).
        before: The velocity the projection was given (its boundary faces set), for the flux correction.

    Returns:
        The flux as a StaggeredGrid on the velocity's grid.
    """
    check_velocity(velocity)
    if layout is None or (layout.slip is None and layout.sharp is None):
        return velocity
    values = velocity.values
    flux = _flux(values, layout, None if before is None else before.values, velocity.grid)
    out = []
    for i, (u, f) in enumerate(zip(values, flux)):
        share = [x[i].to(u.dtype) for x in (layout.slip, layout.sharp) if x is not None]
        sl = share[0] if len(share) == 1 else share[0] + share[1]
        out.append(u + sl * (f - u))
    return velocity.with_values(tuple(out))


def make_incompressible(
    velocity: StaggeredGrid,
    obstacles=None,
    *,
    solve: Solve | None = None,
    pressure_guess: CenteredGrid | torch.Tensor | None = None,
    method: str = "auto",
    return_info: bool = False,
    time: float = 0.0,
) -> tuple[StaggeredGrid, CenteredGrid]:
    """Project a MAC velocity onto the discretely divergence-free fields (pressure projection).

    Walls and inflows of ``velocity.boundary`` set their boundary faces; obstacles and bodies close or
    weight the faces they cover; then the pressure equation is solved and the correction applied (see
    the module docstring for the discretisation and the boundary conditions). 1-D, 2-D and 3-D, batched.

    Args:
        velocity: MAC velocity, component ``i`` of shape ``(B, *face_shape(i))``.
        obstacles: None, an :class:`~phisim.fluid.bodies.Obstacle`, a :class:`~phisim.fluid.bodies.Body`, a
            :class:`~phisim.fluid.geometry.Geometry`, a boolean solid mask ``(*res)``/``(B, *res)``, or a
            sequence of those.
        solve: CG settings of the masked solve. Default: :data:`PRESSURE_SOLVE` (rtol 1e-6) for float64,
            rtol 1e-5 for float32, where stopping at float32's precision floor is accepted. An explicit
            ``solve`` is applied as given. Not used by the direct spectral solve.
        pressure_guess: Start iterate of the CG solve (the previous step's pressure), a CenteredGrid or a
            tensor ``(B, *res)``. The direct solve ignores it.
        method: ``'auto'`` (spectral without solids, CG with them), ``'spectral'`` (rejects solids) or
            ``'cg'`` (weighted CG with spectral preconditioner even without solids).
        return_info: Removed (only ``False`` is accepted): a :class:`Projection` returns the velocity, the
            pressure and the :class:`~phisim.solvers.linalg.SolveInfo`.
        time: Simulation time: positions and velocities of moving bodies.

    Returns:
        ``(velocity, pressure)``: the divergence-free StaggeredGrid (same grid/boundary) and the pressure
        potential as a scalar CenteredGrid ``(B, *res)`` with boundary ``velocity.boundary.for_pressure()``
        (zero mean over each closed fluid region; 0 deep inside bodies).

    Raises:
        GridMismatchError: If ``velocity`` is not a StaggeredGrid.
        ParameterError: For an unknown ``method``, ``method='spectral'`` with solids, solids covering the
            whole domain, bodies outside the domain or over an inflow, or prescribed fluxes that cannot
            balance.
        ShapeError: For masks or guesses of the wrong shape.
        SolveError: If the CG solve does not converge.
    """
    check_velocity(velocity)
    if return_info:
        raise ParameterError("return_info was removed: make_incompressible returns (velocity, pressure); "
                             "phisim.fluid.Projection(grid, boundary, obstacles)(velocity) also returns the SolveInfo")
    if method not in ("auto", "spectral", "cg"):
        raise ParameterError(f"method must be 'auto', 'spectral' or 'cg', got {method!r}")
    grid, boundary = velocity.grid, velocity.boundary
    _guess_tensor(pressure_guess, velocity)  # checked also where the exact solve does not use it
    layout = solid_layout(obstacles, grid, boundary, time, velocity.dtype, velocity.device)
    if layout is not None and method == "spectral":
        raise ParameterError("the direct spectral pressure solve cannot handle obstacles; use method='auto' or 'cg'")
    if layout is None and method != "cg":
        return project_box(velocity.with_boundary_faces(), check=True)
    out = _project(velocity.with_boundary_faces(), layout, solve, pressure_guess)
    return out.velocity, out.pressure


def _box_constants(boundary: Boundary):
    """Per velocity boundary (memoised): the pressure boundary, its solver kinds, and whether the inflow needs
    no balance check (an open side, or a zero normal velocity prescribed on every non-periodic side)."""
    def make():
        kinds = normalize_kinds(_pressure_kinds(boundary), boundary.rank)
        exempt = boundary.has_open_side or all(
            boundary.is_periodic(a) or all(_zero_normal(c, a) for c in boundary.sides[a])
            for a in range(boundary.rank))
        return boundary.for_pressure(), kinds, exempt
    return boundary._memo("projection", make)


#: The box solve's multipliers per (resolution, dx, kinds, dtype, device): a plain dict, so that a traced step
#: finds the tensor (built at the stepper's construction, or at the first eager call) instead of tracing its
#: construction.
_BOX_INVERSE: dict = {}


def _box_inverse(res, dx, kinds, dtype, device) -> torch.Tensor:
    key = (res, tuple(dx), kinds, dtype, device)
    inv = _BOX_INVERSE.get(key)
    if inv is None:
        if len(_BOX_INVERSE) >= 64:
            _BOX_INVERSE.clear()
        inv = _BOX_INVERSE[key] = solve_multiplier(res, tuple(dx), kinds, device, dtype)
    return inv


def project_box(v: StaggeredGrid, check: bool = True):
    """The projection without solids by the direct spectral solve of ``v`` with its boundary faces set.

    ``check`` raises NonFiniteError for a non-finite divergence (as the spectral solve does) and
    ParameterError for boundary fluxes that cannot balance (both read a value back to the host); the other
    checks of :func:`make_incompressible` are the caller's. ``check=False`` is the trusted path of a stepper:
    no host read and no branch on tensor values.
    """
    grid, boundary = v.grid, v.boundary
    p_boundary, kinds, _ = _box_constants(boundary)
    if check:
        check_balance(v)
    dx = grid.dx
    div = face_divergence(v.values, dx)  # the MAC divergence
    if check and not math.isfinite(float(div.detach().sum())) and not all_finite(div):  # one reduction unless suspect
        raise NonFiniteError("spectral_poisson_solve: rhs contains NaN or Inf")
    if is_singular(kinds):
        div = div - div.mean(dim=tuple(range(1, div.ndim)), keepdim=True)
    p = apply_multiplier(div, kinds, _box_inverse(tuple(div.shape[1:]), dx, kinds, div.dtype, div.device), None,
                         prescaled=True)
    pressure = CenteredGrid._trusted(p, grid, p_boundary)
    comps = tuple(c - g for c, g in zip(v.values, face_gradient(p, dx, kinds)))  # zero pressure values
    out = StaggeredGrid._trusted(comps, grid, boundary).with_boundary_faces()
    return out, pressure


def project_trusted(velocity: StaggeredGrid, layout: SolidLayout | None, *, solve: Solve | None = None,
                    pressure_guess=None) -> tuple[StaggeredGrid, CenteredGrid]:
    """:func:`make_incompressible` of a validated velocity with its solids already rasterised (the step of a
    stepper): no balance, finiteness or coverage check, so nothing is read back to the host on the way.

    Without solids this is the spectral solve (traceable as one graph); with solids the masked solve of
    ``layout`` (its failure is not checked when ``solve`` allows failures).

    Args:
        velocity: MAC velocity (its boundary faces are set here).
        layout: The rasterised solids, or None.
        solve, pressure_guess: As for :func:`make_incompressible`.

    Returns:
        ``(velocity, pressure)`` as :func:`make_incompressible`.
    """
    v = velocity.with_boundary_faces()
    if layout is None:
        return project_box(v, check=False)
    out = _project(v, layout, solve, pressure_guess, trusted=True)
    return out.velocity, out.pressure


def _project(v, layout, solve, pressure_guess, trusted: bool = False) -> ProjectionResult:
    """The CG projection (solids, or ``method='cg'``) of ``v`` with its boundary faces set."""
    grid, boundary = v.grid, v.boundary
    if not trusted:
        check_balance(v)
    p_boundary = boundary.for_pressure()
    kinds = _pressure_kinds(boundary)
    info = None
    if layout is None:
        ones = tuple(torch.ones((1, *grid.face_shape(i)), dtype=v.dtype, device=v.device) for i in range(grid.rank))
        layout = SolidLayout(ones, None, None, torch.ones((1, *grid.resolution), dtype=v.dtype), ())
    cell = layout.cell_fraction.detach()
    if not trusted and layout.bodies and bool((cell.flatten(1).max(1).values <= 0).any()):
        raise ParameterError("obstacles cover every cell of a sample; there is no fluid to project")
    values = v.values
    flux = _flux(values, layout, grid=grid)
    op = _operator(layout, normalize_kinds(kinds, grid.rank), grid.dx)
    rhs = -op.divergence(flux)
    x0 = _guess_tensor(pressure_guess, v)
    if trusted and torch.compiler.is_compiling() and op.uses_direct_solve:
        p = _direct_pressure(op, rhs)
    elif solve is None:
        default = PRESSURE_SOLVE if rhs.dtype == torch.float64 else _PRESSURE_SOLVE_LOW
        p, info = op.solve(rhs, solve=replace(default, raise_on_failure=False), x0=x0)
        failed = [f"sample {b}: {st}" for b, st in enumerate(info.status) if st not in ("converged", "precision_floor")]
        if failed:
            raise SolveError(f"pressure solve failed ({', '.join(failed)}); {info!r}",
                             iterations=info.iterations, residual=info.residual)
    else:
        p, info = op.solve(rhs, solve=solve, x0=x0)
    grad = op.gradient(p)
    corrected = tuple(u - g for u, g in zip(values, grad))
    stored = _blend(values, layout, corrected)
    out = v.with_values(stored).with_boundary_faces()
    pressure = CenteredGrid(p, grid, p_boundary)
    return ProjectionResult(out, pressure, info)


def _direct_pressure(op: MaskedPoisson, rhs: torch.Tensor) -> torch.Tensor:
    """The direct (capacitance) solve of a held operator without the CG pass that checks and polishes it: that
    pass tests convergence on the host, so a traced step (``torch.compile``) takes the exact solve alone."""
    act = op.active.to(rhs.dtype)
    b = op.project(rhs * act)
    return op.project(op._direct_solver(rhs.dtype).solve(b) * act) * act


def relative_divergence(velocity: StaggeredGrid, reference: StaggeredGrid | None = None) -> torch.Tensor:
    """Per-sample relative MAC divergence: ``||D u|| / ||D u_ref||`` or ``max|D u| dx / max|u|``.

    Args:
        velocity: The (projected) MAC velocity.
        reference: The velocity before projection; its divergence norm is the scale. Without it the scale
            is ``max_i max|u_i| / min(dx)`` (the divergence a velocity of that size could have).

    Returns:
        ``(B,)`` tensor (detached).
    """
    check_velocity(velocity)
    with torch.no_grad():
        d = divergence(velocity).values.flatten(1)
        if reference is not None:
            check_velocity(reference, "reference")
            check_batch_compatible(velocity, reference, ("velocity", "reference"), "compare")
            ref = divergence(reference.with_boundary_faces()).values.flatten(1).norm(dim=1)
            return d.norm(dim=1) / ref.clamp_min(torch.finfo(d.dtype).tiny)
        scale = torch.stack([c.flatten(1).abs().max(1).values for c in velocity.values]).max(0).values
        scale = scale / min(velocity.grid.dx)
        return d.abs().max(1).values / scale.clamp_min(torch.finfo(d.dtype).tiny)


def uncover_faces(values, layout: SolidLayout, grid, t_old: float, t_new: float):
    """``values`` with the faces that moving sharp no-slip bodies of ``layout`` uncovered between ``t_old`` and
    ``t_new`` set to the linear wall profile (:func:`~phisim.fluid.bodies.uncovered_stencil`); unchanged without
    moving sharp no-slip bodies.

    Why: such a face still holds the velocity it was given inside the body (the body's velocity, then advected),
    which the viscous step and the projection would take as the fluid's. The profile is what the sharp surface
    imposes on the faces next to it (the linear ghost values of the viscous stencil, the flux correction's wall
    profile), from values already in the fluid: it changes the stored velocity continuously as a face leaves
    the body (``phi -> 0`` gives the body's velocity).
    """

    sharp = sharp_no_slip(layout.bodies)
    if all(b.static for b in sharp) or t_new == t_old:
        return values
    out = []
    for i, u in enumerate(values):
        st = uncovered_stencil(sharp, grid, i, t_old, t_new, torch.float64, u.device)
        if st is not None:  # not where another solid (a staircase obstacle, a blended body) closes the face
            wet = layout.theta[i].detach().amax(0).reshape(-1)[st[0]] > 0
            st = None if not bool(wet.any()) else tuple(x[wet] for x in st)
        out.append(u if st is None else set_from_probes(u, st))
    return tuple(out)
