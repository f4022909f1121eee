"""Boundary conditions per side of each axis, and how they pad cell-centred and face-centred arrays.

**Convention: boundary values sit on the domain boundary (the cell face)**, second-order accurate, as in a
finite-volume code. For a cell-centred array with interior values ``u_1, u_2, ...`` counted inward from a
boundary face, the ghost cells ``g_1, g_2, ...`` counted outward are

* ``Dirichlet(v)``: ``g_k = 2 v - u_k`` (odd reflection about the face; the linear interpolant is ``v`` on it);
* ``Neumann(f)``:   ``g_k = u_k + (2k - 1) dx f`` where ``f = du/dn`` is the *outward* normal derivative;
* ``Periodic()``:   values from the opposite end.

For a face-centred array sampled along its own normal axis (a MAC velocity component ``u_i`` along axis
``i``), sample ``0`` and sample ``n`` lie on the boundary faces; ghosts sit at distance ``k dx`` outside:
``g_k = 2 v - u_k`` (odd) or ``g_k = u_k + 2 k dx f`` (even).

Walls and open sides act differently on each *role* a quantity plays at that side:

================  ====================  ========================  ==========================
condition         scalar                normal velocity           tangential velocity
================  ====================  ========================  ==========================
Dirichlet(v)      value v               value v                   value v
Neumann(f)        flux f                flux f                    flux f
NoSlipWall(w)     zero flux             0                         wall velocity w (moving lid)
FreeSlipWall()    zero flux             0                         zero flux
Open()            zero flux             zero flux                 zero flux
Inflow(u)         value 0               u(x, t)                   u(x, t)
================  ====================  ========================  ==========================

The pressure of an incompressible flow takes zero flux wherever the normal velocity is prescribed (walls,
Dirichlet and Inflow sides), value 0 at open sides, and stays periodic: :meth:`Boundary.for_pressure`
derives it. An :class:`Open` side is the outflow: its velocity ghosts have zero normal derivative, so the
boundary faces are carried out of the domain by the advection step (a convective outflow with the local
velocity) and corrected by the projection against pressure 0.
"""

from __future__ import annotations

import inspect
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np
import torch

from phisim.errors import BoundaryError, NonFiniteError, ShapeError
from phisim.grid import AXIS_NAMES
from phisim.padding import fast_face_plan as _fast_face_plan
from phisim.padding import fast_plan as _fast_plan

__all__ = [
    "BoundaryCondition",
    "Periodic",
    "Dirichlet",
    "Neumann",
    "NoSlipWall",
    "FreeSlipWall",
    "Open",
    "Inflow",
    "Boundary",
    "pad",
    "pad_staggered_component",
    "set_boundary_faces",
]

SCALAR, NORMAL, TANGENTIAL = "scalar", "normal", "tangential"
#: Pad and set boundary faces by the cached gather plans of :mod:`phisim.padding` wherever every rule is
#: constant (bit-identical to the general per-side path, which tests select by setting this to False).
_FAST_PADDING = True
#: ... for arrays of at most this many samples per batch entry: the plans save per-operation overhead, which
#: dominates small grids, but a gather over the whole array costs more than the slice copies of the general
#: path on large ones (plume step at 256^2: semi-Lagrangian velocity 1.05 -> 1.7 ms, buoyancy 0.2 -> 0.32).
_FAST_PADDING_MAX = 20_000


def _fast_padding(shape) -> bool:
    """Whether the plans apply to an array whose per-sample shape is ``shape``."""
    return _FAST_PADDING and math.prod(shape) <= _FAST_PADDING_MAX


class BoundaryCondition:
    """Base class of the condition on one side of one axis."""

    name: str = "?"

    def rule(self, role: str, component: int | None) -> tuple:
        """The ghost rule for a quantity playing ``role`` at this side.

        Args:
            role: ``'scalar'``, ``'normal'`` (velocity component normal to this side) or ``'tangential'``.
            component: The vector component index (for per-component values), or ``None`` for scalars.

        Returns:
            ``('periodic',)``, ``('odd', value)`` (value on the face) or ``('even', flux)`` (outward flux).
        """
        raise NotImplementedError


def _component_value(value, component: int | None):
    if isinstance(value, (tuple, list)):
        if component is None:
            raise BoundaryError(f"a per-component boundary value {value} was applied to a scalar field")
        if component >= len(value):
            raise BoundaryError(f"boundary value {value} has no entry for component {component}")
        return float(value[component])
    return value


