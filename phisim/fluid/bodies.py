"""Bodies in the flow: resting cell-mask obstacles and moving, no-slip or free-slip geometric bodies.

Two kinds of solid exist:

* :class:`Obstacle` -- a resting staircase obstacle: a cell is solid when its centre lies inside (box,
  sphere or a boolean cell mask). Faces touching a solid cell are closed (weight 0), so the body is made
  of whole cells. Cheap and exact for shapes aligned with the grid.
* :class:`Body` -- a :class:`~phisim.fluid.geometry.Geometry` (signed distance) with an optional prescribed
  motion (translation and rotation, constant or functions of time) and a wall condition (no-slip or
  free-slip). Each MAC face gets its *fluid fraction* ``theta``: the fluid part of the face's control
  volume (a cell-sized square/cube centred on the face), from the signed distance with
  :func:`~phisim.fluid.geometry.fluid_fraction`. Fractions vary smoothly as the body moves or changes
  shape, so forces and the flow near the body converge under refinement instead of staircasing.

How the fractions enter the fluid solver (:mod:`phisim.fluid.projection`): the projection enforces
``D(theta u + (1 - theta) u_s) = 0`` with the weighted pressure operator ``D(theta G p)`` (Batty, Bertails &
Bridson 2007; Ng, Min & Gibou 2009). A no-slip body (``sharp=True``, the default) keeps the fluid velocity on the
faces it cuts, uses the exact wetted area of each face as ``theta``, adds the flux of the linear wall profile that
the blend misses (``extension``) and enters the viscous stencil at its true surface (``walls``): second order. A
blended no-slip body (``sharp=False``) stores ``theta u + (1 - theta) u_s`` on every face (first order); a
free-slip body only closes the flux and keeps the fluid velocity on cut faces.

:func:`solid_layout` rasterises a set of solids once per grid (and per time for moving bodies) into a
:class:`SolidLayout`; static layouts are cached.
"""

from __future__ import annotations

import itertools
import math
from collections import OrderedDict
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace

import torch

from phisim.boundary import Boundary, Inflow
from phisim.errors import BoundaryError, ParameterError, ShapeError
from phisim.fluid.geometry import Geometry, cut_centroid, cut_fractions, floats, fluid_fraction, rotation_matrix
from phisim.grid import Grid
from phisim.ops.tensors import sum_last, unravel

__all__ = ["Obstacle", "Body", "SolidLayout", "solid_layout", "obstacle_mask", "open_face_masks"]


# ---- resting cell-mask obstacles ---------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class Obstacle:
    """A solid, resting staircase obstacle: a box, a sphere (disc in 2-D) or an arbitrary boolean cell mask.

    Build it with :meth:`box`, :meth:`sphere` or :meth:`from_mask`. A cell is solid when its centre lies
    inside the geometry (boundary included). Faces touching a solid cell carry zero normal velocity, and
    (no-slip) zero tangential velocity. For bodies that converge under refinement use :class:`Body`.

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
            ParameterError: If ``lower`` and ``upper`` differ in length, hold NaN/Inf, or ``upper < lower``.
        """
        lo, hi = tuple(float(v) for v in lower), tuple(float(v) for v in upper)
        if len(lo) != len(hi) or any(h < l for l, h in zip(lo, hi)) or not all(map(math.isfinite, lo + hi)):
            raise ParameterError(f"Obstacle.box needs finite lower <= upper with one entry per axis, got {lo}, {hi}")
        return cls("box", (lo, hi))

    @classmethod
    def sphere(cls, center: Sequence[float], radius: float) -> Obstacle:
        """A ball ``|x - center| <= radius`` (a disc in 2-D).

        Raises:
            ParameterError: If ``radius`` is not positive and finite or the centre is not finite.
        """
        r = float(radius)
        c = tuple(float(v) for v in center)
        if not (math.isfinite(r) and r > 0) or not all(map(math.isfinite, c)):
            raise ParameterError(f"Obstacle.sphere needs a finite centre and radius > 0, got {center}, {radius}")
        return cls("sphere", (c, r))

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
            if tuple(m.shape[m.ndim - grid.rank :]) != grid.resolution or m.ndim not in (grid.rank, grid.rank + 1):
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


# ---- moving geometric bodies --------------------------------------------------------------------------------


def _const_vector(v, rank: int | None, name: str):
    if v is None or callable(v):
        return v
    if isinstance(v, torch.Tensor):
        if not bool(torch.isfinite(v.detach()).all()):
            raise ParameterError(f"Body {name} contains NaN or Inf")
        return v
    vals = tuple(float(x) for x in (v if isinstance(v, (tuple, list)) else (v,)))
    if not all(map(math.isfinite, vals)):
        raise ParameterError(f"Body {name} must be finite, got {v!r}")
    if rank is not None and len(vals) != rank:
        raise ParameterError(f"Body {name} needs {rank} entries, got {v!r}")
    return vals


