"""Poisson solves on uniform grids: a fast direct spectral solver and masked-domain PCG.

The discrete problem is ``∇²_h u = f`` with the standard second-order stencil (3 points per axis,
``(u_{i-1} - 2 u_i + u_{i+1}) / dx²``) on cell centres. Boundary values sit on the cell **face**
(phisim's convention, see :mod:`phisim.boundary`): a Dirichlet value ``v`` gives the ghost
``2 v - u_0``, a Neumann flux ``g`` (outward normal derivative) gives ``u_0 + g dx``. Each axis has a
``(lower, upper)`` pair of kinds, and the zero-value problem along it is diagonalised exactly by

==================  ===========  =================================================  ==========
lower / upper       transform    eigenvalue of mode ``k = 0..n-1`` (times dx²)     inverse
==================  ===========  =================================================  ==========
periodic            FFT          ``-4 sin²(π k / n)``                               iFFT
Dirichlet/Dirichlet DST-II       ``-4 sin²(π (k+1) / 2n)``                          DST-III/2n
Neumann/Neumann     DCT-II       ``-4 sin²(π k / 2n)``                              DCT-III/2n
Dirichlet/Neumann   DST-IV       ``-4 sin²(π (2k+1) / 4n)``                         DST-IV/2n
Neumann/Dirichlet   DCT-IV       ``-4 sin²(π (2k+1) / 4n)``                         DCT-IV/2n
==================  ===========  =================================================  ==========

so the solve is a forward transform, a division by the summed eigenvalues and the inverse transform:
``O(N log N)``, exact up to round-off (about 1e-13 relative in float64). Non-zero boundary values
enter the right-hand side: ``f_0 -= 2 v / dx²`` (Dirichlet) and ``f_0 -= g / dx`` (Neumann) in the
boundary cell. The solve is differentiable w.r.t. ``f`` and the boundary values (the operator is
symmetric, and the transforms' adjoints are transforms of the same family; see :mod:`phisim.spectral.fft`).

**Singular problems.** When no axis has a Dirichlet side (all periodic / Neumann), the operator
annihilates constants. A solution exists only if the effective right-hand side has zero sum
(``Σ f = Σ boundary fluxes / dx``). The solver checks this per sample: a mean within
``compat_rtol`` of the rhs's RMS is round-off and is removed; a larger one is reported by
``incompatible='raise'`` (default, :class:`~phisim.errors.ParameterError`), ``'warn'`` (warning, then
removed) or ``'project'`` (removed silently, at the caller's request). The returned solution is the
one with **zero mean**.

**Masked domains** (:func:`masked_poisson_solve`): cells where ``mask`` is False are obstacles,
excluded from the solve; the faces between fluid and obstacle cells are **zero-Neumann** (no flux —
what the pressure of an incompressible flow needs at solid obstacles), and the solution is 0 inside
obstacles. The system ``-∇²_h u = -f`` on the fluid cells is symmetric positive (semi-)definite and
is solved by :func:`phisim.solvers.linalg.cg` with the spectral solver of the obstacle-free box as
preconditioner (``M⁻¹ = mask · (-∇²_box)⁻¹ · mask``, symmetric positive definite on fluid cells).

Reference: the fast diagonalisation method, e.g. Schumann & Sweet (1988), "A direct method for the
solution of Poisson's equation with Neumann boundary conditions on a staggered grid of arbitrary
size", J. Comput. Phys. 75, and Strang (1999), "The discrete cosine transform", SIAM Review 41.
"""

from __future__ import annotations

import warnings
from typing import Any, NamedTuple

import torch

from phisim.checks import all_finite
from phisim.errors import BoundaryError, NonFiniteError, ParameterError, ShapeError
from phisim.field import CenteredGrid
from phisim.ops.stencil import (
    AXIS_KINDS,
    Kinds,
    boundary_source,
    check_rhs,
    laplace_zero,
    negative_laplacian,
    normalize_dx,
    normalize_kinds,
    stencil_laplacian,
)
from phisim.solvers.box import (
    apply_multiplier,
    is_singular,
    laplacian_eigenvalues,
    solve_multiplier,
    spectral_apply,
)
from phisim.solvers.linalg import Solve, SolveInfo
from phisim.solvers.masked import MaskedPoisson

