"""Fields: immutable values on a grid with a boundary. Cell-centred (`CenteredGrid`) and MAC (`StaggeredGrid`).

Layout (batch first, always):

* ``CenteredGrid`` scalar: ``(B, *resolution)``; vector: ``(B, d, *resolution)``.
* ``StaggeredGrid``: a tuple of ``d`` arrays; component ``i`` has shape ``(B, *resolution)`` except
  ``resolution[i] + 1`` along axis ``i`` (the faces normal to axis ``i``, both boundary faces included).

Operations return new fields. Combining fields on different grids, sample locations or boundaries raises
:class:`~phisim.errors.GridMismatchError` instead of broadcasting. Batch sizes of two operands (two fields, or a
field and a tensor with a batch axis) must be equal or one of them 1, which is then shared by every sample of the
other; anything else raises :class:`~phisim.errors.ShapeError` naming both sizes. Fields never hold an empty
batch (batch size 0). Sample points must be finite (:class:`~phisim.errors.NonFiniteError`).
"""

from __future__ import annotations

import operator
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from phisim.boundary import Boundary, pad, pad_staggered_component, set_boundary_faces
from phisim.checks import all_finite, check_batch_compatible, check_device, check_int, check_nonempty_batch
from phisim.errors import GridMismatchError, NonFiniteError, ParameterError, ShapeError
from phisim.grid import Grid

__all__ = ["CenteredGrid", "StaggeredGrid", "Field", "sample_padded"]


def _as_float_tensor(values, dtype=None, device=None) -> torch.Tensor:
    if isinstance(values, np.ndarray) and values.dtype.kind not in "fiub":
        raise ParameterError(f"field values must be a real numeric array, got numpy dtype {values.dtype}")
    if isinstance(values, (str, bytes)) or values is None:
        raise ParameterError(f"field values must be a tensor or array, got {values!r}")
    device = None if device is None else check_device(device)
    try:
        if isinstance(values, np.ndarray) and values.dtype == np.float64 and dtype is None:
            t = torch.as_tensor(values)
        else:
            t = torch.as_tensor(values, device=device)
    except (TypeError, ValueError, RuntimeError) as exc:
        raise ParameterError(f"field values must be a real numeric tensor or array: {exc}") from exc
    if t.is_complex():
        raise ParameterError("field values must be real; store the real and imaginary parts as two fields")
    if dtype is not None or device is not None:
        t = t.to(dtype=dtype or t.dtype, device=device or t.device)
    if not (t.is_floating_point() or t.is_complex()):
        t = t.to(torch.get_default_dtype())
    return t


def _check_count(n, name: str) -> int:
    return check_int(n, name, minimum=1)


def _finite_points(index: torch.Tensor, name: str) -> torch.Tensor | None:
    """Sample coordinates must be finite. On the CPU a NaN/Inf coordinate raises :class:`NonFiniteError`; on an
    accelerator (where the check would cost a device sync per call) the mask of finite points ``(B, N)`` is
    returned instead, and the caller makes the values sampled there NaN rather than a plausible finite number."""
    if index.device.type == "cpu" and not torch.compiler.is_compiling():
        if not all_finite(index.detach()):
            bad = int((~torch.isfinite(index.detach())).any(-1).sum())
            raise NonFiniteError(f"{name} contains {bad} NaN/Inf coordinate(s); sample points must be finite")
        return None
    return torch.isfinite(index.detach()).all(-1)


# ---- interpolation ------------------------------------------------------------------------------------