class Body:
    """A rigid body in the flow: a geometry, its motion and its wall condition.

    Motion is prescribed, in one of two forms: constant ``velocity`` / ``angular_velocity`` (the body then
    sits at ``center + velocity * t`` rotated by ``angular_velocity * t``), or functions of time ``path(t)``
    (the displacement of the reference point :attr:`Geometry.center`) and ``rotation(t)`` (2-D: an angle;
    3-D: a rotation vector or matrix); their velocities are taken by central differences in time.
    Rotation is about the geometry's reference point. A body without motion is static: its fractions are
    computed once per grid.

    Args:
        geometry: A :class:`~phisim.fluid.geometry.Geometry`.
        velocity: Constant translation velocity (one entry per axis), or None.
        angular_velocity: Constant angular velocity: a float in 2-D (counter-clockwise), a vector in 3-D.
        path: ``path(t) -> displacement`` (sequence or tensor of ``d`` entries), instead of ``velocity``.
        rotation: ``rotation(t) -> angle`` (2-D) or rotation vector / matrix (3-D), instead of
            ``angular_velocity``.
        no_slip: True: the fluid takes the body's velocity at its surface; False: free-slip (only the
            normal flux through the surface is closed, with exact wetted fractions and the flux correction of
            :func:`phisim.fluid.extension.free_slip_flux`; the viscous step reads ghost values of the free-slip
            condition inside, :func:`phisim.fluid.extension.free_slip_ghosts`). Measured on a rigid rotation:
            within 0.2-1 % of the wall speed, not yet converging at single faces (docs/VALIDATION.md).
        name: A label used in outputs (forces, files).
        sharp: How a no-slip body imposes its velocity. True (default): sharply, at the true surface: cut faces
            keep the fluid velocity and the viscous stencil of every fluid face next to the body takes the body's
            velocity at the point where the stencil's arm crosses the surface (second order, see
            :class:`SolidLayout` ``walls``). False: blended over the cut faces, ``theta u + (1 - theta) u_s``
            (about one cell wide, first order; the method before the sharp one).

    Raises:
        ParameterError: For non-finite values, wrong lengths, or both a constant and a function motion.
    """

    def __init__(self, geometry: Geometry, *, velocity=None, angular_velocity=None,
                 path: Callable | None = None, rotation: Callable | None = None, no_slip: bool = True,
                 name: str | None = None, sharp: bool = True):
        if not isinstance(geometry, Geometry):
            raise ParameterError(f"Body needs a Geometry (Box, Sphere, RotatedBox, Union, SDF), got "
                                 f"{type(geometry).__name__}")
        if velocity is not None and path is not None:
            raise ParameterError("give a Body either a constant velocity or a path(t), not both")
        if angular_velocity is not None and rotation is not None:
            raise ParameterError("give a Body either a constant angular_velocity or a rotation(t), not both")
        for f, n in ((path, "path"), (rotation, "rotation")):
            if f is not None and not callable(f):
                raise ParameterError(f"Body {n} must be a function of time")
        self.geometry = geometry
        self.rank = geometry.rank
        self.velocity = _const_vector(velocity, self.rank, "velocity")
        wrank = 1 if self.rank == 2 else 3
        self.angular_velocity = _const_vector(angular_velocity, wrank, "angular_velocity")
        self.path, self.rotation = path, rotation
        self.no_slip = bool(no_slip)
        self.sharp = bool(sharp)
        self.name = name
        self._derived: OrderedDict = OrderedDict()

    def derived(self, key, make: Callable[[], torch.Tensor]) -> torch.Tensor:
        """A quantity derived from this resting body's geometry on a grid (e.g. its surface area vectors), made
        by ``make()`` and kept on the body (the 8 most recent keys); made anew for a moving body, and not kept
        when it depends on tensors requiring grad (shape parameters).

        Args:
            key: Hashable description (grid, dtype, device, what).
            make: Builds the quantity.

        Returns:
            The quantity.
        """
        if not self.static:
            return make()
        hit = self._derived.get(key)
        if hit is not None:
            self._derived.move_to_end(key)
            return hit
        value = make()
        if not value.requires_grad:
            self._derived[key] = value
            while len(self._derived) > 8:
                self._derived.popitem(last=False)
        return value

    @property
    def static(self) -> bool:
        """Whether the body rests (no velocity, rotation or path)."""
        return all(v is None for v in (self.velocity, self.angular_velocity, self.path, self.rotation))

    def _like(self):
        return torch.zeros((), dtype=torch.float64)

    def _offset(self, t: float, like: torch.Tensor) -> torch.Tensor:
        if self.path is not None:
            return torch.as_tensor(self.path(t), dtype=like.dtype).to(like.device).reshape(self.rank)
        if self.velocity is not None:
            return torch.as_tensor(self.velocity, dtype=like.dtype).to(like.device) * t
        return torch.zeros(self.rank, dtype=like.dtype, device=like.device)

    def _rotation(self, t: float, like: torch.Tensor) -> torch.Tensor | None:
        if self.rotation is not None:
            return rotation_matrix(self.rotation(t), self.rank, like)
        if self.angular_velocity is not None:
            w = torch.as_tensor(self.angular_velocity, dtype=like.dtype).to(like.device)
            return rotation_matrix(w.reshape(()) * t if self.rank == 2 else w * t, self.rank, like)
        return None

    def reference_point(self, t: float = 0.0, like: torch.Tensor | None = None) -> torch.Tensor:
        """Position of the reference point (centre of rotation) at time ``t``, shape ``(d,)``."""
        like = self._like() if like is None else like
        return torch.as_tensor(self.geometry.center, dtype=like.dtype).to(like.device) + self._offset(t, like)

    def sdf(self, x: torch.Tensor, t: float = 0.0) -> torch.Tensor:
        """Signed distance of the moved body at points ``x`` ``(..., d)`` at time ``t``."""
        if self.static:
            return self.geometry.sdf(x)
        c0 = torch.as_tensor(self.geometry.center, dtype=x.dtype).to(x.device)
        local = x - c0 - self._offset(t, x)
        r = self._rotation(t, x)
        if r is not None:
            local = local @ r
        return self.geometry.sdf(local + c0)

    def velocity_at(self, x: torch.Tensor, t: float = 0.0) -> torch.Tensor:
        """Rigid-body velocity ``V + omega x (x - c(t))`` at points ``x`` ``(..., d)``; shape ``(..., d)``."""
        v, w = self.motion(t, x)
        out = v.expand(x.shape)
        if w is None:
            return out
        r = x - self.reference_point(t, x)
        if self.rank == 2:
            return out + torch.stack([-w * r[..., 1], w * r[..., 0]], -1)
        return out + torch.linalg.cross(w.expand(r.shape), r, dim=-1)

    def motion(self, t: float = 0.0, like: torch.Tensor | None = None):
        """``(V, omega)`` at time ``t``: translation velocity ``(d,)`` and angular velocity (scalar in 2-D,
        ``(3,)`` in 3-D; None without rotation)."""
        like = self._like() if like is None else like
        h = 1e-6
        if self.path is not None:
            v = (self._offset(t + h, like) - self._offset(t - h, like)) / (2 * h)
        elif self.velocity is not None:
            v = torch.as_tensor(self.velocity, dtype=like.dtype).to(like.device)
        else:
            v = torch.zeros(self.rank, dtype=like.dtype, device=like.device)
        w = None
        if self.angular_velocity is not None:
            w = torch.as_tensor(self.angular_velocity, dtype=like.dtype).to(like.device)
            w = w.reshape(()) if self.rank == 2 else w
        elif self.rotation is not None:
            rp, rm = self._rotation(t + h, like), self._rotation(t - h, like)
            r0 = self._rotation(t, like)
            om = (rp - rm) / (2 * h) @ r0.T
            w = 0.5 * (om[1, 0] - om[0, 1]) if self.rank == 2 else 0.5 * torch.stack(
                [om[2, 1] - om[1, 2], om[0, 2] - om[2, 0], om[1, 0] - om[0, 1]])
        return v, w

    def bounding_box(self, t: float = 0.0):
        """Corners of a box containing the body at time ``t`` (floats)."""
        lo, hi = self.geometry.bounding_box()
        if self.static:
            return lo, hi
        off = list(floats(self._offset(t, self._like())))
        if self._rotation(t, self._like()) is not None:  # conservative: sphere around the reference point
            c = list(floats(self.geometry.center))
            rad = max(math.dist(c, corner) for corner in _corners(lo, hi))
            return tuple(ci + o - rad for ci, o in zip(c, off)), tuple(ci + o + rad for ci, o in zip(c, off))
        return tuple(a + o for a, o in zip(lo, off)), tuple(b + o for b, o in zip(hi, off))

    def __repr__(self):
        motion = "" if self.static else ", moving"
        return f"Body({self.geometry!r}{motion}, {'no-slip' if self.no_slip else 'free-slip'})"


def _corners(lo, hi):
    import itertools

    return list(itertools.product(*zip(lo, hi)))