__all__ = [
    "AXIS_KINDS",
    "normalize_kinds",
    "laplacian_eigenvalues",
    "stencil_laplacian",
    "negative_laplacian",
    "boundary_source",
    "spectral_poisson_solve",
    "spectral_apply",
    "masked_poisson_solve",
    "masked_poisson_solve_with_info",
    "Solved",
    "masked_laplacian",
    "solve_poisson",
    "solve_poisson_with_info",
    "field_kinds_and_values",
]

# ----------------------------------------------------------------------------------------------
# the direct solver


def _compat_tol(dtype: torch.dtype) -> float:
    return 1e-4 if dtype == torch.float32 else 1e-9


def _remove_mean(f: torch.Tensor, *, incompatible: str, compat_rtol: float | None, what: str) -> torch.Tensor:
    dims = tuple(range(1, f.ndim))
    mean = f.mean(dim=dims, keepdim=True)
    if incompatible == "project":  # removed silently: no diagnostics to compute
        return f - mean
    tol = _compat_tol(f.dtype) if compat_rtol is None else compat_rtol
    with torch.no_grad():
        rms = f.pow(2).mean(dim=dims).sqrt()
        bad = mean.flatten().abs() > tol * rms
    if bool(bad.any()):
        idx = [int(i) for i in torch.nonzero(bad).flatten()]
        ratio = (mean.flatten().abs() / rms.clamp_min(torch.finfo(f.dtype).tiny)).detach()
        msg = (
            f"{what}: the problem is singular (no Dirichlet side: solutions differ by a constant) and the "
            f"right-hand side including boundary fluxes is incompatible for samples {idx}: its mean is "
            f"{[f'{float(ratio[i]):.3g}' for i in idx]} x its RMS (tolerance {tol:g}). Its sum must equal the"
            " net boundary flux / dx. Fix the data, or pass incompatible='project' (remove the mean) or "
            "'warn'."
        )
        if incompatible == "raise":
            raise ParameterError(msg)
        if incompatible == "warn":
            warnings.warn(msg + " The mean was removed.", RuntimeWarning, stacklevel=3)
    return f - mean


def _check_incompatible(incompatible: str) -> None:
    if incompatible not in ("raise", "warn", "project"):
        raise ParameterError(f"incompatible must be 'raise', 'warn' or 'project', got {incompatible!r}")


def spectral_poisson_solve(
    rhs: torch.Tensor,
    dx=1.0,
    kinds="dirichlet",
    values=None,
    *,
    incompatible: str = "raise",
    compat_rtol: float | None = None,
    engine: str | None = None,
) -> torch.Tensor:
    """Solve ``∇²_h u = rhs`` directly on a rectangular grid (FFT / DST / DCT per axis).

    Exact up to round-off for the standard second-order stencil with boundary values on the cell face
    (see the module docstring for the transform per axis and the eigenvalues).

    Args:
        rhs: Right-hand side ``(B, *resolution)`` (1-3 spatial axes), float32/float64, any device.
        dx: Cell spacing, a float or one per axis.
        kinds: Per axis ``'periodic'``, ``'dirichlet'``, ``'neumann'`` or a ``(lower, upper)`` pair
            (e.g. ``('dirichlet', 'periodic')`` for a 2-D channel); a single string applies to all axes.
        values: None (zero boundary values) or per axis a ``(lower, upper)`` pair: the Dirichlet value
            on the face or the Neumann outward flux ``du/dn``; each None/0, a float, or a tensor
            broadcastable to the boundary slab (``rhs``'s shape with that axis of length 1).
        incompatible: For singular problems (no Dirichlet side): what to do when the effective rhs has
            a mean beyond ``compat_rtol`` x its RMS: ``'raise'`` (ParameterError), ``'warn'`` or
            ``'project'`` (remove the mean silently).
        compat_rtol: Tolerance of that check (default 1e-9 in float64, 1e-4 in float32).
        engine: FFT engine (see :func:`phisim.spectral.fft.resolve_engine`).

    Returns:
        ``u`` with ``rhs``'s shape, dtype and device; for singular problems the zero-mean solution.
        Differentiable w.r.t. ``rhs`` and tensor boundary values.

    Raises:
        ParameterError: Bad dtype/dx/option, or an incompatible rhs with ``incompatible='raise'``.
        BoundaryError: Invalid kinds or values.
        ShapeError: Wrong rhs rank or value shapes.
        NonFiniteError: NaN/Inf in ``rhs``.
    """
    rank = check_rhs(rhs)
    kinds = normalize_kinds(kinds, rank)
    dx = normalize_dx(dx, rank)
    _check_incompatible(incompatible)
    if not all_finite(rhs):
        raise NonFiniteError("spectral_poisson_solve: rhs contains NaN or Inf")
    f = rhs
    b = boundary_source(rhs, dx, kinds, values)
    if b is not None:
        f = f - b
    singular = is_singular(kinds)
    if singular:
        f = _remove_mean(f, incompatible=incompatible, compat_rtol=compat_rtol, what="spectral_poisson_solve")
    inv = solve_multiplier(tuple(rhs.shape[1:]), dx, kinds, rhs.device, rhs.dtype)
    return apply_multiplier(f, kinds, inv, engine, prescaled=True)