def _check_value(value, what: str, *, scalar_ok: bool = True) -> None:
    """Raise a BoundaryError/NonFiniteError unless ``value`` is a finite number, tuple of numbers or real array."""
    if isinstance(value, bool) or value is None or isinstance(value, (str, bytes)):
        raise BoundaryError(f"{what} must be a number, a tuple of numbers or a real tensor, got {value!r}")
    if isinstance(value, (tuple, list)):
        if not value:
            raise BoundaryError(f"{what} is an empty sequence; give one number per vector component")
        for v in value:
            if isinstance(v, bool) or not isinstance(v, (int, float, np.number)):
                raise BoundaryError(f"{what} must hold numbers, got {value!r}")
            if not math.isfinite(float(v)):
                raise NonFiniteError(f"{what} contains NaN or Inf: {value!r}")
        return
    if isinstance(value, (int, float, np.number)):
        if not scalar_ok:
            raise BoundaryError(f"{what} must be a vector (one number per axis), got the scalar {value!r}")
        if isinstance(value, complex) or not math.isfinite(float(value)):
            raise NonFiniteError(f"{what} must be a finite real number, got {value!r}")
        return
    if isinstance(value, np.ndarray):
        if value.dtype.kind not in "fiu":
            raise BoundaryError(f"{what} must be a real numeric array, got dtype {value.dtype}")
        if not np.isfinite(value).all():
            raise NonFiniteError(f"{what} contains NaN or Inf")
        return
    if isinstance(value, torch.Tensor):
        if value.is_complex() or value.dtype == torch.bool:
            raise BoundaryError(f"{what} must be a real tensor, got dtype {value.dtype}")
        if value.is_floating_point() and not bool(torch.isfinite(value.detach()).all()):
            raise NonFiniteError(f"{what} contains NaN or Inf")
        return
    raise BoundaryError(f"{what} must be a number, a tuple of numbers or a real tensor, got {type(value).__name__}")


@dataclass(frozen=True)
class Periodic(BoundaryCondition):
    """Periodic side: the domain wraps around. Must be used on both sides of an axis."""

    name = "periodic"

    def rule(self, role, component):
        """See :meth:`BoundaryCondition.rule`."""
        return ("periodic",)


@dataclass(frozen=True)
class Dirichlet(BoundaryCondition):
    """Prescribed value on the boundary face.

    Args:
        value: The boundary value: a float, a tuple (one per vector component) or a tensor broadcastable
            to the boundary slab ``(B, [C,] ...)`` with the normal axis of length 1.
    """

    value: object = 0.0
    name = "dirichlet"

    def __post_init__(self):
        _check_value(self.value, "Dirichlet value")

    def rule(self, role, component):
        """See :meth:`BoundaryCondition.rule`."""
        return ("odd", _component_value(self.value, component))


@dataclass(frozen=True)
class Neumann(BoundaryCondition):
    """Prescribed outward normal derivative ``du/dn = flux`` on the boundary face.

    Args:
        flux: Outward normal derivative (float, per-component tuple, or broadcastable tensor).
    """

    flux: object = 0.0
    name = "neumann"

    def __post_init__(self):
        _check_value(self.flux, "Neumann flux")

    def rule(self, role, component):
        """See :meth:`BoundaryCondition.rule`."""
        return ("even", _component_value(self.flux, component))


@dataclass(frozen=True)
class NoSlipWall(BoundaryCondition):
    """Solid wall: zero normal velocity, tangential velocity equal to the wall's (0 unless moving).

    Args:
        velocity: The wall velocity as a vector (one float per axis), e.g. ``(1.0, 0.0)`` for a lid
            moving in +x. Its component normal to the wall is ignored (walls do not move through
            themselves). ``None`` means a wall at rest. Scalars see a zero-flux wall.
    """

    velocity: tuple[float, ...] | None = None
    name = "no_slip"

    def __post_init__(self):
        if self.velocity is not None:
            if isinstance(self.velocity, (int, float, np.number)) and not isinstance(self.velocity, bool):
                raise BoundaryError(
                    f"NoSlipWall velocity must be a vector (one number per axis), e.g. (1.0, 0.0), got "
                    f"{self.velocity!r}"
                )
            if not isinstance(self.velocity, (tuple, list)):
                raise BoundaryError(f"NoSlipWall velocity must be a tuple of numbers, got {self.velocity!r}")
            _check_value(tuple(self.velocity), "NoSlipWall velocity")

    def rule(self, role, component):
        """See :meth:`BoundaryCondition.rule`."""
        if role == SCALAR:
            return ("even", 0.0)
        if role == NORMAL or self.velocity is None:
            return ("odd", 0.0)
        return ("odd", _component_value(tuple(self.velocity), component))