# ---- rasterisation --------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class SolidLayout:
    """Solids rasterised on a grid at one time: what the projection, viscosity and forces need.

    Attributes:
        theta: Per MAC component ``i``, fluid fraction of each face ``(1 or B, *face_shape(i))``.
        solid_velocity: Per component, the solids' velocity on each face (None if every solid rests).
        slip: Per component, the share of the solid part of each face that belongs to bodies whose cut faces keep
            the fluid velocity: free-slip bodies and sharp no-slip bodies (None if there is none). The other
            solids' cut faces store the blend ``theta u + (1 - theta) u_s``.
        cell_fraction: Fluid fraction of each cell ``(1 or B, *res)``.
        bodies: The solids, in the order given.
        sharp: Per component, the share of the solid part of each face that belongs to sharp no-slip bodies (None
            without them).
        tangents: Per component, the stencil of the tangential pressure correction of the viscous wall values (None
            without sharp no-slip bodies; an entry None where no face has a wall arm): ``(index, weight, normal,
            neighbours)``: the flat indices of the faces with an arm to the surface, their weight ``sum 1 / (s
            dx_a^2)`` in ``source`` (a change ``g`` of the wall value of every arm of a face changes its Laplacian by
            ``g * weight``), the unit normal of the nearest body there, and per other component ``j`` the flat indices
            ``(P, 4)`` and weights of the four ``j`` faces around each face (those with a wetted part, ``theta > 0``:
            both diagonals, else the one diagonal pair that has it, else what has it; the weights sum to 1, or to 0
            when none has) (:func:`phisim.fluid.step.anticipate_pressure`).
        walls: Per component, the sharp no-slip condition of the viscous stencil (None without sharp no-slip
            bodies): ``(cut, coef, source)``, each ``(1 or B, *face_shape(i))``. ``cut`` marks the faces whose centre
            lies in a sharp body (``phi <= 0``): they are no unknowns of the viscous step, and the stencil of a fluid
            face ``F`` does not read them. For each arm of that stencil from ``F`` to a cut face (along axis ``a``)
            the surface crossing at the fraction ``s = phi_F / (phi_F - phi_N)`` of the arm takes its place: the
            linear ghost value ``u_w / s + (1 - 1 / s) u_F`` (Gibou, Fedkiw, Cheng & Kang 2002), so that
            ``L u = L_0 u - coef u + source`` with ``L_0`` the box stencil reading 0 on cut faces,
            ``coef = sum (1 / s - 1) / dx_a^2`` and ``source = sum u_w / (s dx_a^2)`` (``u_w`` the body's velocity
            at the crossing point; ``source`` None for resting bodies). Only the diagonal changes, so the
            operator stays symmetric.
        extension: Per component, the flux correction of the faces cut by sharp no-slip bodies (None without
            sharp bodies): ``(index, corners, weights, kappa, base)``. Face ``index[k]`` (a flat index into the
            component) gets the extra flux ``base[k] + kappa[k] * sum_j weights[k, j] u[corners[k, j]]``: the
            relative velocity ``u - u_s`` at a probe two cells out along the normal (multilinear weights of the
            component's faces around it) times ``kappa = (E[phi_+] - theta max(phi_F, 0)) / d`` — the mean wall
            profile ``g phi_+`` over the wetted face (``g`` = relative velocity at the probe over its distance
            ``d``) less the part ``theta u_F`` already carries (:func:`~phisim.fluid.projection.flux_correction`).
        time: The time the solids were rasterised at (where moving bodies are); what is evaluated later from the
            bodies' geometry (the free-slip flux correction) is evaluated at this time.
        solvers: ``None`` for a layout used once (a moving body at one instant, a call of a pure function):
            its solves are iterative. A dict for a layout that is used again and again (a stepper's static
            bodies, see :meth:`persistent`): the pressure operator and the viscous capacitance solves built
            for it are kept there, and the direct solves that pay off only when reused are used.
    """

    theta: tuple
    solid_velocity: tuple | None
    slip: tuple | None
    cell_fraction: torch.Tensor
    bodies: tuple
    solvers: dict | None = field(default=None, repr=False)
    walls: tuple | None = field(default=None, repr=False)
    extension: tuple | None = field(default=None, repr=False)
    sharp: tuple | None = field(default=None, repr=False)
    tangents: tuple | None = field(default=None, repr=False)
    time: float = 0.0

    def persistent(self, direct: bool | str = "auto") -> SolidLayout:
        """This layout marked for reuse: solvers built for it are kept on it.

        Args:
            direct: ``'auto'``: the direct solves that pay off when reused (the pressure's capacitance solve where
                it applies and pays, the viscous capacitance solves) are used; ``False``: iterative solves only.

        Layouts that depend on tensors requiring grad (shape parameters) stay one-off.
        """
        if direct not in ("auto", False):
            raise ParameterError(f"direct must be 'auto' or False, got {direct!r}")
        if any(t.requires_grad for t in self.theta):
            return self
        if self.solvers is not None and self.solvers.get("direct") == direct:
            return self
        return replace(self, solvers={"direct": direct})

    @property
    def direct(self) -> bool | str:
        """The direct-solve policy of a persistent layout (False for a one-off layout)."""
        return False if self.solvers is None else self.solvers["direct"]

    def to(self, dtype=None, device=None) -> SolidLayout:
        """A copy with tensors converted."""
        def cv(t):
            return None if t is None else t.to(dtype=dtype, device=device)

        def cvs(ts):
            return None if ts is None else tuple(cv(t) for t in ts)

        walls = None if self.walls is None else tuple(
            None if w is None else (w[0].to(device=device), cv(w[1]), cv(w[2])) for w in self.walls)
        extension = None if self.extension is None else tuple(
            None if e is None else (e[0].to(device=device), e[1].to(device=device), cv(e[2]), cv(e[3]), cv(e[4]))
            for e in self.extension)
        out = SolidLayout(cvs(self.theta), cvs(self.solid_velocity), cvs(self.slip), cv(self.cell_fraction),
                          self.bodies, walls=walls, extension=extension, sharp=cvs(self.sharp),
                          tangents=None if self.tangents is None else tuple(
                              None if w is None else (w[0].to(device=device), cv(w[1]), cv(w[2]),
                                                      tuple(None if nb is None else (nb[0].to(device=device), cv(nb[1]))
                                                            for nb in w[3])) for w in self.tangents),
                          time=self.time)
        return out if self.solvers is None else out.persistent(self.direct)


def sdf_gradient(body: Body, x: torch.Tensor, t: float, h: float) -> torch.Tensor:
    """``grad phi`` at points ``x`` ``(..., d)`` by central differences of step ``h`` (differentiable in the
    body's parameters); shape ``(..., d)``."""
    eye = torch.eye(x.shape[-1], dtype=x.dtype, device=x.device) * h
    return torch.stack([(body.sdf(x + e, t) - body.sdf(x - e, t)) / (2 * h) for e in eye], -1)


def unit_normal(body: Body, x: torch.Tensor, t: float, h: float) -> torch.Tensor:
    """Outward unit normal ``grad phi / |grad phi|`` at points ``x`` ``(..., d)``."""
    g = sdf_gradient(body, x, t, h)
    return g / g.norm(dim=-1, keepdim=True).clamp_min(1e-12)


#: Sub-faces per in-face axis (by dimension) of the wetted fraction of a FREE-SLIP body's faces, each a planar
#: cut. On a curved surface one planar cut of a face errs by ``O(kappa dx)`` of its area, and at the O(1) tangential
#: velocity a free-slip surface carries that is an ``O(kappa u)`` flux error in the cut cell, which held the free-slip
#: Couette flows near first order; ``m`` sub-faces divide it by ``m^2`` (docs/VALIDATION.md, "Free-slip bodies").
#: No-slip bodies keep one cut (their relative velocity vanishes at the surface).
FREE_SLIP_SUBFACES = {1: 1, 2: 8, 3: 4}

#: Sub-faces per in-face axis (by dimension) of a free-slip body's faces nearly parallel to its surface (the unit
#: normal's component along the face's axis at least ``FREE_SLIP_PARALLEL`` at the face centre, and the surface curved
#: there: a flat side parallel to the face is cut exactly by any count, see :func:`free_slip_cuts`). There the surface
#: crosses the face's plane in a tight curve (a sphere nearly tangent to the plane: a circle a few cells across) and a
#: sub-face may be cut off at a corner, where the curvature-corrected cut's error is largest; in 3-D these few faces
#: held the largest velocity error of the finest grids above its second-order trend (docs/VALIDATION.md, "Free-slip
#: bodies in 3-D"). About a fifth of a sphere's cut faces: 1.6 times the sub-cuts of ``FREE_SLIP_SUBFACES`` alone,
#: against 4 times for the fine count everywhere.
FREE_SLIP_FINE_SUBFACES = {1: 1, 2: 8, 3: 8}
#: Smallest component of the unit normal along a face's axis for ``FREE_SLIP_FINE_SUBFACES`` (see above).
FREE_SLIP_PARALLEL = 0.8