class Solved(NamedTuple):
    """A solution with the report of the solve that produced it."""

    #: The solution (tensor or field, as the function documents).
    solution: Any
    #: The :class:`~phisim.solvers.linalg.SolveInfo` of an iterative solve; None for an exact spectral solve.
    info: SolveInfo | None


# ----------------------------------------------------------------------------------------------
# masked domains


def _open_faces(mask: torch.Tensor, kinds: Kinds) -> list[torch.Tensor]:
    faces = []
    for a, (lo, _) in enumerate(kinds):
        dim = 1 + a
        n = mask.shape[dim]
        if lo == "periodic":
            faces.append(mask * torch.roll(mask, -1, dim))
        else:
            faces.append(mask.narrow(dim, 1, n - 1) * mask.narrow(dim, 0, n - 1))
    return faces


def masked_laplacian(u: torch.Tensor, mask: torch.Tensor, dx, kinds, values=None) -> torch.Tensor:
    """The stencil Laplacian on the fluid cells of a masked domain (zero flux through obstacle faces).

    Args:
        u: Tensor ``(B, *resolution)``.
        mask: Fluid indicator, bool or float, shape ``resolution`` or ``(B, *resolution)``; True = fluid.
        dx: Spacing (float or one per axis).
        kinds: Boundary kinds of the box (see :func:`normalize_kinds`).
        values: Boundary values of the box (see :func:`boundary_source`).

    Returns:
        ``∇²_h u`` on fluid cells (obstacle neighbours contribute no flux), 0 on obstacle cells.

    Raises:
        BoundaryError, ParameterError, ShapeError: For invalid arguments.
    """
    rank = check_rhs(u, "u")
    kinds = normalize_kinds(kinds, rank)
    dx = normalize_dx(dx, rank)
    m = _mask_tensor(mask, u)
    out = laplace_zero(u * m, dx, kinds, _open_faces(m, kinds)) * m
    b = boundary_source(u, dx, kinds, values)
    return out if b is None else out + b * m


def _mask_tensor(mask, like: torch.Tensor) -> torch.Tensor:
    try:
        m = torch.as_tensor(mask, device=like.device)
    except (TypeError, ValueError, RuntimeError) as exc:
        raise ParameterError(f"mask must be a bool or 0/1 array, got {type(mask).__name__}") from exc
    if m.ndim == like.ndim - 1:
        m = m[None]
    if (
        m.ndim != like.ndim
        or tuple(m.shape[1:]) != tuple(like.shape[1:])
        or m.shape[0] not in (1, like.shape[0])
    ):
        raise ShapeError(
            f"mask must have shape {tuple(like.shape[1:])} or (B, *resolution) matching "
            f"{tuple(like.shape)}, got {tuple(m.shape)}"
        )
    if m.dtype != torch.bool:
        if m.is_complex() or not bool(((m == 0) | (m == 1)).all()):
            raise ParameterError(
                "mask must hold only 0/1 (False/True): a cell is fluid or not; a fractional mask would "
                "silently scale the operator. Threshold it first, e.g. mask > 0.5"
            )
    return m.to(like.dtype)


