"""Second-order finite-difference operators on centred and staggered (MAC) fields, boundary-aware.

All stencils use ghost values from :mod:`phisim.boundary` (boundary values on the cell face).

Accuracy. In the interior every operator is second order. At a boundary cell the compact stencil with a
face-located value is exact for fields that continue across the face the way the ghost rule assumes
(odd about a Dirichlet value, even plus the prescribed flux about a Neumann face), and so second order for
smooth fields that satisfy the condition's symmetry; for a general smooth field its *local* truncation
error at the boundary cells is O(1) (Dirichlet) or O(dx) (Neumann), which is the standard situation for
this finite-volume stencil: the solution of a Poisson problem built from it still converges at second
order (tests measure both).

Shapes: scalar ``CenteredGrid`` ``(B, *res)``, vector ``(B, d, *res)``; ``StaggeredGrid`` component ``i``
``(B, *res)`` with ``res[i] + 1`` along axis ``i``.
"""

from __future__ import annotations

import torch

from phisim.boundary import SCALAR, Boundary, pad
from phisim.errors import ShapeError
from phisim.field import CenteredGrid, StaggeredGrid
from phisim.ops.stencil import laplace_fused

__all__ = ["gradient", "divergence", "laplace", "curl", "velocity_from_stream_function"]


def diff(x: torch.Tensor, dim: int) -> torch.Tensor:
    n = x.shape[dim]
    return x.narrow(dim, 1, n - 1) - x.narrow(dim, 0, n - 1)


def _central(padded: torch.Tensor, dim: int, dx: float) -> torch.Tensor:
    """Central difference along ``dim`` of an array padded by one ghost layer on that dim only."""
    n = padded.shape[dim]
    return (padded.narrow(dim, 2, n - 2) - padded.narrow(dim, 0, n - 2)) / (2 * dx)


def _require_scalar(f, what: str) -> None:
    if not isinstance(f, CenteredGrid) or f.is_vector:
        raise ShapeError(f"{what} needs a scalar CenteredGrid, got {f!r}")


def gradient(field: CenteredGrid, at: str = "center", boundary=None) -> CenteredGrid | StaggeredGrid:
    """Gradient of a scalar field.

    Args:
        field: Scalar ``CenteredGrid`` ``(B, *res)``.
        at: ``'center'``: central differences at cell centres, a vector ``CenteredGrid`` ``(B, d, *res)``;
            ``'face'``: ``(f_i - f_{i-1}) / dx`` on every face (boundary faces from the ghost cells), a
            ``StaggeredGrid`` (the MAC pressure gradient).
        boundary: Boundary of the result (default: the field's). Pass the velocity boundary when the
            result is combined with a velocity.

    Returns:
        The gradient, second order at cell centres (``'center'``) or face centres (``'face'``).

    Raises:
        ShapeError: If ``field`` is not a scalar ``CenteredGrid`` or ``at`` is unknown.
    """
    _require_scalar(field, "gradient")
    dx = field.grid.dx
    out_boundary = field.boundary if boundary is None else boundary
    if at == "face":
        comps = []
        for a in range(field.rank):
            p = pad(field.values, field.boundary, dx, 1, axes=[a])
            comps.append(diff(p, 1 + a) / dx[a])
        return StaggeredGrid(tuple(comps), field.grid, out_boundary)
    if at == "center":
        comps = [_central(pad(field.values, field.boundary, dx, 1, axes=[a]), 1 + a, dx[a]) for a in range(field.rank)]
        return CenteredGrid(torch.stack(comps, dim=1), field.grid, out_boundary)
    raise ShapeError(f"gradient: at must be 'center' or 'face', got {at!r}")


def divergence(field: StaggeredGrid | CenteredGrid) -> CenteredGrid:
    """Divergence of a vector field at cell centres.

    For a ``StaggeredGrid`` this is the exact MAC divergence ``sum_i (u_i[k+1] - u_i[k]) / dx_i`` (the flux
    balance of each cell; needs no ghosts). For a vector ``CenteredGrid`` it is the sum of central
    differences with boundary ghosts (normal components see the walls).

    Args:
        field: ``StaggeredGrid`` or vector ``CenteredGrid`` with one component per axis.

    Returns:
        Scalar ``CenteredGrid`` ``(B, *res)`` with the scalar boundary derived from the field's
        (``Boundary.for_scalar``).

    Raises:
        ShapeError: For scalar input or a wrong number of components.
    """
    if isinstance(field, StaggeredGrid):
        dx = field.grid.dx
        div = sum(diff(v, 1 + a) / dx[a] for a, v in enumerate(field.values))
        return CenteredGrid(div, field.grid, field.boundary.for_scalar())
    if not isinstance(field, CenteredGrid) or not field.is_vector or field.values.shape[1] != field.rank:
        raise ShapeError(f"divergence needs a StaggeredGrid or a vector CenteredGrid with d components, got {field!r}")
    dx = field.grid.dx
    total = 0
    for a in range(field.rank):
        p = pad(field.values, field.boundary, dx, 1, vector=True, axes=[a])[:, a]
        total = total + _central(p, 1 + a, dx[a])
    return CenteredGrid(total, field.grid, field.boundary.for_scalar())