@dataclass(frozen=True)
class FreeSlipWall(BoundaryCondition):
    """Slip wall: zero normal velocity, zero normal derivative of the tangential velocity."""

    name = "free_slip"

    def rule(self, role, component):
        """See :meth:`BoundaryCondition.rule`."""
        return ("odd", 0.0) if role == NORMAL else ("even", 0.0)


@dataclass(frozen=True)
class Open(BoundaryCondition):
    """Open / outflow side: zero normal derivative for every quantity (pressure 0 in the projection)."""

    name = "open"

    def rule(self, role, component):
        """See :meth:`BoundaryCondition.rule`."""
        return ("even", 0.0)


class BoundaryProfile:
    """Boundary values that vary along a side: one tensor per sample layout, picked by the array's shape.

    A MAC component is sampled on faces along its own axis and at cell centres along the others, so the
    same physical profile needs a differently shaped tensor for a face-centred and a cell-centred array.
    :func:`pad` and :func:`set_boundary_faces` pick the tensor that broadcasts against the boundary slab.

    Args:
        candidates: Tensors of shape ``(1, *slab)`` with length 1 along the side's normal axis.
    """

    def __init__(self, *candidates: torch.Tensor):
        self.candidates = candidates

    def match(self, like: torch.Tensor) -> torch.Tensor:
        """The candidate broadcastable to ``like`` (same length on every axis but the normal one)."""
        for c in self.candidates:
            if c.ndim == like.ndim and all(a == 1 or a == b for a, b in zip(c.shape[1:], like.shape[1:])):
                return c.to(dtype=like.dtype, device=like.device)
        raise BoundaryError(
            f"a boundary profile resolved for slabs {[tuple(c.shape) for c in self.candidates]} does not fit an "
            f"array slab of shape {tuple(like.shape)}; resolve the boundary on this grid (Boundary.at)"
        )


def _match(value, like: torch.Tensor):
    return value.match(like) if isinstance(value, BoundaryProfile) else value