def _mask_face_weights(m: torch.Tensor, kinds: Kinds) -> tuple[torch.Tensor, ...]:
    """0/1 face weights of a cell mask: open between two fluid cells and on Dirichlet sides of a fluid cell."""
    out = []
    for a, (lo, hi) in enumerate(kinds):
        dim, n = 1 + a, m.shape[1 + a]
        if lo == "periodic":
            wrap = m.narrow(dim, n - 1, 1) * m.narrow(dim, 0, 1)
            out.append(torch.cat([wrap, m.narrow(dim, 1, n - 1) * m.narrow(dim, 0, n - 1), wrap], dim))
            continue
        inner = m.narrow(dim, 1, n - 1) * m.narrow(dim, 0, n - 1)
        first = m.narrow(dim, 0, 1) if lo == "dirichlet" else torch.zeros_like(m.narrow(dim, 0, 1))
        last = m.narrow(dim, n - 1, 1) if hi == "dirichlet" else torch.zeros_like(m.narrow(dim, 0, 1))
        out.append(torch.cat([first, inner, last], dim))
    return tuple(out)


def masked_poisson_solve(
    rhs: torch.Tensor,
    mask: torch.Tensor,
    dx=1.0,
    kinds="neumann",
    values=None,
    *,
    solve=None,
    x0: torch.Tensor | None = None,
    preconditioner: str | None = "spectral",
    incompatible: str = "raise",
    compat_rtol: float | None = None,
    engine: str | None = None,
    return_info: bool = False,
) -> torch.Tensor:
    """Solve ``∇²_h u = rhs`` on the fluid cells of a box with obstacles by preconditioned CG.

    Obstacle cells (``mask`` False) are excluded; faces between fluid and obstacle cells are
    zero-Neumann (no flux), the box sides follow ``kinds``/``values``; ``u`` is 0 in obstacles. The
    solve is :class:`phisim.solvers.masked.MaskedPoisson` with 0/1 face weights (the same operator the
    fluid projection uses): CG on ``-∇²_h`` (symmetric positive (semi-)definite on fluid cells, identity
    on obstacle cells), preconditioned by the exact spectral inverse of the obstacle-free box.

    Every connected fluid region that reaches no Dirichlet side is singular on its own (a closed box, or a
    pocket enclosed by obstacles): its rhs mean is checked as in :func:`spectral_poisson_solve` (per
    region) and the solution has zero mean over each such region.

    Args:
        rhs: Right-hand side ``(B, *resolution)``, float32/float64.
        mask: Fluid indicator (bool/float), shape ``resolution`` or ``(B, *resolution)``.
        dx: Cell spacing (float or one per axis).
        kinds: Box boundary kinds (see :func:`normalize_kinds`); default all Neumann (a closed box).
        values: Box boundary values (see :func:`boundary_source`).
        solve: :class:`phisim.solvers.linalg.Solve` settings (default ``Solve()``: rtol 1e-5).
        x0: Optional start iterate.
        preconditioner: ``'spectral'`` (default) or None (plain CG).
        incompatible: ``'raise'``, ``'warn'`` or ``'project'`` (see :func:`spectral_poisson_solve`).
        compat_rtol: Tolerance of the compatibility check.
        return_info: Removed (only ``False`` is accepted): :func:`masked_poisson_solve_with_info` returns the
            solution with its :class:`~phisim.solvers.linalg.SolveInfo`.
        engine: FFT engine of the preconditioner.

    Returns:
        ``u`` (shape of ``rhs``). Differentiable w.r.t. ``rhs``
        (implicit adjoint solve).

    Raises:
        SolveError: CG did not converge.
        ParameterError, BoundaryError, ShapeError, NonFiniteError: For invalid input.
    """
    if return_info:
        _no_return_info({"return_info": True})
    return _masked_solve(rhs, mask, dx, kinds, values, solve=solve, x0=x0, preconditioner=preconditioner,
                         incompatible=incompatible, compat_rtol=compat_rtol, engine=engine).solution


