"""Geometry of bodies as signed distance functions (SDF): boxes, spheres/discs, rotated boxes, unions, your own.

A geometry maps points ``x`` of shape ``(..., d)`` to the signed distance ``phi(x)`` to its surface: negative
inside, positive outside, ``|grad phi| = 1`` near the surface (a union or a user function may be only an
approximate distance; it must have the right sign and be Lipschitz with constant about 1).

Parameters (centres, radii, sizes, angles) may be torch tensors that require grad: the distance, and
everything computed from it (face fractions, forces, the flow) is then differentiable with respect to
the shape. The fluid solver turns a geometry into fractional face weights with
:func:`fluid_fraction` (see :mod:`phisim.fluid.bodies`).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import torch

from phisim.errors import ParameterError, ShapeError
from phisim.ops.tensors import sum_last

__all__ = ["Geometry", "Box", "Sphere", "RotatedBox", "Union", "SDF", "fluid_fraction", "cut_fractions", "cut_centroid",
           "rotation_matrix"]


def floats(value) -> tuple[float, ...]:
    """A vector (a tuple of numbers or a tensor, perhaps one that requires grad) as plain floats, without autograd's
    warning about reading a value that requires grad."""
    if isinstance(value, torch.Tensor):
        value = value.detach().reshape(-1).tolist()
    return tuple(float(v) for v in value)


def _vector(value, name: str) -> torch.Tensor | tuple[float, ...]:
    """A coordinate vector: a tuple of floats, or a float tensor (kept, so gradients can flow)."""
    if isinstance(value, torch.Tensor):
        if value.ndim != 1 or not value.is_floating_point():
            raise ParameterError(f"{name} must be a 1-D floating-point tensor, got shape {tuple(value.shape)}")
        if not bool(torch.isfinite(value.detach()).all()):
            raise ParameterError(f"{name} contains NaN or Inf: {value}")
        return value
    try:
        out = tuple(float(v) for v in value)
    except (TypeError, ValueError) as exc:
        raise ParameterError(f"{name} must be a sequence of numbers, got {value!r}") from exc
    if not out or not all(math.isfinite(v) for v in out):
        raise ParameterError(f"{name} must be a non-empty sequence of finite numbers, got {value!r}")
    return out


def _scalar(value, name: str, positive: bool = False):
    if isinstance(value, torch.Tensor):
        if value.numel() != 1 or not value.is_floating_point():
            raise ParameterError(f"{name} must be a scalar floating-point tensor, got shape {tuple(value.shape)}")
        v = float(value.detach())
    else:
        try:
            v = float(value)
        except (TypeError, ValueError) as exc:
            raise ParameterError(f"{name} must be a number, got {value!r}") from exc
        value = v
    if not math.isfinite(v) or (positive and v <= 0):
        raise ParameterError(f"{name} must be finite{' and > 0' if positive else ''}, got {v}")
    return value


def _as(value, like: torch.Tensor) -> torch.Tensor:
    return torch.as_tensor(value, dtype=like.dtype, device=like.device) if not isinstance(value, torch.Tensor) \
        else value.to(dtype=like.dtype, device=like.device)


def _check_points(x: torch.Tensor, rank: int, what: str) -> None:
    if not isinstance(x, torch.Tensor) or x.shape[-1:] != (rank,):
        raise ShapeError(f"{what} is {rank}-D: points must have shape (..., {rank}), got "
                         f"{tuple(getattr(x, 'shape', ()))}")


def rotation_matrix(angle, rank: int, like: torch.Tensor | None = None) -> torch.Tensor:
    """The rotation matrix of an angle (2-D, counter-clockwise) or of a 3x3 matrix / rotation vector (3-D).

    Args:
        angle: 2-D: an angle in radians (float or scalar tensor). 3-D: a 3x3 rotation matrix, or a rotation
            vector (axis times angle, Rodrigues' formula).
        rank: 2 or 3.
        like: Tensor whose dtype/device the result takes (default float64 on the CPU).

    Returns:
        ``(rank, rank)`` tensor ``R``; a body rotated by ``R`` maps its reference point ``x0`` to ``R x0``.
    """
    like = torch.zeros((), dtype=torch.float64) if like is None else like
    if rank == 2:
        a = _as(angle, like).reshape(())
        c, s = torch.cos(a), torch.sin(a)
        return torch.stack([torch.stack([c, -s]), torch.stack([s, c])])
    if rank != 3:
        raise ParameterError(f"rotations need a 2-D or 3-D geometry, got rank {rank}")
    a = _as(angle, like)
    if a.shape == (3, 3):
        return a
    if a.shape != (3,):
        raise ParameterError(f"a 3-D rotation is a 3x3 matrix or a rotation vector of 3 entries, got {tuple(a.shape)}")
    theta = torch.sqrt((a * a).sum() + torch.finfo(a.dtype).tiny)
    k = a / theta
    z = a.new_zeros(())
    kx = torch.stack([torch.stack([z, -k[2], k[1]]), torch.stack([k[2], z, -k[0]]), torch.stack([-k[1], k[0], z])])
    eye = torch.eye(3, dtype=a.dtype, device=a.device)
    return eye + torch.sin(theta) * kx + (1 - torch.cos(theta)) * (kx @ kx)


class Geometry:
    """Base class: a body shape given by its signed distance function (negative inside).

    Subclasses implement :meth:`sdf`, :attr:`rank`, :attr:`center` (the reference point, e.g. the centre of
    rotation) and :meth:`bounding_box`. ``a | b`` is their :class:`Union`.
    """

    rank: int

    def sdf(self, x: torch.Tensor) -> torch.Tensor:
        """Signed distance at points ``x`` ``(..., d)``: negative inside, shape ``(...)``."""
        raise NotImplementedError

    @property
    def center(self) -> torch.Tensor | tuple[float, ...]:
        """The reference point (centre of rotation of a moving body)."""
        raise NotImplementedError

    def bounding_box(self) -> tuple[tuple[float, ...], tuple[float, ...]]:
        """Lower and upper corners (floats) of a box containing the body."""
        raise NotImplementedError

    def __or__(self, other: Geometry) -> Union:
        return Union(self, other)


class Box(Geometry):
    """An axis-aligned box ``lower <= x <= upper``.

    Args:
        lower: Lower corner, one entry per axis (floats or a tensor).
        upper: Upper corner.

    Raises:
        ParameterError: For corners of different lengths, non-finite entries or ``upper <= lower``.
    """

    def __init__(self, lower, upper):
        self.lower, self.upper = _vector(lower, "Box lower"), _vector(upper, "Box upper")
        lo = list(floats(self.lower))
        hi = list(floats(self.upper))
        if len(lo) != len(hi) or any(h <= l for l, h in zip(lo, hi)):
            raise ParameterError(f"Box needs lower < upper with one entry per axis, got {lo}, {hi}")
        self.rank = len(lo)

    def sdf(self, x):
        """Exact signed distance to the box surface."""
        _check_points(x, self.rank, "the box")
        lo, hi = _as(self.lower, x), _as(self.upper, x)
        c, h = 0.5 * (lo + hi), 0.5 * (hi - lo)
        q = (x - c).abs() - h
        outside = sum_last(q.clamp_min(0).pow(2)).add(torch.finfo(x.dtype).tiny).sqrt()
        inside = q.max(-1).values.clamp_max(0)
        return outside + inside

    @property
    def center(self):
        """The box centre."""
        if any(isinstance(v, torch.Tensor) for v in (self.lower, self.upper)):
            lo = torch.as_tensor(self.lower, dtype=torch.float64)
            return 0.5 * (lo + torch.as_tensor(self.upper, dtype=torch.float64))
        return tuple(0.5 * (float(a) + float(b)) for a, b in zip(self.lower, self.upper))

    def bounding_box(self):
        """The box itself."""
        return floats(self.lower), floats(self.upper)

    def __repr__(self):
        return f"Box({[round(v, 6) for v in floats(self.lower)]}, {[round(v, 6) for v in floats(self.upper)]})"


class Sphere(Geometry):
    """A ball ``|x - center| <= radius``: a disc in 2-D, a sphere in 3-D.

    Args:
        center: Centre, one entry per axis (floats or a tensor, e.g. one that requires grad).
        radius: Radius ``> 0`` (float or scalar tensor).

    Raises:
        ParameterError: For a non-positive or non-finite radius or a bad centre.
    """

    def __init__(self, center, radius):
        self._center = _vector(center, "Sphere center")
        self.radius = _scalar(radius, "Sphere radius", positive=True)
        self.rank = len(self._center)

    def sdf(self, x):
        """Exact signed distance ``|x - c| - r``."""
        _check_points(x, self.rank, "the sphere")
        d = x - _as(self._center, x)
        return sum_last(d.pow(2)).add(torch.finfo(x.dtype).tiny).sqrt() - _as(self.radius, x)

    @property
    def center(self):
        """The centre."""
        return self._center

    def bounding_box(self):
        """Centre plus/minus the radius."""
        r = float(torch.as_tensor(self.radius).detach())
        return tuple(c - r for c in floats(self._center)), tuple(c + r for c in floats(self._center))

    def __repr__(self):
        return f"Sphere({[round(v, 6) for v in floats(self._center)]}, {floats(torch.as_tensor(self.radius))[0]:.6g})"


class RotatedBox(Geometry):
    """A box of full side lengths ``size`` centred at ``center``, rotated by ``angle`` about its centre.

    Args:
        center: Centre.
        size: Side lengths (full, not half), one per axis.
        angle: 2-D: angle in radians (counter-clockwise). 3-D: a 3x3 rotation matrix or a rotation vector.

    Raises:
        ParameterError: For non-positive sizes or mismatched lengths.
    """

    def __init__(self, center, size, angle=0.0):
        self._center, self.size = _vector(center, "RotatedBox center"), _vector(size, "RotatedBox size")
        if len(self._center) != len(self.size) or any(s <= 0 for s in floats(self.size)):
            raise ParameterError(f"RotatedBox needs sizes > 0, one per axis of the centre, got {self.size}")
        self.rank = len(self._center)
        if self.rank not in (2, 3):
            raise ParameterError("RotatedBox is 2-D or 3-D")
        self.angle = angle

    def sdf(self, x):
        """Exact signed distance (the box distance in the box's own frame)."""
        _check_points(x, self.rank, "the rotated box")
        r = rotation_matrix(self.angle, self.rank, x)
        local = (x - _as(self._center, x)) @ r  # R^T (x - c) for row vectors
        q = local.abs() - 0.5 * _as(self.size, x)
        outside = sum_last(q.clamp_min(0).pow(2)).add(torch.finfo(x.dtype).tiny).sqrt()
        return outside + q.max(-1).values.clamp_max(0)

    @property
    def center(self):
        """The centre (of rotation)."""
        return self._center

    def bounding_box(self):
        """Centre plus/minus half the diagonal (conservative)."""
        h = 0.5 * math.sqrt(sum(s**2 for s in floats(self.size)))
        return tuple(c - h for c in floats(self._center)), tuple(c + h for c in floats(self._center))

    def __repr__(self):
        return f"RotatedBox({list(floats(self._center))}, {list(floats(self.size))}, angle={self.angle})"


class Union(Geometry):
    """The union of geometries: ``phi = min_k phi_k`` (exact outside, a lower bound of the depth inside).

    Args:
        *parts: Two or more geometries of the same dimension.
    """

    def __init__(self, *parts: Geometry):
        flat: list[Geometry] = []
        for p in parts:
            if not isinstance(p, Geometry):
                raise ParameterError(f"Union takes geometries, got {type(p).__name__}")
            flat.extend(p.parts if isinstance(p, Union) else [p])
        if not flat or len({p.rank for p in flat}) != 1:
            raise ParameterError("Union needs geometries of one dimension")
        self.parts = tuple(flat)
        self.rank = flat[0].rank

    def sdf(self, x):
        """Minimum of the parts' distances."""
        return torch.stack([p.sdf(x) for p in self.parts], -1).min(-1).values

    @property
    def center(self):
        """Centre of the bounding box."""
        lo, hi = self.bounding_box()
        return tuple(0.5 * (a + b) for a, b in zip(lo, hi))

    def bounding_box(self):
        """Box around all parts."""
        boxes = [p.bounding_box() for p in self.parts]
        lo = tuple(min(b[0][a] for b in boxes) for a in range(self.rank))
        hi = tuple(max(b[1][a] for b in boxes) for a in range(self.rank))
        return lo, hi

    def __repr__(self):
        return "Union(" + ", ".join(map(repr, self.parts)) + ")"


class SDF(Geometry):
    """A geometry from your own signed distance function.

    Args:
        fn: ``fn(x) -> phi`` mapping points ``(..., d)`` to distances ``(...)`` (negative inside), written
            with torch operations (so it runs on any device and is differentiable).
        center: Reference point (centre of rotation for moving bodies).
        bounds: ``(lower, upper)`` corners of a box containing the body (used to check that the body lies
            inside the domain).

    Raises:
        ParameterError: If ``fn`` is not callable or the corners are inconsistent.
    """

    def __init__(self, fn: Callable[[torch.Tensor], torch.Tensor], center: Sequence[float],
                 bounds: tuple[Sequence[float], Sequence[float]]):
        if not callable(fn):
            raise ParameterError(f"SDF needs a callable fn(x) -> phi, got {type(fn).__name__}")
        self.fn = fn
        self._center = _vector(center, "SDF center")
        self.rank = len(self._center)
        lo, hi = (_vector(b, "SDF bounds") for b in bounds)
        if len(lo) != self.rank or len(hi) != self.rank or any(h < l for l, h in zip(floats(lo), floats(hi))):
            raise ParameterError(f"SDF bounds must be (lower, upper) with {self.rank} entries each")
        self._bounds = (floats(lo), floats(hi))

    def sdf(self, x):
        """The user's function, checked for shape."""
        _check_points(x, self.rank, "the SDF geometry")
        phi = self.fn(x)
        if not isinstance(phi, torch.Tensor) or phi.shape != x.shape[:-1]:
            raise ShapeError(f"the SDF function must return a tensor of shape {tuple(x.shape[:-1])}, got "
                             f"{tuple(getattr(phi, 'shape', ()))}")
        return phi

    @property
    def center(self):
        """The reference point."""
        return self._center

    def bounding_box(self):
        """The bounds given at construction."""
        return self._bounds

    def __repr__(self):
        return f"SDF({getattr(self.fn, '__name__', 'fn')}, center={self._center})"


def fluid_fraction(phi: torch.Tensor, normal_l1: torch.Tensor, dx: float) -> torch.Tensor:
    """Fluid volume fraction of a square/cube control volume of side ``dx`` around a point.

    For a planar surface at signed distance ``phi`` from the centre with unit normal ``n``, the fraction is
    0 for ``phi <= -w/2`` and 1 for ``phi >= w/2`` with ``w = dx * sum_k |n_k|`` (the extent of the cell
    along ``n``); in between this function uses the linear ramp ``1/2 + phi / w``, exact at the centre and
    at the ends and within 0.07 of the exact piecewise-quadratic fraction (2-D). It is continuous and
    piecewise linear in ``phi``, so shape gradients exist.

    Args:
        phi: Signed distances at the control-volume centres.
        normal_l1: ``sum_k |n_k|`` there (1 for an axis-aligned surface, ``sqrt(2)`` on a 2-D diagonal).
        dx: Side of the control volume.

    Returns:
        Fractions in ``[0, 1]``, shape of ``phi``.
    """
    w = dx * normal_l1.clamp_min(1.0)
    return (0.5 + phi / w).clamp(0.0, 1.0)


def cut_fractions(phi: torch.Tensor, normal: torch.Tensor, dx: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Exact fluid fraction and mean positive distance of a square/cube control volume of side ``dx`` cut by a plane.

    The signed distance inside the control volume is ``d(x) = phi + n . (x - c)``: a sum of independent uniform
    variables of widths ``dx |n_k|``, so the fraction ``P(d > 0)`` and the mean ``E[max(d, 0)]`` over the control
    volume are iterated divided differences (one per axis) of ``x_+^m / m!`` with ``m = d`` and ``d + 1``
    (``d`` the dimension): exact for a planar surface, second order for a curved one. Widths below ``1e-3 dx``
    are raised to it (the answer changes by less than ``1e-6 dx``), which keeps the differences well conditioned.

    Args:
        phi: Signed distances at the control-volume centres, shape ``(...)``.
        normal: Unit normals there, ``(..., d)``.
        dx: Side of the control volume.

    Returns:
        ``(theta, mean)``: the fraction in ``[0, 1]`` and ``E[max(d, 0)]`` (a length), both of shape ``(...)``;
        differentiable in ``phi`` and ``normal``.
    """
    rank = normal.shape[-1]
    widths = (normal.abs() * dx).clamp_min(1e-3 * dx)
    terms = [(phi, 1.0)]
    for k in range(rank):
        w = widths[..., k]
        terms = [t for x, sg in terms for t in ((x + w / 2, sg), (x - w / 2, -sg))]
    scale = widths.prod(-1)
    theta = sum(sg * x.clamp_min(0) ** rank for x, sg in terms) / (math.factorial(rank) * scale)
    mean = sum(sg * x.clamp_min(0) ** (rank + 1) for x, sg in terms) / (math.factorial(rank + 1) * scale)
    # outside the cut band the answers are exact without the differences' rounding: 1 and phi, or 0 and 0
    half = sum_last(widths) / 2
    inside, outside = phi <= -half, phi >= half
    theta = torch.where(outside, torch.ones_like(theta), torch.where(inside, torch.zeros_like(theta), theta))
    mean = torch.where(outside, phi, torch.where(inside, torch.zeros_like(mean), mean))
    return theta.clamp(0.0, 1.0), mean.clamp_min(0.0)


def cut_centroid(phi: torch.Tensor, normal: torch.Tensor, dx: float
                 ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """:func:`cut_fractions` and the centroid of the fluid part of the control volume, relative to its centre.

    With ``M(n) = E[max(phi + n . y, 0)]`` over the control volume (``y`` uniform in the cube of side ``dx``), the
    fluid part's first moment is ``E[y H(phi + n . y)] = dM / dn``; along axis ``a``, ``M`` depends on ``n_a`` only
    through the width ``w_a = dx |n_a|``, so the moment is ``sign(n_a) dx dM / dw_a``, which this function takes from
    the same divided differences as ``M`` (exact for a planar surface). The centroid's component along ``n`` is
    ``(M - theta phi) / theta`` (``M`` is homogeneous of degree one in ``(phi, n)``); the components across ``n``,
    nonzero where the cut is not symmetric about ``n`` (a 3-D face or cell cut off near a corner), come with it.
    Axes with ``|n_a| < 1e-3`` (widths raised to ``1e-3 dx``) get a zero component (the fluid part is symmetric
    along them to within ``1e-3 dx``).

    Args:
        phi: Signed distances at the control-volume centres, shape ``(...)``.
        normal: Unit normals there, ``(..., d)`` (on a face: the normal's part in the face, its own axis zero).
        dx: Side of the control volume.

    Returns:
        ``(theta, mean, centroid)``: :func:`cut_fractions`' fraction and mean, and the centroid ``(..., d)``, each
        component in ``[-dx/2, dx/2]`` (zero where nothing or everything is fluid); differentiable in ``phi`` and
        ``normal``.
    """
    rank = normal.shape[-1]
    raw = normal.abs() * dx
    widths = raw.clamp_min(1e-3 * dx)
    theta, mean = cut_fractions(phi, normal, dx)
    terms = [(phi, 1.0, ())]
    for k in range(rank):
        w = widths[..., k]
        terms = [t for x, sg, s in terms for t in ((x + w / 2, sg, s + (1.0,)), (x - w / 2, -sg, s + (-1.0,)))]
    scale = widths.prod(-1)
    powers = [x.clamp_min(0) ** rank for x, _, _ in terms]
    comps = []
    for a in range(rank):
        # dM/dw_a (M = mean in the cut band, where the moment is used): each term's x moves by s_a / 2 with w_a,
        # and the 1 / prod(w) falls by 1 / w_a
        a_sum = sum(sg * s[a] * p for (_, sg, s), p in zip(terms, powers)) / (2 * math.factorial(rank) * scale)
        dm = a_sum - mean / widths[..., a]
        comps.append(torch.sign(normal[..., a]) * dx * dm)
    moment = torch.stack(comps, -1) * (raw > 1e-3 * dx).to(normal.dtype)
    half = sum_last(widths) / 2
    band = ((phi > -half) & (phi < half)).unsqueeze(-1)
    centroid = torch.where(band, moment / theta.clamp_min(1e-12).unsqueeze(-1), torch.zeros_like(moment))
    return theta, mean, centroid.clamp(-dx / 2, dx / 2)