def body_fraction(body: Body, points: torch.Tensor, t: float, dx: float, axis: int | None = None) -> torch.Tensor:
    """Fluid fraction at ``points``: for sharp no-slip and free-slip bodies the exact fraction of a planar cut
    (:func:`~phisim.fluid.geometry.cut_fractions`) of the square/cube of side ``dx`` (``axis`` None) or of the face
    of side ``dx`` normal to ``axis`` (the wetted area of a MAC face; a free-slip body's faces within ``dx`` of
    its surface: the mean of its sub-faces' curvature-corrected cuts, :func:`free_slip_cuts`); for blended no-slip
    bodies the linear ramp of :func:`~phisim.fluid.geometry.fluid_fraction` over the control volume of side
    ``dx``.

    A sharp or free-slip body's fraction is cut only at the points within ``dx`` of its surface (the band, found from
    one evaluation of the signed distance): a planar cut with a unit normal is exactly 1 or 0 beyond
    ``dx (sqrt(d) + d 1e-3) / 2 < dx`` (:func:`~phisim.fluid.geometry.cut_fractions`), so the points outside take
    ``phi > 0`` directly, the same numbers as cutting every point (and the same gradients: zero there). On a grid of
    ``N^d`` points the band holds ``O(N^(d-1))``: the layout of a sphere on ``224 x 128 x 128`` cells is built 4.7
    times faster, a carried sphere's step on ``64^3`` cells 2.35 times (``docs/BENCHMARKS.md``, "Building body
    layouts"). A traced call (no host reads) cuts every point."""
    phi = body.sdf(points, t)
    if body.no_slip and not body.sharp:  # blended: the ramp's width depends on |grad phi|, not bounded by phi
        grad = sdf_gradient(body, points, t, 1e-3 * dx)
        return fluid_fraction(phi, sum_last(grad.abs()), dx)
    if torch.compiler.is_compiling() or points.dim() < 2:
        return _cut_fraction(body, points, phi, t, dx, axis)
    near = ~(phi.detach().abs() >= dx)  # NaN distances stay in the band (and give NaN fractions, as before)
    idx = near.nonzero(as_tuple=True)
    if 2 * idx[0].numel() > near.numel():  # mostly band: no gain from selecting
        return _cut_fraction(body, points, phi, t, dx, axis)
    theta = (phi.detach() > 0).to(phi.dtype)
    if idx[0].numel() == 0:
        return theta
    return theta.index_put(idx, _cut_fraction(body, points[idx], phi[idx], t, dx, axis))


def _cut_fraction(body: Body, points: torch.Tensor, phi: torch.Tensor, t: float, dx: float, axis: int | None
                  ) -> torch.Tensor:
    """:func:`body_fraction` of a sharp or free-slip body at every one of ``points`` (``phi`` the distance there)."""
    grad = sdf_gradient(body, points, t, 1e-3 * dx)
    theta = cut_fractions(phi, face_normal(grad, axis), dx)[0]
    m = FREE_SLIP_SUBFACES[points.shape[-1]]
    if axis is None or body.no_slip or m == 1:
        return theta
    band = phi.abs() < dx
    if torch.compiler.is_compiling():  # no host read in a traced step: every face, the band selected after
        return torch.where(band, free_slip_cuts(body, points, t, dx, axis, grad)[0], theta)
    idx = band.nonzero(as_tuple=True)
    return theta.index_put(idx, free_slip_cuts(body, points[idx], t, dx, axis, grad[idx])[0])


def planar_cut(phi: torch.Tensor, g: torch.Tensor, side: float) -> tuple[torch.Tensor, torch.Tensor]:
    """The wetted fraction and the wetted part's centroid of square faces of side ``side`` cut by the plane on which
    the signed distance, ``phi`` at the face centre, changes with the in-face gradient ``g`` ``(..., d)`` (the unit
    normal's part in the face; its own axis 0).

    Returns:
        ``(theta, centroid)``: :func:`~phisim.fluid.geometry.cut_fractions`' fraction, and the wetted part's centroid
        relative to the face centre (:func:`~phisim.fluid.geometry.cut_centroid`, exact: ``phi`` is linear over the
        face): along ``g / |g|`` it is ``(E[phi_+] / theta - phi) / |g|``; in 3-D it also has a component across
        ``g`` where the cut is not symmetric about ``g`` (a corner cut off).
    """
    theta, _, centroid = cut_centroid(phi, g, side)
    return theta, centroid


def curved_cut(body: Body, x: torch.Tensor, t: float, g: torch.Tensor, side: float, axis: int
               ) -> tuple[torch.Tensor, torch.Tensor]:
    """The wetted fraction and first moment of faces of side ``side`` normal to ``axis`` centred at ``x`` ``(..., d)``,
    from the planar cut with the in-face gradient ``g`` (:func:`planar_cut`) and one correction for the surface's
    curvature, read from the signed distance on the cut.

    The plane ``L`` on which the linear model ``phi(x) + g . y`` vanishes misses the surface by ``-phi(y) / |g|``
    along ``g`` (one Newton step), so the wetted area grows by ``int_L phi dl / |g|`` and its first moment by
    ``int_L y phi dl / |g|``. ``phi`` is quadratic along ``L`` to leading order, so Simpson's rule on the cut (its
    ends and middle: three evaluations of the distance; in 2-D ``L`` is one point) takes these integrals exactly
    there: the fraction's error falls from ``O(kappa side)`` to ``O(kappa^2 side^2)``, the moment's likewise
    (docs/VALIDATION.md, "Free-slip bodies"). The fraction is clamped to ``[0, 1]``.

    Returns:
        ``(theta, moment)``: the fraction ``(...)`` and ``theta`` times the wetted part's centroid relative to ``x``
        ``(..., d)``.
    """
    phi = body.sdf(x, t)
    theta, centroid = planar_cut(phi, g, side)
    moment = theta.unsqueeze(-1) * centroid
    gn2 = sum_last(g * g)
    flat = gn2 < 1e-18  # a face parallel to the surface: no cut line
    gn2 = torch.where(flat, torch.ones_like(gn2), gn2)
    gn = gn2.sqrt()
    foot = -(phi / gn2).unsqueeze(-1) * g  # the point of L nearest the face centre
    others = [a for a in range(x.shape[-1]) if a != axis]
    half = side / 2
    if len(others) == 1:  # 2-D: L is the point foot
        (b,) = others
        cut = ~flat & (foot[..., b].abs() < half)
        points, weights = [foot], [torch.where(cut, 1.0 / (gn * side), torch.zeros_like(gn))]
    else:  # 3-D: L is the segment foot + s tau, clipped to the face
        a, b = others
        tau = torch.zeros_like(g)
        tau[..., a], tau[..., b] = -g[..., b] / gn, g[..., a] / gn
        lo, hi = torch.full_like(phi, -2 * side), torch.full_like(phi, 2 * side)
        for k in (a, b):
            tk = tau[..., k]
            moves = tk.abs() > 1e-12
            tk = torch.where(moves, tk, torch.ones_like(tk))
            s1, s2 = (-half - foot[..., k]) / tk, (half - foot[..., k]) / tk
            within = foot[..., k].abs() < half
            lo = torch.where(moves, torch.maximum(lo, torch.minimum(s1, s2)), torch.where(within, lo, hi))
            hi = torch.where(moves, torch.minimum(hi, torch.maximum(s1, s2)), torch.where(within, hi, lo))
        length = torch.where(flat, torch.zeros_like(lo), (hi - lo).clamp_min(0.0))
        lo, hi = torch.where(length > 0, lo, 0.0), torch.where(length > 0, hi, 0.0)
        points = [foot + u.unsqueeze(-1) * tau for u in (lo, (lo + hi) / 2, hi)]
        w = length / (6 * gn * side * side)
        weights = [w, 4 * w, w]
    grow = torch.zeros_like(theta)
    for p, w in zip(points, weights):
        ph = body.sdf(x + p, t) * w
        grow = grow + ph
        moment = moment + ph.unsqueeze(-1) * p
    return (theta + grow).clamp(0.0, 1.0), moment