def _laplace_padded(p: torch.Tensor, dims_dx: list[tuple[int, float]], core_shape) -> torch.Tensor:
    """Sum of second differences of an array padded by one layer on the listed dims."""
    out = 0
    for dim, dx in dims_dx:
        n = p.shape[dim]
        c = p.narrow(dim, 1, n - 2)
        lo = p.narrow(dim, 0, n - 2)
        hi = p.narrow(dim, 2, n - 2)
        d2 = (hi - 2 * c + lo) / (dx * dx)
        # crop the other padded dims back to the core
        for other, _ in dims_dx:
            if other != dim:
                d2 = d2.narrow(other, 1, d2.shape[other] - 2)
        out = out + d2
    return out


def _scalar_stencil(boundary: Boundary):
    """``(kinds, sources)`` of a scalar field's ghost rules when every side is periodic or has a ghost rule with a
    constant number (``('odd', v)``: ghost ``2v - u``; ``('even', g)``: ghost ``u + g dx``), else None (a tensor
    or varying value: the padded path). ``sources`` lists ``(axis, side, f)`` for the non-zero values, ``f(dx)`` the
    constant the value adds to the boundary cells (``2v/dx²`` or ``g/dx``)."""
    kinds, sources = [], []
    for a, pair in enumerate(boundary.sides):
        kind = []
        for side, cond in enumerate(pair):
            rule = cond.rule(SCALAR, None)
            if rule[0] == "periodic":
                kind.append("periodic")
                continue
            v = rule[1] if len(rule) > 1 else None
            if rule[0] not in ("odd", "even") or isinstance(v, bool) or not isinstance(v, (int, float)):
                return None
            kind.append("dirichlet" if rule[0] == "odd" else "neumann")
            if v != 0:
                sources.append((a, side, (lambda d, v=float(v): 2.0 * v / (d * d)) if rule[0] == "odd"
                                else (lambda d, v=float(v): v / d)))
        kinds.append(tuple(kind))
    return tuple(kinds), sources


def laplace(field: CenteredGrid | StaggeredGrid) -> CenteredGrid | StaggeredGrid:
    """The (2d+1)-point Laplacian, second order, with boundary ghosts.

    Args:
        field: Scalar or vector ``CenteredGrid`` (components are treated with their wall roles), or a
            ``StaggeredGrid`` (each component on its own faces; values on boundary faces are computed too,
            a projection or :meth:`StaggeredGrid.with_boundary_faces` resets walls).

    Returns:
        A field of the same kind, grid and boundary.
    """
    if not isinstance(field, (CenteredGrid, StaggeredGrid)):
        raise ShapeError(
            f"laplace needs a CenteredGrid or StaggeredGrid, got {type(field).__name__}; wrap a tensor as "
            "CenteredGrid(values, grid, boundary), or use phisim.solvers.poisson.stencil_laplacian for raw tensors"
        )
    dx = field.grid.dx
    rank = field.grid.rank
    if isinstance(field, StaggeredGrid):
        comps = []
        for i in range(rank):
            p = field.padded_component(i, 1)
            comps.append(_laplace_padded(p, [(1 + a, dx[a]) for a in range(rank)], None))
        return StaggeredGrid(tuple(comps), field.grid, field.boundary)
    if not isinstance(field, CenteredGrid):
        raise ShapeError(f"laplace needs a CenteredGrid or StaggeredGrid, got {type(field).__name__}")
    off = 2 if field.is_vector else 1
    if not field.is_vector or field.values.shape[1] != rank:
        plain = _scalar_stencil(field.boundary)
        if plain is not None:  # ghost values folded into the stencil: no padded copy
            kinds, sources = plain
            values = field.values
            if field.is_vector:  # generic multi-channel data: every channel as a scalar
                values = values.reshape(values.shape[0] * values.shape[1], *field.grid.resolution)
            lap = laplace_fused(values, tuple(float(d) for d in dx), kinds)
            for a, side, source in sources:
                n = lap.shape[1 + a]
                lap.narrow(1 + a, 0 if side == 0 else n - 1, 1).add_(source(dx[a]))
            return field.with_values(lap.reshape(field.values.shape))
    if field.is_vector and field.values.shape[1] != rank:
        # generic multi-channel data: every channel as a scalar
        b, c = field.values.shape[:2]
        flat = field.values.reshape(b * c, *field.grid.resolution)
        p = pad(flat, field.boundary, dx, 1)
        lap = _laplace_padded(p, [(1 + a, dx[a]) for a in range(rank)], None)
        return field.with_values(lap.reshape(field.values.shape))
    p = pad(field.values, field.boundary, dx, 1, vector=field.is_vector)
    lap = _laplace_padded(p, [(off + a, dx[a]) for a in range(rank)], None)
    return field.with_values(lap)


