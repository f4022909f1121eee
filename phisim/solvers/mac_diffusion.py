"""Viscous diffusion of MAC (staggered) velocities: explicit, backward Euler, Crank-Nicolson, exact.

Internal module behind :func:`phisim.solvers.diffusion.diffuse_staggered`. Component ``i`` of a MAC velocity is
sampled on the faces normal to axis ``i`` (``n_i + 1`` samples, both boundary faces included) and is
cell-centred along the other axes. Its (2d+1)-point Laplacian with the velocity boundary's ghost rules
(:func:`phisim.boundary.pad_staggered_component`) separates into one 1-D operator per axis, each
diagonalised by a real-to-real transform or an FFT:

=========================  ===========================  ==================  ====================================
axis / sides               unknowns                     transform (fwd/inv) eigenvalue times dx² (k = 0..)
=========================  ===========================  ==================  ====================================
periodic (any axis)        ``n`` (face n = face 0)      rFFT / irFFT        ``-4 sin²(π k / n)``
own axis, wall / wall      faces ``1..n-1``             DST-I / DST-I       ``-4 sin²(π (k+1) / 2n)``
own axis, open / open      faces ``0..n``               DCT-I / DCT-I       ``-4 sin²(π k / 2n)``
own axis, wall / open      faces ``1..n``               DST-III / DST-II    ``-4 sin²(π (2k+1) / 4n)``
own axis, open / wall      faces ``0..n-1``             DCT-III / DCT-II    ``-4 sin²(π (2k+1) / 4n)``
other axis                 cells (face boundary)        as :mod:`phisim.solvers.poisson` (DST-II, DCT-II, type 4)
=========================  ===========================  ==================  ====================================

("wall" stands for any odd ghost rule of the normal velocity: no-slip, free-slip, Dirichlet; "open" for an
even one: open, Neumann). Samples fixed by the boundary are not unknowns; non-zero boundary values (a
moving lid, an inflow profile, a flux) enter as a constant source ``b``: ``L u = L₀ u + b``. So a
backward-Euler or Crank-Nicolson step in a box is one forward transform, a division and one inverse
transform per component, exact to round-off. With walls on both sides of a component's own axis that axis
needs a DST-I, computed from a real FFT of twice its length; on grids of about 90² and more the solve instead
treats it as periodic over faces ``0..n-1`` (an FFT of length n) and restores the zero on face 0 with one
Green's-function correction per transverse mode (:func:`phisim.spectral.fft.wall_solve`, exact, 20-30 % faster).

Faces fixed inside the domain (solid bodies: the caller sets their velocity) break the separability. Where the
caller keeps the faces for reuse (it passes a ``capacitance`` dict, e.g. a stepper's static bodies) the θ-scheme
is solved directly with a capacitance matrix on the body surface (:class:`_CapacitanceSolve`: two box solves
and a small LU solve per call; :class:`_SharpCapacitanceSolve` for sharp surfaces: one box solve of the component and
one on a window around the body where the Green's function decays fast enough, else two), built at the first
request and kept in that dict; otherwise by
:func:`phisim.solvers.linalg.cg` on the free faces, preconditioned with the exact box solve. The CG operator is made
symmetric by halving the rows of free boundary faces on open sides (the vertex-centred Neumann stencil is symmetric
in that weighted inner product).
"""

from __future__ import annotations

import math
from functools import lru_cache

import torch

from phisim.boundary import pad_staggered_component, set_boundary_faces
from phisim.checks import check_dt, check_nonnegative
from phisim.compiled import is_compiling
from phisim.errors import ParameterError, ShapeError, SlowPathWarning, warn_from_caller
from phisim.field import StaggeredGrid
from phisim.ops.tensors import unravel
from phisim.solvers.box import TRANSFORMS, axis_eigenvalues
from phisim.solvers.green import green_block, symmetric_factors
from phisim.solvers.linalg import Solve, cg
from phisim.spectral import fft as _fft
from phisim.spectral.pocket import wall_transposes

STAGGERED_METHODS = ("implicit", "crank_nicolson", "spectral", "explicit")

_OWN_AXIS = {  # (lower odd?, upper odd?) -> (forward kind, inverse kind, first unknown, unknowns - n)
    (True, True): ("dst1", "dst1", 1, -1),
    (False, False): ("dct1", "dct1", 0, 1),
    (True, False): ("dst3", "dst2", 1, 0),
    (False, True): ("dct3", "dct2", 0, 0),
}




