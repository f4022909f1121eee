"""Advection of cell-centred and staggered fields: semi-Lagrangian and MacCormack schemes.

Both schemes trace every sample point of the advected field backwards along the velocity and interpolate
the old field there (multilinear interpolation, boundary-aware through one ghost layer, see
:func:`phisim.boundary.pad`):

* **Semi-Lagrangian** (Stam 1999): ``q^{n+1}(x) = q^n(x - dt v(x))``. Unconditionally stable, first order
  in space and time (at a fixed Courant number the error of a smooth solution falls like ``dx``).
* **MacCormack** (Selle, Fedkiw, Kim, Liu, Rossignac 2008, "An unconditionally stable MacCormack method",
  J. Sci. Comput. 35): a forward semi-Lagrangian step ``q^ = A(q^n)``, a backward step ``q~ = A^R(q^)``
  (the same trace with ``-dt``), and the error-corrected value ``q^{n+1} = q^ + (q^n - q~) / 2``, second
  order for smooth solutions. The corrected value is clamped to the minimum and maximum of the ``2^d``
  samples of ``q^n`` that the forward step interpolated from, so the scheme creates no new extrema
  (``clamp='minmax'``, the default); ``clamp='revert'`` falls back to the semi-Lagrangian value where the
  corrected value leaves that range (Selle et al., section 3), and ``clamp=None`` disables limiting.

Back-tracing uses the velocity at the sample point itself (first-order Euler, ``trace='euler'``, the
standard choice and PhiFlow's) or a midpoint rule (``trace='midpoint'``), which samples the velocity once
more at ``x - dt/2 v(x)``. For a velocity that is uniform in space both are exact.

Sample points and velocities:

* ``CenteredGrid`` (scalar ``(B, *res)`` or vector ``(B, C, *res)``): the cell centres; the velocity at the
  centres is the velocity itself (centred) or the average of the two faces of each component (staggered).
* ``StaggeredGrid`` (self-advection of a MAC velocity, or advection of any MAC field): component ``i`` is
  traced from its own faces (normal to axis ``i``, boundary faces included), with the velocity at those
  faces: component ``i`` itself and, for ``j != i``, the average of the four surrounding ``j`` faces
  (ghosts from the velocity boundary where they lie outside). After the step the boundary is re-imposed on
  the normal velocity at boundary faces (walls 0, Dirichlet values, periodic copies).

Boundaries: a back-traced point outside a non-periodic side is interpolated from the ghost layer built by
the field's own boundary (so a Dirichlet value is met on the face; beyond the ghost layer the ghost value
is held); periodic axes wrap.

Performance: the sample indices of every location are cached per grid, dtype and device; the back-traced
coordinates are built directly in the normalised form that ``torch.nn.functional.grid_sample`` expects,
so one step is a pad, a few element-wise operations and one ``grid_sample`` per array (MacCormack: three).

Everything is differentiable w.r.t. the field values, the velocity and ``dt`` (a tensor ``dt`` keeps its
graph). Interpolation is piecewise linear in the velocity (kinks where a trace crosses a grid line), and
MacCormack's clamp is piecewise too.
"""

from __future__ import annotations

import functools
import math
import warnings

import torch
import torch.nn.functional as F

from phisim import boundary as bmod
from phisim.boundary import Boundary, pad, pad_staggered_component, set_boundary_faces
from phisim.checks import check_batch_compatible, check_dt, check_finite, check_nonempty_batch
from phisim.errors import GridMismatchError, ParameterError, ShapeError
from phisim.field import CenteredGrid, Field, StaggeredGrid
from phisim.grid import Grid
from phisim.ops.conservative import conservative_step
from phisim.padding import const, plan_for

__all__ = ["advect", "semi_lagrangian", "maccormack", "conservative", "SCHEMES", "SCALAR_SCHEMES", "LIMITERS", "TRACES",
           "validate_advection", "advect_trusted"]