def subface_cuts(body: Body, points: torch.Tensor, t: float, dx: float, axis: int, m: int
                 ) -> tuple[torch.Tensor, torch.Tensor]:
    """The wetted fraction and the wetted part's centroid of the faces normal to ``axis`` centred at ``points``
    ``(..., d)``, from the curvature-corrected cuts (:func:`curved_cut`) of their ``m^(d-1)`` sub-faces of side
    ``dx / m`` (each cut at its own centre).

    Returns:
        ``(theta, centroid)``: the mean of the sub-faces' fractions ``(...)`` and the centroid of the wetted part
        relative to the face centre ``(..., d)`` (the sub-faces' moments over their fractions; the face centre where
        nothing is wetted). On a curved surface an uncorrected planar cut errs by ``O(kappa dx)`` in the fraction and
        places the centroid ``O(kappa dx^2 / |g|)`` off, which on faces nearly parallel to the surface (small ``|g|``)
        is a large part of the face; ``m`` sub-faces divide the planar cut's errors by ``m^2``, the correction takes
        them to second order.
    """
    rank = points.shape[-1]
    others = [a for a in range(rank) if a != axis]
    offsets = [((j + 0.5) / m - 0.5) * dx for j in range(m)]
    total = points.new_zeros(points.shape[:-1])
    moment = torch.zeros_like(points)
    # one row of m sub-faces along the last in-face axis at a time, batched in a new dimension before the last (the
    # traced graph grows with the rows, not with m^(d-1); the memory with faces times m)
    row = torch.zeros(m, rank, dtype=points.dtype, device=points.device)
    row[:, others[-1]] = torch.tensor(offsets, dtype=points.dtype, device=points.device)
    for combo in itertools.product(offsets, repeat=len(others) - 1):
        sh = row.clone()
        for a, o in zip(others[:-1], combo):
            sh[:, a] = o
        x = points.unsqueeze(-2) + sh
        theta, mom = curved_cut(body, x, t, face_normal(sdf_gradient(body, x, t, 1e-3 * dx), axis), dx / m, axis)
        total = total + theta.sum(-1)
        moment = moment + (theta.unsqueeze(-1) * sh + mom).sum(-2)
    centroid = torch.where((total > 0).unsqueeze(-1), moment / total.clamp_min(1e-12).unsqueeze(-1), 0.0)
    return total / m ** len(others), centroid.clamp(-dx / 2, dx / 2)