class _Component:
    """Geometry of one MAC component: unknown slice along its own axis, transforms, eigenvalues, weights."""

    def __init__(self, grid, boundary, i: int):
        self.i = i
        self.rank = grid.rank
        self.dx = grid.dx
        self.boundary = boundary
        n = grid.resolution[i]
        self.n = n
        self.face_shape = grid.face_shape(i)
        kinds = []  # per axis: ('periodic',) or (forward, inverse)
        eigs = []
        scale = 1.0
        for a in range(grid.rank):
            lo, hi = boundary.sides[a]
            if boundary.is_periodic(a):
                kinds.append(None)
                m = grid.resolution[a]
                k = torch.arange(m, dtype=torch.float64)
                eigs.append(-4 * torch.sin(math.pi * k / m) ** 2 / self.dx[a] ** 2)
                continue
            if a == i:
                odd = (lo.rule("normal", i)[0] == "odd", hi.rule("normal", i)[0] == "odd")
                fwd, inv, first, extra = _OWN_AXIS[odd]
                self.first, self.count = first, n + extra
                k = torch.arange(self.count, dtype=torch.float64)
                if fwd == "dst1":
                    lam = -4 * torch.sin(math.pi * (k + 1) / (2 * n)) ** 2
                elif fwd == "dct1":
                    lam = -4 * torch.sin(math.pi * k / (2 * n)) ** 2
                else:
                    lam = -4 * torch.sin(math.pi * (2 * k + 1) / (4 * n)) ** 2
                eigs.append(lam / self.dx[a] ** 2)
                kinds.append((fwd, inv))
                scale /= 2 * n
                self.odd = odd
                continue
            pair = tuple("dirichlet" if c.rule("tangential", i)[0] == "odd" else "neumann" for c in (lo, hi))
            kinds.append(TRANSFORMS[pair])
            eigs.append(axis_eigenvalues(grid.resolution[a], pair, self.dx[a], False))
            scale /= 2 * grid.resolution[a]
        if boundary.is_periodic(i):
            self.first, self.count, self.odd = 0, n, None
        self.kinds = kinds
        self.scale = scale
        self.eigs = eigs  # per axis, float64, times 1/dx²
        self.periodic = [a for a in range(grid.rank) if kinds[a] is None]
        # walls on both sides of the own axis: the box solve may run as periodic + one-face correction
        self.walls = not self.periodic and kinds[i] == ("dst1", "dst1")
        self.r2r = [a for a in range(grid.rank) if kinds[a] is not None]
        self.fwd_kinds = tuple(kinds[a][0] for a in self.r2r)
        self.inv_kinds = tuple(kinds[a][1] for a in self.r2r)
        self.r2r_axes = tuple(1 + a for a in self.r2r)
        # eigenvalue sum in the spectral layout (last periodic axis halved for the rfft)
        total = torch.zeros((), dtype=torch.float64)
        for a, lam in enumerate(eigs):
            if self.periodic and a == self.periodic[-1]:
                lam = lam[: lam.numel() // 2 + 1]
            shape = [1] * grid.rank
            shape[a] = -1
            total = total + lam.reshape(shape)
        self.lam = total
        self._mults: dict = {}  # (method, theta * alpha, dtype, device) -> prescaled multiplier (shared by copies)
        # the source of non-zero boundary values is needed only when a rule carries a value
        self.has_values = any(
            not _is_zero_rule(c.rule("normal" if a == i else "tangential", i))
            for a in range(grid.rank) for c in boundary.sides[a] if not boundary.is_periodic(a)
        )
        # row weights that make the operator symmetric: 1/2 on free boundary faces of open sides
        self.weight = None
        if self.odd is not None and not all(self.odd):
            w = torch.ones(self.count, dtype=torch.float64)
            if not self.odd[0]:
                w[0] = 0.5
            if not self.odd[1]:
                w[-1] = 0.5
            shape = [1] * (grid.rank + 1)
            shape[1 + i] = -1
            self.weight = w.reshape(shape)
        #: What identifies this component's box operator in a solver cache (built once, shared by copies).
        self.key = (i, tuple(self.face_shape), tuple(self.dx), repr(kinds), self.first, self.count, self.odd)

    # -- unknowns <-> full component --------------------------------------------------------------------

    def restrict(self, u: torch.Tensor) -> torch.Tensor:
        """The unknown samples of a full component ``(B, *face_shape)``."""
        return u.narrow(1 + self.i, self.first, self.count)

    def embed(self, x: torch.Tensor, like: torch.Tensor) -> torch.Tensor:
        """Full component from unknowns: boundary faces from the boundary, face n = face 0 if periodic."""
        dim = 1 + self.i
        if self.odd is None:
            return torch.cat([x, x.narrow(dim, 0, 1)], dim=dim)
        parts = []
        if self.first:
            parts.append(torch.zeros_like(like.narrow(dim, 0, 1)))
        parts.append(x)
        if self.first + self.count < self.n + 1:
            parts.append(torch.zeros_like(like.narrow(dim, 0, 1)))
        full = torch.cat(parts, dim=dim) if len(parts) > 1 else x
        return set_boundary_faces(full, self.i, self.boundary)

    def solve_box(self, rhs: torch.Tensor, mult: torch.Tensor, like: torch.Tensor, engine,
                  op: tuple[str, float] | None = None) -> torch.Tensor | None:
        """``embed(apply(rhs, mult, prescaled=True), like)`` written in place into one new full component.

        The fast path of the exact box solve: no autograd, no periodic axis, zero boundary values on the
        faces outside the unknowns (walls); the transforms run on the interior view of the output. With
        ``op = ('implicit', c)`` (``mult`` is ``1 / (1 - c λ)``) or ``('crank_nicolson', α)`` and walls on both
        sides of the own axis, that axis is solved by a periodic FFT and a one-face correction instead of a
        DST-I (:func:`phisim.spectral.fft.wall_solve`; same answer to round-off, 20-30 % less time). Returns None where
        the fast path does not apply (the caller composes :meth:`apply` and :meth:`embed`).
        """
        if (self.periodic or not self.r2r or self.has_values or rhs.requires_grad or like.requires_grad
                or mult.requires_grad):
            return None
        full = torch.empty(like.shape, dtype=rhs.dtype, device=rhs.device)
        dim = 1 + self.i
        if (op is not None and op[0] in ("implicit", "crank_nicolson") and self.walls
                and like.numel() >= _fft.get_fft_settings().wall_solve_min_samples):
            shape = list(like.shape)
            shape[dim] -= 1
            last = wall_transposes(shape, dim, rhs.element_size())
            wm, green = self.wall_operator(op[0], op[1], rhs.dtype, rhs.device, last)
            other = [a for a in self.r2r if a != self.i]
            if _fft.wall_solve(rhs, full, dim, tuple(self.kinds[a][0] for a in other),
                               tuple(self.kinds[a][1] for a in other), tuple(1 + a for a in other), wm, green,
                               subtract=op[0] == "crank_nicolson", engine=engine) is not None:
                return full
        if _fft.r2r_multiply(rhs, self.fwd_kinds, self.inv_kinds, self.r2r_axes, mult, engine=engine,
                             out=full.narrow(dim, self.first, self.count)) is None:
            return None
        if self.first:
            full.narrow(dim, 0, 1).zero_()
        if self.first + self.count < self.n + 1:
            full.narrow(dim, self.n, 1).zero_()
        return full

    def wall_operator(self, method: str, coef: float, dtype, device, last: bool = False
                      ) -> tuple[torch.Tensor, torch.Tensor]:
        """``(mult, green)`` of :func:`phisim.spectral.fft.wall_solve` for ``'implicit'`` ``(I - coef L)⁻¹`` or
        ``'crank_nicolson'`` with ``α = coef`` (``2 (I - α/2 L)⁻¹``, the caller subtracts the input); cached.

        The own axis is periodic over the faces ``0..n-1``: eigenvalues ``-4 sin²(π k / n) / dx²`` on the half
        spectrum. ``green`` is the periodic Green's function of face 0 per transverse mode, divided by its
        value on face 0 (``n`` samples along the own axis), computed in float64. ``last``: the own axis moved
        last (the layout of a transposed solve).
        """
        key = ("wall", method, float(coef), dtype, str(device), last)
        cached = self._mults.get(key)
        if cached is not None:
            return cached
        i, n = self.i, self.n
        c, factor = (float(coef), 1.0) if method == "implicit" else (0.5 * float(coef), 2.0)
        shape = [1] * self.rank
        shape[i] = -1
        k = torch.arange(n // 2 + 1, dtype=torch.float64)
        lam = (-4 * torch.sin(math.pi * k / n) ** 2 / self.dx[i] ** 2).reshape(shape)
        for a in range(self.rank):
            if a != i:
                shape = [1] * self.rank
                shape[a] = -1
                lam = lam + self.eigs[a].reshape(shape)
        m = 1.0 / (1.0 - c * lam)
        g = torch.fft.irfft(m, n=n, dim=i)
        green = (g / g.narrow(i, 0, 1))[None]
        # the transverse transforms' normalisation (self.scale without the DST-I's 1/2n) and the FFT's 1/n
        mult = (m * (factor * self.scale * 2))[None]
        if last:
            green, mult = green.movedim(1 + i, -1), mult.movedim(1 + i, -1)
        green = green.to(dtype=dtype, device=device).contiguous()
        mult = mult.to(dtype=dtype, device=device).contiguous()
        if len(self._mults) > 8:
            self._mults.clear()
        self._mults[key] = (mult, green)
        return mult, green

    def laplace(self, u: torch.Tensor) -> torch.Tensor:
        """The full stencil ``L u`` on the full component (ghosts and boundary values from the rules)."""
        p = pad_staggered_component(u, self.i, self.boundary, self.dx, 1)
        out = 0
        for a in range(self.rank):
            dim = 1 + a
            m = p.shape[dim] - 2
            d2 = p.narrow(dim, 2, m) - 2 * p.narrow(dim, 1, m) + p.narrow(dim, 0, m)
            for b in range(self.rank):
                if b != a:
                    d2 = d2.narrow(1 + b, 1, d2.shape[1 + b] - 2)
            out = out + d2 / self.dx[a] ** 2
        return out

    def source(self, like: torch.Tensor) -> torch.Tensor | None:
        """``b`` on the unknowns: the stencil of the boundary values alone."""
        if not self.has_values:
            return None
        z = self.embed(torch.zeros_like(self.restrict(like)), like)
        return self.restrict(self.laplace(z))

    # -- spectral application ------------------------------------------------------------------------------

    def green_factors(self, coef: float) -> tuple[list[tuple[torch.Tensor, torch.Tensor]], torch.Tensor]:
        """The box operator ``A = I - coef L₀`` on the unknowns, separated (:func:`phisim.solvers.green.green_block`):
        per axis ``(L_a, R_a)`` (the inverse and the normalised forward transform as matrices, float64 on the CPU; a
        real orthonormal eigenbasis along periodic axes) and the inverse eigenvalues ``1 / (1 - coef Σ_a λ_a)``."""
        shape = [self.count if a == self.i else int(self.face_shape[a]) for a in range(self.rank)]
        factors, lam = [], torch.zeros((), dtype=torch.float64)
        for a, n in enumerate(shape):
            if self.kinds[a] is None:
                mu, left, right = symmetric_factors(n, float(self.dx[a]), ("periodic", "periodic"))
                ev = -mu
            else:
                fwd, inv = self.kinds[a]
                eye = torch.eye(n, dtype=torch.float64)[None]
                right = _fft.r2rn(eye, (fwd,), (1,))[0]  # modes x cells
                left = _fft.r2rn(eye, (inv,), (1,))[0]  # cells x modes
                grid_n = self.n if a == self.i else n
                right = right / (2 * grid_n)
                ev = self.eigs[a]
            factors.append((left.contiguous(), right.contiguous()))
            lam = lam.unsqueeze(-1) + ev
        return factors, 1.0 / (1.0 - float(coef) * lam)

    def inverse_multiplier(self, coef, dtype, device) -> torch.Tensor:
        """``1 / (1 - coef λ)`` with the transforms' normalisation, in ``dtype`` (cached for a float ``coef``)."""
        if isinstance(coef, torch.Tensor):
            return (self.scale / (1.0 - coef * self.lam.to(device))).to(dtype)
        key = ("implicit", float(coef), dtype, str(device))
        m = self._mults.get(key)
        if m is None:
            m = (self.scale / (1.0 - float(coef) * self.lam)).to(dtype=dtype, device=device)
            if len(self._mults) > 8:
                self._mults.clear()
            self._mults[key] = m
        return m

    def step_multiplier(self, method: str, alpha: float, dtype, device) -> torch.Tensor:
        """A whole box step as one normalised multiplier (cached): ``'crank_nicolson'``
        ``(1 + αλ/2) / (1 - αλ/2)`` or ``'spectral'`` ``e^{αλ}`` (zero boundary values)."""
        key = (method, float(alpha), dtype, str(device))
        m = self._mults.get(key)
        if m is None:
            a = float(alpha)
            m = torch.exp(a * self.lam) if method == "spectral" else (1 + 0.5 * a * self.lam) / (1 - 0.5 * a * self.lam)
            m = (self.scale * m).to(dtype=dtype, device=device)
            if len(self._mults) > 8:
                self._mults.clear()
            self._mults[key] = m
        return m

    def apply(self, x: torch.Tensor, mult: torch.Tensor, engine, prescaled: bool = False) -> torch.Tensor:
        """``T⁻¹ (mult · T x)`` on unknowns ``(B, *unknown_shape)``; ``mult`` in spectral layout (float64, or
        already normalised and in ``x``'s dtype when ``prescaled``)."""
        if prescaled and self.r2r and not self.periodic:
            y = _fft.r2r_multiply(x, self.fwd_kinds, self.inv_kinds, self.r2r_axes, mult, engine=engine)
            if y is not None:  # no autograd, pyfftw engine: transform, multiply, transform back in one pass
                return y
        y = x
        if self.r2r:
            y = _fft.r2rn(y, tuple(self.kinds[a][0] for a in self.r2r), tuple(1 + a for a in self.r2r),
                          engine=engine)
        m = mult if prescaled else (mult * self.scale).to(x.dtype)
        if self.periodic:
            axes = tuple(1 + a for a in self.periodic)
            Y = _fft.rfftn(y, axes, engine=engine)
            y = _fft.irfftn(Y * m, tuple(x.shape[d] for d in axes), axes, engine=engine)
        else:
            y = y * m
        if self.r2r:
            y = _fft.r2rn(y, tuple(self.kinds[a][1] for a in self.r2r), tuple(1 + a for a in self.r2r),
                          engine=engine)
        return y


def _is_zero_rule(rule) -> bool:
    return len(rule) < 2 or (isinstance(rule[1], (int, float)) and rule[1] == 0)


@lru_cache(maxsize=64)
def _cached_component(grid, boundary, i: int) -> _Component:
    return _Component(grid, boundary, i)


class _Bound(_Component):
    """A cached component geometry read through, with the caller's boundary for the value terms.

    Its own attributes are the geometry and the boundary; every other attribute is the geometry's (shared: the
    arrays and the multiplier cache). Plain attribute reads, no copy of the object: ``torch.compile`` traces it on
    every torch version (``copy.copy`` is outside what some versions trace)."""

    def __init__(self, geometry: _Component, boundary):  # noqa: D107 - no _Component.__init__: nothing is rebuilt
        self._geometry = geometry
        self.boundary = boundary

    def __getattr__(self, name: str):
        if name == "_geometry":  # not set yet (e.g. while unpickling): no recursion
            raise AttributeError(name)
        return getattr(self._geometry, name)


def _component(grid, boundary, i: int) -> _Component:
    """The (cached) geometry of component ``i``, bound to this very ``boundary`` object.

    Boundaries that compare equal may still hold different evaluated inflow profiles (not part of their
    equality), so the cached geometry is read through a :class:`_Bound` holding the caller's boundary.
    """
    try:
        geometry = _cached_component(grid, boundary, i)
    except TypeError:  # boundaries holding unhashable values (tensors in lists)
        return _Component(grid, boundary, i)
    return geometry if geometry.boundary is boundary else _Bound(geometry, boundary)


def _fixed_masks(fixed, velocity):
    if fixed is None:
        return None
    if not isinstance(fixed, (tuple, list)) or len(fixed) != velocity.rank:
        raise ShapeError(f"fixed must hold one face mask per component ({velocity.rank}), got {type(fixed).__name__}")
    out = []
    for i, m in enumerate(fixed):
        if m is None:
            out.append(None)
            continue
        m = torch.as_tensor(m, device=velocity.device)
        shape = velocity.grid.face_shape(i)
        if m.ndim == len(shape):
            m = m[None]
        if tuple(m.shape[1:]) != shape or m.shape[0] not in (1, velocity.batch_size):
            raise ShapeError(f"fixed[{i}] must have shape (1 or B, *{shape}), got {tuple(m.shape)}")
        m = m if m.dtype == torch.bool else m != 0
        # an empty mask is dropped (a host read); a traced step is given no empty masks (the stepper's layout
        # drops them once, eagerly) and reads nothing back
        out.append(m if is_compiling() or bool(m.any()) else None)
    return out


def _walls(walls, velocity, masks):
    """Validated sharp-wall stencils (``(cut, coef, source)`` per component or None) and the fixed masks with the
    cut faces added."""
    if walls is None:
        return None, masks
    if not isinstance(walls, (tuple, list)) or len(walls) != velocity.rank:
        raise ShapeError(f"walls must hold one entry per component ({velocity.rank}), got {type(walls).__name__}")
    masks = list(masks) if masks is not None else [None] * velocity.rank
    out = []
    for i, w in enumerate(walls):
        if w is None:
            out.append(None)
            continue
        cut, coef, source = w
        shape = velocity.grid.face_shape(i)
        for t in (cut, coef) + (() if source is None else (source,)):
            if tuple(t.shape[1:]) != shape or t.shape[0] not in (1, velocity.batch_size):
                raise ShapeError(f"walls[{i}] tensors must have shape (1 or B, *{shape}), got {tuple(t.shape)}")
        cut = cut.to(device=velocity.device)
        masks[i] = cut if masks[i] is None else (masks[i] | cut)
        out.append((cut, coef.to(device=velocity.device),
                    None if source is None else source.to(device=velocity.device)))
    return out, masks


def diffuse_staggered(velocity, dt, *, viscosity, method: str = "implicit", fixed=None, solve=None,
                      capacitance: dict | None = None, engine: str | None = None, walls=None):
    """See :func:`phisim.solvers.diffusion.diffuse_staggered` (the public entry point).

    ``walls``: per component None or ``(cut, coef, source)`` (see :class:`phisim.fluid.bodies.SolidLayout`): a sharp
    no-slip surface. The ``cut`` faces are held (added to ``fixed``) and read as 0 by the stencil of their
    neighbours, whose Laplacian becomes ``L_0 u - coef u + source``; every scheme uses this operator (the explicit
    one treats ``coef`` point-implicitly, ``u' = (u + α (L_0 u + source)) / (1 + α coef)``, so that a surface close
    to a face does not limit the step).
    """

    if not isinstance(velocity, StaggeredGrid):
        raise ParameterError(f"diffuse_staggered expects a StaggeredGrid, got {type(velocity).__name__}")
    if method not in STAGGERED_METHODS:
        raise ParameterError(f"method must be one of {STAGGERED_METHODS}, got {method!r}")
    dt = check_dt(dt)
    nu = check_nonnegative(viscosity, "viscosity")
    masks = _fixed_masks(fixed, velocity)
    walls, masks = _walls(walls, velocity, masks)
    if masks is not None and method == "spectral" and any(m is not None for m in masks):
        raise ParameterError(
            "method='spectral' is exact only in a box; with fixed faces (bodies) use 'implicit' or 'crank_nicolson'"
        )
    if not isinstance(dt, torch.Tensor) and not isinstance(nu, torch.Tensor) and (float(dt) == 0 or float(nu) == 0):
        return velocity
    alpha = dt * nu
    grid, boundary = velocity.grid, velocity.boundary
    if method == "explicit":
        number = float(alpha) * sum(2.0 / d**2 for d in grid.dx)
        if number > 1.0:
            raise ParameterError(
                f"explicit viscosity is unstable: viscosity * dt * sum(2/dx^2) = {number:.3g} > 1; reduce dt "
                "or use method='implicit' / 'crank_nicolson' / 'spectral'"
            )
    theta = 0.5 if method == "crank_nicolson" else 1.0
    out = []
    for i, u in enumerate(velocity.values):
        comp = _component(grid, boundary, i)
        mask = None if masks is None else masks[i]
        wall = None if walls is None else walls[i]
        if wall is not None:
            out.append(_sharp_component(comp, u, mask, wall, method, alpha, theta, solve, engine, capacitance))
            continue
        if method == "explicit":
            new = u + alpha * comp.laplace(u)
            if mask is not None:
                new = torch.where(mask, u, new)
            out.append(new)
            continue
        lam = comp.lam.to(u.device)
        x = comp.restrict(u)
        b = comp.source(u)
        if mask is None and b is None and method != "implicit" and not isinstance(alpha, torch.Tensor):
            # Crank-Nicolson and the exact step in a box: one multiplier, one transform pair, no stencil
            full = comp.solve_box(x, comp.step_multiplier(method, alpha, u.dtype, u.device), u, engine,
                                  op=(method, alpha))
            if full is not None:
                out.append(full)
                continue
        if method == "spectral":
            y = comp.apply(x, torch.exp(alpha * lam), engine)
            if b is not None:
                y = y + comp.apply(b, alpha * _phi1(alpha * lam), engine)
            out.append(comp.embed(y, u))
            continue
        rhs = x
        if theta < 1:
            rhs = rhs + ((1 - theta) * alpha) * comp.restrict(comp.laplace(u))
            if b is not None:
                rhs = rhs + (theta * alpha) * b
        elif b is not None:
            rhs = rhs + alpha * b
        inverse = comp.inverse_multiplier(theta * alpha, u.dtype, u.device)
        if mask is None:
            op = None if isinstance(alpha, torch.Tensor) else ("implicit", theta * alpha)
            full = comp.solve_box(rhs, inverse, u, engine, op=op)
            out.append(full if full is not None else comp.embed(comp.apply(rhs, inverse, engine, prescaled=True), u))
            continue
        # bodies: a direct capacitance solve once the same body and ν dt come back (fixed steps), else CG
        cap = _capacitance(comp, mask, theta * alpha, u.device, engine, capacitance)
        if cap is not None:
            out.append(cap.solve(comp, rhs, x, inverse, u, engine))
            continue
        # CG on the free faces, the exact box solve as preconditioner
        p = 1 - comp.restrict(mask).to(u.dtype)
        w = None if comp.weight is None else comp.weight.to(dtype=u.dtype, device=u.device)
        a_t = torch.as_tensor(theta * alpha, dtype=u.dtype, device=u.device)
        v_fixed = (1 - p) * x

        def lap0(y, u=u, comp=comp, b=b):  # the stencil with zero boundary values, on unknowns
            full = comp.restrict(comp.laplace(comp.embed(y, u)))
            return full if b is None else full - b

        def weighted(y, w=w):
            return y if w is None else y * w

        def operator(y, a, p=p, lap0=lap0, weighted=weighted):
            return p * weighted(y - a * lap0(p * y)) + (1 - p) * y

        def precond(r, p=p, comp=comp, inverse=inverse, w=w):
            z = p * r if w is None else p * r / w
            # no gradient through a preconditioner (it changes the iterations, not the answer)
            return p * comp.apply(z, inverse.detach().to(r.dtype), engine, prescaled=True) + (1 - p) * r

        rhs_cg = p * weighted(rhs + a_t * lap0(v_fixed))
        if solve is None:
            solve = Solve(rtol=1e-10 if u.dtype == torch.float64 else 1e-6)
        y = cg(operator, rhs_cg, (p * x).detach(), solve=solve, preconditioner=precond, operator_params=(a_t,))
        out.append(comp.embed(y + v_fixed, u))
    result = velocity.with_values(tuple(out))
    # the solves embed their unknowns with the boundary faces already set (embed / solve_box)
    return result.with_boundary_faces() if method == "explicit" else result


def _sharp_component(comp, u, mask, wall, method, alpha, theta, solve, engine, capacitance):
    """One component's viscous step with a sharp no-slip surface (``wall = (cut, coef, source)``)."""
    cut, coef, source = wall
    coef = coef.to(u.dtype)
    source = None if source is None else source.to(u.dtype)

    def zeroed():  # the stencil reads 0 on cut faces
        keep = _open_faces(comp, cut, u.dtype, capacitance)
        return u.masked_fill(cut, 0) if keep is None else u * keep

    if method == "explicit":
        num = u + alpha * comp.laplace(zeroed())
        if source is not None:
            num = num + alpha * source
        return torch.where(mask, u, num / _explicit_denominator(comp, coef, alpha, capacitance))
    x = comp.restrict(u)
    b = comp.source(u)
    rhs = x
    if theta < 1:
        u0 = zeroed()
        lap = comp.laplace(u0) - coef * u  # L u = L_0 u - coef u + source on the full component
        if source is not None:
            lap = lap + source
        rhs = rhs + ((1 - theta) * alpha) * comp.restrict(lap)
        if b is not None:
            rhs = rhs + (theta * alpha) * b
        if source is not None:
            rhs = rhs + (theta * alpha) * comp.restrict(source)
    else:
        if b is not None:
            rhs = rhs + alpha * b
        if source is not None:
            rhs = rhs + alpha * comp.restrict(source)
    inverse = comp.inverse_multiplier(theta * alpha, u.dtype, u.device)
    cap = _sharp_capacitance(comp, mask, cut, coef, theta * alpha, u.device, engine, capacitance)
    if cap is not None:
        return cap.solve(comp, rhs, inverse, u, engine)
    x0 = comp.restrict(zeroed())
    d = comp.restrict(coef)
    p = 1 - comp.restrict(mask).to(u.dtype)
    w = None if comp.weight is None else comp.weight.to(dtype=u.dtype, device=u.device)
    a_t = torch.as_tensor(theta * alpha, dtype=u.dtype, device=u.device)
    v_fixed = (1 - p) * x0

    def lap0(y):  # the stencil with zero boundary values, on unknowns
        full = comp.restrict(comp.laplace(comp.embed(y, u)))
        return full if b is None else full - b

    def weighted(y):
        return y if w is None else y * w

    def operator(y, a, d):
        return p * weighted(y - a * (lap0(p * y) - d * y)) + (1 - p) * y

    def precond(r):
        z = p * r if w is None else p * r / w
        return p * comp.apply(z, inverse.detach().to(r.dtype), engine, prescaled=True) + (1 - p) * r

    rhs_cg = p * weighted(rhs + a_t * lap0(v_fixed))
    if solve is None:
        solve = Solve(rtol=1e-10 if u.dtype == torch.float64 else 1e-6)
    y = cg(operator, rhs_cg, (p * x).detach(), solve=solve, preconditioner=precond, operator_params=(a_t, d))
    return comp.embed(p * y + (1 - p) * x, u)


def _same(kept, t: torch.Tensor) -> bool:
    """Whether ``t`` is the tensor a cache entry was built from: the very object, not modified in place since
    (``kept = (t, t._version, copy)``), or, failing that, equal to the copy kept then."""
    obj, version, copy_ = kept
    if is_compiling():  # a traced step reads nothing back: the very tensors of the eager steps, or a miss
        return obj is t
    if obj is t and t._version == version:
        return True
    return copy_.shape == t.shape and copy_.device == t.device and torch.equal(copy_, t)


def _kept(t: torch.Tensor):
    return (t, t._version, t.detach().clone())


def _open_faces(comp, cut: torch.Tensor, dtype, cache: dict | None) -> torch.Tensor | None:
    """``1 - cut`` in ``dtype`` (a product with it zeroes the cut faces), kept in ``cache``; None without one."""
    if cache is None:
        return None
    key = ("open-faces", comp.key, dtype, str(cut.device))
    hit = cache.get(key)
    if hit is not None and _same(hit[0], cut):
        return hit[1]
    keep = (~cut).to(dtype)
    if not is_compiling():  # what a trace computes is not kept
        cache[key] = (_kept(cut), keep)
    return keep


def _explicit_denominator(comp, coef: torch.Tensor, alpha, cache: dict | None) -> torch.Tensor:
    """``1 + α coef``, the point-implicit diagonal of an explicit step; kept in ``cache`` for a float ``α``."""
    if cache is None or isinstance(alpha, torch.Tensor) or coef.requires_grad:
        return 1 + alpha * coef
    key = ("explicit-denominator", comp.key, float(alpha), coef.dtype, str(coef.device))
    hit = cache.get(key)
    if hit is not None and _same(hit[0], coef):
        return hit[1]
    den = 1 + alpha * coef
    if not is_compiling():  # what a trace computes is not kept
        cache[key] = (_kept(coef), den)
    return den


def staggered_laplace(velocity, walls=None):
    """The (2d+1)-point Laplacian of each MAC component with the boundary's ghost rules, and with sharp no-slip
    surfaces (``walls``, as for :func:`diffuse_staggered`): ``L_0 u - coef u + source`` on the free faces, 0 on the
    cut faces."""
    walls, _ = _walls(walls, velocity, None)
    out = []
    for i, u in enumerate(velocity.values):
        comp = _component(velocity.grid, velocity.boundary, i)
        wall = None if walls is None else walls[i]
        if wall is None:
            out.append(comp.laplace(u))
            continue
        cut, coef, source = wall
        lap = comp.laplace(torch.where(cut, torch.zeros_like(u), u)) - coef.to(u.dtype) * u
        if source is not None:
            lap = lap + source.to(u.dtype)
        out.append(torch.where(cut, torch.zeros_like(lap), lap))
    return velocity.with_values(tuple(out))


def _phi1(z: torch.Tensor) -> torch.Tensor:
    small = z.abs() < 1e-8
    safe = torch.where(small, torch.ones_like(z), z)
    return torch.where(small, 1.0 + z / 2, torch.expm1(safe) / safe)


# ----------------------------------------------------------------------------------------------------------
# fixed faces by the capacitance matrix

#: Most surface faces per component for which a dense capacitance matrix is built.
CAPACITANCE_MAX_FACES = 4096


def _green_rows(comp, index: torch.Tensor, shape, coef: float, mult, device, engine) -> torch.Tensor | None:
    """``g[j] = (A⁻¹ e_(index_j))[index]`` for the box operator of ``comp`` (``(k, k)`` float64 on ``device``) from its
    separable decomposition, checked against two box solves; None where they disagree (the caller solves the columns
    one by one)."""
    coords = [c.cpu() for c in unravel(index, shape)]
    factors, inverse = comp.green_factors(coef)
    g = green_block(factors, inverse, coords).to(device)
    n_all = math.prod(shape)
    k = index.numel()
    for j in sorted({0, k - 1}):
        e = torch.zeros(1, n_all, dtype=torch.float64, device=device)
        e[0, index[j]] = 1.0
        z = comp.apply(e.reshape(1, *shape), mult, engine, prescaled=True).reshape(-1)[index]
        err = float((z - g[j]).abs().max())
        if err > 1e-9 * max(float(z.abs().max()), 1e-300):
            warn_from_caller(f"viscous capacitance solve: the separable block differs from an exact box solve by "
                             f"{err:.2e} (relative tolerance 1e-9); building it by {k} box solves instead (the same "
                             "block, built more slowly)", SlowPathWarning)
            return None
    return g


def _capacitance_rows(comp, index: torch.Tensor, shape, coef: float, mult, device, engine) -> torch.Tensor:
    """``g[j] = (A⁻¹ e_(index_j))[index]``: :func:`_green_rows`, or, where its check fails, ``k`` box solves (in
    batches of at most 32 MB)."""
    k = index.numel()
    g = _green_rows(comp, index, shape, coef, mult, device, engine) if k else None
    if g is None:
        g = torch.empty(k, k, dtype=torch.float64, device=device)
        chunk = max(1, (1 << 22) // math.prod(shape))
        for start in range(0, k, chunk):
            z = _SharpCapacitanceSolve._columns(comp, index[start : start + chunk], shape, mult, engine)
            g[start : start + z.shape[0]] = z[:, index]
    return g


class _CapacitanceSolve:
    """Exact solve of ``(I - a L₀) u = f`` on the free faces with ``u`` prescribed on the fixed faces.

    Let ``A = I - a L₀`` be the box operator on the unknowns (inverted exactly by the transforms) and ``S`` the
    fixed faces with a free stencil neighbour (the body surface). The free-face equations see no other fixed
    face, so the answer is ``u = A⁻¹ (f + Pᵀ σ)`` with sources ``σ`` on ``S`` chosen so that ``u_S = g_S``:
    ``C σ = g_S - (A⁻¹ f)_S`` with the capacitance matrix ``C = (A⁻¹)_{SS}`` (|S| x |S|, dense, read from the
    box's separable eigen-decomposition and LU-factored once in float64). Per call: two box solves and one small
    triangular solve, no iterations; the other fixed faces (inside the body) are overwritten by their prescribed
    values. Buzbee, Dorr, George & Golub (1971),
    "The direct solution of the discrete Poisson equation on irregular regions", SIAM J. Numer. Anal. 8(4).
    """

    def __init__(self, comp, surface: torch.Tensor, fixed: torch.Tensor, coef: float, device, engine):
        self.surface = surface  # flat indices into the unknowns
        self.op = ("implicit", coef)  # the box operator, for the fast box solves
        self.fixed = fixed  # (1, *unknown_shape) bool
        shape = tuple(fixed.shape[1:])
        # the same faces as flat indices into the full component, and the fixed faces there
        full = torch.zeros((1, *comp.face_shape), dtype=torch.bool, device=device)
        comp.restrict(full).copy_(fixed)
        self.fixed_full = full
        index = torch.arange(math.prod(comp.face_shape), device=device).reshape(comp.face_shape)
        self.surface_full = comp.restrict(index[None]).reshape(-1)[surface]
        mult = comp.inverse_multiplier(coef, torch.float64, device)
        cap = _capacitance_rows(comp, surface, shape, coef, mult, device, engine)
        self.lu, self.pivots = torch.linalg.lu_factor(cap)

    def _sigma(self, resid: torch.Tensor) -> torch.Tensor:
        return torch.linalg.lu_solve(self.lu, self.pivots, resid.T.to(torch.float64)).T.to(resid.dtype)

    def solve(self, comp, rhs, x, inverse, like, engine) -> torch.Tensor:
        """The full component: free faces solved, fixed faces ``x``, boundary faces from the boundary."""
        full = comp.solve_box(rhs, inverse, like, engine, op=self.op) if self.surface.numel() else None
        if full is not None:  # no autograd, walls: both box solves written into new full components
            b = full.shape[0]
            resid = like.reshape(b, -1)[:, self.surface_full] - full.view(b, -1)[:, self.surface_full]
            src = full.new_zeros((b, math.prod(self.fixed.shape[1:])))
            src.index_copy_(1, self.surface, self._sigma(resid))
            src = src.view(b, *self.fixed.shape[1:])
            corr = comp.solve_box(src, inverse, like, engine, op=self.op)
            if corr is None:
                comp.restrict(full).add_(comp.apply(src, inverse, engine, prescaled=True))
            else:
                full.add_(corr)  # the boundary faces are zero in both
            return torch.where(self.fixed_full, like, full)
        z = comp.apply(rhs, inverse, engine, prescaled=True)
        if self.surface.numel():
            flat = z.flatten(1)
            resid = x.flatten(1)[:, self.surface] - flat[:, self.surface]
            src = torch.zeros_like(flat).index_copy(1, self.surface, self._sigma(resid)).reshape(z.shape)
            z = z + comp.apply(src, inverse, engine, prescaled=True)
        return comp.embed(torch.where(self.fixed, x, z), like)


def _surface(comp, fixed: torch.Tensor) -> torch.Tensor:
    """Flat indices of the fixed unknowns with a free neighbour in the stencil (``fixed``: ``(*unknowns)``)."""
    free = ~fixed
    near = torch.zeros_like(fixed)
    for a in range(fixed.ndim):
        n = fixed.shape[a]
        if a in comp.periodic:
            near |= torch.roll(free, 1, a) | torch.roll(free, -1, a)
        elif n > 1:
            near.narrow(a, 0, n - 1).logical_or_(free.narrow(a, 1, n - 1))
            near.narrow(a, 1, n - 1).logical_or_(free.narrow(a, 0, n - 1))
    return (fixed & near).flatten().nonzero().squeeze(1)


def _capacitance(comp, mask: torch.Tensor, coef, device, engine, cache: dict | None) -> _CapacitanceSolve | None:
    """The capacitance solve for this component, body and ``coef = θ ν dt``, kept in ``cache``; or None (CG).

    None without a ``cache`` (a one-off solve: the matrix costs a block of the box's Green's function and an
    ``|S|``-sized LU factorisation, more than one PCG solve, so it pays only when the same body and time step come
    back, and the owner of the body's layout says so by passing its cache), for a tensor ``coef`` (its gradient
    needs the CG path), per-sample masks and more than :data:`CAPACITANCE_MAX_FACES` surface faces. With a cache the
    solve is built at the first request, so every solve of one owner takes the same path.
    """
    if cache is None or isinstance(coef, torch.Tensor) or mask.shape[0] != 1 or mask.requires_grad:
        return None
    key = ("capacitance", comp.i, tuple(comp.face_shape), tuple(comp.dx), repr(comp.kinds), comp.first,
           comp.count, comp.odd, float(coef), str(device))
    hit = cache.get(key)
    if hit is not None and _same(hit[0], mask):
        return hit[1] or None
    if is_compiling():  # built by the eager steps only
        return None
    fixed = comp.restrict(mask).detach()
    surface = _surface(comp, fixed[0])
    solver = False if surface.numel() > CAPACITANCE_MAX_FACES else _CapacitanceSolve(
        comp, surface, fixed, float(coef), device, engine)
    cache[key] = (_kept(mask), solver)
    return solver or None


#: Relative size (per dtype) below which the correction of a sharp capacitance solve is dropped outside its window:
#: a sixteenth of the round-off that the box solve of the whole component leaves on every face (see
#: :class:`_SharpCapacitanceSolve`).
WINDOW_TOLERANCE = {torch.float64: 2.0**-56, torch.float32: 2.0**-28}


class _SharpCapacitanceSolve:
    """Exact solve of ``(I - a (L₀ - C)) u = f`` on the free faces, ``u`` read as ``g`` on the held faces.

    ``C`` is the diagonal ``coef`` of a sharp no-slip surface on the free faces ``N`` next to it. With the box
    operator ``A = I - a L₀`` (inverted exactly by the transforms) the answer is ``u = A⁻¹ (f + Pᵀ σ)`` with sources
    ``σ`` on the held surface faces ``S`` and on ``N``: on ``S`` they make ``u_S = g_S``, on ``N`` they supply the
    diagonal, ``σ_N = -a C u_N``. With ``G = A⁻¹`` restricted to ``J = S ∪ N`` and ``z = A⁻¹ f``:
    ``(G_JJ + diag(0_S, (a C)⁻¹_N)) σ = [g_S, 0_N] - z_J`` (the rows of ``N`` divided by ``a C``; ``G_JJ`` is read
    from the box's separable eigen-decomposition, :func:`_green_rows`, and the matrix inverted once in float64).
    ``g`` is the held value as the stencil reads it: the face's value, 0 on the cut faces.

    The correction ``w = A⁻¹ Pᵀ σ = G_{:,J} σ`` is a second box solve of the whole component, or, where ``G``
    decays fast enough (``a`` small against the cell size), a box solve on a window ``W`` around the body alone:
    the same operator with ``w = 0`` outside ``W`` (DST-I along every axis). The bound: the row sums
    ``h = G 1_J ≥ 0`` (``A`` is an M-matrix) satisfy ``A h = 0`` outside the box ``R`` around ``J``, and
    ``ψ = H λ^(d - m)``, ``d`` the Chebyshev distance to that box, is a supersolution there for ``λ = c / (1 + c)``,
    ``c = a / dx²`` the largest off-diagonal of ``-a L₀`` away from open sides: a step changes ``d`` by at most one,
    only one neighbour is closer, and ``-L₀`` is weakly diagonally dominant with every ghost rule. An open side of
    the own axis (an even ghost about the boundary face, which doubles the inward coefficient there) is unfolded
    into mirror images of the sources, each no closer than ``R``: a factor 4 on ``ψ`` covers them. With ``H`` the
    largest ``h`` at ``d = m`` (measured from the columns; ``m = 0`` or a distance where ``h`` is still far above
    their round-off) the discrete maximum principle gives ``h <= H λ^(d - m)`` (times the images' factor) beyond,
    so ``|w| <= h ‖σ‖_∞`` is below :data:`WINDOW_TOLERANCE` ``max h ‖σ‖_∞`` outside the window's margin; the
    window's solve differs from ``w`` by a screened-harmonic function of its values on the ring around ``W``, no
    larger there (maximum principle again). Both are under the round-off of the whole component's box solve
    (``2⁻⁵⁶`` in float64, ``2⁻²⁸`` in float32, per unit ``max h ‖σ‖_∞``). The window is used where it lies inside
    the unknowns with a ring to spare, holds at most half of them, and the component has no periodic axis. Per
    call: one box solve of the component, the gathers of ``z_J`` and ``g_S``, a ``|J| x |J|`` product and the
    window's box solve.
    """

    def __init__(self, comp, surface, near, dcoef, fixed, coef: float, device, engine, cut=None):
        self.surface, self.near = surface, near
        self.fixed = fixed
        self.index = torch.cat([surface, near])
        shape = tuple(fixed.shape[1:])
        n_all = math.prod(shape)
        k = self.index.numel()
        self.ad = (coef * dcoef).to(torch.float64)  # a C on the faces of N
        mult = comp.inverse_multiplier(coef, torch.float64, device)
        g = _capacitance_rows(comp, self.index, shape, coef, mult, device, engine)  # g[j] = (A⁻¹ e_j) on J
        # the row sums of G_{:,J}, all >= 0 (A is an M-matrix): one box solve
        ones = torch.zeros(1, n_all, dtype=torch.float64, device=device)
        ones[0, self.index] = 1.0
        h = comp.apply(ones.reshape(1, *shape), mult, engine, prescaled=True).reshape(-1).abs()
        self.op = ("implicit", coef)
        full = torch.zeros((1, *comp.face_shape), dtype=torch.bool, device=device)
        comp.restrict(full).copy_(fixed)
        self.fixed_full = full
        grid_index = torch.arange(math.prod(comp.face_shape), device=device).reshape(comp.face_shape)
        unknown_to_full = comp.restrict(grid_index[None]).reshape(-1)
        self.surface_full, self.near_full = unknown_to_full[surface], unknown_to_full[near]
        self.index_full = torch.cat([self.surface_full, self.near_full])
        # the held faces (as flat indices into the full component and into the unknowns): written, not blended
        self.fixed_index = full.reshape(-1).nonzero().squeeze(1)
        self.fixed_unknowns = fixed.reshape(-1).nonzero().squeeze(1)
        # the surface faces whose held value the stencil reads (not cut; a cut face reads 0): their places in J
        # and their flat indices into the full component
        read = torch.ones(surface.numel(), dtype=torch.bool, device=device)
        if cut is not None:
            read = ~cut.detach().reshape(cut.shape[0], -1)[0, self.surface_full]
        self.read_pos = read.nonzero().squeeze(1)
        self.read_full = self.surface_full[self.read_pos]
        ns = surface.numel()
        m = g.T.clone()  # m[r, j] = G[index_r, index_j]
        m[ns:, ns:] += torch.diag(1.0 / self.ad)
        lu, pivots = torch.linalg.lu_factor(m)
        # σ = r M⁻ᵀ for rows r: the inverse's transpose, applied as one small product per call
        self._inverse = torch.linalg.lu_solve(lu, pivots, torch.eye(k, dtype=torch.float64, device=device),
                                              adjoint=True)
        # per dtype: the window's solve (slices, the places of J in it, its normalised DST-I multiplier) or None
        self.windows: dict = {}
        for dt, tol in WINDOW_TOLERANCE.items():
            window = self._window(comp, shape, h, coef, k, tol)
            if window is None:
                self.windows[dt] = None
                continue
            wshape = tuple(sl.stop - sl.start for sl in window)
            local = unravel(self.index, shape)
            flat = torch.zeros_like(self.index)
            for a, (sl, m) in enumerate(zip(window, wshape)):
                flat = flat * m + (local[a] - sl.start)
            lam = torch.zeros((), dtype=torch.float64)
            scale = 1.0
            for a, m in enumerate(wshape):
                kk = torch.arange(m, dtype=torch.float64)
                ev = -4 * torch.sin(math.pi * (kk + 1) / (2 * (m + 1))) ** 2 / comp.dx[a] ** 2
                lam = lam.unsqueeze(-1) + ev
                scale /= 2 * (m + 1)
            mult_w = (scale / (1.0 - coef * lam)).to(dtype=dt, device=device)
            self.windows[dt] = (window, wshape, flat, mult_w)

    @staticmethod
    def _columns(comp, idx, shape, mult, engine) -> torch.Tensor:
        """``A⁻¹ e_j`` for the unknowns ``idx``, as rows ``(len(idx), n)``."""
        n_all = math.prod(shape)
        e = torch.zeros(idx.numel(), n_all, dtype=torch.float64, device=mult.device)
        e[torch.arange(idx.numel(), device=mult.device), idx] = 1.0
        return comp.apply(e.reshape(idx.numel(), *shape), mult, engine, prescaled=True).reshape(idx.numel(), n_all)

    def _window(self, comp, shape, h: torch.Tensor, coef: float, k: int, tol: float):
        """The window (slices of the unknowns) outside which the correction is dropped at tolerance ``tol``, or None
        (see the class)."""
        if comp.periodic or k == 0:
            return None
        n_all = math.prod(shape)
        coords = torch.stack(unravel(self.index, shape), 1)
        lo, hi = coords.min(0).values.tolist(), coords.max(0).values.tolist()
        dist = torch.zeros(shape, dtype=torch.long, device=h.device)  # Chebyshev distance to the box of J
        for a, n in enumerate(shape):
            x = torch.arange(n, device=h.device)
            d = torch.clamp(torch.maximum(lo[a] - x, x - hi[a]), min=0)
            dist = torch.maximum(dist, d.reshape([-1 if b == a else 1 for b in range(len(shape))]))
        top = int(dist.max())
        if top == 0:
            return None
        # the largest h at each distance
        at = torch.zeros(top + 1, dtype=torch.float64, device=h.device).scatter_reduce(
            0, dist.reshape(-1), h, reduce="amax", include_self=True).tolist()
        hmax = float(h.max())
        c = coef * max(1.0 / d**2 for d in comp.dx)
        lam = c / (1.0 + c)
        # an open side of the own axis mirrors the sources (even ghost about the boundary face): up to two images
        # per side, each no closer than the box itself
        images = 1.0
        if comp.odd is not None and not all(comp.odd):
            if lam ** (2 * shape[comp.i]) > 1.0 / 3.0:
                return None
            images = 4.0
        target = tol * hmax
        margin = None
        for m0, h0 in enumerate(at):
            if m0 and h0 < 1e-9 * hmax:  # measured values of this size are still exact to 1e-4 (round-off 1e-13)
                break
            h0 = images * (h0 + 1e-13 * hmax)
            q = 0 if h0 <= target else math.ceil(math.log(target / h0) / math.log(lam))
            margin = m0 + q if margin is None else min(margin, m0 + q)
        window = tuple(slice(lo[a] - margin, hi[a] + margin + 1) for a in range(len(shape)))
        # inside the unknowns with a ring to spare (the ring is where the window's zero condition is checked)
        if any(sl.start < 1 or sl.stop > n - 1 for sl, n in zip(window, shape)):
            return None
        if 2 * math.prod(sl.stop - sl.start for sl in window) > n_all:
            return None
        return window

    @staticmethod
    def _window_solve(src: torch.Tensor, mult: torch.Tensor, engine) -> torch.Tensor:
        """``A_W⁻¹ src`` on the window (zero outside): DST-I along every axis, ``mult`` normalised."""
        axes = tuple(range(1, src.ndim))
        kinds = ("dst1",) * len(axes)
        out = _fft.r2r_multiply(src, kinds, kinds, axes, mult, engine=engine)
        if out is None:  # autograd or another engine
            out = _fft.r2rn(_fft.r2rn(src, kinds, axes, engine=engine) * mult, kinds, axes, engine=engine)
        return out

    def _residual(self, z_flat: torch.Tensor, g_flat: torch.Tensor, z_index) -> torch.Tensor:
        """``[g_S, 0_N] - z_J`` from flat components (``z_index``: where ``J`` lies in ``z_flat``)."""
        r = z_flat.index_select(1, z_index).neg_()
        return r.index_add_(1, self.read_pos, g_flat.index_select(1, self.read_full))

    def solve(self, comp, rhs, inverse, like, engine) -> torch.Tensor:
        """The full component: free faces solved, held faces ``like`` (read as 0 on the cut faces by the stencil),
        boundary faces from the boundary."""
        full = comp.solve_box(rhs, inverse, like, engine, op=self.op)
        if full is not None:  # no autograd, walls: the box solve written into a new full component
            b = full.shape[0]
            flat = full.view(b, -1)
            z = comp.restrict(full)
            r = self._residual(flat, like.reshape(like.shape[0], -1), self.index_full)
        else:
            z = comp.apply(rhs, inverse, engine, prescaled=True)
            b = z.shape[0]
            r = self._residual(z.reshape(b, -1), like.reshape(like.shape[0], -1), self.index)
        grad = z.requires_grad or r.requires_grad
        win = self.windows.get(r.dtype, self.windows[torch.float64])
        if win is not None:
            window, wshape, places, mult_w = win
            sigma = (r.to(torch.float64) @ self._inverse).to(r.dtype)
            src = torch.zeros((b, math.prod(wshape)), dtype=z.dtype, device=z.device)
            src = src.index_copy(1, places, sigma).view(b, *wshape)
            corr = self._window_solve(src, mult_w.to(z.dtype), engine)
            if grad:
                pad = []
                for sl, n in reversed(list(zip(window, z.shape[1:]))):
                    pad += [sl.start, n - sl.stop]
                z = z + torch.nn.functional.pad(corr, pad)
            else:
                z[(slice(None), *window)].add_(corr)
        else:
            sigma = (r.to(torch.float64) @ self._inverse).to(r.dtype)  # small; float64 as built
            src = torch.zeros((b, math.prod(self.fixed.shape[1:])), dtype=z.dtype, device=z.device)
            src = src.index_copy(1, self.index, sigma).view(b, *self.fixed.shape[1:])
            corr = comp.solve_box(src, inverse, like, engine, op=self.op) if full is not None else None
            if corr is not None:
                full.add_(corr)  # the boundary faces are zero in both
            elif grad:
                z = z + comp.apply(src, inverse, engine, prescaled=True)
            else:
                z.add_(comp.apply(src, inverse, engine, prescaled=True))
        if full is not None:
            held = like.reshape(like.shape[0], -1).index_select(1, self.fixed_index)
            full.view(b, -1).index_copy_(1, self.fixed_index, held.expand(b, -1))
            return full
        x = comp.restrict(like)
        if grad:
            return comp.embed(torch.where(self.fixed, x, z), like)
        held = x.reshape(x.shape[0], -1).index_select(1, self.fixed_unknowns)
        z.view(b, -1).index_copy_(1, self.fixed_unknowns, held.expand(b, -1))
        return comp.embed(z, like)


def _sharp_capacitance(comp, mask, cut, coef_full, coef, device, engine, cache):
    """The capacitance solve of a sharp surface for this component and ``coef = θ ν dt``, kept in ``cache``; None
    where the CG path is taken (no cache, gradients, per-sample layouts, too many faces)."""
    if (cache is None or isinstance(coef, torch.Tensor) or mask.shape[0] != 1 or coef_full.shape[0] != 1
            or coef_full.requires_grad):
        return None
    key = ("sharp-capacitance", comp.key, float(coef), str(device))
    hit = cache.get(key)
    if hit is not None and _same(hit[0], mask) and _same(hit[1], coef_full) and _same(hit[2], cut):
        return hit[3] or None
    if is_compiling():  # built by the eager steps only
        return None
    fixed = comp.restrict(mask).detach()
    surface = _surface(comp, fixed[0])
    d = comp.restrict(coef_full.detach())[0].flatten()
    near = (d != 0).nonzero().squeeze(1)
    solver = False
    if surface.numel() + near.numel() <= 2 * CAPACITANCE_MAX_FACES:
        solver = _SharpCapacitanceSolve(comp, surface, near, d[near].to(torch.float64), fixed, float(coef), device,
                                        engine, cut=cut[:1])
    cache[key] = (_kept(mask), _kept(coef_full), _kept(cut), solver)
    return solver or None