def curl(field: CenteredGrid | StaggeredGrid, at: str = "center"):
    """Curl (rotation) of a field.

    * 2-D ``StaggeredGrid`` ``(u, v)``: vorticity ``dv/dx - du/dy``. ``at='node'`` returns the exact MAC
      value on the cell corners as a tensor ``(B, nx + 1, ny + 1)`` (corners on the boundary use the
      velocity ghosts); ``at='center'`` averages the four corners into a scalar ``CenteredGrid``.
    * 2-D vector ``CenteredGrid``: central differences, a scalar ``CenteredGrid``.
    * 2-D scalar ``CenteredGrid`` (a stream function ``psi``): the velocity ``(dpsi/dy, -dpsi/dx)`` at
      cell centres, a vector ``CenteredGrid``.
    * 3-D vector ``CenteredGrid``: central differences, a vector ``CenteredGrid``; a 3-D
      ``StaggeredGrid`` is first averaged to the centres.

    Raises:
        ShapeError: For 1-D fields or unsupported combinations.
    """
    if not isinstance(field, (CenteredGrid, StaggeredGrid)):
        raise ShapeError(f"curl needs a CenteredGrid or StaggeredGrid, got {type(field).__name__}")
    rank = field.grid.rank
    dx = field.grid.dx
    if rank == 2 and isinstance(field, StaggeredGrid):
        u, v = field.values
        dv_dx = diff(field.padded_component(1, 1).narrow(2, 1, v.shape[2]), 1) / dx[0]
        du_dy = diff(field.padded_component(0, 1).narrow(1, 1, u.shape[1]), 2) / dx[1]
        w = dv_dx - du_dy  # (B, nx + 1, ny + 1)
        if at == "node":
            return w
        if at != "center":
            raise ShapeError(f"curl: at must be 'center' or 'node', got {at!r}")
        wc = 0.25 * (w[:, :-1, :-1] + w[:, 1:, :-1] + w[:, :-1, 1:] + w[:, 1:, 1:])
        return CenteredGrid(wc, field.grid, field.boundary.for_scalar())
    if isinstance(field, StaggeredGrid):
        field = field.at_centers()
    if not isinstance(field, CenteredGrid):
        raise ShapeError(f"curl needs a CenteredGrid or StaggeredGrid, got {type(field).__name__}")
    if rank == 2 and not field.is_vector:
        dpsi = gradient(field, "center").values
        return CenteredGrid(torch.stack([dpsi[:, 1], -dpsi[:, 0]], dim=1), field.grid, field.boundary)
    if not field.is_vector or field.values.shape[1] != rank or rank not in (2, 3):
        raise ShapeError(f"curl needs a 2-D/3-D vector field (or a 2-D scalar stream function), got {field!r}")

    def d(comp: int, axis: int) -> torch.Tensor:
        p = pad(field.values, field.boundary, dx, 1, vector=True, axes=[axis])[:, comp]
        return _central(p, 1 + axis, dx[axis])

    if rank == 2:
        return CenteredGrid(d(1, 0) - d(0, 1), field.grid, field.boundary.for_scalar())
    w = torch.stack([d(2, 1) - d(1, 2), d(0, 2) - d(2, 0), d(1, 0) - d(0, 1)], dim=1)
    return CenteredGrid(w, field.grid, field.boundary)


def velocity_from_stream_function(psi_nodes: torch.Tensor, grid, boundary) -> StaggeredGrid:
    """MAC velocity ``u = dpsi/dy``, ``v = -dpsi/dx`` from a 2-D stream function on the cell corners.

    The result is discretely divergence-free: its MAC divergence vanishes to round-off in every cell.

    Args:
        psi_nodes: ``(B, nx + 1, ny + 1)`` stream function values at the cell corners.
        grid: 2-D grid.
        boundary: Velocity boundary of the result.

    Returns:
        The staggered velocity.
    """
    if grid.rank != 2 or psi_nodes.ndim != 3 or tuple(psi_nodes.shape[1:]) != (grid.resolution[0] + 1,
                                                                                  grid.resolution[1] + 1):
        raise ShapeError(f"psi_nodes must have shape (B, nx + 1, ny + 1) for a 2-D grid, got {tuple(psi_nodes.shape)}")
    dx, dy = grid.dx
    u = diff(psi_nodes, 2) / dy
    v = -diff(psi_nodes, 1) / dx
    return StaggeredGrid((u, v), grid, Boundary.create(boundary, 2))