@dataclass(frozen=True)
class Inflow(BoundaryCondition):
    """Prescribed velocity on a side (an inflow), constant or varying in space and time.

    The normal component sets the flux through the side; the projection leaves it as given (the pressure
    has zero flux there, see :meth:`Boundary.for_pressure`). The tangential components are imposed on the
    face too (no-slip with respect to the given velocity). Scalars (a marker) enter with value 0.

    Args:
        velocity: A number (the velocity component along the side's axis, signed: ``Inflow(1.0)`` on the
            lower x side blows towards +x), a vector (one float per axis), a float tensor of either form
            (e.g. one that requires grad: gradients then flow to it), or a callable ``f(x)`` or
            ``f(x, t)`` mapping boundary points ``(..., d)`` (and the time) to velocities ``(..., d)``,
            e.g. a parabolic channel profile. Callables are evaluated on the grid by :meth:`Boundary.at`
            (fields do that when they are created; the fluid step at each new time).
        time: The time at which a callable was evaluated (set by :meth:`Boundary.at`).

    Raises:
        BoundaryError: For a non-finite or malformed velocity.
    """

    velocity: object = 0.0
    time: float = 0.0
    profile: object = field(default=None, compare=False, repr=False)
    name = "inflow"

    def __post_init__(self):
        v = self.velocity
        if callable(v):
            return
        if isinstance(v, torch.Tensor):  # a tensor (e.g. one that requires grad): a number or a vector
            if v.ndim > 1 or not v.is_floating_point() or not bool(torch.isfinite(v.detach()).all()):
                raise BoundaryError(f"Inflow velocity tensor must be finite, scalar or 1-D, got {v!r}")
            if v.ndim == 1:
                object.__setattr__(self, "velocity", tuple(v.unbind(0)))
            return
        if isinstance(v, (tuple, list)):
            try:
                vals = tuple(float(x) for x in v)
            except (TypeError, ValueError) as exc:
                raise BoundaryError(f"Inflow velocity {v!r} must hold numbers") from exc
            if not all(math.isfinite(x) for x in vals):
                raise BoundaryError(f"Inflow velocity {v!r} must be finite")
            object.__setattr__(self, "velocity", vals if not any(isinstance(x, torch.Tensor) for x in v) else tuple(v))
            return
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(float(v)):
            raise BoundaryError(
                f"Inflow velocity must be a finite number, a vector or a callable f(x[, t]), got {v!r}"
            )
        object.__setattr__(self, "velocity", float(v))

    @property
    def varying(self) -> bool:
        """Whether the velocity is a callable (needs :meth:`Boundary.at` to be evaluated)."""
        return callable(self.velocity)

    def rule(self, role, component):
        """See :meth:`BoundaryCondition.rule`."""
        if role == SCALAR:
            return ("odd", 0.0)
        v = self.velocity
        if callable(v):
            if self.profile is None:
                raise BoundaryError(
                    "this Inflow's velocity is a function; evaluate it on the grid with Boundary.at(grid, t) "
                    "(fields created with it do so automatically)"
                )
            return ("odd", self.profile[component])
        if isinstance(v, tuple):
            return ("odd", v[component] if isinstance(v[component], torch.Tensor) else _component_value(v, component))
        return ("odd", v if role == NORMAL else 0.0)

    def normal_velocity(self, axis: int):
        """The constant normal velocity component (None for a callable velocity)."""
        v = self.velocity
        if callable(v):
            return None
        return v[axis] if isinstance(v, tuple) else v

    def resolved(self, grid, axis: int, side: int, time: float, dtype=None, device=None) -> Inflow:
        """This inflow evaluated on ``grid`` at ``time`` (a copy holding the boundary profiles).

        Args:
            grid: The :class:`~phisim.grid.Grid`.
            axis: The axis whose side this is.
            side: 0 (lower) or 1 (upper).
            time: Simulation time passed to ``f(x, t)``.
            dtype, device: Of the profile tensors (default float64 / CPU).

        Raises:
            BoundaryError: If the function returns the wrong shape or non-finite values.
        """
        if not callable(self.velocity):
            return self
        dtype = dtype or torch.float64
        fn = self.velocity
        try:
            nargs = len([p for p in inspect.signature(fn).parameters.values()
                         if p.kind in (p.POSITIONAL_ONLY, p.POSITIONAL_OR_KEYWORD)])
        except (TypeError, ValueError):
            nargs = 1
        bound = grid.bounds[axis][side]
        per_comp = []
        for c in range(grid.rank):
            cands = []
            for staggered in (True, False):
                coords = []
                for a in range(grid.rank):
                    if a == axis:
                        coords.append(torch.tensor([bound], dtype=torch.float64))
                    elif staggered and a == c:
                        coords.append(grid.face_coords(a, torch.float64))
                    else:
                        coords.append(grid.center_coords(a, torch.float64))
                pts = torch.stack(torch.meshgrid(*coords, indexing="ij"), -1)
                val = fn(pts, time) if nargs >= 2 else fn(pts)
                val = torch.as_tensor(val, dtype=torch.float64)
                if val.shape != pts.shape:
                    raise BoundaryError(
                        f"the Inflow function must return velocities of shape (..., {grid.rank}) for points "
                        f"(..., {grid.rank}); got {tuple(val.shape)} for {tuple(pts.shape)}"
                    )
                if not bool(torch.isfinite(val).all()):
                    raise BoundaryError(f"the Inflow function returned NaN/Inf at t={time}")
                cands.append(val[..., c].unsqueeze(0).to(dtype=dtype, device=device))
            per_comp.append(BoundaryProfile(*cands))
        return Inflow(self.velocity, float(time), tuple(per_comp))

    def flux(self, grid, axis: int, side: int, time: float | None = None) -> float:
        """Volume flux into the domain through this side (area-weighted normal velocity), as a float."""
        inflow = self.resolved(grid, axis, side, self.time if time is None else time)
        slab = torch.zeros((1, *[1 if a == axis else n for a, n in enumerate(grid.resolution)]), dtype=torch.float64)
        un = slab + _match(inflow.rule(NORMAL, axis)[1], slab)
        area = math.prod(d for a, d in enumerate(grid.dx) if a != axis)
        sign = 1.0 if side == 0 else -1.0
        return sign * float(un.sum()) * area


_NAMES = {
    "periodic": Periodic,
    "dirichlet": Dirichlet,
    "zero": Dirichlet,
    "neumann": Neumann,
    "wall": NoSlipWall,
    "no_slip": NoSlipWall,
    "noslip": NoSlipWall,
    "free_slip": FreeSlipWall,
    "freeslip": FreeSlipWall,
    "slip": FreeSlipWall,
    "open": Open,
    "outflow": Open,
    "inflow": Inflow,
}