#: Schemes that advect any field, staggered velocities included (``advect(v, v, dt)``).
SCHEMES = ("semi_lagrangian", "maccormack")
#: Schemes accepted by :func:`advect` for cell-centred fields: :data:`SCHEMES` and the finite-volume
#: ``'conservative'`` scheme (mass-conserving, non-negative; see :func:`conservative`).
SCALAR_SCHEMES = (*SCHEMES, "conservative")
#: Slope limiters of the conservative scheme (``None``: unlimited central slopes).
LIMITERS = ("van_leer", "mc", "minmod", None)
#: Back-trace rules (``trace=``).
TRACES = ("euler", "midpoint")


def _trace_rule(trace: str, integrator: str | None) -> str:
    """The back-trace rule; ``integrator=`` is its former name (``'rk2'`` meant ``'midpoint'``)."""
    if integrator is None:
        return trace
    warnings.warn("advection's integrator= is now trace= ('euler' or 'midpoint'); 'integrator' names the time "
                  "integrator of a whole fluid step", DeprecationWarning, stacklevel=3)
    return {"rk2": "midpoint"}.get(integrator, integrator)
_CLAMPS = ("minmax", "revert", None)
_WIDTH = 1  # ghost layers used for interpolation


# ---- cached geometry ---------------------------------------------------------------------------------