def sample_padded(array: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
    """Multilinear interpolation of ``array`` at fractional sample indices.

    Args:
        array: ``(B, C, *shape)`` samples (``len(shape)`` in 1..3).
        index: ``(B, N, d)`` fractional indices into ``shape`` (index ``k`` is sample ``k``); values are
            clamped to ``[0, shape - 1]``.

    Returns:
        ``(B, C, N)`` interpolated values, differentiable w.r.t. both inputs.

    Raises:
        ShapeError: Wrong coordinate count, an empty batch, or batch sizes of ``array`` and ``index`` that differ.
        NonFiniteError: NaN/Inf indices (on the CPU; on accelerators the values sampled there are NaN).
    """
    d = array.ndim - 2
    if index.ndim != 3 or index.shape[-1] != d:
        raise ShapeError(f"index must have shape (B, N, {d}) for a {d}-D array, got {tuple(index.shape)}")
    check_nonempty_batch(array, "array")
    if index.shape[0] != array.shape[0]:
        raise ShapeError(f"index has batch size {index.shape[0]} but array has {array.shape[0]}")
    finite = _finite_points(index, "index")
    out = _sample_padded(array, index if finite is None else torch.where(finite[..., None], index, 0.0))
    return out if finite is None else torch.where(finite[:, None, :], out, torch.nan)


def _sample_padded(array: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
    d = array.ndim - 2
    shape = array.shape[2:]
    if d == 1:
        n = shape[0]
        t = index[..., 0].clamp(0, n - 1)
        i0 = t.detach().floor().clamp(0, max(n - 2, 0)).long()
        w = (t - i0.to(t.dtype)).unsqueeze(1)
        i1 = (i0 + 1).clamp(max=n - 1)
        c = array.shape[1]
        g0 = torch.gather(array, 2, i0.unsqueeze(1).expand(-1, c, -1))
        g1 = torch.gather(array, 2, i1.unsqueeze(1).expand(-1, c, -1))
        return g0 * (1 - w) + g1 * w
    sizes = torch.tensor([s - 1 for s in shape], dtype=index.dtype, device=index.device)
    norm = 2 * index / sizes - 1
    norm = norm.flip(-1)  # grid_sample wants (W, H[, D]) order, i.e. the last array axis first
    B, N = index.shape[0], index.shape[1]
    grid = norm.reshape(B, N, *([1] * (d - 1)), d)
    out = F.grid_sample(array, grid, mode="bilinear", padding_mode="border", align_corners=True)
    return out.reshape(B, array.shape[1], N)


def _points_to_index(points: torch.Tensor, grid: Grid, boundary: Boundary, face_axis: int | None, width: int):
    """Physical points -> fractional indices into an array padded by ``width`` ghost layers."""
    lower = torch.tensor(grid.lower, dtype=points.dtype, device=points.device)
    dx = torch.tensor(grid.dx, dtype=points.dtype, device=points.device)
    t = (points - lower) / dx
    cols = []
    for a in range(grid.rank):
        ta = t[..., a] if a == face_axis else t[..., a] - 0.5
        n = grid.resolution[a]
        if boundary.is_periodic(a):
            ta = torch.remainder(ta, n)
        else:
            upper = n if a == face_axis else n - 1
            ta = ta.clamp(-width, upper + width)
        cols.append(ta + width)
    return torch.stack(cols, dim=-1)


def _prepare_points(points, batch_size: int, rank: int, dtype, device, per_sample: bool):
    p = torch.as_tensor(points, device=device)
    if not p.is_floating_point():
        p = p.to(dtype)
    if p.ndim < 1 or p.shape[-1] != rank:
        raise ShapeError(f"points must end in a coordinate axis of size {rank}, got shape {tuple(p.shape)}")
    if per_sample:
        if p.ndim < 3 or p.shape[0] != batch_size:
            raise ShapeError(f"per-sample points must have shape (B={batch_size}, *P, {rank}), got {tuple(p.shape)}")
        return p.reshape(batch_size, -1, rank), p.shape[1:-1]
    return p.reshape(1, -1, rank).expand(batch_size, -1, -1), p.shape[:-1]


def _sample_at(arr: torch.Tensor, flat: torch.Tensor, grid, boundary, face_axis) -> torch.Tensor:
    """:func:`sample_padded` of ``arr`` (padded by one layer) at physical points ``flat`` ``(B, N, d)``; NaN/Inf
    points raise (CPU) or give NaN (accelerators) instead of a clamped, finite value."""
    finite = _finite_points(flat, "points")
    if finite is not None:
        flat = torch.where(finite[..., None], flat, 0.0)
    out = _sample_padded(arr, _points_to_index(flat, grid, boundary, face_axis, 1))
    return out if finite is None else torch.where(finite[:, None, :], out, torch.nan)


# ---- fields -------------------------------------------------------------------------------------------


def _check_same_domain(source: Grid, target, what: str) -> Grid:
    """``target`` as a Grid covering the same box as ``source`` (to 1e-9 of each extent)."""
    if not isinstance(target, Grid):
        raise ParameterError(f"{what} needs a phisim.Grid, got {type(target).__name__}")
    if target.rank != source.rank:
        raise GridMismatchError(f"cannot {what} a {source.rank}-D field onto a {target.rank}-D grid")
    for axis, ((a0, a1), (b0, b1)) in enumerate(zip(source.bounds, target.bounds)):
        tol = 1e-9 * (a1 - a0)
        if abs(a0 - b0) > tol or abs(a1 - b1) > tol:
            raise GridMismatchError(
                f"cannot {what} onto a grid covering another box: axis {axis} spans ({b0}, {b1}), the field's "
                f"({a0}, {a1}); only the resolution may change"
            )
    return target


class Field:
    """Common behaviour of `CenteredGrid` and `StaggeredGrid`: arithmetic and conversions."""

    grid: Grid
    boundary: Boundary

    # subclasses implement _map(fn) -> same type with fn applied to every values tensor,
    # and _zip(other, fn) -> same type combining matching tensors
    def _check_compatible(self, other: Field, what: str) -> None:
        if type(self) is not type(other):
            raise GridMismatchError(
                f"cannot {what} a {type(self).__name__} and a {type(other).__name__}; resample one of them "
                "first (StaggeredGrid.at_centers() or CenteredGrid.to_staggered())"
            )
        if self.grid != other.grid:
            raise GridMismatchError(f"cannot {what} fields on different grids: {self.grid} vs {other.grid}")
        if self.device != other.device:
            raise GridMismatchError(f"cannot {what} fields on different devices: {self.device} vs {other.device}")
        if self.boundary != other.boundary:
            raise GridMismatchError(
                f"cannot {what} fields with different boundaries: {self.boundary} vs {other.boundary}; "
                "use .with_boundary() on one of them"
            )

    def _binary(self, other, op, what: str, reverse: bool = False):
        # Batch rule of all field arithmetic: the two batch sizes are equal, or one of them is 1 (that operand is
        # shared by every sample of the other); anything else is a ShapeError naming both sizes. A tensor operand
        # with as many axes as the field's values carries a batch axis first; fewer axes broadcast as in torch.
        if isinstance(other, Field):
            self._check_compatible(other, what)
            check_batch_compatible(self, other, ("the left field", "the right field") if not reverse
                                   else ("the right field", "the left field"), what + " fields")
            return self._zip(other, (lambda a, b: op(b, a)) if reverse else op)
        if isinstance(other, np.ndarray):
            other = _as_float_tensor(other)
        if isinstance(other, (str, bytes)) or other is None:
            raise ParameterError(f"cannot {what} a {type(self).__name__} and {other!r}")
        if isinstance(other, torch.Tensor) and other.ndim > self._values_ndim():
            raise ShapeError(
                f"cannot {what} a {type(self).__name__} with values of {self._values_ndim()} axes and a tensor of "
                f"shape {tuple(other.shape)}: the operand has more axes than the field's values (it would broadcast "
                "into a new batch or channel axis)")
        if isinstance(other, torch.Tensor) and other.ndim == self._values_ndim():
            check_batch_compatible(self, other, ("the field", "the tensor operand"),
                                   f"{what} a {type(self).__name__} and a tensor")
        try:
            return self._map((lambda a: op(other, a)) if reverse else (lambda a: op(a, other)))
        except (RuntimeError, TypeError) as exc:
            shape = tuple(other.shape) if isinstance(other, torch.Tensor) else type(other).__name__
            raise ShapeError(
                f"cannot {what} a {type(self).__name__} and {shape}: the operand must be a number or broadcast "
                f"to the field's values (and live on its device {self.device}): {exc}"
            ) from exc

    def __add__(self, other):
        return self._binary(other, operator.add, "add")

    def __radd__(self, other):
        return self._binary(other, operator.add, "add", True)

    def __sub__(self, other):
        return self._binary(other, operator.sub, "subtract")

    def __rsub__(self, other):
        return self._binary(other, operator.sub, "subtract", True)

    def __mul__(self, other):
        return self._binary(other, operator.mul, "multiply")

    def __rmul__(self, other):
        return self._binary(other, operator.mul, "multiply", True)

    def __truediv__(self, other):
        return self._binary(other, operator.truediv, "divide")

    def __rtruediv__(self, other):
        return self._binary(other, operator.truediv, "divide", True)

    def __pow__(self, other):
        return self._binary(other, operator.pow, "raise")

    def __neg__(self):
        return self._map(operator.neg)

    def detach(self):
        """A copy with values detached from the autograd graph."""
        return self._map(torch.Tensor.detach)

    def to(self, device=None, dtype: torch.dtype | None = None):
        """A copy with values moved to ``device`` and/or cast to ``dtype``."""
        device = None if device is None else check_device(device)
        return self._map(lambda a: a.to(device=device or a.device, dtype=dtype or a.dtype))


@dataclass(frozen=True, eq=False, init=False)
class CenteredGrid(Field):
    """Values at cell centres of a ``Grid`` with a ``Boundary``.

    Args:
        values: ``(B, *resolution)`` for a scalar field or ``(B, C, *resolution)`` for a vector field
            (``C == rank`` for velocities). Numpy arrays and nested lists are accepted; integer input is
            converted to the default float dtype.
        grid: The grid.
        boundary: A ``Boundary`` or anything :meth:`Boundary.create` accepts (``'periodic'``, ...).

    Raises:
        ShapeError: If the spatial shape differs from ``grid.resolution``, the batch axis is missing or the
            batch is empty (batch size 0 is refused here, so no operation downstream meets one).
        BoundaryError: For an unknown boundary specification.
    """

    values: torch.Tensor
    grid: Grid
    boundary: Boundary

    def __init__(self, values, grid: Grid, boundary):
        if not isinstance(grid, Grid):
            raise GridMismatchError(f"grid must be a phisim Grid, got {type(grid).__name__}")
        v = _as_float_tensor(values)
        rank = grid.rank
        if v.ndim not in (rank + 1, rank + 2) or tuple(v.shape[v.ndim - rank:]) != grid.resolution:
            raise ShapeError(
                f"CenteredGrid values must have shape (B, {', '.join(map(str, grid.resolution))}) or "
                f"(B, C, {', '.join(map(str, grid.resolution))}) for {grid}, got {tuple(v.shape)}; "
                "add a batch axis with values[None] if needed"
            )
        check_nonempty_batch(v, "CenteredGrid values")
        object.__setattr__(self, "values", v)
        object.__setattr__(self, "grid", grid)
        object.__setattr__(self, "boundary", Boundary.create(boundary, rank).on(grid))

    # constructors
    @classmethod
    def _trusted(cls, values: torch.Tensor, grid: Grid, boundary: Boundary) -> CenteredGrid:
        """A field from parts already known to be valid (internal fast path: no checks, no conversion)."""
        obj = object.__new__(cls)
        object.__setattr__(obj, "values", values)
        object.__setattr__(obj, "grid", grid)
        object.__setattr__(obj, "boundary", boundary)
        return obj

    @classmethod
    def zeros(cls, grid: Grid, boundary, batch_size: int = 1, channels: int | None = None,
              dtype: torch.dtype | None = None, device=None) -> CenteredGrid:
        """A zero field; ``channels=None`` gives a scalar field, an int a vector field with that many channels."""
        _check_count(batch_size, "batch_size")
        if channels is not None:
            _check_count(channels, "channels")
        shape = (batch_size,) + (() if channels is None else (channels,)) + grid.resolution
        device = None if device is None else check_device(device)  # a missing GPU is a ParameterError
        return cls(torch.zeros(shape, dtype=dtype or torch.get_default_dtype(), device=device), grid, boundary)

    @classmethod
    def from_function(cls, fn: Callable[[torch.Tensor], torch.Tensor], grid: Grid, boundary,
                      batch_size: int = 1, dtype: torch.dtype | None = None, device=None) -> CenteredGrid:
        """Sample ``fn`` at the cell centres.

        Args:
            fn: Maps coordinates ``(*resolution, d)`` to ``(*resolution)`` (scalar) or
                ``(*resolution, C)`` (vector).
            grid: The grid.
            boundary: The boundary.
            batch_size: Copies along the batch axis.
            dtype: Floating dtype (default: torch's default).
            device: Torch device.
        """
        x = grid.cell_centers(dtype, device)
        v = torch.as_tensor(fn(x), device=x.device)
        if tuple(v.shape) == grid.resolution:
            v = v[None]
        elif v.ndim == grid.rank + 1 and tuple(v.shape[:-1]) == grid.resolution:
            v = torch.movedim(v, -1, 0)[None]
        else:
            raise ShapeError(f"fn returned shape {tuple(v.shape)}; expected {grid.resolution} or (*resolution, C)")
        return cls(v.expand(batch_size, *v.shape[1:]).clone(), grid, boundary)

    # properties
    @property
    def rank(self) -> int:
        """Number of spatial axes."""
        return self.grid.rank

    @property
    def is_vector(self) -> bool:
        """Whether the field has a channel axis."""
        return self.values.ndim == self.grid.rank + 2

    def _values_ndim(self) -> int:
        return self.values.ndim

    @property
    def batch_size(self) -> int:
        """Size of the batch axis."""
        return self.values.shape[0]

    @property
    def dtype(self) -> torch.dtype:
        """Dtype of the values."""
        return self.values.dtype

    @property
    def device(self) -> torch.device:
        """Device of the values."""
        return self.values.device

    @property
    def points(self) -> torch.Tensor:
        """Cell centres, ``(*resolution, d)``, in the values' dtype and device."""
        return self.grid.cell_centers(self.dtype, self.device)

    # functional updates
    def with_values(self, values) -> CenteredGrid:
        """Same grid and boundary, new values (validated)."""
        return CenteredGrid(values, self.grid, self.boundary)

    def with_boundary(self, boundary) -> CenteredGrid:
        """Same values, new boundary."""
        return CenteredGrid(self.values, self.grid, boundary)

    def _map(self, fn) -> CenteredGrid:
        return CenteredGrid(fn(self.values), self.grid, self.boundary)

    def _zip(self, other: CenteredGrid, fn) -> CenteredGrid:
        a, b = self.values, other.values
        if self.is_vector != other.is_vector:  # scalar * vector broadcasts over components
            a = a.unsqueeze(1) if not self.is_vector else a
            b = b.unsqueeze(1) if not other.is_vector else b
        return CenteredGrid(fn(a, b), self.grid, self.boundary)

    def numpy(self) -> np.ndarray:
        """Values as a numpy array (detached, on the CPU)."""
        return self.values.detach().cpu().numpy()

    def padded(self, width: int = 1) -> torch.Tensor:
        """Values with ``width`` ghost layers per side (see :func:`phisim.boundary.pad`).

        A vector field with one component per axis pads as a velocity (component ``c`` normal to axis ``c``);
        any other channel count pads channel by channel with the scalar rules.
        """
        if self.is_vector and self.values.shape[1] != self.rank:
            B, C = self.values.shape[:2]
            p = pad(self.values.reshape(B * C, *self.grid.resolution), self.boundary, self.grid.dx, width)
            return p.reshape(B, C, *p.shape[1:])
        return pad(self.values, self.boundary, self.grid.dx, width, vector=self.is_vector)

    def sample(self, points, per_sample: bool = False) -> torch.Tensor:
        """Multilinear, boundary-aware interpolation at physical ``points``.

        Points outside a non-periodic side are extrapolated from the ghost layer (so a Dirichlet value is
        met exactly on the boundary face); periodic axes wrap.

        Args:
            points: ``(*P, d)`` shared by all samples, or ``(B, *P, d)`` with ``per_sample=True``.
            per_sample: Whether ``points`` carries a leading batch axis.

        Returns:
            ``(B, *P)`` for scalar fields, ``(B, C, *P)`` for vector fields.

        Raises:
            ShapeError: ``points`` do not end in one coordinate per axis (or lack the batch axis).
            NonFiniteError: A point is NaN/Inf (on the CPU; on accelerators, where the check would cost a device
                sync, the values sampled there are NaN instead).
        """
        flat, lead = _prepare_points(points, self.batch_size, self.rank, self.dtype, self.device, per_sample)
        arr = self.padded(1)
        arr = arr.unsqueeze(1) if not self.is_vector else arr
        out = _sample_at(arr, flat.to(self.dtype), self.grid, self.boundary, None)
        out = out.reshape(out.shape[0], out.shape[1], *lead)
        return out if self.is_vector else out[:, 0]

    def resampled(self, grid: Grid) -> CenteredGrid:
        """The field on another resolution of the same box: :meth:`sample` at the new cell centres (multilinear,
        boundary-aware; exact for fields linear in each axis away from the boundaries). For grid sequencing,
        where a coarse run's state starts a fine one.

        Raises:
            GridMismatchError: ``grid`` covers another box or has another number of axes.
        """
        grid = _check_same_domain(self.grid, grid, "resample")
        values = self.sample(grid.cell_centers(self.dtype, self.device))
        return CenteredGrid._trusted(values.contiguous(), grid, self.boundary.on_grid(grid, self.dtype, self.device))

    def to_staggered(self) -> StaggeredGrid:
        """Resample a velocity (vector, ``C == rank``) to the MAC faces by averaging the two adjacent cells.

        Boundary faces use the ghost cells, so walls and Dirichlet sides get their exact face values.
        """
        if not self.is_vector or self.values.shape[1] != self.rank:
            raise ShapeError("to_staggered needs a vector field with one component per axis")
        comps = []
        for i in range(self.rank):
            p = pad(self.values, self.boundary, self.grid.dx, 1, vector=True, axes=[i])[:, i]
            dim = 1 + i
            n = p.shape[dim]
            comps.append(0.5 * (p.narrow(dim, 0, n - 1) + p.narrow(dim, 1, n - 1)))
        return StaggeredGrid(tuple(comps), self.grid, self.boundary)

    def __repr__(self) -> str:
        kind = f"vector[{self.values.shape[1]}]" if self.is_vector else "scalar"
        return (f"CenteredGrid({kind}, batch={self.batch_size}, {self.grid}, {self.boundary}, "
                f"dtype={self.dtype}, device={self.device})")


@dataclass(frozen=True, eq=False, init=False)
class StaggeredGrid(Field):
    """A MAC (staggered) vector field: component ``i`` on the faces normal to axis ``i``.

    Args:
        values: A sequence of ``rank`` arrays; component ``i`` has shape ``(B, *grid.face_shape(i))``
            (``resolution[i] + 1`` samples along axis ``i``, both boundary faces included).
        grid: The grid.
        boundary: The velocity boundary (walls, open sides, periodic, ...).

    Raises:
        ShapeError: For a wrong number of components, wrong component shapes or an empty batch.
    """

    values: tuple[torch.Tensor, ...]
    grid: Grid
    boundary: Boundary

    def __init__(self, values: Sequence, grid: Grid, boundary):
        if not isinstance(grid, Grid):
            raise GridMismatchError(f"grid must be a phisim Grid, got {type(grid).__name__}")
        if isinstance(values, (torch.Tensor, np.ndarray)) or len(values) != grid.rank:
            raise ShapeError(f"StaggeredGrid needs a sequence of {grid.rank} component arrays for {grid}")
        comps = tuple(_as_float_tensor(v) for v in values)
        batch = comps[0].shape[0] if comps[0].ndim else None
        for i, c in enumerate(comps):
            expected = (batch, *grid.face_shape(i))
            if tuple(c.shape) != expected:
                raise ShapeError(
                    f"StaggeredGrid component {i} must have shape {expected} (resolution + 1 along axis {i}), "
                    f"got {tuple(c.shape)}"
                )
            if c.dtype != comps[0].dtype or c.device != comps[0].device:
                raise ShapeError("all StaggeredGrid components must share dtype and device")
        check_nonempty_batch(comps[0], "StaggeredGrid values")
        object.__setattr__(self, "values", comps)
        object.__setattr__(self, "grid", grid)
        object.__setattr__(self, "boundary", Boundary.create(boundary, grid.rank).on(grid))

    @classmethod
    def _trusted(cls, values: tuple[torch.Tensor, ...], grid: Grid, boundary: Boundary) -> StaggeredGrid:
        """A field from parts already known to be valid (internal fast path: no checks, no conversion)."""
        obj = object.__new__(cls)
        object.__setattr__(obj, "values", tuple(values))
        object.__setattr__(obj, "grid", grid)
        object.__setattr__(obj, "boundary", boundary)
        return obj

    @classmethod
    def zeros(cls, grid: Grid, boundary, batch_size: int = 1, dtype: torch.dtype | None = None,
              device=None) -> StaggeredGrid:
        """A zero velocity field."""
        _check_count(batch_size, "batch_size")
        dtype = dtype or torch.get_default_dtype()
        device = None if device is None else check_device(device)
        return cls(tuple(torch.zeros((batch_size, *grid.face_shape(i)), dtype=dtype, device=device)
                         for i in range(grid.rank)), grid, boundary)

    @classmethod
    def from_function(cls, fn: Callable[[torch.Tensor], torch.Tensor], grid: Grid, boundary,
                      batch_size: int = 1, dtype: torch.dtype | None = None, device=None) -> StaggeredGrid:
        """Sample a vector function at the face centres.

        Args:
            fn: Maps coordinates ``(..., d)`` to velocities ``(..., d)``; component ``i`` is taken at the
                faces normal to axis ``i``.
            grid: The grid.
            boundary: Velocity boundary.
            batch_size: Copies along the batch axis.
            dtype: Floating dtype.
            device: Torch device.
        """
        comps = []
        for i in range(grid.rank):
            x = grid.face_centers(i, dtype, device)
            v = torch.as_tensor(fn(x))
            if tuple(v.shape) != (*grid.face_shape(i), grid.rank):
                raise ShapeError(f"fn must return (..., {grid.rank}) vectors, got {tuple(v.shape)}")
            comps.append(v[..., i][None].expand(batch_size, *grid.face_shape(i)).clone())
        return cls(tuple(comps), grid, boundary)

    @classmethod
    def uniform(cls, velocity: Sequence[float], grid: Grid, boundary, batch_size: int = 1,
                dtype: torch.dtype | None = None, device=None) -> StaggeredGrid:
        """A spatially constant velocity ``velocity`` (one number per axis)."""
        if len(velocity) != grid.rank:
            raise ShapeError(f"uniform velocity needs {grid.rank} components, got {len(velocity)}")
        z = cls.zeros(grid, boundary, batch_size, dtype, device)
        return cls(tuple(c + float(v) for c, v in zip(z.values, velocity)), grid, boundary)

    @property
    def rank(self) -> int:
        """Number of spatial axes (and of components)."""
        return self.grid.rank

    def _values_ndim(self) -> int:
        return self.grid.rank + 1

    @property
    def batch_size(self) -> int:
        """Size of the batch axis."""
        return self.values[0].shape[0]

    @property
    def dtype(self) -> torch.dtype:
        """Dtype of the values."""
        return self.values[0].dtype

    @property
    def device(self) -> torch.device:
        """Device of the values."""
        return self.values[0].device

    def with_values(self, values: Sequence) -> StaggeredGrid:
        """Same grid and boundary, new component arrays (validated)."""
        return StaggeredGrid(values, self.grid, self.boundary)

    def with_boundary(self, boundary) -> StaggeredGrid:
        """Same values, new boundary."""
        return StaggeredGrid(self.values, self.grid, boundary)

    def _map(self, fn) -> StaggeredGrid:
        return StaggeredGrid(tuple(fn(v) for v in self.values), self.grid, self.boundary)

    def _zip(self, other: StaggeredGrid, fn) -> StaggeredGrid:
        return StaggeredGrid(tuple(fn(a, b) for a, b in zip(self.values, other.values)), self.grid, self.boundary)

    def numpy(self) -> tuple[np.ndarray, ...]:
        """Component arrays as numpy arrays."""
        return tuple(v.detach().cpu().numpy() for v in self.values)

    def padded_component(self, component: int, width: int = 1) -> torch.Tensor:
        """Component ``component`` with ``width`` ghost samples per side on every axis."""
        return pad_staggered_component(self.values[component], component, self.boundary, self.grid.dx, width)

    def with_boundary_faces(self) -> StaggeredGrid:
        """Impose the boundary on the normal velocity at boundary faces (walls 0, periodic face n = face 0)."""
        return self._with_components(set_boundary_faces(v, i, self.boundary) for i, v in enumerate(self.values))

    def _with_components(self, comps) -> StaggeredGrid:
        # the components come from this field's own (same shape, dtype and device): no re-validation
        return StaggeredGrid._trusted(tuple(comps), self.grid, self.boundary)

    def at_centers(self) -> CenteredGrid:
        """Average each component's two faces to the cell centre: a ``(B, d, *res)`` `CenteredGrid`."""
        comps = []
        for i, v in enumerate(self.values):
            dim = 1 + i
            n = v.shape[dim] - 1
            comps.append(0.5 * (v.narrow(dim, 0, n) + v.narrow(dim, 1, n)))
        return CenteredGrid(torch.stack(comps, dim=1), self.grid, self.boundary)

    def resampled(self, grid: Grid) -> StaggeredGrid:
        """The velocity on another resolution of the same box: each component interpolated (multilinear,
        boundary-aware, as :meth:`sample`) at the new grid's faces of its axis. The result is not divergence-free in
        general; a projection (any step) makes it so. For grid sequencing, where a coarse run's state starts a fine
        one.

        Raises:
            GridMismatchError: ``grid`` covers another box or has another number of axes.
        """
        grid = _check_same_domain(self.grid, grid, "resample")
        comps = []
        for i in range(self.rank):
            points = grid.face_centers(i, self.dtype, self.device).reshape(1, -1, self.rank)
            points = points.expand(self.batch_size, -1, -1)
            v = _sample_at(self.padded_component(i, 1).unsqueeze(1), points, self.grid, self.boundary, i)[:, 0]
            comps.append(v.reshape(self.batch_size, *grid.face_shape(i)).contiguous())
        return StaggeredGrid._trusted(tuple(comps), grid, self.boundary.on_grid(grid, self.dtype, self.device))

    def sample(self, points, per_sample: bool = False) -> torch.Tensor:
        """Multilinear, boundary-aware interpolation of every component at physical ``points``.

        Args:
            points: ``(*P, d)`` shared by all samples, or ``(B, *P, d)`` with ``per_sample=True``.
            per_sample: Whether ``points`` carries a leading batch axis.

        Returns:
            ``(B, d, *P)``.

        Raises:
            ShapeError: ``points`` do not end in one coordinate per axis (or lack the batch axis).
            NonFiniteError: A point is NaN/Inf (on the CPU; NaN values on accelerators).
        """
        flat, lead = _prepare_points(points, self.batch_size, self.rank, self.dtype, self.device, per_sample)
        flat = flat.to(self.dtype)
        out = []
        for i in range(self.rank):
            out.append(_sample_at(self.padded_component(i, 1).unsqueeze(1), flat, self.grid, self.boundary, i)[:, 0])
        res = torch.stack(out, dim=1)
        return res.reshape(res.shape[0], self.rank, *lead)

    def __repr__(self) -> str:
        return (f"StaggeredGrid(batch={self.batch_size}, {self.grid}, {self.boundary}, dtype={self.dtype}, "
                f"device={self.device})")