def _condition(spec) -> BoundaryCondition:
    if isinstance(spec, BoundaryCondition):
        return spec
    if isinstance(spec, str):
        key = spec.strip().lower().replace("-", "_")
        if key not in _NAMES:
            raise BoundaryError(
                f"unknown boundary condition {spec!r}; known names: {sorted(set(_NAMES))}, or pass a "
                "BoundaryCondition such as Dirichlet(1.0)"
            )
        return _NAMES[key]()
    raise BoundaryError(f"cannot interpret {spec!r} as a boundary condition")


def _side_pair(spec) -> tuple[BoundaryCondition, BoundaryCondition]:
    if isinstance(spec, (tuple, list)):
        if len(spec) != 2:
            raise BoundaryError(f"a per-axis boundary pair needs (lower, upper), got {spec!r}")
        return _condition(spec[0]), _condition(spec[1])
    c = _condition(spec)
    return c, c


@dataclass(frozen=True)
class Boundary:
    """The boundary conditions of a domain: one ``(lower, upper)`` pair of conditions per axis.

    Build it with :meth:`create` from a name (``'periodic'``, ``'dirichlet'``, ``'neumann'``, ``'wall'``,
    ``'free_slip'``, ``'open'``), a condition (``Dirichlet(1.0)``), a per-axis sequence, or a mapping
    ``{'x': 'periodic', 'y': ('wall', NoSlipWall(velocity=(1.0, 0.0)))}``.

    Raises:
        BoundaryError: For unknown names, missing axes, or periodic on only one side of an axis.
    """

    sides: tuple[tuple[BoundaryCondition, BoundaryCondition], ...]

    def __post_init__(self):
        if not isinstance(self.sides, tuple) or not 1 <= len(self.sides) <= 3:
            raise BoundaryError(f"Boundary needs one (lower, upper) pair per axis (1-3 axes), got {self.sides!r}")
        rank = len(self.sides)
        for axis, pair in enumerate(self.sides):
            if not isinstance(pair, tuple) or len(pair) != 2 or not all(
                    isinstance(c, BoundaryCondition) for c in pair):
                raise BoundaryError(f"axis {axis}: expected a (lower, upper) pair of conditions, got {pair!r}")
            for c in pair:
                vec = c.velocity if isinstance(c, NoSlipWall) else getattr(c, "value", getattr(c, "flux", None))
                if isinstance(vec, (tuple, list)) and len(vec) != rank:
                    raise BoundaryError(
                        f"axis {AXIS_NAMES[axis]}: the per-component value {tuple(vec)} of {c.name} has "
                        f"{len(vec)} entries for a {rank}-D domain; give one per axis"
                    )
        for axis, (lo, hi) in enumerate(self.sides):
            if isinstance(lo, Periodic) != isinstance(hi, Periodic):
                raise BoundaryError(
                    f"axis {AXIS_NAMES[axis]}: periodic must be used on both sides, got {lo.name}/{hi.name}"
                )

    @classmethod
    def create(cls, spec, rank: int) -> Boundary:
        """Build a boundary for a ``rank``-dimensional domain from a flexible specification.

        Args:
            spec: A ``Boundary``, a condition or its name (all sides), a sequence with one entry per axis
                (each a condition or a ``(lower, upper)`` pair), or a mapping from axis name/index to such.
            rank: Number of spatial axes.

        Returns:
            The boundary.

        Raises:
            BoundaryError: If the specification is unknown, incomplete or inconsistent.
        """
        if isinstance(rank, bool) or not isinstance(rank, (int, np.integer)) or not 1 <= rank <= 3:
            raise BoundaryError(f"rank must be 1, 2 or 3, got {rank!r}")
        if isinstance(spec, Boundary):
            if spec.rank != rank:
                raise BoundaryError(f"boundary is {spec.rank}-D but the grid is {rank}-D")
            return spec
        if isinstance(spec, Mapping):
            keys = {}
            for k, v in spec.items():
                idx = AXIS_NAMES.index(k) if isinstance(k, str) and k in AXIS_NAMES else k
                if not isinstance(idx, int) or not 0 <= idx < rank:
                    raise BoundaryError(f"boundary mapping key {k!r} is not an axis of a {rank}-D grid")
                keys[idx] = v
            missing = [AXIS_NAMES[a] for a in range(rank) if a not in keys]
            if missing:
                raise BoundaryError(f"boundary mapping misses axes {missing}")
            return cls(tuple(_side_pair(keys[a]) for a in range(rank)))
        if isinstance(spec, (list, tuple)):
            if len(spec) != rank:
                raise BoundaryError(f"boundary sequence has {len(spec)} entries for a {rank}-D grid")
            return cls(tuple(_side_pair(s) for s in spec))
        c = _condition(spec)
        return cls(tuple((c, c) for _ in range(rank)))

    @property
    def rank(self) -> int:
        """Number of axes."""
        return len(self.sides)

    def is_periodic(self, axis: int) -> bool:
        """Whether ``axis`` is periodic."""
        return isinstance(self.sides[axis][0], Periodic)

    @property
    def periodic_axes(self) -> tuple[bool, ...]:
        """Per axis, whether it is periodic."""
        return tuple(self.is_periodic(a) for a in range(self.rank))

    def at(self, grid, time: float = 0.0, dtype=None, device=None) -> Boundary:
        """This boundary with every :class:`Inflow` function evaluated on ``grid`` at ``time``.

        Args:
            grid: The grid the boundary is used on.
            time: Simulation time.
            dtype, device: Of the evaluated profiles.

        Returns:
            ``self`` when nothing varies, else a boundary whose inflows hold their profiles.
        """
        if not any(isinstance(c, Inflow) and c.varying for pair in self.sides for c in pair):
            return self
        sides = []
        for a, pair in enumerate(self.sides):
            sides.append(tuple(c.resolved(grid, a, s, time, dtype, device) if isinstance(c, Inflow) else c
                               for s, c in enumerate(pair)))
        return Boundary(tuple(sides))

    def on(self, grid) -> Boundary:
        """This boundary with every not yet evaluated :class:`Inflow` function evaluated on ``grid`` at its
        own ``time`` (fields call this when they are created)."""
        if not any(isinstance(c, Inflow) and c.varying and c.profile is None for pair in self.sides for c in pair):
            return self
        sides = []
        for a, pair in enumerate(self.sides):
            sides.append(tuple(c.resolved(grid, a, s, c.time) if isinstance(c, Inflow) and c.profile is None
                               else c for s, c in enumerate(pair)))
        return Boundary(tuple(sides))

    def on_grid(self, grid, dtype=None, device=None) -> Boundary:
        """This boundary with every varying :class:`Inflow` (re-)evaluated on ``grid`` at its own time: a field
        moved to another resolution (:meth:`~phisim.field.StaggeredGrid.resampled`) takes its boundary this way."""
        if not any(isinstance(c, Inflow) and c.varying for pair in self.sides for c in pair):
            return self
        sides = []
        for a, pair in enumerate(self.sides):
            sides.append(tuple(c.resolved(grid, a, s, c.time, dtype, device) if isinstance(c, Inflow) and c.varying
                               else c for s, c in enumerate(pair)))
        return Boundary(tuple(sides))

    @property
    def has_open_side(self) -> bool:
        """Whether some side is :class:`Open` (the pressure is then fixed there, no compatibility needed)."""
        return any(isinstance(c, Open) for pair in self.sides for c in pair)

    def for_pressure(self) -> Boundary:
        """Boundary of the pressure of a flow with this velocity boundary.

        Open sides give pressure 0 (the projection corrects the normal velocity there); every side whose
        normal velocity is prescribed (walls, :class:`Dirichlet` and :class:`Inflow` velocities, Neumann
        sides) gives zero pressure flux, so the projection leaves the prescribed boundary faces as they are
        and the cells beside them become divergence-free; periodic stays periodic.
        """

        def conv(c: BoundaryCondition) -> BoundaryCondition:
            if isinstance(c, Periodic):
                return c
            if isinstance(c, Open):
                return Dirichlet(0.0)
            return Neumann(0.0)

        return self._memo("pressure", lambda: Boundary(tuple((conv(lo), conv(hi)) for lo, hi in self.sides)))

    def __hash__(self):
        h = self.__dict__.get("_hash")
        if h is None:
            h = hash(self.sides)
            object.__setattr__(self, "_hash", h)
        return h

    def __getstate__(self):
        return {k: v for k, v in self.__dict__.items() if k not in ("_derived", "_hash")}

    def _memo(self, key, make):
        """``make()`` computed once per boundary object (derived boundaries, padding plans)."""
        memo = self.__dict__.get("_derived")
        if memo is None:
            memo = {}
            object.__setattr__(self, "_derived", memo)
        hit = memo.get(key)
        if hit is None:
            hit = memo[key] = make()
        return hit

    def for_scalar(self) -> Boundary:
        """Boundary for a scalar quantity (e.g. a marker) transported in a flow with this boundary.

        Walls and open sides give zero flux, inflows bring clean fluid (value 0); Dirichlet/Neumann/periodic
        are kept.
        """

        def conv(c: BoundaryCondition) -> BoundaryCondition:
            if isinstance(c, Inflow):
                return Dirichlet(0.0)
            return Neumann(0.0) if isinstance(c, (NoSlipWall, FreeSlipWall, Open)) else c

        return self._memo("scalar", lambda: Boundary(tuple((conv(lo), conv(hi)) for lo, hi in self.sides)))

    def __repr__(self) -> str:
        parts = []
        for a, (lo, hi) in enumerate(self.sides):
            parts.append(f"{AXIS_NAMES[a]}={lo!r}" if lo == hi else f"{AXIS_NAMES[a]}=({lo!r}, {hi!r})")
        return "Boundary(" + ", ".join(parts) + ")"