def _masked_solve(rhs, mask, dx=1.0, kinds="neumann", values=None, *, solve=None, x0=None,
                  preconditioner="spectral", incompatible="raise", compat_rtol=None, engine=None) -> Solved:

    rank = check_rhs(rhs)
    kinds = normalize_kinds(kinds, rank)
    dx = normalize_dx(dx, rank)
    _check_incompatible(incompatible)
    if preconditioner not in ("spectral", None):
        raise ParameterError(f"preconditioner must be 'spectral' or None, got {preconditioner!r}")
    if not all_finite(rhs):
        raise NonFiniteError("masked_poisson_solve: rhs contains NaN or Inf")
    solve = Solve() if solve is None else solve
    m = _mask_tensor(mask, rhs)
    if bool((m.flatten(1).sum(1) == 0).any()):
        raise ParameterError("masked_poisson_solve: the mask has no fluid cell in some sample")

    f = rhs
    b = boundary_source(rhs, dx, kinds, values)
    if b is not None:
        f = f - b
    f = f * m
    op = MaskedPoisson(_mask_face_weights(m, kinds), dx, kinds, engine=engine, direct=False)
    if op.singular:  # every closed fluid region needs a compatible rhs of its own
        tol = _compat_tol(rhs.dtype) if compat_rtol is None else compat_rtol
        with torch.no_grad():
            z = (op.null > 0).to(f.dtype)
            count = z.flatten(2).sum(-1).clamp_min(1)
            mean = op.region_sums(f) / count
            rms = (op.region_sums(f**2) / count).sqrt()
            bad = (mean.abs() > tol * rms) & (count > 0) & (z.flatten(2).sum(-1) > 0)
        if bool(bad.any()):
            b_i, k_i = (int(v) for v in torch.nonzero(bad)[0])
            msg = (
                f"masked_poisson_solve: singular problem with an incompatible rhs: sample {b_i}, closed fluid "
                f"region {k_i + 1} of {op.null.shape[1]} (a pocket of "
                f"{int(count[min(b_i, count.shape[0] - 1), k_i])} cells, no Dirichlet side) has a rhs mean of "
                f"{float(mean[b_i, k_i]):.3g} (beyond {tol:g} x RMS {float(rms[b_i, k_i]):.3g}). Each region "
                "enclosed by obstacles and closed sides needs a zero net source of its own: fix the data, open "
                "the region, or pass incompatible='project'/'warn' "
                "(the mean of each region is then removed)."
            )
            if incompatible == "raise":
                raise ParameterError(msg)
            if incompatible == "warn":
                warnings.warn(msg, RuntimeWarning, stacklevel=2)
    x, info = op.solve(-f, solve=solve, x0=x0, preconditioned=preconditioner is not None)
    return Solved(x * m, info)


def masked_poisson_solve_with_info(rhs: torch.Tensor, mask: torch.Tensor, dx=1.0, kinds="neumann", values=None,
                                   **settings) -> Solved:
    """:func:`masked_poisson_solve` that also returns the report of its CG solve.

    Args:
        rhs, mask, dx, kinds, values: As :func:`masked_poisson_solve`.
        **settings: Its keyword settings (``solve``, ``x0``, ``preconditioner``, ``incompatible``,
            ``compat_rtol``, ``engine``).

    Returns:
        ``Solved(solution, info)``: the solution ``(B, *resolution)`` and its
        :class:`~phisim.solvers.linalg.SolveInfo`.
    """
    _no_return_info(settings)
    return _masked_solve(rhs, mask, dx, kinds, values, **settings)


def _no_return_info(settings: dict) -> None:
    if settings.pop("return_info", False):
        raise ParameterError("return_info was removed: the *_with_info functions return (solution, info)")


# ----------------------------------------------------------------------------------------------
# fields