@functools.lru_cache(maxsize=128)
def _base_index(shape: tuple[int, ...], axis: int, dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    """``arange(shape[axis])`` shaped to broadcast against ``(B, *shape)`` along ``axis``."""
    view = [1] * (len(shape) + 1)
    view[1 + axis] = shape[axis]
    return torch.arange(shape[axis], dtype=dtype, device=device).reshape(view)


class _Location:
    """Sample points of one array (cell centres, or the faces of one MAC component) and how to pad it.

    Attributes:
        shape: Samples per axis.
        period: Per axis the period in samples (``resolution[a]``) if the axis is periodic, else ``None``.
        dx: Cell spacing per axis.
    """

    def __init__(self, grid: Grid, boundary: Boundary, face_axis: int | None):
        self.grid = grid
        self.boundary = boundary
        self.face_axis = face_axis
        self.shape = grid.resolution if face_axis is None else grid.face_shape(face_axis)
        self.period = tuple(grid.resolution[a] if boundary.is_periodic(a) else None for a in range(grid.rank))
        self.dx = grid.dx
        padded = [s + 2 * _WIDTH for s in self.shape]
        # index t (unpadded) -> normalised grid_sample coordinate: (t + w) * 2 / (S - 1) - 1
        self.scale = tuple(2.0 / (s - 1) for s in padded)
        self.offset = tuple(_WIDTH * c - 1.0 for c in self.scale)
        self.padded_shape = tuple(padded)
        self._consts: dict = {}

    def _const(self, dtype, device):
        """Per dtype/device: base indices per axis; scale, offset, clamp bounds and strides in stacked order."""
        key = (dtype, device)
        hit = self._consts.get(key)
        if hit is None:
            d = len(self.shape)
            rev = list(range(d))[::-1]
            view = [1, d] + [1] * d
            bases = [_base_index(self.shape, a, dtype, device) for a in range(d)]
            scale = torch.tensor([self.scale[a] for a in rev], dtype=dtype, device=device).reshape(view)
            offset = torch.tensor([self.offset[a] for a in rev], dtype=dtype, device=device).reshape(view)
            # stencil corners: lower corner k in [0, padded - 2] per axis; flat index in the (padded - 1) array
            sizes = [p - 1 for p in self.padded_shape]
            upper = torch.tensor([sizes[a] - 1 for a in rev], dtype=dtype, device=device).reshape(view)
            strides = [math.prod(sizes[a + 1:]) for a in range(d)]
            stride = torch.tensor([strides[a] for a in rev], dtype=torch.long, device=device).reshape(view)
            one = torch.tensor(float(_WIDTH), dtype=dtype, device=device)
            hit = self._consts[key] = (bases, scale, offset, upper, stride, one, torch.zeros_like(upper))
        return hit

    def padder(self, dtype, device):
        """Pads ``(B, C, *shape)`` channel by channel (scalars, or MAC component ``face_axis``) by a cached
        gather plan, or ``None`` where the boundary has non-constant rules (then the general path pads)."""
        if not bmod._fast_padding(self.shape):
            return None
        key = ("pad", dtype, device)
        if key not in self._consts:
            plan = plan_for(self.boundary, self.dx, _WIDTH, tuple(range(len(self.shape))), None, self.shape,
                            self.face_axis, dtype, device)
            self._consts[key] = None if plan is None else plan.per_channel
        return self._consts[key]

    def physical_points(self, dtype, device) -> torch.Tensor:
        """Physical sample positions ``(*shape, d)``."""
        if self.face_axis is None:
            return self.grid.cell_centers(dtype, device)
        return self.grid.face_centers(self.face_axis, dtype, device)

    def trace(self, velocity: list[torch.Tensor], step) -> list[torch.Tensor]:
        """Unpadded fractional indices ``x - step * v / dx`` per axis, wrapped on periodic axes.

        Args:
            velocity: Per axis ``(B, *shape)`` velocity at the sample points.
            step: The signed time step (number or 0-d tensor).

        Returns:
            Per axis ``(B, *shape)`` indices.
        """
        out = []
        bases = self._const(velocity[0].dtype, velocity[0].device)[0]
        for a, v in enumerate(velocity):
            base = bases[a]
            if isinstance(step, torch.Tensor):
                t = base - v * (step / self.dx[a])
            else:
                t = torch.add(base, v, alpha=-float(step) / self.dx[a])
            if self.period[a] is not None:
                t = torch.remainder(t, self.period[a])
            out.append(t)
        return out

    def sample(self, padded: torch.Tensor, index: list[torch.Tensor]) -> torch.Tensor:
        """Interpolate the padded array ``(B, C, *padded_shape)`` at unpadded indices; returns ``(B, C, *shape)``."""
        cols = [index[a] * self.scale[a] + self.offset[a] for a in range(len(index))]
        if len(cols) == 1:  # 1-D: a 2-D kernel on a single row
            zero = torch.zeros_like(cols[0])
            grid = torch.stack([cols[0], zero], dim=1).movedim(1, -1).unsqueeze(1)
            out = F.grid_sample(padded.unsqueeze(2), grid, mode="bilinear", padding_mode="border",
                                align_corners=True)
            return out[:, :, 0]
        # grid_sample wants the last array axis first in the coordinate axis; stacking on dim 1 and moving
        # that axis last as a view is much faster than stacking on the last (strided) axis
        grid = torch.stack(cols[::-1], dim=1).movedim(1, -1)
        return F.grid_sample(padded, grid, mode="bilinear", padding_mode="border", align_corners=True)

    def stack(self, index: list[torch.Tensor]) -> torch.Tensor:
        """The indices stacked in ``grid_sample``'s coordinate order (last axis first): ``(B, d, *shape)``."""
        return torch.stack(index[::-1], dim=1)

    def sample_stacked(self, padded: torch.Tensor, stacked: torch.Tensor) -> torch.Tensor:
        """:meth:`sample` from indices stacked by :meth:`stack` (one scale and one shift for all axes)."""
        if stacked.shape[1] == 1:
            return self.sample(padded, [stacked[:, 0]])
        scale, offset = self._const(stacked.dtype, stacked.device)[1:3]
        grid = (stacked * scale + offset).movedim(1, -1)
        # F.grid_sample(mode='bilinear', padding_mode='border', align_corners=True) without its argument checks
        return torch.grid_sampler(padded, grid, 0, 1, True)

    def bounds_stacked(self, padded: torch.Tensor, stacked: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """:meth:`stencil_bounds` from indices stacked by :meth:`stack` (the corner index in a few ops)."""
        hi, lo = padded, padded
        for a in range(stacked.shape[1]):
            dim = 2 + a
            n = hi.shape[dim] - 1
            hi = torch.maximum(hi.narrow(dim, 0, n), hi.narrow(dim, 1, n))
            lo = torch.minimum(lo.narrow(dim, 0, n), lo.narrow(dim, 1, n))
        _, _, _, upper, stride, one, zero = self._const(stacked.dtype, stacked.device)
        # one = _WIDTH; a NaN index (a NaN velocity, unchecked on a stepper's path) reads corner 0, not out of bounds
        k = torch.clamp((stacked.detach() + one).floor_().nan_to_num_(0.0), min=zero, max=upper).long()
        flat = (k * stride).sum(1)
        B, C = padded.shape[0], padded.shape[1]
        flat = flat.reshape(flat.shape[0], 1, -1).expand(B, C, -1)
        hi = torch.gather(hi.reshape(B, C, -1), 2, flat).reshape(B, C, *self.shape)
        lo = torch.gather(lo.reshape(B, C, -1), 2, flat).reshape(B, C, *self.shape)
        return lo, hi

    def stencil_bounds(self, padded: torch.Tensor, index: list[torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor]:
        """Minimum and maximum of the ``2^d`` samples that linear interpolation at ``index`` reads.

        Args:
            padded: ``(B, C, *padded_shape)``.
            index: Per axis ``(B, *shape)`` unpadded indices (as passed to :meth:`sample`).

        Returns:
            Two ``(B, C, *shape)`` tensors (differentiable w.r.t. ``padded``; the stencil choice is not).
        """
        hi, lo = padded, padded
        for a in range(len(index)):
            dim = 2 + a
            n = hi.shape[dim] - 1
            hi = torch.maximum(hi.narrow(dim, 0, n), hi.narrow(dim, 1, n))
            lo = torch.minimum(lo.narrow(dim, 0, n), lo.narrow(dim, 1, n))
        # hi[k] = max(padded[k], padded[k + 1]) per axis: the stencil with lower corner k
        flat = None
        stride = 1
        for a in reversed(range(len(index))):
            size = hi.shape[2 + a]
            k = (index[a].detach() + _WIDTH).floor().nan_to_num_(0.0).clamp_(0, size - 1).long()
            flat = k * stride if flat is None else flat + k * stride
            stride *= size
        B, C = padded.shape[0], padded.shape[1]
        flat = flat.reshape(flat.shape[0], 1, -1).expand(B, C, -1)
        hi = torch.gather(hi.reshape(B, C, -1), 2, flat).reshape(B, C, *self.shape)
        lo = torch.gather(lo.reshape(B, C, -1), 2, flat).reshape(B, C, *self.shape)
        return lo, hi


def _location(grid: Grid, boundary: Boundary, face_axis: int | None) -> _Location:
    """The sample location, kept on the boundary object: an eager call builds it (with its padding plans and
    index tensors) and a step traced by ``torch.compile`` finds it there instead of tracing its construction."""
    return boundary._memo(("advection_location", grid, face_axis), lambda: _Location(grid, boundary, face_axis))


# ---- velocity at sample points -----------------------------------------------------------------------


def _check_velocity(velocity, grid: Grid) -> None:
    if not isinstance(velocity, (CenteredGrid, StaggeredGrid)):
        raise GridMismatchError(
            f"velocity must be a CenteredGrid (vector) or StaggeredGrid, got {type(velocity).__name__}"
        )
    if velocity.grid != grid:
        raise GridMismatchError(
            f"the velocity lives on {velocity.grid} but the advected field on {grid}; resample one of them"
        )
    if isinstance(velocity, CenteredGrid) and (not velocity.is_vector or velocity.values.shape[1] != grid.rank):
        raise ShapeError(
            f"a centred velocity needs one component per axis, shape (B, {grid.rank}, *resolution), got "
            f"{tuple(velocity.values.shape)}"
        )


def _velocity_at_centers(velocity: Field) -> list[torch.Tensor]:
    """Per axis ``(B, *res)`` velocity at the cell centres."""
    if isinstance(velocity, CenteredGrid):
        return [velocity.values[:, a] for a in range(velocity.rank)]
    out = []
    half = const(0.5, velocity.dtype, velocity.device)
    for i, v in enumerate(velocity.values):
        dim = 1 + i
        n = v.shape[dim] - 1
        out.append((v.narrow(dim, 0, n) + v.narrow(dim, 1, n)) * half)
    return out


def _velocity_at_faces(velocity: Field, axis: int) -> list[torch.Tensor]:
    """Per component ``(B, *face_shape(axis))`` velocity at the faces normal to ``axis``."""
    grid, boundary = velocity.grid, velocity.boundary
    dim_i = 1 + axis
    if isinstance(velocity, CenteredGrid):
        p = pad(velocity.values, boundary, grid.dx, 1, vector=True, axes=[axis])
        n = p.shape[2 + axis] - 1
        avg = 0.5 * (p.narrow(2 + axis, 0, n) + p.narrow(2 + axis, 1, n))
        return [avg[:, c] for c in range(grid.rank)]
    out = []
    half = const(0.5, velocity.dtype, velocity.device)
    for j, v in enumerate(velocity.values):
        if j == axis:
            out.append(v)
            continue
        p = pad_staggered_component(v, j, boundary, grid.dx, 1, axes=[axis])
        n = p.shape[dim_i] - 1
        p = (p.narrow(dim_i, 0, n) + p.narrow(dim_i, 1, n)) * half  # centre along axis -> faces
        dim_j = 1 + j
        m = p.shape[dim_j] - 1
        out.append((p.narrow(dim_j, 0, m) + p.narrow(dim_j, 1, m)) * half)  # faces along j -> centres
    return out


def _as_dtype(vel: list[torch.Tensor], dtype) -> list[torch.Tensor]:
    return vel if vel[0].dtype == dtype else [v.to(dtype) for v in vel]


def _broadcast_batch(vel: list[torch.Tensor], batch: int) -> list[torch.Tensor]:
    b = vel[0].shape[0]
    if b == batch:
        return vel
    if b == 1:
        return [v.expand(batch, *v.shape[1:]) for v in vel]
    raise ShapeError(f"velocity batch size {b} does not match the field's batch size {batch} (nor is it 1)")


def _midpoint_velocity(velocity: Field, loc: _Location, vel: list[torch.Tensor], step) -> list[torch.Tensor]:
    """Velocity at ``x - step/2 v(x)`` (the midpoint of an RK2 trace), per axis ``(B, *shape)``."""
    pts = loc.physical_points(vel[0].dtype, vel[0].device)
    v = torch.stack(vel, dim=-1)  # (B, *shape, d)
    mid = pts - 0.5 * step * v
    if velocity.batch_size == 1 and mid.shape[0] != 1:
        velocity = velocity._map(lambda a: a.expand(mid.shape[0], *a.shape[1:]))
    s = velocity.sample(mid, per_sample=True)  # (B, d, *shape)
    return [s[:, a] for a in range(s.shape[1])]


# ---- the core step on one array ---------------------------------------------------------------------


def _advect_array(values: torch.Tensor, pad_fn, loc: _Location, vel: list[torch.Tensor], dt, scheme: str,
                  clamp, back_vel: list[torch.Tensor] | None) -> torch.Tensor:
    """Advect ``values`` ``(B, C, *shape)`` whose padded form ``pad_fn(values)`` is ``(B, C, *padded_shape)``."""
    padded = pad_fn(values)
    index = loc.stack(loc.trace(vel, dt))
    forward = loc.sample_stacked(padded, index)
    if scheme == "semi_lagrangian":
        return forward
    back = loc.stack(loc.trace(back_vel if back_vel is not None else vel, -dt))
    backward = loc.sample_stacked(pad_fn(forward), back)
    corrected = forward + (values - backward) * const(0.5, values.dtype, values.device)
    if clamp is None:
        return corrected
    lo, hi = loc.bounds_stacked(padded, index)
    if clamp == "minmax":
        return torch.minimum(torch.maximum(corrected, lo), hi)
    outside = (corrected < lo) | (corrected > hi)
    return torch.where(outside, forward, corrected)


def _pad_centered(x: torch.Tensor, boundary: Boundary, dx, velocity_like: bool) -> torch.Tensor:
    """Pad ``(B, C, *res)``: as a velocity (component ``c`` normal to axis ``c``) or channel by channel as scalars."""
    if velocity_like:
        return pad(x, boundary, dx, _WIDTH, vector=True)
    B, C = x.shape[:2]
    p = pad(x.reshape(B * C, *x.shape[2:]), boundary, dx, _WIDTH)
    return p.reshape(B, C, *p.shape[1:])


def validate_advection(field, velocity, dt, scheme, trace, clamp):
    if scheme not in SCALAR_SCHEMES:
        raise ParameterError(f"unknown advection scheme {scheme!r}; choose one of {SCALAR_SCHEMES}")
    if scheme == "conservative" and isinstance(field, StaggeredGrid):
        raise ParameterError(
            "the conservative scheme transports cell-centred fields (markers, densities); advect a "
            f"StaggeredGrid with one of {SCHEMES}"
        )
    if trace not in TRACES:
        raise ParameterError(f"unknown back-trace rule trace={trace!r}; choose one of {TRACES}")
    if clamp not in _CLAMPS:
        raise ParameterError(f"unknown clamp {clamp!r}; choose one of {_CLAMPS}")
    if not isinstance(field, (CenteredGrid, StaggeredGrid)):
        raise GridMismatchError(f"can only advect a CenteredGrid or StaggeredGrid, got {type(field).__name__}")
    dt = check_dt(dt)
    _check_velocity(velocity, field.grid)
    check_nonempty_batch(field, "the advected field")
    check_batch_compatible(field, velocity, ("the advected field", "the velocity"), "advect")
    if velocity.device.type == "cpu":  # on accelerators this check would force a device sync per step
        comps = velocity.values if isinstance(velocity, StaggeredGrid) else (velocity.values,)
        # one cheap reduction per component and one read-back: NaN/Inf make the sum non-finite; an
        # overflowing sum of finite values falls through to the exact element-wise check
        total = None
        for v in comps:
            s = v.detach().sum()
            total = s if total is None else total + s
        if not math.isfinite(float(total)):
            for i, v in enumerate(comps):
                check_finite(v, "velocity" if isinstance(velocity, CenteredGrid) else f"velocity component {i}")
    return dt


def advect(field: Field, velocity: Field, dt, *, scheme: str = "semi_lagrangian", trace: str = "euler",
           clamp: str | None = "minmax", limiter: str | None = "van_leer", cfl: float = 0.5,
           integrator: str | None = None) -> Field:
    """Advect ``field`` by ``velocity`` over one time step ``dt``.

    Args:
        field: A ``CenteredGrid`` (scalar ``(B, *res)`` or vector ``(B, C, *res)``) or a ``StaggeredGrid``
            (each component is traced from its own faces; ``advect(v, v, dt)`` is self-advection).
        velocity: A centred vector field ``(B, d, *res)`` or a ``StaggeredGrid`` on the same grid as
            ``field``; batch size equal to the field's or 1 (shared by all samples).
        dt: Time step ``>= 0`` (number or 0-d tensor; gradients w.r.t. a tensor ``dt`` are kept).
        scheme: ``'semi_lagrangian'`` (first order), ``'maccormack'`` (second order, clamped) or, for
            ``CenteredGrid`` fields only, ``'conservative'`` (finite-volume flux form, second order, keeps the
            total to round-off and non-negative data non-negative; see :func:`conservative`).
        trace: Back-trace rule: ``'euler'`` (``x - dt v(x)``) or ``'midpoint'``.
        clamp: MacCormack limiter: ``'minmax'`` (clamp to the interpolation stencil of the forward step),
            ``'revert'`` (use the semi-Lagrangian value where the corrected one leaves that range) or
            ``None``. Ignored by the semi-Lagrangian scheme.
        limiter: Slope limiter of the conservative scheme (see :func:`conservative`); ignored otherwise.
        cfl: Largest outflow Courant number per sub-step of the conservative scheme; ignored otherwise.
        integrator: Former name of ``trace`` (``'rk2'`` = ``'midpoint'``); deprecated.

    Returns:
        A field of the same type, grid, boundary, shape and dtype as ``field``.

    Raises:
        ParameterError: For a negative or non-finite ``dt`` or an unknown scheme/trace/clamp.
        GridMismatchError: If the field and the velocity live on different grids, or are not fields.
        ShapeError: If a centred velocity does not have one component per axis, or the batch sizes differ.
        NonFiniteError: If the velocity contains NaN/Inf (checked on CPU only, where it costs no sync).
    """
    trace = _trace_rule(trace, integrator)
    dt = validate_advection(field, velocity, dt, scheme, trace, clamp)
    return advect_trusted(field, velocity, dt, scheme, trace, clamp, limiter, cfl)


def advect_trusted(field: Field, velocity: Field, dt, scheme: str = "semi_lagrangian", trace: str = "euler",
            clamp: str | None = "minmax", limiter: str | None = "van_leer", cfl: float = 0.5) -> Field:
    """:func:`advect` on arguments already validated by the caller (the entry of a fluid step)."""
    if scheme == "conservative":

        return conservative_step(field, velocity, dt, limiter=limiter, cfl=cfl)
    grid, boundary = field.grid, field.boundary
    if isinstance(field, CenteredGrid):
        vel = _broadcast_batch(_as_dtype(_velocity_at_centers(velocity), field.dtype), field.batch_size)
        loc = _location(grid, boundary, None)
        vel, back = _trace_velocity(velocity, loc, vel, dt, trace, scheme)
        values = field.values if field.is_vector else field.values.unsqueeze(1)

        velocity_like = field.is_vector and values.shape[1] == grid.rank
        pad_fn = None if velocity_like else loc.padder(values.dtype, values.device)
        if pad_fn is None:
            pad_fn = functools.partial(_pad_centered, boundary=boundary, dx=grid.dx, velocity_like=velocity_like)
        out = _advect_array(values, pad_fn, loc, vel, dt, scheme, clamp, back)
        return CenteredGrid._trusted(out if field.is_vector else out[:, 0], grid, boundary)
    comps = []
    for i, comp in enumerate(field.values):
        vel = _broadcast_batch(_as_dtype(_velocity_at_faces(velocity, i), field.dtype), field.batch_size)
        loc = _location(grid, boundary, i)
        vel, back = _trace_velocity(velocity, loc, vel, dt, trace, scheme)

        pad_fn = loc.padder(comp.dtype, comp.device)
        if pad_fn is None:
            def pad_fn(x, i=i):
                return pad_staggered_component(x[:, 0], i, boundary, grid.dx, _WIDTH).unsqueeze(1)

        out = _advect_array(comp.unsqueeze(1), pad_fn, loc, vel, dt, scheme, clamp, back)[:, 0]
        if not boundary.is_periodic(i):
            out = set_boundary_faces(out, i, boundary)
        comps.append(out)
    return StaggeredGrid._trusted(tuple(comps), grid, boundary)


def _trace_velocity(velocity, loc, vel, dt, trace, scheme):
    """Velocities for the forward and (MacCormack) backward trace under the chosen rule."""
    if trace == "euler":
        return vel, None
    forward = _midpoint_velocity(velocity, loc, vel, dt)
    backward = _midpoint_velocity(velocity, loc, vel, -dt) if scheme == "maccormack" else None
    return forward, backward


def semi_lagrangian(field: Field, velocity: Field, dt, *, trace: str = "euler", integrator: str | None = None
                    ) -> Field:
    """Semi-Lagrangian advection ``q(x) <- q(x - dt v(x))`` (first order; Stam 1999).

    Args:
        field: ``CenteredGrid`` (scalar or vector) or ``StaggeredGrid`` to advect.
        velocity: Centred vector or staggered velocity on the same grid.
        dt: Time step ``>= 0``.
        trace: ``'euler'`` or ``'midpoint'`` back-trace.
        integrator: Former name of ``trace`` (deprecated).

    Returns:
        The advected field (same type, grid and boundary).

    Raises:
        ParameterError, GridMismatchError, ShapeError, NonFiniteError: See :func:`advect`.
    """
    return advect(field, velocity, dt, scheme="semi_lagrangian", trace=_trace_rule(trace, integrator))


def maccormack(field: Field, velocity: Field, dt, *, trace: str = "euler", clamp: str | None = "minmax",
               integrator: str | None = None) -> Field:
    """MacCormack advection with extrema clamping (second order; Selle et al. 2008).

    ``q^ = SL(q, dt)``, ``q~ = SL(q^, -dt)``, ``q_new = q^ + (q - q~)/2``, clamped to the range of the
    ``2^d`` samples of ``q`` read by the forward step (``clamp='minmax'``), or replaced by ``q^`` where it
    leaves that range (``clamp='revert'``).

    Args:
        field: ``CenteredGrid`` (scalar or vector) or ``StaggeredGrid`` to advect.
        velocity: Centred vector or staggered velocity on the same grid.
        dt: Time step ``>= 0``.
        trace: ``'euler'`` or ``'midpoint'`` back-trace.
        clamp: ``'minmax'``, ``'revert'`` or ``None``.
        integrator: Former name of ``trace`` (deprecated).

    Returns:
        The advected field (same type, grid and boundary).

    Raises:
        ParameterError, GridMismatchError, ShapeError, NonFiniteError: See :func:`advect`.
    """
    return advect(field, velocity, dt, scheme="maccormack", trace=_trace_rule(trace, integrator), clamp=clamp)


def conservative(field: CenteredGrid, velocity: Field, dt, *, limiter: str | None = "van_leer",
                 cfl: float = 0.5) -> CenteredGrid:
    """Conservative finite-volume transport ``∂q/∂t + ∇·(u q) = 0`` of a cell-centred field.

    Each cell changes by the fluxes through its faces, ``q_i -= dt/dx (F_{i+1/2} - F_{i-1/2})`` on every
    axis, so whatever leaves one cell enters its neighbour: the total ``Σ q dV`` is kept to round-off in
    periodic domains and closed boxes (walls carry no flux), and changes only by the fluxes through open,
    inflow or Dirichlet sides. The face flux is ``u_f q_f`` with the face velocity ``u_f`` (the MAC
    velocity itself, or the average of two cell centres for a centred velocity) and the upwind value
    ``q_f`` of a MUSCL reconstruction (piecewise-linear, slopes limited per axis by ``limiter``); time
    integration is Heun's SSP-RK2. Second order in space and time on smooth fields (the limiter clips
    extrema, where the scheme is locally first order; measured L1 orders in ``tests``).

    Non-negativity and the maximum principle: with a TVD limiter every reconstructed face value of a
    cell lies in ``[0, 2 q_i]`` for non-negative data, so a forward-Euler stage keeps ``q >= 0`` when the
    outflow Courant number of every cell, ``dt Σ_axes (max(u_hi, 0) + max(-u_lo, 0)) / dx``, is at most
    1/2; the step is split into equal sub-steps so that this holds (``cfl``), and SSP-RK2 keeps the
    property. Cells next to a non-periodic side use zero slope; inflow through such a side carries the
    boundary value (Dirichlet) or the ghost value (Neumann, walls, open sides).

    For a divergence-free velocity this is also the advective form ``∂q/∂t + u·∇q = 0`` (constants stay
    constant); for a divergent one it is the conservative form (a density accumulates where flow
    converges).

    Args:
        field: Scalar ``(B, *res)`` or multi-channel ``(B, C, *res)`` CenteredGrid (a ``C == rank`` field
            is padded as a vector with its wall roles).
        velocity: StaggeredGrid (preferred: its face values are the fluxes' velocities) or centred vector
            field on the same grid; batch size equal to the field's or 1.
        dt: Time step ``>= 0`` (number or 0-d tensor).
        limiter: ``'van_leer'`` (default; harmonic mean of the one-sided slopes), ``'mc'`` (monotonised
            central), ``'minmod'`` (most diffusive) or ``None`` (unlimited central slopes: second order
            everywhere, neither non-negative nor monotone).
        cfl: Largest outflow Courant number per sub-step, ``0 < cfl``; ``<= 0.5`` guarantees
            non-negativity with a limiter.

    Returns:
        The transported field (same grid, boundary, shape and dtype); differentiable w.r.t. the values,
        the velocity and a tensor ``dt`` (the sub-step count is chosen from the detached velocity).

    Raises:
        ParameterError: For a negative or non-finite ``dt``, an unknown limiter, a bad ``cfl`` or a
            StaggeredGrid ``field``.
        GridMismatchError, ShapeError, NonFiniteError: See :func:`advect`.
    """
    return advect(field, velocity, dt, scheme="conservative", limiter=limiter, cfl=cfl)