# ---- padding ------------------------------------------------------------------------------------------


def _ghosts(inside: torch.Tensor, rule: tuple, dim: int, spacing: torch.Tensor | None) -> torch.Tensor:
    """Ghosts g_1..g_w (ordered outward) from mirror samples u_1..u_w (ordered inward) along ``dim``."""
    kind = rule[0]
    if kind == "odd":
        v = _match(rule[1], inside)
        return 2 * v - inside if not (isinstance(v, (int, float)) and v == 0) else -inside
    f = rule[1]
    if isinstance(f, (int, float)) and f == 0:
        return inside
    return inside + f * spacing


def _spacing(width: int, dim: int, ndim: int, dx: float, face: bool, like: torch.Tensor) -> torch.Tensor:
    k = torch.arange(1, width + 1, dtype=like.dtype, device=like.device)
    dist = (2 * k if face else 2 * k - 1) * dx
    shape = [1] * ndim
    shape[dim] = width
    return dist.reshape(shape)


def _pad_axis(x, dim, n, width, lo_rule, hi_rule, dx, face):
    """Pad one axis of ``x`` (length ``n`` cells; ``n + 1`` samples if ``face``) by ``width`` ghosts per side."""
    if width == 0:
        return x
    if width > n:
        raise ShapeError(f"cannot pad {width} ghost layers onto an axis of {n} cells")
    length = x.shape[dim]
    if lo_rule[0] == "periodic":
        lo = x.narrow(dim, n - width, width)
        hi = x.narrow(dim, 1 if face else 0, width)
        return torch.cat([lo, x, hi], dim=dim)
    start = 1 if face else 0
    lo_in = x.narrow(dim, start, width).flip(dim)  # u_w .. u_1 (outermost first after flip of ghosts)
    hi_in = x.narrow(dim, length - start - width, width)  # u_w .. u_1 reading outward
    sp = None
    if lo_rule[0] == "even" or hi_rule[0] == "even":
        sp = _spacing(width, dim, x.ndim, dx, face, x)
    # lower ghosts in array order: g_w .. g_1 ; inside in matching order u_w .. u_1
    lo_g = _ghosts(lo_in, lo_rule, dim, None if sp is None else sp.flip(dim))
    hi_g = _ghosts(hi_in.flip(dim), hi_rule, dim, sp)  # g_1 .. g_w
    return torch.cat([lo_g, x, hi_g], dim=dim)