def field_kinds_and_values(boundary, component: int | None = None) -> tuple[Kinds, tuple]:
    """Translate a :class:`phisim.boundary.Boundary` into per-side kinds and values.

    Each side's ghost rule for the quantity decides: an odd rule (Dirichlet, walls for a normal velocity)
    gives ``'dirichlet'`` with its face value, an even rule (Neumann, walls for a scalar, open)
    ``'neumann'`` with its outward flux, periodic stays periodic.

    Args:
        boundary: A :class:`phisim.boundary.Boundary`.
        component: ``None`` for a scalar; else the velocity component (normal to its own axis,
            tangential to the others).

    Returns:
        ``(kinds, values)`` as accepted by :func:`spectral_poisson_solve`.

    Raises:
        BoundaryError: For a rule this solver does not know.
    """
    kinds, values = [], []
    for axis, (lo, hi) in enumerate(boundary.sides):
        role = "scalar" if component is None else ("normal" if component == axis else "tangential")
        pk, pv = [], []
        for cond in (lo, hi):
            rule = cond.rule(role, component)
            if rule[0] == "periodic":
                pk.append("periodic")
                pv.append(None)
            elif rule[0] in ("odd", "even"):
                pk.append("dirichlet" if rule[0] == "odd" else "neumann")
                pv.append(rule[1])
            else:
                raise BoundaryError(f"boundary condition {cond!r} has an unknown ghost rule {rule!r}")
        kinds.append(tuple(pk))
        values.append(tuple(pv))
    return tuple(kinds), tuple(values)


def solve_poisson(
    rhs,
    *,
    mask=None,
    solve=None,
    incompatible: str = "raise",
    compat_rtol: float | None = None,
    engine: str | None = None,
    return_info: bool = False,
) -> CenteredGrid:
    """Solve ``∇² u = rhs`` for a scalar :class:`phisim.field.CenteredGrid`, boundary from the field.

    The solution takes the grid and boundary of ``rhs``: its boundary conditions (values on the cell
    face) are the ones the solution satisfies. Without ``mask`` the direct spectral solver is used
    (exact to round-off); with ``mask`` (True = fluid) masked PCG (:func:`masked_poisson_solve`).

    Args:
        rhs: Scalar CenteredGrid, values ``(B, *resolution)``.
        mask: Optional fluid indicator (``resolution`` or ``(B, *resolution)``), or a CenteredGrid of it.
        solve: :class:`phisim.solvers.linalg.Solve` settings for the masked solve.
        incompatible: Singular-problem policy (see :func:`spectral_poisson_solve`).
        compat_rtol: Tolerance of the compatibility check.
        engine: FFT engine.
        return_info: Removed (only ``False`` is accepted): :func:`solve_poisson_with_info` also returns the
            report.

    Returns:
        The solution as a CenteredGrid.

    Raises:
        ShapeError: For a vector field.
        ParameterError, BoundaryError, SolveError: See the tensor-level solvers.
    """
    if return_info:
        _no_return_info({"return_info": True})
    return solve_poisson_with_info(rhs, mask=mask, solve=solve, incompatible=incompatible, compat_rtol=compat_rtol,
                                   engine=engine).solution


def solve_poisson_with_info(rhs, *, mask=None, solve=None, incompatible: str = "raise",
                            compat_rtol: float | None = None, engine: str | None = None) -> Solved:
    """:func:`solve_poisson` that also returns the report of the solve.

    Args:
        rhs, mask, solve, incompatible, compat_rtol, engine: As :func:`solve_poisson`.

    Returns:
        ``Solved(solution, info)``: the CenteredGrid and the :class:`~phisim.solvers.linalg.SolveInfo` of the
        masked CG solve, or ``None`` for the exact spectral solve (no mask).
    """

    if not isinstance(rhs, CenteredGrid):
        raise ParameterError(
            f"solve_poisson expects a CenteredGrid, got {type(rhs).__name__}; "
            "use spectral_poisson_solve for tensors"
        )
    if rhs.values.ndim != rhs.grid.rank + 1:
        raise ShapeError(
            "solve_poisson needs a scalar field (B, *resolution); solve vector components separately"
        )
    kinds, values = field_kinds_and_values(rhs.boundary)
    dx = rhs.grid.dx
    if mask is None:
        u = spectral_poisson_solve(
            rhs.values, dx, kinds, values, incompatible=incompatible, compat_rtol=compat_rtol, engine=engine
        )
        return Solved(rhs.with_values(u), None)
    if isinstance(mask, CenteredGrid):
        mask = mask.values
    out = _masked_solve(rhs.values, mask, dx, kinds, values, solve=solve, incompatible=incompatible,
                        compat_rtol=compat_rtol, engine=engine)
    return Solved(rhs.with_values(out.solution), out.info)
