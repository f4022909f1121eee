"""Cached gather plans for ghost padding with constant boundary rules (the fast path of :mod:`phisim.boundary`).

With constant rules (periodic, and odd/even reflections whose value or flux is a plain number) every padded
sample is ``sign * x[source] + offset``: a ghost copies a mirror or periodic sample, negated by an odd
reflection and shifted by ``2 v`` (odd, value ``v``) or by the flux times the ghost distance (even). A plan
stores, per padded axis, the source index, the signs and the offsets as tensors, so that padding costs one
``index_select`` per axis (plus a multiply and an add where signs or offsets are present) instead of a
narrow, flip, arithmetic and concatenation per side. When no offset is present the axes compose into one
gather over the flattened sample axes and one multiply by the product of the signs.

The arithmetic reproduces :func:`phisim.boundary._pad_axis` exactly: ``-u`` is ``u * -1``, ``2 v - u`` is
``-u + c`` with ``c`` the same float of the dtype, and ``u + f * spacing`` adds the same offset tensor.
"""

from __future__ import annotations

import functools
import math

import torch

from phisim.errors import ShapeError


@functools.lru_cache(maxsize=256)
def const(value: float, dtype, device) -> torch.Tensor:
    """A cached 0-d tensor: ``x * const(0.5, x.dtype, x.device)`` is ``0.5 * x`` bit for bit (the number is
    rounded to the dtype either way) without wrapping a Python number on every call."""
    return torch.tensor(value, dtype=dtype, device=device)