def _role(axis: int, component: int | None) -> str:
    if component is None:
        return SCALAR
    return NORMAL if component == axis else TANGENTIAL


def pad(
    values: torch.Tensor,
    boundary: Boundary,
    dx: Sequence[float],
    width: int = 1,
    *,
    vector: bool = False,
    axes: Sequence[int] | None = None,
) -> torch.Tensor:
    """Pad a cell-centred array with ghost cells according to ``boundary``.

    Args:
        values: ``(B, *res)`` for a scalar field, ``(B, d, *res)`` for a vector field with ``d == rank``
            (component ``c`` is normal to axis ``c``).
        boundary: The boundary conditions.
        dx: Cell spacing per axis (Neumann fluxes are scaled by it).
        width: Ghost layers per side.
        vector: Whether ``values`` carries a component axis.
        axes: Which spatial axes to pad (default all). Axes are padded in order, so corner ghosts are
            consistent with the sides.

    Returns:
        The padded array, each padded axis ``2 * width`` longer.

    Raises:
        ShapeError: If the array does not fit the boundary's rank, is too small for ``width`` or has an empty
            batch (batch size 0).
    """
    rank = boundary.rank
    expected = rank + (2 if vector else 1)
    if values.ndim != expected:
        raise ShapeError(
            f"expected a {'vector' if vector else 'scalar'} array with {expected} dims (batch"
            f"{', component' if vector else ''}, {rank} spatial), got shape {tuple(values.shape)}"
        )
    if values.shape[0] == 0:
        raise ShapeError("pad: values have an empty batch (batch size 0); pass at least one sample")
    axes = tuple(range(rank)) if axes is None else tuple(axes)
    if width and (not vector or values.shape[1] == rank) and _fast_padding(values.shape[1:]):
        plan = _fast_plan(values, boundary, dx, width, axes, None if not vector else rank,
                          tuple(values.shape[2 if vector else 1:]), None)
        if plan is not None:
            return plan(values)
    if not vector:
        out = values
        for a in axes:
            lo, hi = boundary.sides[a]
            dim = 1 + a
            out = _pad_axis(out, dim, values.shape[dim], width, lo.rule(SCALAR, None), hi.rule(SCALAR, None),
                            dx[a], False)
        return out
    if values.shape[1] != rank:
        raise ShapeError(f"vector array has {values.shape[1]} components, the grid is {rank}-D")
    comps = []
    for c in range(rank):
        comp = values[:, c]
        for a in axes:
            lo, hi = boundary.sides[a]
            dim = 1 + a
            role = _role(a, c)
            comp = _pad_axis(comp, dim, values.shape[2 + a], width, lo.rule(role, c), hi.rule(role, c), dx[a], False)
        comps.append(comp)
    return torch.stack(comps, dim=1)


