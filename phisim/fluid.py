"""Incompressible flow on MAC (staggered) grids: pressure projection with obstacles, Navier-Stokes steps.

Discretisation. Velocities live on the faces (:class:`~phisim.field.StaggeredGrid`), the pressure at cell
centres. The projection makes ``u`` discretely divergence-free,

    ``u_new = u - G p``   with   ``D G p = D u``,

where ``D`` is the exact MAC divergence (flux balance of each cell, :func:`phisim.differential.divergence`)
and ``G`` the face gradient ``(p_k - p_{k-1}) / dx`` (:func:`phisim.differential.gradient` with
``at='face'``; boundary faces use the pressure's ghost cells). ``D G`` is the standard ``(2d+1)``-point
Laplacian. The returned "pressure" ``p`` is the potential of that correction (``dt`` is not divided out:
``p = dt * p_physical / rho``), as in PhiFlow.

Boundary conditions (per side, from the velocity boundary, see :mod:`phisim.boundary`):

* **walls** (:class:`~phisim.boundary.NoSlipWall`, :class:`~phisim.boundary.FreeSlipWall`): the normal
  velocity on the boundary face is 0 before and after the projection; the pressure is zero-flux there;
* **open / outflow** sides (:class:`~phisim.boundary.Open`, also ``Dirichlet`` velocity sides): pressure 0
  on the face; the normal velocity on the boundary face is free and corrected like an interior face;
* **periodic** axes: face ``n`` is face ``0``.
* **obstacles** (:class:`Obstacle`): cells whose centre lies inside an obstacle are solid. Every face
  touching a solid cell gets zero normal velocity and zero pressure flux; the pressure is 0 inside.

Solvers. Without obstacles the pressure equation is solved directly by the spectral solver of
:mod:`phisim.poisson` (FFT / DCT / DST per axis, exact to round-off, ``O(N log N)``); for a box with only
walls and periodic axes the operator is singular and the solver returns the zero-mean pressure (the
right-hand side is compatible automatically: with the boundary faces set, the divergence sums to zero).
With obstacles the masked system is solved by conjugate gradients (:func:`phisim.linalg.cg`) with the
spectral solver of the obstacle-free box as preconditioner, warm-started from ``pressure_guess``.
Gradients never flow through CG iterations (implicit adjoint solve), so memory does not grow with them.

Navier-Stokes. :func:`navier_stokes_step` composes pure functions: self-advection
(:func:`phisim.advection.advect`, semi-Lagrangian or MacCormack), a body force (e.g. :func:`buoyancy`),
viscosity (:func:`diffuse_velocity`, explicit or implicit), projection, and optionally a rescaling to the
kinetic energy the step started with (:func:`normalize_energy`). :func:`step` advances a
:class:`FluidState` (velocity, marker, pressure) for smoke-like simulations.

References: Harlow & Welch (1965), "Numerical calculation of time-dependent viscous incompressible flow
of fluid with free surface", Phys. Fluids 8 (the MAC grid); Chorin (1968), "Numerical solution of the
Navier-Stokes equations", Math. Comp. 22 (projection); Stam (1999), "Stable fluids", SIGGRAPH.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np
import torch
from scipy import ndimage

from .advection import SCHEMES, advect
from .boundary import Boundary, pad, pad_staggered_component, set_boundary_faces
from .checks import all_finite, check_dt, check_finite, check_finite_number, check_nonnegative, check_positive
from .differential import divergence, gradient, laplace
from .errors import GridMismatchError, ParameterError, ShapeError, SolveError
from .field import CenteredGrid, StaggeredGrid
from .grid import Grid
from .linalg import Solve, SolveInfo, cg
from .poisson import field_kinds_and_values, masked_laplacian, spectral_poisson_solve

__all__ = [
    "Obstacle",
    "obstacle_mask",
    "open_face_masks",
    "make_incompressible",
    "relative_divergence",
    "buoyancy",
    "diffuse_velocity",
    "kinetic_energy",
    "normalize_energy",
    "cfl_dt",
    "navier_stokes_step",
    "FluidState",
    "step",
    "PRESSURE_SOLVE",
]

#: Default CG settings of the masked pressure solve in float64: a relative residual of 1e-6 keeps the
#: relative divergence after the projection below 1e-5 with a margin. Float32 input uses rtol 1e-5, and
#: with these defaults a solve that stops at float32's precision floor is accepted (the pressure is then as
#: accurate as float32 can represent it); any other failure raises SolveError.
PRESSURE_SOLVE = Solve(rtol=1e-6)
_PRESSURE_SOLVE_LOW = Solve(rtol=1e-5)


# ---- obstacles ----------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class Obstacle:
    """A solid, resting obstacle: a box, a sphere (disc in 2-D) or an arbitrary boolean cell mask.

    Build it with :meth:`box`, :meth:`sphere` or :meth:`from_mask`. A cell is solid when its centre lies
    inside the geometry (boundary included). Faces touching a solid cell carry zero normal velocity.

    Attributes:
        kind: ``'box'``, ``'sphere'`` or ``'mask'``.
        params: The geometry: ``(lower, upper)`` corners, ``(center, radius)`` or ``(mask,)``.
    """

    kind: str
    params: tuple

    @classmethod
    def box(cls, lower: Sequence[float], upper: Sequence[float]) -> Obstacle:
        """An axis-aligned box ``lower <= x <= upper`` (physical coordinates, one entry per axis).

        Raises:
            ParameterError: If ``lower`` and ``upper`` differ in length or ``upper < lower``.
        """
        lo, hi = tuple(float(v) for v in lower), tuple(float(v) for v in upper)
        if len(lo) != len(hi) or not all(math.isfinite(v) for v in lo + hi) or any(h < l for l, h in zip(lo, hi)):
            raise ParameterError(f"Obstacle.box needs lower <= upper with one entry per axis, got {lo}, {hi}")
        return cls("box", (lo, hi))

    @classmethod
    def sphere(cls, center: Sequence[float], radius: float) -> Obstacle:
        """A ball ``|x - center| <= radius`` (a disc in 2-D).

        Raises:
            ParameterError: If ``radius`` is not positive and finite.
        """
        r = float(radius)
        if not (math.isfinite(r) and r > 0):
            raise ParameterError(f"Obstacle.sphere radius must be finite and > 0, got {radius}")
        return cls("sphere", (tuple(float(c) for c in center), r))

    @classmethod
    def from_mask(cls, mask) -> Obstacle:
        """An obstacle given cell by cell: a boolean array ``(*res)`` or ``(B, *res)``, True = solid.

        Raises:
            ParameterError: If ``mask`` is not boolean (0/1 numbers are accepted and converted).
        """
        m = torch.as_tensor(mask)
        if m.dtype != torch.bool:
            if not bool(((m == 0) | (m == 1)).all()):
                raise ParameterError("Obstacle.from_mask needs a boolean mask (True = solid) or 0/1 values")
            m = m != 0
        return cls("mask", (m,))

    def cell_mask(self, grid: Grid, device=None) -> torch.Tensor:
        """Rasterise onto ``grid``: a boolean tensor ``(*res)`` (``(B, *res)`` for a batched mask).

        Args:
            grid: The grid.
            device: Torch device of the result.

        Returns:
            True where the cell is solid.

        Raises:
            ShapeError: If the geometry's dimension or a mask's shape does not fit ``grid``.
        """
        if self.kind == "mask":
            m = self.params[0].to(device)
            if tuple(m.shape[m.ndim - grid.rank :]) != grid.resolution or m.ndim not in (
                grid.rank,
                grid.rank + 1,
            ):
                raise ShapeError(
                    f"obstacle mask of shape {tuple(m.shape)} does not fit {grid} "
                    f"(expected {grid.resolution} or (B, *resolution))"
                )
            return m
        x = grid.cell_centers(torch.float64, device)
        if self.kind == "box":
            lo, hi = self.params
            if len(lo) != grid.rank:
                raise ShapeError(f"a {len(lo)}-D box obstacle cannot be placed on a {grid.rank}-D grid")
            lo_t = torch.tensor(lo, dtype=x.dtype, device=x.device)
            hi_t = torch.tensor(hi, dtype=x.dtype, device=x.device)
            return ((x >= lo_t) & (x <= hi_t)).all(-1)
        center, radius = self.params
        if len(center) != grid.rank:
            raise ShapeError(f"a {len(center)}-D sphere obstacle cannot be placed on a {grid.rank}-D grid")
        c = torch.tensor(center, dtype=x.dtype, device=x.device)
        return ((x - c) ** 2).sum(-1) <= radius**2

    def __repr__(self) -> str:
        if self.kind == "mask":
            return f"Obstacle.from_mask(shape={tuple(self.params[0].shape)})"
        return f"Obstacle.{self.kind}{self.params}"


def obstacle_mask(obstacles, grid: Grid, device=None) -> torch.Tensor | None:
    """Union of obstacles as a boolean solid mask ``(1 or B, *resolution)``, or None when nothing is solid.

    Args:
        obstacles: None, an :class:`Obstacle`, a boolean tensor (True = solid, ``(*res)`` or ``(B, *res)``),
            or a sequence of those.
        grid: The grid.
        device: Torch device of the mask.

    Returns:
        The mask, or None for no obstacles (or obstacles covering no cell centre).

    Raises:
        ParameterError: For entries that are neither obstacles nor masks.
        ShapeError: For masks that do not fit the grid.
    """
    if obstacles is None:
        return None
    if isinstance(obstacles, (Obstacle, torch.Tensor)):
        obstacles = [obstacles]
    solid = None
    for ob in obstacles:
        if isinstance(ob, torch.Tensor):
            ob = Obstacle.from_mask(ob)
        if not isinstance(ob, Obstacle):
            raise ParameterError(
                f"obstacles must be Obstacle objects or boolean masks, got {type(ob).__name__}"
            )
        m = ob.cell_mask(grid, device)
        if m.ndim == grid.rank:
            m = m[None]
        if solid is None:
            solid = m
        else:
            if m.shape[0] != solid.shape[0] and 1 not in (m.shape[0], solid.shape[0]):
                raise ShapeError(
                    f"obstacle masks with batch sizes {m.shape[0]} and {solid.shape[0]} cannot be combined"
                )
            solid = solid | m
    if solid is None or not bool(solid.any()):
        return None
    return solid


def open_face_masks(fluid: torch.Tensor, boundary: Boundary) -> tuple[torch.Tensor, ...]:
    """Per MAC component, 1 on faces between two fluid cells and 0 on faces touching a solid cell.

    A boundary face counts as open when its inside cell is fluid (walls are imposed separately by the
    boundary); on a periodic axis the boundary faces look at the cell on the other side.

    Args:
        fluid: Fluid indicator ``(1 or B, *resolution)`` (bool or float).
        boundary: The velocity boundary (periodicity per axis).

    Returns:
        One float tensor per axis ``i``, shape ``(1 or B, *face_shape(i))``.
    """
    f = fluid.to(torch.get_default_dtype()) if fluid.dtype == torch.bool else fluid
    out = []
    for a in range(boundary.rank):
        dim = 1 + a
        n = f.shape[dim]
        if boundary.is_periodic(a):
            p = torch.cat([f.narrow(dim, n - 1, 1), f, f.narrow(dim, 0, 1)], dim=dim)
        else:
            p = torch.cat([f.narrow(dim, 0, 1), f, f.narrow(dim, n - 1, 1)], dim=dim)
        out.append(p.narrow(dim, 0, n + 1) * p.narrow(dim, 1, n + 1))
    return tuple(out)


def _zero_obstacle_faces(velocity: StaggeredGrid, obstacles) -> StaggeredGrid:
    """Set the velocity on every face touching a solid cell to 0 (resting obstacles), walls too."""
    v = velocity.with_boundary_faces()
    solid = obstacle_mask(obstacles, velocity.grid, velocity.device)
    if solid is None:
        return v
    faces = open_face_masks((~solid).to(velocity.dtype), velocity.boundary)
    return v.with_values(tuple(c * o for c, o in zip(v.values, faces)))


# ---- projection ---------------------------------------------------------------------------------------


def _check_velocity(velocity, what: str = "velocity") -> None:
    if not isinstance(velocity, StaggeredGrid):
        raise GridMismatchError(
            f"{what} must be a StaggeredGrid (MAC velocity), got {type(velocity).__name__}; convert a centred"
            " "
            "velocity with CenteredGrid.to_staggered()"
        )


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


def make_incompressible(
    velocity: StaggeredGrid,
    obstacles=None,
    *,
    solve: Solve | None = None,
    pressure_guess: CenteredGrid | torch.Tensor | None = None,
    method: str = "auto",
    return_info: bool = False,
):
    """Project a MAC velocity onto the discretely divergence-free fields (pressure projection).

    Walls of ``velocity.boundary`` get zero normal velocity, faces touching obstacles too; then
    ``D G p = D u`` is solved and ``u - G p`` returned (see the module docstring for the discretisation
    and the boundary conditions). Works for 1-D, 2-D and 3-D grids and any batch size.

    Args:
        velocity: MAC velocity, component ``i`` of shape ``(B, *face_shape(i))``.
        obstacles: None, an :class:`Obstacle`, a boolean solid mask ``(*res)``/``(B, *res)``, or a sequence.
        solve: CG settings of the masked solve. Default: :data:`PRESSURE_SOLVE` (rtol 1e-6) for float64,
            rtol 1e-5 for float32, where stopping at float32's precision floor is accepted. An explicit
            ``solve`` is applied as given. Not used by the direct spectral solve.
        pressure_guess: Start iterate of the CG solve (the previous step's pressure), a CenteredGrid or a
            tensor ``(B, *res)``. The direct solve needs none and ignores it.
        method: ``'auto'`` (spectral without obstacles, CG with them), ``'spectral'`` (rejects obstacles)
            or ``'cg'`` (masked CG with spectral preconditioner even without obstacles).
        return_info: Also return the :class:`~phisim.linalg.SolveInfo` of the CG solve (None for the
            direct solve).

    Returns:
        ``(velocity, pressure)``: the divergence-free StaggeredGrid (same grid/boundary) and the pressure
        potential as a scalar CenteredGrid ``(B, *res)`` with boundary ``velocity.boundary.for_pressure()``
        (zero-mean over fluid cells when there is no open side; 0 inside obstacles). With ``return_info``
        a third element, the SolveInfo or None.

    Raises:
        GridMismatchError: If ``velocity`` is not a StaggeredGrid.
        ParameterError: For an unknown ``method``, ``method='spectral'`` with obstacles, or obstacles
            covering the whole domain of a sample.
        ShapeError: For masks or guesses of the wrong shape.
        SolveError: If the CG solve does not converge.
    """
    _check_velocity(velocity)
    if method not in ("auto", "spectral", "cg"):
        raise ParameterError(f"method must be 'auto', 'spectral' or 'cg', got {method!r}")
    grid, boundary = velocity.grid, velocity.boundary
    solid = obstacle_mask(obstacles, grid, velocity.device)
    if solid is not None and method == "spectral":
        raise ParameterError(
            "the direct spectral pressure solve cannot handle obstacles; use method='auto' or 'cg'"
        )
    v = velocity.with_boundary_faces()
    open_faces = None
    if solid is not None:
        fluid = (~solid).to(velocity.dtype)
        if bool((fluid.flatten(1).sum(1) == 0).any()):
            raise ParameterError("obstacles cover every cell of a sample; there is no fluid to project")
        open_faces = open_face_masks(fluid, boundary)
        v = v.with_values(tuple(c * o for c, o in zip(v.values, open_faces)))
    div = divergence(v).values
    p_boundary = boundary.for_pressure()
    kinds, values = field_kinds_and_values(p_boundary)
    info = None
    if solid is None and method != "cg":
        p = spectral_poisson_solve(div, grid.dx, kinds, values, incompatible="project")
    else:
        mask = torch.ones_like(div[:1]) if solid is None else fluid
        x0 = _guess_tensor(pressure_guess, velocity)
        if solve is None:
            default = PRESSURE_SOLVE if div.dtype == torch.float64 else _PRESSURE_SOLVE_LOW
            p, info = _masked_pressure_solve(
                div, mask, boundary, grid.dx, kinds, replace(default, raise_on_failure=False), x0
            )
            failed = [
                f"sample {b}: {st}"
                for b, st in enumerate(info.status)
                if st not in ("converged", "precision_floor")
            ]
            if failed:
                raise SolveError(
                    f"pressure solve failed ({', '.join(failed)}); {info!r}",
                    iterations=info.iterations,
                    residual=info.residual,
                )
        else:
            p, info = _masked_pressure_solve(div, mask, boundary, grid.dx, kinds, solve, x0)
    pressure = CenteredGrid(p, grid, p_boundary)
    grad = gradient(pressure, at="face").values
    if open_faces is not None:
        grad = tuple(g * o for g, o in zip(grad, open_faces))
    out = v.with_values(tuple(c - g for c, g in zip(v.values, grad))).with_boundary_faces()
    if return_info:
        return out, pressure, info
    return out, pressure


def _find(parent: list[int], a: int) -> int:
    """Root of ``a`` in a union-find forest (with path halving)."""
    while parent[a] != a:
        parent[a] = parent[parent[a]]
        a = parent[a]
    return a


def _singular_components(fluid: torch.Tensor, boundary: Boundary, kinds) -> torch.Tensor | None:
    """Normalised indicators of the fluid regions whose pressure is only fixed up to a constant.

    Fluid cells are connected through faces (periodic axes wrap). A region that touches a side with zero
    pressure (open) is regular; every other region (a closed box, or a pocket enclosed by obstacles and
    walls) adds a constant to the null space of the masked pressure operator.

    Returns:
        ``(Bm, K, *res)`` orthonormal indicators (zero-padded to the largest ``K`` of the batch), or None
        when every region is regular.
    """
    rank = boundary.rank
    masks = fluid.detach().cpu().numpy() > 0.5
    structure = ndimage.generate_binary_structure(rank, 1)
    per_sample = []
    for m in masks:
        labels, n = ndimage.label(m, structure=structure)
        parent = list(range(n + 1))
        for a in range(rank):
            if boundary.is_periodic(a):
                lo = np.take(labels, 0, axis=a).ravel()
                hi = np.take(labels, -1, axis=a).ravel()
                for x, y in zip(lo, hi):
                    if x and y:
                        parent[_find(parent, x)] = _find(parent, y)
        roots = np.array([_find(parent, k) for k in range(n + 1)])
        labels = roots[labels]
        regular = set()
        for a, pair in enumerate(kinds):
            for side, kind in enumerate(pair):
                if kind == "dirichlet":
                    regular.update(int(k) for k in np.unique(np.take(labels, 0 if side == 0 else -1, axis=a)))
        singular = [int(k) for k in np.unique(labels) if k != 0 and int(k) not in regular]
        per_sample.append([labels == k for k in singular])
    kmax = max(len(c) for c in per_sample)
    if kmax == 0:
        return None
    z = np.zeros((len(per_sample), kmax, *masks.shape[1:]))
    for b, comps in enumerate(per_sample):
        for k, c in enumerate(comps):
            z[b, k] = c / math.sqrt(c.sum())
    return torch.as_tensor(z, dtype=fluid.dtype, device=fluid.device)


def _masked_pressure_solve(
    div: torch.Tensor,
    fluid: torch.Tensor,
    boundary: Boundary,
    dx,
    kinds,
    solve: Solve,
    x0: torch.Tensor | None,
) -> tuple[torch.Tensor, SolveInfo]:
    """Solve ``D G p = div`` on the fluid cells by CG: ``-masked_laplacian`` (identity on solid cells).

    Preconditioner: the spectral inverse of the obstacle-free box, restricted to the fluid cells. The null
    space (one constant per closed fluid region, see :func:`_singular_components`) is projected out of the
    right-hand side, the residuals and the preconditioned residuals, so the solve stays on the range of
    the operator even when obstacles enclose several separate pockets of fluid; the returned pressure has
    zero mean over every closed region.
    """
    z = _singular_components(fluid, boundary, kinds)
    dims = tuple(range(2, div.ndim + 1))

    def project(t: torch.Tensor) -> torch.Tensor:
        if z is None:
            return t
        zz = z.to(t.dtype)
        coef = (zz * t.unsqueeze(1)).sum(dim=dims, keepdim=True)
        return t - (coef * zz).sum(1)

    def operator(x: torch.Tensor) -> torch.Tensor:
        m = fluid.to(x.dtype)
        return -masked_laplacian(x, m, dx, kinds) + (1 - m) * x

    def preconditioner(r: torch.Tensor) -> torch.Tensor:
        m = fluid.to(r.dtype)
        r = project(r)
        y = -spectral_poisson_solve(r * m, dx, kinds, incompatible="project")
        return project(y * m + (1 - m) * r)

    rhs = -div * fluid.to(div.dtype)
    if x0 is not None:
        x0 = x0 * fluid.to(x0.dtype)
    x, info = cg(
        operator,
        rhs,
        x0,
        solve=solve,
        preconditioner=preconditioner,
        return_info=True,
        project=project if z is not None else None,
    )
    return x * fluid.to(x.dtype), info


def relative_divergence(velocity: StaggeredGrid, reference: StaggeredGrid | None = None) -> torch.Tensor:
    """Per-sample relative MAC divergence: ``||D u|| / ||D u_ref||`` or ``max|D u| dx / max|u|``.

    Args:
        velocity: The (projected) MAC velocity.
        reference: The velocity before projection; its divergence norm is the scale. Without it the scale
            is ``max_i max|u_i| / min(dx)`` (the divergence a velocity of that size could have).

    Returns:
        ``(B,)`` tensor (detached).
    """
    _check_velocity(velocity)
    with torch.no_grad():
        d = divergence(velocity).values.flatten(1)
        if reference is not None:
            _check_velocity(reference, "reference")
            ref = divergence(reference.with_boundary_faces()).values.flatten(1).norm(dim=1)
            return d.norm(dim=1) / ref.clamp_min(torch.finfo(d.dtype).tiny)
        scale = torch.stack([c.flatten(1).abs().max(1).values for c in velocity.values]).max(0).values
        scale = scale / min(velocity.grid.dx)
        return d.abs().max(1).values / scale.clamp_min(torch.finfo(d.dtype).tiny)


# ---- forces, viscosity, energy, time step ----------------------------------------------------------------


def _scalar_values(marker, grid: Grid) -> tuple[torch.Tensor, Boundary | None]:
    if isinstance(marker, CenteredGrid):
        if marker.is_vector:
            raise ShapeError("the marker must be a scalar CenteredGrid (B, *res)")
        if marker.grid != grid:
            raise GridMismatchError(f"marker grid {marker.grid} differs from the velocity grid {grid}")
        return marker.values, marker.boundary
    m = torch.as_tensor(marker)
    if m.ndim != grid.rank + 1 or tuple(m.shape[1:]) != grid.resolution:
        raise ShapeError(
            f"marker must have shape (B, {', '.join(map(str, grid.resolution))}), got {tuple(m.shape)}"
        )
    return m, None


def buoyancy(
    velocity: StaggeredGrid, marker, dt, *, strength: float = 1.0, direction: Sequence[float] | None = None
) -> StaggeredGrid:
    """Add the Boussinesq buoyancy force ``dt * strength * marker * direction`` to a MAC velocity.

    The marker (smoke density or temperature) is averaged from the two cells adjacent to each face (on
    boundary faces the marker's ghost cell is used: its own boundary, or zero flux for a plain tensor).
    Walls stay impermeable: boundary faces are reset afterwards.

    Args:
        velocity: MAC velocity ``(B, *face_shape(i))`` per component.
        marker: Scalar CenteredGrid or tensor ``(B, *res)`` on the velocity's grid (batch 1 broadcasts).
        dt: Time step ``>= 0``.
        strength: Buoyancy per unit marker (acceleration); negative values sink.
        direction: The "up" vector, one entry per axis; default the last axis (``+y`` in 2-D, ``+z`` in 3-D).

    Returns:
        The accelerated velocity (same grid and boundary).

    Raises:
        ParameterError: For a negative dt or a direction of the wrong length.
        ShapeError, GridMismatchError: For a marker that does not fit the velocity.
    """
    _check_velocity(velocity)
    dt = check_dt(dt)
    strength = check_finite_number(strength, "buoyancy strength")
    grid = velocity.grid
    direction = (
        tuple(float(c) for c in direction) if direction is not None else (0.0,) * (grid.rank - 1) + (1.0,)
    )
    if len(direction) != grid.rank:
        raise ParameterError(f"direction needs {grid.rank} entries, got {direction}")
    m, mb = _scalar_values(marker, grid)
    m = m.to(dtype=velocity.dtype, device=velocity.device)
    mb = mb if mb is not None else velocity.boundary.for_scalar()
    comps = []
    for i, c in enumerate(velocity.values):
        if direction[i] == 0.0:
            comps.append(c)
            continue
        p = pad(m, mb, grid.dx, 1, axes=[i])
        dim = 1 + i
        n = p.shape[dim] - 1
        face = 0.5 * (p.narrow(dim, 0, n) + p.narrow(dim, 1, n))
        comps.append(c + (dt * strength * direction[i]) * face)
    return velocity.with_values(tuple(comps)).with_boundary_faces()


def diffuse_velocity(
    velocity: StaggeredGrid, dt, *, viscosity: float, scheme: str = "explicit", solve: Solve | None = None
) -> StaggeredGrid:
    """Viscous diffusion ``du/dt = viscosity * lap(u)`` of a MAC velocity over one step ``dt``.

    Wall velocities enter through the ghost cells of :meth:`StaggeredGrid.padded_component`: a moving
    lid (``NoSlipWall(velocity=(1, 0))``) drags the tangential velocity next to it.

    Args:
        velocity: MAC velocity.
        dt: Time step ``>= 0``.
        viscosity: Kinematic viscosity ``>= 0``.
        scheme: ``'explicit'`` (forward Euler, first order in time, stable for
            ``viscosity * dt * sum(2 / dx_i^2) <= 1``) or ``'implicit'`` (backward Euler, unconditionally
            stable; each component solved by CG, symmetric stencil with boundary faces treated exactly).
        solve: CG settings of the implicit scheme (default ``Solve(rtol=1e-8)``).

    Returns:
        The diffused velocity with boundary faces re-imposed.

    Raises:
        ParameterError: For negative dt/viscosity, an unknown scheme, or an explicit step beyond its
            stability limit.
        SolveError: If the implicit solve does not converge.
    """
    _check_velocity(velocity)
    dt = check_dt(dt)
    viscosity = check_nonnegative(viscosity, "viscosity")
    if scheme not in ("explicit", "implicit"):
        raise ParameterError(f"viscosity scheme must be 'explicit' or 'implicit', got {scheme!r}")
    if float(viscosity) == 0 or float(dt) == 0:
        return velocity
    alpha = dt * viscosity
    if scheme == "explicit":
        number = float(alpha) * sum(2.0 / d**2 for d in velocity.grid.dx)
        if number > 1.0:
            raise ParameterError(
                f"explicit viscosity is unstable: viscosity * dt * sum(2/dx^2) = {number:.3g} > 1; reduce dt"
                " or "
                "use scheme='implicit'"
            )
        return (velocity + alpha * laplace(velocity)).with_boundary_faces()
    if solve is None:  # (1 - alpha L) is well conditioned: float64 reaches 1e-8, float32 about 1e-6
        solve = Solve(rtol=1e-8 if velocity.dtype == torch.float64 else 1e-6)
    return _implicit_diffusion(velocity, alpha, solve)


def _implicit_diffusion(velocity: StaggeredGrid, alpha, solve: Solve) -> StaggeredGrid:
    """Backward Euler ``(1 - alpha L) u_new = u`` per component by CG.

    Unknowns are the free face samples. Samples fixed by the boundary (wall/Dirichlet boundary faces, and
    face ``n`` of a periodic axis, a copy of face 0) are excluded from the operator. Free boundary faces of
    open sides (ghost mirrored about the face sample) get half weight, which makes the stencil symmetric.
    """
    grid, boundary = velocity.grid, velocity.boundary
    out = []
    for i, u in enumerate(velocity.values):
        dim = 1 + i
        n = grid.resolution[i]
        fixed = torch.zeros((1, *grid.face_shape(i)), dtype=u.dtype, device=u.device)
        weight = torch.ones_like(fixed)
        periodic = boundary.is_periodic(i)
        if periodic:
            fixed.narrow(dim, n, 1).fill_(1.0)
        else:
            for side, pos in ((0, 0), (1, n)):
                rule = boundary.sides[i][side].rule("normal", i)
                if rule[0] == "odd":
                    fixed.narrow(dim, pos, 1).fill_(1.0)
                else:
                    weight.narrow(dim, pos, 1).fill_(0.5)
        free = 1.0 - fixed

        def complete(x, i=i, dim=dim, n=n, periodic=periodic):
            if periodic:
                return torch.cat([x.narrow(dim, 0, n), x.narrow(dim, 0, 1)], dim=dim)
            return x

        def lap(x, i=i):
            return _component_laplace(x, i, boundary, grid.dx)

        fixed_vals = set_boundary_faces(torch.zeros_like(u), i, boundary) * fixed
        zero_lap = lap(torch.zeros_like(u))
        rhs = weight * free * (u + alpha * lap(fixed_vals)) + fixed * fixed_vals

        def operator(x, free=free, weight=weight, fixed=fixed, complete=complete, lap=lap, zero_lap=zero_lap):
            y = complete(x * free)
            return weight * free * (x - alpha * (lap(y) - zero_lap)) + fixed * x

        x = cg(operator, rhs, u.detach() * free + fixed_vals, solve=solve)
        out.append(complete(x * free) + fixed_vals)
    return velocity.with_values(tuple(out)).with_boundary_faces()


def _component_laplace(x: torch.Tensor, component: int, boundary: Boundary, dx) -> torch.Tensor:
    """The (2d+1)-point Laplacian of one MAC component, ghosts from the velocity boundary."""
    p = pad_staggered_component(x, component, boundary, dx, 1)
    out = 0
    for a in range(boundary.rank):
        dim = 1 + a
        d2 = (
            p.narrow(dim, 2, p.shape[dim] - 2)
            - 2 * p.narrow(dim, 1, p.shape[dim] - 2)
            + p.narrow(dim, 0, p.shape[dim] - 2)
        )
        for b in range(boundary.rank):
            if b != a:
                d2 = d2.narrow(1 + b, 1, d2.shape[1 + b] - 2)
        out = out + d2 / dx[a] ** 2
    return out


def kinetic_energy(velocity: StaggeredGrid) -> torch.Tensor:
    """Per-sample ``E = sum_i mean(u_i^2)`` over the face values of each component (the E5 ``mean(v^2)``).

    Args:
        velocity: MAC velocity.

    Returns:
        ``(B,)`` tensor, differentiable.
    """
    _check_velocity(velocity)
    return sum(c.flatten(1).pow(2).mean(1) for c in velocity.values)


def normalize_energy(velocity: StaggeredGrid, energy: torch.Tensor) -> StaggeredGrid:
    """Rescale each sample of ``velocity`` so that :func:`kinetic_energy` equals ``energy``.

    Args:
        velocity: MAC velocity.
        energy: Target energies ``(B,)`` (or a scalar). Samples at rest are left at rest.

    Returns:
        The rescaled velocity ``u * sqrt(energy / E(u))`` (differentiable in both arguments).
    """
    _check_velocity(velocity)
    e = kinetic_energy(velocity)
    target = torch.as_tensor(energy, dtype=e.dtype, device=e.device)
    if not all_finite(target) or bool((target.detach() < 0).any()):
        raise ParameterError(f"normalize_energy: the target energy must be finite and >= 0, got {energy!r}")
    tiny = torch.finfo(e.dtype).tiny
    factor = torch.where(e > tiny, torch.sqrt(target / e.clamp_min(tiny)), torch.ones_like(e))
    return velocity.with_values(tuple(c * factor.reshape(-1, *([1] * (c.ndim - 1))) for c in velocity.values))


def cfl_dt(velocity: StaggeredGrid, cfl: float = 0.5, *, max_dt: float = math.inf) -> float:
    """A stable time step from the Courant number: ``dt = cfl / max_b sum_i (max|u_i| / dx_i)``.

    Args:
        velocity: MAC velocity (all samples are considered; the most restrictive one decides).
        cfl: Courant number ``> 0`` (cells travelled per step); ``<= 1`` for explicit schemes, semi-Lagrangian
            advection is stable beyond but loses accuracy.
        max_dt: Upper limit, returned for a fluid at rest.

    Returns:
        The time step as a Python float.

    Raises:
        ParameterError: For a non-positive ``cfl`` or ``max_dt``.
        NonFiniteError: For a velocity containing NaN/Inf.
    """
    _check_velocity(velocity)
    cfl = check_positive(cfl, "cfl")
    if isinstance(max_dt, (str, bytes)) or not max_dt > 0:
        raise ParameterError(f"max_dt must be > 0, got {max_dt}")
    with torch.no_grad():
        rate = 0.0
        for i, c in enumerate(velocity.values):
            check_finite(c, f"velocity component {i}")
            rate = rate + c.flatten(1).abs().max(1).values / velocity.grid.dx[i]
        r = float(rate.max())
    return min(max_dt, cfl / r) if r > 0 else max_dt


# ---- time steps -----------------------------------------------------------------------------------------


def navier_stokes_step(
    velocity: StaggeredGrid,
    dt,
    *,
    viscosity: float = 0.0,
    advection: str = "semi_lagrangian",
    viscosity_scheme: str = "explicit",
    force: StaggeredGrid | None = None,
    obstacles=None,
    solve: Solve | None = None,
    pressure_guess: CenteredGrid | torch.Tensor | None = None,
    energy_normalization: bool = False,
) -> tuple[StaggeredGrid, CenteredGrid]:
    """One incompressible Navier-Stokes step: advect, force, diffuse, project (and optionally renormalise).

    ``u* = A(u; u, dt) + dt f`` (then 0 on faces touching obstacles, so that viscosity sees resting
    obstacles), ``u** = diffuse(u*)``, ``u_new, p = make_incompressible(u**)``; with
    ``energy_normalization`` the result is rescaled to the kinetic energy of ``u`` (E5 of the paper).
    First order in time (operator splitting); second order in space with MacCormack advection.

    Args:
        velocity: MAC velocity ``(B, *face_shape(i))`` per component.
        dt: Time step ``>= 0``.
        viscosity: Kinematic viscosity ``>= 0`` (0 skips diffusion).
        advection: ``'semi_lagrangian'`` or ``'maccormack'`` self-advection.
        viscosity_scheme: ``'explicit'`` or ``'implicit'`` (see :func:`diffuse_velocity`).
        force: Optional body force (acceleration) as a StaggeredGrid on the same grid.
        obstacles: Obstacles (see :func:`make_incompressible`).
        solve: CG settings of the masked pressure solve and of implicit viscosity.
        pressure_guess: Previous pressure, the warm start of the CG pressure solve.
        energy_normalization: Rescale the result to ``kinetic_energy(velocity)``.

    Returns:
        ``(velocity, pressure)`` after the step.

    Raises:
        ParameterError: For invalid parameters or schemes.
        GridMismatchError: If ``velocity``/``force`` are not matching StaggeredGrids.
        SolveError: If a CG solve does not converge.
    """
    _check_velocity(velocity)
    dt = check_dt(dt)
    if advection not in SCHEMES:
        raise ParameterError(f"unknown advection scheme {advection!r}; choose one of {SCHEMES}")
    e0 = kinetic_energy(velocity) if energy_normalization else None
    v = advect(velocity, velocity, dt, scheme=advection)
    if force is not None:
        _check_velocity(force, "force")
        v = v + dt * force
    return _finish_step(v, dt, e0, viscosity, viscosity_scheme, obstacles, solve, pressure_guess)


def _finish_step(v, dt, e0, viscosity, viscosity_scheme, obstacles, solve, pressure_guess):
    """The part of a step after advection and forcing: obstacle faces, viscosity, projection, energy."""
    if obstacles is not None:
        v = _zero_obstacle_faces(v, obstacles)
    if float(viscosity) != 0:
        v = diffuse_velocity(v, dt, viscosity=viscosity, scheme=viscosity_scheme,
                             solve=solve if viscosity_scheme == "implicit" else None)
    v, p = make_incompressible(v, obstacles, solve=solve, pressure_guess=pressure_guess)
    if e0 is not None:
        v = normalize_energy(v, e0)
    return v, p


@dataclass(frozen=True, eq=False)
class FluidState:
    """The state of a smoke-like simulation.

    Attributes:
        velocity: MAC velocity.
        marker: Passive scalar (smoke density / temperature) as a scalar CenteredGrid, or None.
        pressure: Last pressure (warm start of the next CG solve), or None.
        time: Simulated time.
    """

    velocity: StaggeredGrid
    marker: CenteredGrid | None = None
    pressure: CenteredGrid | None = None
    time: float = 0.0


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
) -> FluidState:
    """Advance a smoke simulation by ``dt``: marker transport, buoyancy, Navier-Stokes step.

    Order: ``marker <- A(marker; u) + dt * source`` (zeroed inside obstacles), ``u <- A(u; u)``, buoyancy
    from the new marker, zero velocity on faces touching obstacles, viscosity, projection (warm-started
    from ``state.pressure``), optional energy rescaling.

    Args:
        state: Current :class:`FluidState`.
        dt: Time step ``>= 0``.
        viscosity: Kinematic viscosity.
        buoyancy_strength: Buoyancy per unit marker (see :func:`buoyancy`); needs a marker.
        buoyancy_direction: "Up" vector (default the last axis).
        advection: ``'semi_lagrangian'`` or ``'maccormack'`` (for the marker and the velocity).
        viscosity_scheme: ``'explicit'`` or ``'implicit'``.
        marker_source: Marker added per unit time (an inflow), CenteredGrid or tensor ``(B or 1, *res)``.
        obstacles: Obstacles (see :func:`make_incompressible`).
        solve: CG settings.
        energy_normalization: Rescale the velocity to its energy at the start of the step.

    Returns:
        The new state (``time + dt``).

    Raises:
        ParameterError, ShapeError, GridMismatchError, SolveError: See the functions it composes.
    """
    dt = check_dt(dt)
    v0 = state.velocity
    _check_velocity(v0)
    if advection not in SCHEMES:
        raise ParameterError(f"unknown advection scheme {advection!r}; choose one of {SCHEMES}")
    e0 = kinetic_energy(v0) if energy_normalization else None
    marker = state.marker
    if marker is not None:
        marker = advect(marker, v0, dt, scheme=advection)
        if marker_source is not None:
            src, _ = _scalar_values(marker_source, marker.grid)
            marker = marker + dt * src.to(dtype=marker.dtype, device=marker.device)
        solid = obstacle_mask(obstacles, v0.grid, v0.device)
        if solid is not None:
            marker = marker * (~solid).to(marker.dtype)
    elif buoyancy_strength != 0:
        raise ParameterError("buoyancy_strength needs a marker in the state")
    v = advect(v0, v0, dt, scheme=advection)
    if marker is not None and buoyancy_strength != 0:
        v = buoyancy(v, marker, dt, strength=buoyancy_strength, direction=buoyancy_direction)
    v, p = _finish_step(v, dt, e0, viscosity, viscosity_scheme, obstacles, solve, state.pressure)
    return replace(state, velocity=v, marker=marker, pressure=p, time=state.time + float(dt))