def _is_number(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def constant_rules(rules) -> bool:
    """Whether every rule of ``((lo_rule, hi_rule), ...)`` is periodic or carries a plain number."""
    for pair in rules:
        for r in pair:
            if r[0] != "periodic" and not _is_number(r[1]):
                return False
    return True


def _spacing(width: int, dx: float, face: bool, dtype, device) -> torch.Tensor:
    """Ghost distances ``(2k - 1) dx`` (cell-centred) or ``2 k dx`` (faces), computed as :mod:`boundary` does."""
    k = torch.arange(1, width + 1, dtype=dtype, device=device)
    return (2 * k if face else 2 * k - 1) * dx


def _axis_map(length: int, n: int, width: int, lo_rule, hi_rule, dx: float, face: bool, dtype, device):
    """Source indices, signs and offsets (``None`` when all are 0) of one padded axis of ``length`` samples."""
    if width > n:
        raise ShapeError(f"cannot pad {width} ghost layers onto an axis of {n} cells")
    start = 1 if face else 0
    mid = list(range(length))
    if lo_rule[0] == "periodic":
        src = list(range(n - width, n)) + mid + list(range(start, start + width))
        return src, [1.0] * len(src), None
    lo_src = [start + width - 1 - j for j in range(width)]  # array order: g_w .. g_1
    hi_src = [length - 1 - start - j for j in range(width)]  # g_1 .. g_w
    src = lo_src + mid + hi_src
    sign = [1.0] * len(src)
    off = torch.zeros(len(src), dtype=dtype, device=device)
    any_off = False
    sp = None
    for rule, pos, k_of in ((lo_rule, range(width), lambda j: width - 1 - j),
                            (hi_rule, range(width + length, 2 * width + length), lambda j: j)):
        kind, val = rule[0], rule[1]
        for j, p in enumerate(pos):
            if kind == "odd":
                sign[p] = -1.0
                if val != 0:
                    off[p] = float(2 * val)
                    any_off = True
            elif val != 0:
                if sp is None:
                    sp = _spacing(width, dx, face, dtype, device)
                off[p] = val * sp[k_of(j)]
                any_off = True
    return src, sign, (off if any_off else None)


class PadPlan:
    """Padding of ``(B, *lead, *shape)`` arrays by cached gathers; see the module docstring."""

    def __init__(self, flat, steps, out_shape):
        self.flat = flat  # (index, sign or None) over the flattened non-batch axes, or None
        self.steps = steps  # per axis (dim, index, sign or None, offset or None)
        self.out_shape = out_shape  # non-batch shape of the result

    def __call__(self, x: torch.Tensor) -> torch.Tensor:
        """The padded array."""
        if self.flat is not None:
            idx, sign = self.flat
            y = x.reshape(x.shape[0], -1).index_select(1, idx)
            if sign is not None:
                y = y * sign
            return y.reshape(x.shape[0], *self.out_shape)
        for dim, idx, sign, off in self.steps:
            x = x.index_select(dim, idx)
            if sign is not None:
                x = x * sign
            if off is not None:
                x = x + off
        return x

    def per_channel(self, x: torch.Tensor) -> torch.Tensor:
        """Pad ``(B, C, ...)``, every channel by this (channel-free) plan: the same operations on ``B * C`` rows."""
        B, C = x.shape[0], x.shape[1]
        if self.flat is not None:
            idx, sign = self.flat
            y = x.reshape(B * C, -1).index_select(1, idx)
            if sign is not None:
                y = y * sign
            return y.reshape(B, C, *self.out_shape)
        y = self(x.reshape(B * C, *x.shape[2:]))
        return y.reshape(B, C, *y.shape[1:])


@functools.lru_cache(maxsize=256)
def pad_plan(shape: tuple[int, ...], channels: int | None, axes: tuple[int, ...], counts: tuple[int, ...],
             rules: tuple, width: int, dx: tuple[float, ...], faces: tuple[bool, ...], dtype, device) -> PadPlan:
    """The plan padding ``(B, [C,] *shape)`` along ``axes``.

    Args:
        shape: Spatial shape of the input.
        channels: ``None`` for ``(B, *shape)``; else the number of channels, each with its own rules.
        axes: The padded spatial axes, in padding order.
        counts: Per padded axis the number of cells ``n`` (see :func:`phisim.boundary._pad_axis`).
        rules: Per channel (one entry when ``channels`` is None) and padded axis the ``(lo, hi)`` rules.
        width: Ghost layers per side.
        dx: Per padded axis the cell spacing.
        faces: Per padded axis whether the samples lie on faces along it.
        dtype, device: Of the arrays.
    """
    nch = 1 if channels is None else channels
    lead = 1 if channels is None else 2
    out_shape = list(shape)
    steps = []
    maps = []  # per axis: (src, sign per channel, off per channel)
    for j, a in enumerate(axes):
        srcs, signs, offs = [], [], []
        for c in range(nch):
            lo, hi = rules[c][j]
            src, sign, off = _axis_map(out_shape[a], counts[j], width, lo, hi, dx[j], faces[j], dtype, device)
            srcs.append(src)
            signs.append(sign)
            offs.append(off)
        out_shape[a] += 2 * width
        maps.append((srcs[0], signs, offs))
        dim = lead + a
        idx = torch.tensor(srcs[0], dtype=torch.long, device=device)
        view = [1] * (lead + len(shape))
        view[dim] = len(srcs[0])
        if channels is not None:
            view[1] = nch
        sign = None
        if any(s != 1.0 for sg in signs for s in sg):
            sign = torch.tensor(signs, dtype=dtype, device=device).reshape(view)
        off = None
        if any(o is not None for o in offs):
            off = torch.stack([o if o is not None else torch.zeros(len(srcs[0]), dtype=dtype, device=device)
                               for o in offs]).reshape(view)
        steps.append((dim, idx, sign, off))
    flat = None
    if all(s[3] is None for s in steps):
        flat = _flatten(tuple(shape), nch, axes, maps, tuple(out_shape), dtype, device)
    full_out = tuple(out_shape) if channels is None else (nch, *out_shape)
    return PadPlan(flat, steps, full_out)


def _flatten(shape, nch, axes, maps, out_shape, dtype, device):
    """One gather (and one sign product) over the flattened ``(C, *shape)`` axes for offset-free rules."""
    rank = len(shape)
    src_axes = [torch.arange(s, dtype=torch.long, device=device) for s in out_shape]
    sign_axes = [None] * rank
    for (src, signs, _), a in zip(maps, axes):
        src_axes[a] = torch.tensor(src, dtype=torch.long, device=device)
        sign_axes[a] = signs
    strides = [math.prod(shape[a + 1:]) for a in range(rank)]
    index = torch.zeros(out_shape, dtype=torch.long, device=device)
    for a in range(rank):
        view = [1] * rank
        view[a] = out_shape[a]
        index = index + (src_axes[a] * strides[a]).reshape(view)
    chan = torch.arange(nch, dtype=torch.long, device=device).reshape(nch, *([1] * rank)) * math.prod(shape)
    index = (index.unsqueeze(0) + chan).reshape(-1)
    if not any(s is not None and any(v != 1.0 for sg in s for v in sg) for s in sign_axes):
        return index, None
    sign = torch.ones((nch, *out_shape), dtype=torch.float64, device=device)
    for a in range(rank):
        if sign_axes[a] is None:
            continue
        view = [nch] + [1] * rank
        view[1 + a] = out_shape[a]
        sign = sign * torch.tensor(sign_axes[a], dtype=torch.float64, device=device).reshape(view)
    return index, sign.to(dtype).reshape(-1)


class FacePlan:
    """Boundary faces of a MAC component set by one gather (periodic) or one ``where`` (fixed values)."""

    def __init__(self, dim, index, keep, fill):
        self.dim, self.index, self.keep, self.fill = dim, index, keep, fill

    def __call__(self, x: torch.Tensor) -> torch.Tensor:
        """``x`` with its boundary faces imposed (always a new tensor)."""
        if self.index is not None:
            return x.index_select(self.dim, self.index)
        if self.keep is None:
            return x.clone()
        return torch.where(self.keep, x, self.fill)


@functools.lru_cache(maxsize=256)
def face_plan(ndim: int, dim: int, length: int, rules: tuple, dtype, device) -> FacePlan:
    """The plan of :func:`phisim.boundary.set_boundary_faces` for constant normal-velocity ``rules``.

    Periodic: face ``n`` becomes a copy of face 0. Odd rules (walls, Dirichlet) set their face to the value;
    even rules (open, Neumann) leave it.
    """
    if rules[0][0] == "periodic":
        idx = torch.tensor([*range(length - 1), 0], dtype=torch.long, device=device)
        return FacePlan(dim, idx, None, None)
    view = [1] * ndim
    view[dim] = length
    keep = torch.ones(length, dtype=torch.bool, device=device)
    fill = torch.zeros(length, dtype=dtype, device=device)
    for pos, r in ((0, rules[0]), (length - 1, rules[1])):
        if r[0] == "odd":
            keep[pos] = False
            fill[pos] = float(r[1])
    if bool(keep.all()):
        return FacePlan(dim, None, None, None)
    return FacePlan(dim, None, keep.reshape(view), fill.reshape(view))


def _role(axis: int, component: int | None) -> str:
    """The role of a quantity at the sides of ``axis`` (as :func:`phisim.boundary._role`)."""
    if component is None:
        return "scalar"
    return "normal" if component == axis else "tangential"


def fast_plan(values, boundary, dx, width, axes, channels, shape, component):
    """The cached gather plan of :mod:`phisim.padding` when every rule is constant, else ``None``.

    ``channels`` is the rank for a cell-centred vector array (component ``c`` normal to axis ``c``);
    ``component`` is the MAC component of a face-centred array (``None``: cell-centred).
    """
    return plan_for(boundary, dx, width, axes, channels, shape, component, values.dtype, values.device)


def plan_for(boundary, dx, width, axes, channels, shape, component, dtype, device):
    """:func:`fast_plan` for arrays of ``dtype`` on ``device`` (memoised on the boundary)."""
    key = ("pad", channels, component, shape, axes, width, tuple(dx), dtype, device)
    try:
        return boundary._memo(key, lambda: _build_plan(boundary, dx, width, axes, channels, shape, component,
                                                       dtype, device) or False) or None
    except TypeError:  # unhashable spacing
        return _build_plan(boundary, dx, width, axes, channels, shape, component, dtype, device)


def _build_plan(boundary, dx, width, axes, channels, shape, component, dtype, device):
    """The plan of :func:`fast_plan`, or ``None`` when some rule is not constant (a tensor or a profile)."""
    sides = boundary.sides
    comps = (component,) if channels is None else tuple(range(channels))
    rules = tuple(tuple((sides[a][0].rule(_role(a, c), c), sides[a][1].rule(_role(a, c), c)) for a in axes)
                  for c in comps)
    if not all(constant_rules(r) for r in rules):
        return None
    counts = tuple(shape[a] - (1 if a == component else 0) for a in axes)
    faces = tuple(a == component for a in axes)
    try:
        return pad_plan(shape, channels, axes, counts, rules, width, tuple(float(dx[a]) for a in axes), faces,
                        dtype, device)
    except TypeError:  # unhashable rule values
        return None


def fast_face_plan(lo, hi, component, ndim, n, dtype, device):
    """The :class:`FacePlan` of the sides ``lo``/``hi`` of MAC component ``component`` (``n`` cells along it),
    or ``False`` when a side's normal-velocity rule is not constant."""
    rules = (lo.rule("normal", component), hi.rule("normal", component))
    if not constant_rules((rules,)):
        return False
    try:
        return face_plan(ndim, 1 + component, n + 1, rules, dtype, device)
    except TypeError:
        return False
