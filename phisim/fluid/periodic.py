"""The split fluid step of a fully periodic domain, fused: a few array passes instead of hundreds of operations.

On a domain periodic along every axis, without solids, marker, buoyancy or energy normalisation, the split step
(self-advection, explicit viscosity, exact spectral projection) is the same computation as the general path of
:func:`phisim.fluid.stepper.advance` — the same stencils, the same interpolation, the same spectral solve, equal
to rounding — but organised for the machine:

* the components are stacked into one compact array ``(B, d, *res)`` (the duplicated periodic face dropped),
  wrap-padded once; the velocity of every component at every other component's faces is one box sum per pair
  of axes over that padded array;
* the departure points of all components are one stacked array, wrapped into the period with ``floor``
  (cheaper than ``remainder``) and mapped to ``grid_sample``'s coordinates in the same pass, and every
  component is interpolated by one ``grid_sampler`` call (components folded into the batch);
* explicit viscosity, the MAC divergence and the pressure gradient are shifted views of wrap-padded arrays
  (index tuples built once); the divergence is taken of the advected velocity and the viscous step's factor
  on it, ``1 + nu dt lap`` per Fourier mode (the periodic difference operators commute), is part of the
  pressure multiplier: one real FFT pair (``torch.fft``, a real multiplier precomputed per time step).

A 2-D step is about 40 calls into torch where the general path makes about 140; MacCormack adds the backward
trace and the extrema clamp (about 20 more). Everything is precomputed per time step size (the coefficient
tensors) and nothing is read back to the host, so the step traces as one graph for ``torch.compile``; there the
sampler is one opaque operation (:func:`grid_sample_border`) and the periodic padding plain concatenation, which
the compiler turns into fused copies (measured in ``docs/BENCHMARKS.md``).

:class:`PeriodicStep` is used by :class:`~phisim.fluid.stepper.FluidStepper` whenever its settings allow it
(:meth:`PeriodicStep.applies`); ``FluidStepper(..., fused=False)`` keeps the general path.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F

from phisim.boundary import Boundary
from phisim.compiled import is_compiling
from phisim.field import CenteredGrid, StaggeredGrid
from phisim.grid import Grid
from phisim.ops.stencil import normalize_kinds
from phisim.solvers.box import solve_multiplier

__all__ = ["PeriodicStep", "grid_sample_border"]


def grid_sample_border(source: torch.Tensor, coords: torch.Tensor) -> torch.Tensor:
    """``torch.grid_sampler`` (bilinear/trilinear, border, ``align_corners=True``) as one opaque operation.

    Inside ``torch.compile`` the compiler keeps this call as the library kernel instead of lowering it to
    per-point gathers (measured several times slower on the CPU); the element-wise work around it is still
    fused. Eager steps call ``torch.grid_sampler`` directly. (With a torch older than 2.4, which has no
    ``torch.library.custom_op``, it is the plain call.)
    """
    return torch.grid_sampler(source, coords, 0, 1, True)


def _grid_sample_border_fake(source, coords):
    return source.new_empty((source.shape[0], source.shape[1], *coords.shape[1:-1]))


def _grid_sample_border_context(ctx, inputs, output):
    ctx.save_for_backward(*inputs)


def _grid_sample_border_backward(ctx, grad):
    source, coords = ctx.saved_tensors
    backward = (torch.ops.aten.grid_sampler_2d_backward if source.dim() == 4 else
                torch.ops.aten.grid_sampler_3d_backward)
    g_source, g_coords = backward(grad.contiguous(), source, coords, 0, 1, True,
                                  [ctx.needs_input_grad[0], ctx.needs_input_grad[1]])
    return g_source, g_coords


if hasattr(torch.library, "custom_op"):
    grid_sample_border = torch.library.custom_op("phisim::grid_sample_border", mutates_args=())(grid_sample_border)
    grid_sample_border.register_fake(_grid_sample_border_fake)
    grid_sample_border.register_autograd(_grid_sample_border_backward, setup_context=_grid_sample_border_context)

def _wrap(x: torch.Tensor, pads: tuple[int, ...]) -> torch.Tensor:
    """Periodic padding of the spatial axes of ``(B, C, *res)`` (``pads`` as ``F.pad``'s: last axis first).

    Eager: ``F.pad(mode="circular")``; inside ``torch.compile``: one concatenation per axis, which the compiler
    turns into plain copies (the circular pad becomes masked, nested index arithmetic there).
    """
    if not is_compiling():
        return F.pad(x, pads, mode="circular")
    d = x.dim() - 2
    for a in range(d):
        before, after = pads[2 * (d - 1 - a)], pads[2 * (d - 1 - a) + 1]
        dim, n = 2 + a, x.shape[2 + a]
        parts = ([x.narrow(dim, n - before, before)] if before else []) + [x] + (
            [x.narrow(dim, 0, after)] if after else [])
        x = torch.cat(parts, dim=dim) if len(parts) > 1 else x
    return x


def _sample(source: torch.Tensor, coords: torch.Tensor) -> torch.Tensor:
    if is_compiling():
        return grid_sample_border(source, coords)
    return torch.grid_sampler(source, coords, 0, 1, True)

#: Self-advection schemes of the fused step.
FUSED_SCHEMES = ("semi_lagrangian", "maccormack")


class PeriodicStep:
    """The fused split step of an all-periodic fluid (see the module docstring).

    Args:
        grid: The grid (every axis periodic; 2-D or 3-D).
        boundary: The velocity boundary (periodic along every axis).
        viscosity: Kinematic viscosity ``>= 0`` (explicit, forward Euler).
        scheme: ``'semi_lagrangian'`` or ``'maccormack'`` (clamped to the extrema of the forward stencil).
        dtype, device: Of the states.

    Calling it with a validated velocity (a :class:`~phisim.field.StaggeredGrid` on ``grid``, periodic) and a
    time step returns ``(velocity, pressure)`` as the general split step does.
    """

    def __init__(self, grid: Grid, boundary: Boundary, viscosity: float, scheme: str, dtype: torch.dtype,
                 device: torch.device):
        self.grid, self.boundary = grid, boundary
        self.viscosity, self.scheme = float(viscosity), scheme
        self.dtype, self.device = dtype, device
        d = grid.rank
        self.res = tuple(grid.resolution)
        self.dx = tuple(float(h) for h in grid.dx)
        self.kinds = normalize_kinds("periodic", d)
        # the divergence is accumulated in units of 1/dx[0]; the multiplier carries the 1/dx[0]
        inv = solve_multiplier(self.res, self.dx, self.kinds, device, dtype)
        # rfftn's layout (last axis halved), real: it multiplies the spectrum viewed as (re, im) pairs, one real
        # pass that needs no complex arithmetic (which a compiler may not generate)
        self.multiplier = inv / self.dx[0]
        self.pressure_boundary = boundary.for_pressure()
        self._consts: dict = {}

    @staticmethod
    def applies(boundary: Boundary, *, obstacles, advection: str, viscosity_scheme: str, viscosity: float,
                integrator: str, energy_normalization: bool, buoyancy: float, marker_source) -> bool:
        """Whether a stepper with these settings can take the fused step (for states without a marker)."""
        return (all(boundary.is_periodic(a) for a in range(boundary.rank)) and obstacles is None
                and advection in FUSED_SCHEMES and integrator == "split" and not energy_normalization
                and buoyancy == 0 and marker_source is None
                and (viscosity_scheme == "explicit" or viscosity == 0))

    # ---- constants per time step ----------------------------------------------------------------------
    def _constants(self, dt: float):
        hit = self._consts.get(dt)
        if hit is not None:
            return hit
        if len(self._consts) >= 16:
            self._consts = {k: v for k, v in self._consts.items() if isinstance(k, str)}
        d, res, dx = self.grid.rank, self.res, self.dx
        kw = dict(dtype=torch.float64, device=self.device)
        # coordinate c of grid_sample is array axis a = d - 1 - c; every array below is laid out
        # (batch, component, coordinate, *res) so that its element-wise passes run contiguously
        axes = [d - 1 - c for c in range(d)]
        view = (1, 1, d) + (1,) * d
        # departure index / n of the sample points (every component samples its own compact array at its own
        # indices): base k/n, and the velocity's factor -dt/(dx n), a quarter for the box-summed cross terms
        mesh = torch.meshgrid(*[torch.arange(n, **kw) / n for n in res], indexing="ij")
        base = torch.stack([mesh[a] for a in axes], dim=0).reshape(1, 1, d, *res)
        scale = torch.empty((1, d, d) + (1,) * d, **kw)
        for i in range(d):
            for c, a in enumerate(axes):
                scale[0, i, c] = -dt / (dx[a] * res[a]) * (1.0 if a == i else 0.25)
        # wrapped fraction f in [0, 1) -> grid_sample coordinate of the padded index f n + 1 (align_corners)
        stretch = torch.tensor([2.0 * res[a] / (res[a] + 1) for a in axes], **kw).reshape(view)
        shift = torch.tensor([2.0 / (res[a] + 1) - 1.0 for a in axes], **kw).reshape(view)
        rates = tuple(self.viscosity * dt / h ** 2 for h in dx)
        # the pressure multiplier times the viscous step's symbol 1 + sum_a r_a (2 cos(2 pi f_a) - 2) per mode
        freqs = [torch.fft.fftfreq(n, **kw) for n in res[:-1]] + [torch.fft.rfftfreq(res[-1], **kw)]
        symbol = 1.0 + sum(r * (2.0 * torch.cos(2.0 * math.pi * f) - 2.0).reshape(
            [-1 if b == a else 1 for b in range(d)]) for a, (r, f) in enumerate(zip(rates, freqs)))
        multiplier = (self.multiplier * symbol.to(self.multiplier.dtype)).unsqueeze(-1)
        cast = dict(dtype=self.dtype, device=self.device)
        hit = (base.to(**cast), scale.to(**cast), stretch.to(**cast), shift.to(**cast), rates, multiplier)
        if self.scheme == "maccormack":
            # the lower stencil corner of a padded index f n + 1: floor; flat index in the (n + 1)^d corner array
            sizes = [n + 1 for n in res]
            strides = [math.prod(sizes[a + 1:]) for a in range(d)]
            counts = torch.tensor([float(res[a]) for a in axes], **kw).reshape(view)
            stride = torch.tensor([strides[a] for a in axes], dtype=torch.long, device=self.device).reshape(view)
            upper = torch.tensor([float(res[a]) for a in axes], **kw).reshape(view)
            hit = hit + (counts.to(**cast), stride, upper.to(**cast))
        self._consts[dt] = hit
        return hit

    # ---- the step -------------------------------------------------------------------------------------
    def _slices(self):
        """Index tuples of the shifted views, built once: for a ``(B, C, *(res + 2))`` wrap-padded array,
        ``shifted[a][s]`` is the view shifted by ``s - 1`` cells along axis ``a``; ``pieces[i][c]`` the
        velocity of coordinate ``c`` at component ``i``'s sample points (``None``: the component itself,
        else ``(pair, index)`` into the box sums)."""
        hit = self._consts.get("slices")
        if hit is None:
            d, res = self.grid.rank, self.res
            all_ = slice(None)

            def view(starts):
                return (all_, all_) + tuple(slice(starts.get(a, 1), starts.get(a, 1) + n) for a, n in enumerate(res))

            shifted = [[view({a: s}) for s in range(3)] for a in range(d)]
            halves = [[(all_, all_) + (all_,) * a + (slice(s, s + res[a] + 1),) for s in range(2)] for a in range(d)]
            # the box sum of pair (i, j) holds channels i and j only (positions 0 and 1)
            pieces = [[None if a == i else ((min(i, a), max(i, a)), (all_, int(a > i)) + view({i: 0, a: 1})[2:])
                       for a in reversed(range(d))] for i in range(d)]
            compact = [(all_,) * (1 + a) + (slice(0, res[a]),) for a in range(d)]
            hit = self._consts["slices"] = (shifted, halves, pieces, compact)
        return hit

    def __call__(self, velocity: StaggeredGrid, dt: float) -> tuple[StaggeredGrid, CenteredGrid]:
        d, res = self.grid.rank, self.res
        consts = self._constants(float(dt))
        base, scale, stretch, shift, rates, multiplier = consts[:6]
        shifted, halves, pieces, compact = self._slices()
        v = torch.stack([c[compact[a]] for a, c in enumerate(velocity.values)], dim=1)
        B = v.shape[0]
        wrap = (1, 1) * d
        p = _wrap(v, wrap)  # (B, d, *(res + 2))
        # the velocity at every component's sample points, (B, d comps, d coords, *res), coordinate order of
        # grid_sample (last axis first): own component as it is, the others as box sums over two axes
        boxes = {}
        for i in range(d):
            for j in range(i + 1, d):
                pair = p[:, i:j + 1:j - i]
                q = pair[halves[i][0]] + pair[halves[i][1]]
                boxes[i, j] = q[halves[j][0]] + q[halves[j][1]]
        vel = torch.stack([v[:, i] if pc is None else boxes[pc[0]][pc[1]] for i in range(d) for pc in pieces[i]],
                          dim=1).reshape(B, d, d, *res)
        frac = torch.addcmul(base, vel, scale)
        frac = frac - torch.floor(frac)
        coords = torch.addcmul(shift, frac, stretch).reshape(B * d, d, *res).movedim(1, -1)
        a = _sample(p.reshape(B * d, 1, *p.shape[2:]), coords).reshape(B, d, *res)
        if self.scheme == "maccormack":
            a = self._maccormack(v, p, a, vel, frac, consts)
        # explicit viscosity and the MAC divergence from one wrap-padded array; the divergence is that of the
        # advected velocity (in units of 1/dx[0]): the viscous step's factor on it, (1 + nu dt lap) per mode,
        # is in the multiplier (the periodic difference operators commute)
        pa = _wrap(a, wrap)
        div = None
        for ax in range(d):
            diff = pa[:, ax:ax + 1][shifted[ax][2]] - pa[:, ax:ax + 1][shifted[ax][1]]
            div = diff if div is None else div.add_(diff, alpha=self.dx[0] / self.dx[ax])
        if self.viscosity != 0:
            acc = a * (1.0 - 2.0 * sum(rates))
            for ax in range(d):
                acc = acc.add_(pa[shifted[ax][0]] + pa[shifted[ax][2]], alpha=rates[ax])
            a = acc
        axes = tuple(range(1, d + 1))
        spectrum = torch.view_as_complex(torch.view_as_real(torch.fft.rfftn(div[:, 0], dim=axes)) * multiplier)
        pressure = torch.fft.irfftn(spectrum, s=res, dim=axes)
        # the pressure gradient at the faces (face k between cells k - 1 and k); face n repeats face 0
        pp = _wrap(pressure.unsqueeze(1), wrap)
        comps = []
        for ax in range(d):
            grad = pp[shifted[ax][1]] - pp[shifted[ax][0]]
            new = torch.add(a[:, ax:ax + 1], grad, alpha=-1.0 / self.dx[ax])[:, 0]
            comps.append(torch.cat([new, new[compact[ax][:-1] + (slice(0, 1),)]], dim=1 + ax))
        out = StaggeredGrid._trusted(tuple(comps), self.grid, self.boundary)
        return out, CenteredGrid._trusted(pressure, self.grid, self.pressure_boundary)

    def _maccormack(self, v, p, forward, vel, frac, consts):
        """Backward trace of the forward result, correction, and the clamp to the forward stencil's extrema."""
        d, res = self.grid.rank, self.res
        base, scale, stretch, shift, _, _, counts, stride, upper = consts
        B = v.shape[0]
        back = torch.addcmul(base, vel, scale, value=-1.0)
        back = back - torch.floor(back)
        coords = torch.addcmul(shift, back, stretch).reshape(B * d, d, *res).movedim(1, -1)
        pf = _wrap(forward, (1, 1) * d)
        backward = _sample(pf.reshape(B * d, 1, *pf.shape[2:]), coords).reshape(B, d, *res)
        corrected = forward + (v - backward) * 0.5
        # extrema of the 2^d samples read at the forward departure point: running max/min over the stencil
        hi, lo = p, p
        for ax in range(d):
            m = hi.shape[2 + ax] - 1
            hi = torch.maximum(hi.narrow(2 + ax, 0, m), hi.narrow(2 + ax, 1, m))
            lo = torch.minimum(lo.narrow(2 + ax, 0, m), lo.narrow(2 + ax, 1, m))
        # lower corner of padded index f n + 1, in [0, n] (a NaN index reads corner 0)
        k = torch.clamp(torch.floor(frac.detach() * counts + 1.0).nan_to_num_(0.0), max=upper).long()
        flat = (k * stride).sum(2).reshape(B, d, -1)
        hi = torch.gather(hi.reshape(B, d, -1), 2, flat).reshape(B, d, *res)
        lo = torch.gather(lo.reshape(B, d, -1), 2, flat).reshape(B, d, *res)
        return torch.minimum(torch.maximum(corrected, lo), hi)