def free_slip_cuts(body: Body, points: torch.Tensor, t: float, dx: float, axis: int,
                   grad: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """The wetted fraction and the wetted part's centroid of a free-slip body's faces normal to ``axis`` centred at
    ``points`` ``(..., d)`` (those within a cell of its surface: the layout's fractions and the flux correction's
    centroids): :func:`subface_cuts` with ``FREE_SLIP_SUBFACES`` sub-faces per in-face axis, and
    ``FREE_SLIP_FINE_SUBFACES`` on the faces nearly parallel to a curved surface (``|n_axis| >= FREE_SLIP_PARALLEL``
    and the surface bending within the face, :func:`_bends_within`; a flat surface parallel to the face, such as the
    side of a box aligned with the grid, is cut exactly by any count). ``grad``: the signed distance's gradient at
    ``points`` where the caller has it (:func:`sdf_gradient`; taken here when None). Eager calls cut each face once,
    with its own count; a traced call (no host reads) cuts every face both ways and selects."""
    rank = points.shape[-1]
    m, fine = FREE_SLIP_SUBFACES[rank], FREE_SLIP_FINE_SUBFACES[rank]
    if fine == m:
        return subface_cuts(body, points, t, dx, axis, m)
    n = face_normal(sdf_gradient(body, points, t, 1e-3 * dx) if grad is None else grad, None)
    parallel = (n[..., axis].detach().abs() >= FREE_SLIP_PARALLEL) & _bends_within(body, points, t, dx, axis)
    if torch.compiler.is_compiling():
        theta, centroid = subface_cuts(body, points, t, dx, axis, m)
        ft, fc = subface_cuts(body, points, t, dx, axis, fine)
        return torch.where(parallel, ft, theta), torch.where(parallel.unsqueeze(-1), fc, centroid)
    theta = points.new_zeros(points.shape[:-1])
    centroid = torch.zeros_like(points)
    for sel, count in ((~parallel, m), (parallel, fine)):
        idx = sel.nonzero(as_tuple=True)
        if idx[0].numel():
            th, c = subface_cuts(body, points[idx], t, dx, axis, count)
            theta, centroid = theta.index_put(idx, th), centroid.index_put(idx, c)
    return theta, centroid


#: Smallest curvature, in units of ``1 / dx``, of the signed distance within a face for the fine sub-cuts of a face
#: nearly parallel to the surface (a radius of curvature below a thousand cells).
FREE_SLIP_BENDING = 1e-3


def _bends_within(body: Body, points: torch.Tensor, t: float, dx: float, axis: int) -> torch.Tensor:
    """Whether the signed distance bends over the faces of side ``dx`` normal to ``axis`` at ``points``: the largest
    second difference over half a face along the in-face axes, ``|phi(x + s e) + phi(x - s e) - 2 phi(x)| / s^2`` with
    ``s = dx / 2``, at least ``FREE_SLIP_BENDING / dx`` (zero on a plane; about ``1 / R`` near a sphere of radius
    ``R``). Detached: it only chooses a count of sub-cuts."""
    x = points.detach()
    phi = body.sdf(x, t)
    s = dx / 2
    bend = torch.zeros_like(phi)
    for a in range(x.shape[-1]):
        if a == axis:
            continue
        e = torch.zeros(x.shape[-1], dtype=x.dtype, device=x.device)
        e[a] = s
        bend = torch.maximum(bend, (body.sdf(x + e, t) + body.sdf(x - e, t) - 2 * phi).abs())
    return bend * dx >= FREE_SLIP_BENDING * s * s


def face_normal(grad: torch.Tensor, axis: int | None) -> torch.Tensor:
    """The unit normal ``grad / |grad|`` with its ``axis`` component zeroed (the distance does not vary over a face
    normal to ``axis``; None: kept)."""
    n = grad / grad.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    if axis is None:
        return n
    keep = torch.ones(n.shape[-1], dtype=n.dtype, device=n.device)
    keep[axis] = 0
    return n * keep


#: Smallest fraction of a stencil arm between a fluid face and the surface in the sharp no-slip stencil: closer
#: crossings are moved to this fraction (keeps the diagonal ``1 / s`` finite). The shift of the surface it makes is
#: below ``1e-5`` cells: a clamp of 1 % of a cell measurably held the order in the Couette test to 1.5 at 192^2.
WALL_FRACTION_MIN = 1e-5


def _arm(t: torch.Tensor, axis: int, side: int) -> tuple[torch.Tensor, torch.Tensor]:
    """The values at the faces that have a neighbour on ``side`` (+1/-1) along ``axis`` and at those neighbours."""
    n = t.shape[axis]
    lo, hi = t.narrow(axis, 0, n - 1), t.narrow(axis, 1, n - 1)
    return (lo, hi) if side > 0 else (hi, lo)


#: Distance of the extension's probe from the surface, in cells (its interpolation stencil stays in the fluid).
PROBE_CELLS = 2.0


def extension_stencil(bodies, grid: Grid, i: int, t: float, dtype, device, select: torch.Tensor):
    """The probes of component ``i``'s faces in ``select``: ``(index, corners, weights, factor, base, owner, normal,
    us_probe)`` (flat face indices; multilinear corners and weights of the probe two cells out along the normal;
    ``phi / d``; ``u_s(face) - factor u_s(probe)``; the nearest body; its unit normal; ``u_s`` at the probe), or
    None when ``select`` is empty."""
    h = min(grid.dx)
    x = grid.face_centers(i, dtype, device)
    shape = x.shape[:-1]
    index = select.flatten().nonzero().squeeze(1)
    if index.numel() == 0:
        return None
    xb = x.reshape(-1, grid.rank)[index]  # the distances at the selected faces alone (pointwise: the same numbers)
    phis = torch.stack([b.sdf(xb, t) for b in bodies], 0)
    pb = phis.min(0).values if len(bodies) > 1 else phis[0]
    owner = phis.argmin(0) if len(bodies) > 1 else None
    normal = torch.zeros_like(xb)
    us_face = torch.zeros_like(pb)
    us_probe = torch.zeros_like(pb)
    d_p = PROBE_CELLS * h
    probe = torch.zeros_like(xb)
    for k, b in enumerate(bodies):
        sel = slice(None) if owner is None else (owner == k)
        xs = xb[sel]
        n = unit_normal(b, xs, t, 1e-3 * h)
        pt = xs + (d_p - pb[sel]).unsqueeze(-1) * n  # the surface point plus d_p along the normal
        if owner is None:
            normal, probe = n, pt
        else:
            normal = normal.index_put((sel.nonzero().squeeze(1),), n)
            probe = probe.index_put((sel.nonzero().squeeze(1),), pt)
        if not b.static:
            uf, up = b.velocity_at(xs, t)[..., i], b.velocity_at(pt, t)[..., i]
            if owner is None:
                us_face, us_probe = uf, up
            else:
                us_face = us_face.index_put((sel.nonzero().squeeze(1),), uf)
                us_probe = us_probe.index_put((sel.nonzero().squeeze(1),), up)
    factor = pb / d_p
    # multilinear interpolation of component i at the probes: faces along i, cell centres along the others
    lo = torch.tensor([grid.bounds[a][0] for a in range(grid.rank)], dtype=dtype, device=device)
    dxs = torch.tensor(grid.dx, dtype=dtype, device=device)
    offset = torch.tensor([0.0 if a == i else 0.5 for a in range(grid.rank)], dtype=dtype, device=device)
    frac = (probe - lo) / dxs - offset
    sizes = torch.tensor(shape, device=device)
    base_idx = frac.detach().floor().long().clamp(min=torch.zeros_like(sizes), max=sizes - 2)
    f = frac - base_idx.to(dtype)
    strides = [math.prod(shape[a + 1:]) for a in range(grid.rank)]
    corners, weights = [], []
    for bits in range(2 ** grid.rank):
        idx = torch.zeros_like(index)
        w = torch.ones_like(pb)
        for a in range(grid.rank):
            bit = (bits >> a) & 1
            idx = idx + (base_idx[:, a] + bit) * strides[a]
            w = w * (f[:, a] if bit else 1 - f[:, a])
        corners.append(idx)
        weights.append(w)
    base = us_face - factor * us_probe
    owner = torch.zeros_like(index) if owner is None else owner
    return index, torch.stack(corners, 1), torch.stack(weights, 1), factor, base, owner, normal, us_probe


def sharp_no_slip(solids) -> list:
    """The sharp no-slip :class:`Body` objects among ``solids`` (bodies, obstacles, in any order)."""
    return [s for s in solids if isinstance(s, Body) and s.no_slip and s.sharp]


def set_from_probes(u: torch.Tensor, stencil: tuple) -> torch.Tensor:
    """``u`` (one MAC component ``(B, *face_shape)``) with the faces of an :func:`extension_stencil`-type ``stencil``
    ``(index, corners, weights, factor, base)`` set to ``base + factor * sum_j weights[:, j] u[corners[:, j]]`` (the
    linear wall profile through the probes)."""
    index, corners, weights, factor, base = stencil
    flat = u.reshape(u.shape[0], -1)
    value = base.to(u.dtype) + factor.to(u.dtype) * (flat[:, corners] * weights.to(u.dtype)).sum(-1)
    return flat.index_copy(1, index, value.expand(flat.shape[0], -1)).reshape(u.shape)


def wall_stencil(bodies, grid: Grid, i: int, t: float, dtype, device) -> tuple:
    """``(cut, coef, source)`` of the sharp no-slip stencil of MAC component ``i`` (see :class:`SolidLayout`).

    Args:
        bodies: The sharp no-slip bodies (their union is the solid).
        grid: The grid.
        i: The component.
        t: Time (positions and velocities of moving bodies).
        dtype, device: Of the computation.

    Returns:
        ``cut`` (bool), ``coef``, ``source`` (None when every body rests) and ``weight`` (``sum 1 / (s dx_a^2)`` over
        the arms that cross the surface: the factor of the wall values in ``source``), each of shape
        ``face_shape(i)``.
    """
    x = grid.face_centers(i, dtype, device)
    phis = torch.stack([b.sdf(x, t) for b in bodies], 0)
    phi = phis.min(0).values if len(bodies) > 1 else phis[0]
    owner = phis.argmin(0) if len(bodies) > 1 else None
    moving = any(not b.static for b in bodies)
    cut = phi.detach() <= 0
    coef = torch.zeros_like(phi)
    weight = torch.zeros_like(phi)
    source = torch.zeros_like(phi) if moving else None
    # Each arm's terms are computed at its links alone (the faces beside the surface) and added there: the same
    # numbers as adding them everywhere with zeros off the links, at the cost of the band instead of the grid.
    flat_index = torch.arange(phi.numel(), device=phi.device).reshape(phi.shape)
    for a in range(grid.rank):
        if phi.shape[a] < 2:
            continue
        h2 = grid.dx[a] ** 2
        for side in (1, -1):
            pf, pn = _arm(phi, a, side)
            link = (pf.detach() > 0) & (pn.detach() <= 0)
            at = link.nonzero(as_tuple=True)
            if at[0].numel() == 0:
                continue
            pf, pn = pf[at], pn[at]
            s = (pf / (pf - pn)).clamp(WALL_FRACTION_MIN, 1.0)
            faces = _arm(flat_index, a, side)[0][at]  # the fluid face of each link
            coef = coef.reshape(-1).index_add(0, faces, (1 / s - 1) / h2).reshape(phi.shape)
            weight = weight.reshape(-1).index_add(0, faces, 1 / (s * h2)).reshape(phi.shape)
            if moving:
                xf = _arm(x, a, side)[0][at]
                step = torch.zeros(grid.rank, dtype=dtype, device=device)
                step[a] = side * grid.dx[a]
                xw = xf + s.unsqueeze(-1) * step
                vel = torch.stack([b.velocity_at(xw, t)[..., i] if not b.static else torch.zeros_like(s)
                                   for b in bodies], 0)
                if owner is None:
                    uw = vel[0]
                else:
                    on = _arm(owner, a, side)[1][at]
                    uw = vel.gather(0, on.unsqueeze(0))[0]
                source = source.reshape(-1).index_add(0, faces, uw / (s * h2)).reshape(phi.shape)
    return cut, coef, source, weight


def tangent_stencil(bodies, grid: Grid, boundary: Boundary, i: int, t: float, weight: torch.Tensor, theta: tuple,
                    dtype: torch.dtype) -> tuple | None:
    """The entry of :attr:`SolidLayout.tangents` for component ``i`` (None when no face has a wall arm).

    Args:
        bodies: The sharp no-slip bodies.
        grid, boundary: The grid and the velocity boundary (periodic axes wrap).
        i: The component.
        t: Time (positions of moving bodies).
        weight: The wall weight of :func:`wall_stencil` (``face_shape(i)``, in the work precision).
        theta: Per component, the fluid fractions of the faces ``(1, *face_shape(j))``: a face with ``theta > 0``
            lies between two cells that hold fluid, so its pressure gradient is the fluid's.
        dtype: Of the returned weights and normals.
    """
    index = (weight.detach() > 0).flatten().nonzero().squeeze(1)
    if index.numel() == 0:
        return None
    device = weight.device
    h = min(grid.dx)
    work = weight.dtype
    shape = grid.face_shape(i)
    x = grid.face_centers(i, work, device).reshape(-1, grid.rank)[index]
    phis = torch.stack([b.sdf(x, t) for b in bodies], 0)
    owner = phis.detach().argmin(0)
    normal = torch.zeros_like(x)
    for k, b in enumerate(bodies):
        sel = (owner == k).nonzero().squeeze(1)
        if sel.numel():
            normal = normal.index_put((sel,), unit_normal(b, x[sel], t, 1e-3 * h))
    pos = torch.stack(unravel(index, shape), -1)  # (P, d) face indices
    neighbours = []
    for j in range(grid.rank):
        if j == i:
            neighbours.append(None)
            continue
        jshape = grid.face_shape(j)
        fluid = theta[j].detach()[0] > 0
        corners, ok = [], []
        for di in (-1, 0):
            for dj in (0, 1):
                q = pos.clone()
                q[:, i] += di
                q[:, j] += dj
                inside = torch.ones(len(index), dtype=torch.bool, device=device)
                n_i = grid.resolution[i]
                if boundary.is_periodic(i):
                    q[:, i] = q[:, i] % n_i
                else:
                    inside = inside & (q[:, i] >= 0) & (q[:, i] < n_i)
                    q[:, i] = q[:, i].clamp(0, n_i - 1)
                flat = sum(q[:, a] * math.prod(jshape[a + 1:]) for a in range(grid.rank))
                corners.append(flat)
                ok.append(inside & fluid.flatten()[flat])
        corners = torch.stack(corners, 1)
        ok = torch.stack(ok, 1)
        # corners (-1, 0), (-1, 1), (0, 0), (0, 1) along (i, j): the face centre is the midpoint of either diagonal,
        # so a diagonal pair in the fluid gives the value there exactly for a linear field; without one, the mean
        # of what is in the fluid
        first, second = ok[:, 0] & ok[:, 3], ok[:, 1] & ok[:, 2]
        pairs = torch.stack([first, second, second, first], 1).to(work)
        w = torch.where((first | second).unsqueeze(1), pairs, ok.to(work))
        w = w / w.sum(1, keepdim=True).clamp_min(1.0)
        neighbours.append((corners, w.to(dtype)))
    return index, weight.flatten()[index].to(dtype), normal.to(dtype), tuple(neighbours)


def as_solids(obstacles) -> list:
    if obstacles is None:
        return []
    if isinstance(obstacles, (Obstacle, Body, Geometry, torch.Tensor)):
        obstacles = [obstacles]
    out = []
    for ob in obstacles:
        if isinstance(ob, torch.Tensor):
            ob = Obstacle.from_mask(ob)
        elif isinstance(ob, Geometry):
            ob = Body(ob)
        if not isinstance(ob, (Obstacle, Body)):
            raise ParameterError(
                f"obstacles must be Obstacle, Body or Geometry objects or boolean masks, got {type(ob).__name__}"
            )
        out.append(ob)
    return out


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


def _check_placement(body: Body, grid: Grid, boundary: Boundary, t: float) -> None:
    lo, hi = body.bounding_box(t)
    if len(lo) != grid.rank:
        raise ShapeError(f"a {len(lo)}-D body cannot be placed on a {grid.rank}-D grid")
    if not all(map(math.isfinite, tuple(lo) + tuple(hi))):
        raise ParameterError(f"{body!r} has a non-finite position at t={t}")
    for a in range(grid.rank):
        b0, b1 = grid.bounds[a]
        if hi[a] <= b0 or lo[a] >= b1:
            raise ParameterError(
                f"{body!r} lies outside the domain along {'xyz'[a]} at t={t:g} (body {lo[a]:.4g}..{hi[a]:.4g}, "
                f"domain {b0:.4g}..{b1:.4g})"
            )


def solid_layout(obstacles, grid: Grid, boundary: Boundary, time: float = 0.0, dtype=torch.float64,
                 device=None) -> SolidLayout | None:
    """Rasterise obstacles and bodies on ``grid`` at ``time``.

    Each call rasterises anew (a pure function): a loop that steps past static bodies should hold the layout,
    as :class:`~phisim.fluid.stepper.FluidStepper` does (``solid_layout(...).persistent()``).

    Args:
        obstacles: None, an :class:`Obstacle`, :class:`Body`, :class:`~phisim.fluid.geometry.Geometry`
            (a resting no-slip body), a boolean solid mask ``(*res)``/``(B, *res)``, or a sequence of those.
        grid: The grid.
        boundary: The velocity boundary (periodic axes wrap the staircase masks; inflow sides are checked).
        time: Simulation time (moves moving bodies).
        dtype, device: Of the returned tensors.

    Returns:
        The :class:`SolidLayout`, or None when there is no solid (or it covers no face).

    Raises:
        ParameterError: For a body outside the domain, a body covering an inflow, NaN geometry.
        ShapeError: For masks or bodies that do not fit the grid.
    """
    if isinstance(obstacles, SolidLayout):
        return obstacles.to(dtype=dtype, device=device) if obstacles.theta[0].dtype != dtype else obstacles
    solids = as_solids(obstacles)
    if not solids:
        return None
    return _rasterise(solids, grid, boundary, float(time), dtype, device)


def _rasterise(solids, grid, boundary, t, dtype, device) -> SolidLayout | None:
    rank = grid.rank
    work = torch.float64 if dtype in (torch.float32, torch.float16, torch.bfloat16) else dtype
    h = min(grid.dx)
    thetas, chis, vels, slips, sharps = [], [], [], [], []
    cell = None
    any_moving = any(isinstance(s, Body) and not s.static for s in solids)
    any_slip = any(isinstance(s, Body) and not s.no_slip for s in solids)
    for s in solids:
        if isinstance(s, Obstacle):
            solid = s.cell_mask(grid, device)
            if solid.ndim == rank:
                solid = solid[None]
            fluid = (~solid).to(work)
            th = open_face_masks(fluid, boundary)
            cf = fluid
            sv = None
            no_slip = True
        else:
            _check_placement(s, grid, boundary, t)
            cf = body_fraction(s, grid.cell_centers(work, device), t, h)[None]
            th = tuple(body_fraction(s, grid.face_centers(i, work, device), t, h, i)[None] for i in range(rank))
            sv = None
            if not s.static:
                sv = tuple(s.velocity_at(grid.face_centers(i, work, device), t)[..., i][None] for i in range(rank))
            no_slip = s.no_slip
        thetas.append(th)
        chis.append(tuple(1 - x for x in th))
        vels.append(sv)
        slips.append(no_slip)
        sharps.append(isinstance(s, Body) and s.no_slip and s.sharp)
        cell = cf if cell is None else cell * cf
    theta = tuple(math.prod(th[i] for th in thetas) for i in range(rank)) if len(thetas) > 1 else thetas[0]
    solid_velocity = None
    slip = None
    sharp_share = None
    if any(sharps):
        wsum = [sum(c[i] for c in chis) for i in range(rank)]
        safe = [torch.where(w > 0, w, torch.ones_like(w)) for w in wsum]
        sharp_share = tuple(torch.where(wsum[i] > 0, sum(c[i] * float(sh) for c, sh in zip(chis, sharps)) / safe[i],
                                        torch.ones_like(wsum[i])) for i in range(rank))
    if any_moving or any_slip:
        wsum = [sum(c[i] for c in chis) for i in range(rank)]
        safe = [torch.where(w > 0, w, torch.ones_like(w)) for w in wsum]
    if any_moving:
        solid_velocity = tuple(
            sum(c[i] * (v[i] if v is not None else 0) for c, v in zip(chis, vels)) / safe[i] for i in range(rank)
        )
    if any_slip:
        slip = tuple(sum(c[i] * (0.0 if ns else 1.0) for c, ns in zip(chis, slips)) / safe[i] for i in range(rank))
    # inflow sides must stay clear of bodies
    for a, pair in enumerate(boundary.sides):
        for side, cond in enumerate(pair):
            if isinstance(cond, Inflow):
                face = theta[a].narrow(1 + a, 0 if side == 0 else grid.resolution[a], 1)
                if bool((face.detach() < 1).any()):
                    raise BoundaryError(
                        f"a body covers the inflow on the {'lower' if side == 0 else 'upper'} {'xyz'[a]} side; "
                        "move it into the domain, away from the inflow"
                    )
    def conv(ts):
        return None if ts is None else tuple(x.to(dtype) for x in ts)

    walls = extension = tangents = None
    sharp = sharp_no_slip(solids)
    if sharp:
        walls, extension, tangents = [], [], []
        for i in range(rank):
            cut, coef, source, weight = wall_stencil(sharp, grid, i, t, work, device)
            walls.append((cut[None], coef[None].to(dtype), None if source is None else source[None].to(dtype)))
            tangents.append(tangent_stencil(sharp, grid, boundary, i, t, weight, theta, dtype))
            th_i = theta[i].detach()[0]
            ext = extension_stencil(sharp, grid, i, t, work, device, (th_i > 0) & (th_i < 1))
            if ext is None:
                extension.append(None)
                continue
            # the flux through the wetted part of the face: the relative velocity grows linearly from the surface,
            # w = g phi with g = w(probe) / d; its mean over the face is g E[phi_+] (cut_fractions), of which
            # theta w_F = g theta phi_F is in the blend of a fluid face (nothing of a face centred inside): the rest
            # is kappa w(probe)
            pf = ext[3] * (PROBE_CELLS * h)  # phi at the faces
            thf, mean = cut_fractions(pf, face_normal(ext[6], i), h)
            kappa = (mean - thf * pf.clamp_min(0)) / (PROBE_CELLS * h)
            ext = (ext[0], ext[1], ext[2], kappa, -kappa * ext[7], ext[5])
            extension.append((ext[0], ext[1], ext[2].to(dtype), ext[3].to(dtype), ext[4].to(dtype)))
        walls, extension, tangents = tuple(walls), tuple(extension), tuple(tangents)
    return SolidLayout(conv(theta), conv(solid_velocity), conv(slip), cell.to(dtype), tuple(solids), walls=walls,
                       extension=extension, sharp=conv(sharp_share), tangents=tangents, time=float(t))


def obstacle_mask(obstacles, grid: Grid, device=None) -> torch.Tensor | None:
    """Union of solids as a boolean cell mask ``(1 or B, *resolution)``, or None when nothing is solid.

    Cells of :class:`Obstacle` masks are solid as given; for :class:`Body` objects a cell is solid when
    less than half of it is fluid (at time 0).

    Args:
        obstacles: See :func:`solid_layout`.
        grid: The grid.
        device: Torch device of the mask.

    Returns:
        The mask, or None for no obstacles (or obstacles covering no cell centre).

    Raises:
        ParameterError: For entries that are neither obstacles nor masks.
        ShapeError: For masks that do not fit the grid.
    """
    solids = as_solids(obstacles)
    if not solids:
        return None
    solid = None
    for ob in solids:
        if isinstance(ob, Obstacle):
            m = ob.cell_mask(grid, device)
        else:
            _check_placement(ob, grid, Boundary.create("open", grid.rank), 0.0)
            m = body_fraction(ob, grid.cell_centers(torch.float64, device), 0.0, min(grid.dx)).detach() < 0.5
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


def uncovered_stencil(bodies, grid: Grid, i: int, t_old: float, t_new: float, dtype, device):
    """The faces of component ``i`` that moving sharp no-slip bodies uncover between ``t_old`` and ``t_new``, and the
    value each takes: ``(index, corners, weights, factor, base)``, or None when no face is uncovered.

    A face is uncovered when its centre lies inside the union of ``bodies`` at ``t_old`` (``phi <= 0``) and in the
    fluid at ``t_new``. Its velocity there is the linear wall profile of the relative velocity along the normal,
    ``u = u_s(x) + (phi / d) (u(P) - u_s(P))``: the body's velocity at the surface, the fluid's at the probe ``P`` a
    distance ``d`` (:data:`PROBE_CELLS` cells) from the surface along the normal (the probes of
    :func:`extension_stencil`), i.e. ``base[k] + factor[k] * sum_j weights[k, j] u[corners[k, j]]`` for the face with
    flat index ``index[k]``. Differentiable in the bodies' parameters (``factor``, ``base``, ``weights``).

    Args:
        bodies: The sharp no-slip bodies (their union is the solid).
        grid: The grid.
        i: The component.
        t_old, t_new: The times of the previous and of the new position.
        dtype, device: Of the computation.
    """
    x = grid.face_centers(i, dtype, device)
    with torch.no_grad():
        old = torch.stack([b.sdf(x, t_old) for b in bodies], 0).min(0).values
        if torch.compiler.is_compiling():  # no host reads: every face
            new = torch.stack([b.sdf(x, t_new) for b in bodies], 0).min(0).values
            select = (old <= 0) & (new > 0)
        else:  # the new distances only where the old position covered the face (pointwise: the same selection)
            covered = (old <= 0).reshape(-1).nonzero().squeeze(1)
            xc = x.reshape(-1, grid.rank)[covered]
            new = torch.stack([b.sdf(xc, t_new) for b in bodies], 0).min(0).values
            select = torch.zeros(old.numel(), dtype=torch.bool, device=old.device)
            select[covered] = new > 0
            select = select.reshape(old.shape)
    ext = extension_stencil(bodies, grid, i, t_new, dtype, device, select)
    return None if ext is None else ext[:5]