def pad_staggered_component(
    values: torch.Tensor,
    component: int,
    boundary: Boundary,
    dx: Sequence[float],
    width: int = 1,
    axes: Sequence[int] | None = None,
) -> torch.Tensor:
    """Pad MAC component ``component`` (normal to its faces) with ghost samples on every axis.

    Along its own axis the samples include both boundary faces and ghosts sit at ``k dx`` beyond them
    (odd reflection about the face value for walls/Dirichlet, even for open/Neumann). Along the other
    axes the component is cell-centred and behaves as a tangential velocity.

    Args:
        values: ``(B, *face_shape(component))``.
        component: The velocity component / face normal axis.
        boundary: Velocity boundary.
        dx: Cell spacing per axis.
        width: Ghost layers per side.
        axes: Which spatial axes to pad (default all).

    Returns:
        The padded array.
    """
    rank = boundary.rank
    if values.ndim != rank + 1:
        raise ShapeError(f"staggered component must have shape (B, *face_shape), got {tuple(values.shape)}")
    if values.shape[0] == 0:
        raise ShapeError("pad_staggered_component: values have an empty batch (batch size 0); pass at least one "
                         "sample")
    axes = tuple(range(rank)) if axes is None else tuple(axes)
    if width and _fast_padding(values.shape[1:]):
        plan = _fast_plan(values, boundary, dx, width, axes, None, tuple(values.shape[1:]), component)
        if plan is not None:
            return plan(values)
    out = values
    for a in axes:
        lo, hi = boundary.sides[a]
        role = _role(a, component)
        n = values.shape[1 + a] - (1 if a == component else 0)
        out = _pad_axis(out, 1 + a, n, width, lo.rule(role, component), hi.rule(role, component), dx[a],
                        a == component)
    return out


def set_boundary_faces(values: torch.Tensor, component: int, boundary: Boundary) -> torch.Tensor:
    """Impose the boundary on the normal velocity stored on the boundary faces of MAC component ``component``.

    Walls get 0, Dirichlet sides their value, periodic axes copy face 0 onto face ``n``; open and Neumann
    sides are left as they are (the flow determines them).

    Args:
        values: ``(B, *face_shape(component))``.
        component: The component / axis.
        boundary: Velocity boundary.

    Returns:
        A new array with the boundary faces set.
    """
    lo, hi = boundary.sides[component]
    dim = 1 + component
    n = values.shape[dim] - 1
    plan = _fast_padding(values.shape[1:]) and boundary._memo(
        ("faces", component, values.ndim, n, values.dtype, values.device),
        lambda: _fast_face_plan(lo, hi, component, values.ndim, n, values.dtype, values.device))
    if plan:
        return plan(values)
    if isinstance(lo, Periodic):
        first = values.narrow(dim, 0, 1)
        return torch.cat([values.narrow(dim, 0, n), first], dim=dim)
    parts = [None, values.narrow(dim, 1, n - 1), None]
    for idx, (cond, pos) in enumerate(((lo, 0), (hi, n))):
        face = values.narrow(dim, pos, 1)
        r = cond.rule(NORMAL, component)
        if r[0] == "odd":
            face = torch.zeros_like(face) + _match(r[1], face)
        parts[0 if idx == 0 else 2] = face
    return torch.cat(parts, dim=dim)
