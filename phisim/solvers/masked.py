"""The weighted (cut-cell) Poisson operator ``div(w grad p)`` of a box with bodies, and its PCG solve.

Every face of the MAC grid carries a weight ``w`` in ``[0, 1]``: 1 in open fluid, 0 inside bodies and
fractional where a body cuts the face's control volume (Batty, Bertails & Bridson 2007, "A fast
variational framework for accurate solid-fluid coupling", ACM TOG 26). The operator

    ``(L p)_c = sum_a [ w_{c+1/2} (p_{c+1} - p_c) - w_{c-1/2} (p_c - p_{c-1}) ] / dx_a^2``

is symmetric negative semi-definite on the *active* cells (cells with at least one face of positive
weight). Inactive cells (deep inside bodies) are decoupled and carry the identity, so the system stays
definite there and their pressure is 0. Box sides follow ``kinds``: ``'dirichlet'`` (value 0 on the face,
ghost ``-p``), ``'neumann'`` (zero flux: the boundary face is not corrected) or ``'periodic'``.

Null space. Active cells are connected through faces of positive weight (periodic axes wrap). A connected
region that reaches no Dirichlet side has the constants in the null space: a closed box, or a pocket of
fluid enclosed by bodies. Each such region's constant is projected out of the right-hand side, the CG
residuals and the preconditioned residuals, and the solution has zero mean over the region.

Preconditioner: the exact spectral inverse of the unweighted box (FFT/DCT/DST by ``kinds``) applied to the
active cells. Cells that a cut face ties only weakly to the fluid (mostly solid cells, "leaves") are
eliminated exactly around it (a block LDL^T step: their residual is passed to their neighbours before the
box inverse and their value recovered from the neighbours' after it). Where no leaves can be used (layouts
that differ between samples) the inverse diagonal on the cut cells is added instead (additive Jacobi).
Either way, with fractional bodies this cuts the iterations about threefold against the box inverse alone;
the elimination also takes a quarter to a third off warm-started solves (plume and cylinder wake).
:class:`MaskedPoisson` computes the labels, null space and eigenvalues once; a fluid solver keeps one per
body layout and calls :meth:`MaskedPoisson.solve` every step.

Direct solve. An operator solved again and again (a static body) switches from PCG to an exact solve by the box
inverse and a capacitance matrix on its cut faces (:mod:`phisim.solvers.direct`; two box solves per call,
built once the PCG solves have cost about as much as the build). Its answer is CG's start, so CG still checks
it (zero iterations in float64, a couple in float32) and provides the gradient. :data:`DIRECT` switches it off.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from phisim.errors import ParameterError, ShapeError
from phisim.solvers.direct import MAX_RANK, MAX_RANK_SQUARED_PER_CELL, WoodburySolve
from phisim.solvers.linalg import Solve, SolveInfo, cg
from phisim.solvers.poisson import (
    _TRANSFORM,
    _apply_multiplier,
    _inverse_eigs,
    _layout,
    _normalize_dx,
    _singular,
    _transform_scale,
    normalize_kinds,
)
from phisim.spectral.fft import r2r_multiply

__all__ = ["MaskedPoisson"]

#: Solve a layout that keeps coming back directly (:mod:`phisim.solvers.direct`); False: always PCG.
DIRECT = True
#: Requests of one operator answered by PCG before its direct solve is built, at least ...
DIRECT_BUILD_AFTER = 2
#: ... and one per this many cut faces (the build costs one box solve per face; a PCG solve about 10-20).
DIRECT_FACES_PER_REQUEST = 16

#: Cells whose diagonal is at most this fraction of the open-box diagonal are eliminated exactly in the
#: preconditioner when they couple to no other such cell (0: off). 0.2 measured best over a cold solve with a
#: disc and two boxes and the warm-started plume and cylinder wake at 128^2 and 256^2 (0.4-0.5 leave the
#: warm solves as fast but double the cold iterations; 0.1 gains less).
LEAF_THRESHOLD = 0.2


def _scatter_add(out: torch.Tensor, index: torch.Tensor, values: torch.Tensor,
                 in_rounds: bool | None = None) -> torch.Tensor:
    """``out[:, index] += values`` in place, in a fixed order on every device.

    On the CPU ``index_add_`` accumulates repeated indices in order. Elsewhere it uses atomic additions whose
    order varies between runs, so the values are added in rounds in which no index repeats (each element then
    gets one addition per round, a result that does not depend on scheduling). ``in_rounds`` forces either way.
    """
    if not (out.device.type != "cpu" if in_rounds is None else in_rounds):
        return out.index_add_(1, index, values)
    order = torch.argsort(index, stable=True)
    sorted_index = index[order]
    first = torch.ones_like(sorted_index, dtype=torch.bool)
    first[1:] = sorted_index[1:] != sorted_index[:-1]
    start = torch.cummax(torch.where(first, torch.arange(len(index), device=index.device), 0), 0).values
    occurrence = torch.empty_like(index)
    occurrence[order] = torch.arange(len(index), device=index.device) - start
    for k in range(int(occurrence.max()) + 1 if len(index) else 0):
        sel = torch.nonzero(occurrence == k).flatten()
        out.index_add_(1, index[sel], values.index_select(1, sel))
    return out


class MaskedPoisson:
    """``-div(w grad p)`` on a box with face weights: operator, face gradient and preconditioned CG solve.

    Args:
        weights: One tensor per axis ``a``, shape ``(1 or B, *face_shape(a))`` (``resolution[a] + 1`` faces
            along ``a``, boundary faces included), values in ``[0, 1]``. On a periodic axis face ``n`` is
            face ``0`` (only faces ``0..n-1`` are read). Boundary faces of Neumann sides are ignored.
            Weights may require grad: :meth:`solve` is then differentiable with respect to them.
        dx: Cell spacing, one per axis (or a float).
        kinds: Box boundary kinds of the pressure (see :func:`phisim.solvers.poisson.normalize_kinds`).
        engine: FFT engine of the preconditioner.

    Raises:
        ShapeError: For weights that do not fit one grid.
        ParameterError: For weights outside ``[0, 1]`` or non-finite.
    """

    def __init__(self, weights, dx, kinds, *, engine: str | None = None):
        weights = tuple(weights)
        rank = len(weights)
        if rank == 0:
            raise ShapeError("MaskedPoisson needs one weight tensor per axis")
        res = tuple(int(weights[a].shape[1 + a]) - 1 for a in range(rank))
        for a, w in enumerate(weights):
            expect = tuple(n + 1 if b == a else n for b, n in enumerate(res))
            if w.ndim != rank + 1 or tuple(w.shape[1:]) != expect:
                raise ShapeError(f"weights[{a}] must have shape (B, *{expect}), got {tuple(w.shape)}")
            wd = w.detach()
            if not bool(torch.isfinite(wd).all()) or bool((wd < 0).any()) or bool((wd > 1).any()):
                raise ParameterError(f"face weights of axis {a} must be finite and in [0, 1]")
        self.rank, self.resolution = rank, res
        self.dx = _normalize_dx(dx, rank)
        self.kinds = normalize_kinds(kinds, rank)
        self.engine = engine
        self.weights = weights
        self._casts: dict = {}
        self.batch = max(int(w.shape[0]) for w in weights)
        active = torch.zeros((self.batch, *res), dtype=torch.bool, device=weights[0].device)
        for a, w in enumerate(weights):
            pos = (w.detach() > 0)
            dim = 1 + a
            n = res[a]
            lo_k, hi_k = self.kinds[a]
            left = pos.narrow(dim, 0, n)  # face below cell k
            right = pos.narrow(dim, 1, n)  # face above cell k
            if lo_k == "periodic":
                right = torch.roll(left, -1, dim)
            else:
                if lo_k == "neumann":
                    left = torch.cat([torch.zeros_like(left.narrow(dim, 0, 1)), left.narrow(dim, 1, n - 1)], dim)
                if hi_k == "neumann":
                    right = torch.cat([right.narrow(dim, 0, n - 1), torch.zeros_like(right.narrow(dim, 0, 1))], dim)
            active = active | left | right
        self.active = active
        if bool((active.flatten(1).sum(1) == 0).any()):
            raise ParameterError("every face weight of a sample is 0: there is no fluid to solve for")
        self.null = self._null_space()
        self._inv = _inverse_eigs(res, self.dx, self.kinds, active.device)
        dw = self._diagonal(tuple(w.detach() for w in weights))
        d0 = self._diagonal(tuple(torch.ones_like(w[:1]) for w in weights))
        frac = tuple(((w.detach() > 0) & (w.detach() < 1)).to(w.dtype) for w in weights)
        cut = active & (dw < d0 * (1 - 1e-9)) & (dw > 0) & (self._diagonal(frac) > 0)  # cells with cut faces
        self._cut_inv = torch.where(cut, 1.0 / torch.where(cut, dw, torch.ones_like(dw)), torch.zeros_like(dw))
        self._scale2 = tuple(1.0 / d**2 for d in self.dx)
        self._direct = None  # WoodburySolve once set up; False where the direct solve does not apply
        self._requests = 0
        self._beta_inv = None  # 1 / smallest non-zero box eigenvalue (singular boxes, see _box_inverse)

    # ---- structure ---------------------------------------------------------------------------------------

    def _diagonal(self, weights) -> torch.Tensor:
        """Diagonal of ``-div(w grad)`` per cell (Dirichlet faces count twice: the ghost is ``-p``)."""
        d = 0
        for a, w in enumerate(weights):
            n, dim = self.resolution[a], 1 + a
            lo, hi = w.narrow(dim, 0, n), w.narrow(dim, 1, n)
            lo_k, hi_k = self.kinds[a]
            if lo_k == "periodic":
                hi = torch.roll(lo, -1, dim)
            else:
                scale_lo = torch.ones(n, dtype=w.dtype, device=w.device)
                scale_hi = torch.ones(n, dtype=w.dtype, device=w.device)
                scale_lo[0] = 0.0 if lo_k == "neumann" else 2.0
                scale_hi[-1] = 0.0 if hi_k == "neumann" else 2.0
                shape = [1] * w.ndim
                shape[dim] = n
                lo, hi = lo * scale_lo.reshape(shape), hi * scale_hi.reshape(shape)
            d = d + (lo + hi) / self.dx[a] ** 2
        return d

    def _null_space(self) -> torch.Tensor | None:
        """Normalised indicators ``(B, K, *res)`` of the regions without a Dirichlet side, or None."""
        res = self.resolution
        ncell = math.prod(res)
        idx = np.arange(ncell).reshape(res)
        per_sample = []
        pos_all = [(w.detach() > 0).cpu().numpy() for w in self.weights]
        act_all = self.active.cpu().numpy()
        for b in range(self.batch):
            act = act_all[b]
            rows, cols = [], []
            regular_cells = []
            for a in range(self.rank):
                pos = pos_all[a][min(b, pos_all[a].shape[0] - 1)]
                n = res[a]
                inner = np.take(pos, np.arange(1, n), axis=a)
                lo_i, hi_i = np.take(idx, np.arange(0, n - 1), axis=a), np.take(idx, np.arange(1, n), axis=a)
                rows.append(lo_i[inner])
                cols.append(hi_i[inner])
                lo_k, hi_k = self.kinds[a]
                if lo_k == "periodic":
                    wrap = np.take(pos, 0, axis=a)
                    rows.append(np.take(idx, n - 1, axis=a)[wrap])
                    cols.append(np.take(idx, 0, axis=a)[wrap])
                    continue
                if lo_k == "dirichlet":
                    regular_cells.append(np.take(idx, 0, axis=a)[np.take(pos, 0, axis=a)])
                if hi_k == "dirichlet":
                    regular_cells.append(np.take(idx, n - 1, axis=a)[np.take(pos, n, axis=a)])
            r = np.concatenate(rows) if rows else np.zeros(0, int)
            c = np.concatenate(cols) if cols else np.zeros(0, int)
            graph = coo_matrix((np.ones(len(r), dtype=np.int8), (r, c)), shape=(ncell, ncell))
            _, labels = connected_components(graph, directed=False)
            labels = labels.reshape(res)
            regular = set(np.unique(labels.ravel()[np.concatenate(regular_cells)]).tolist()) if regular_cells else set()
            singular = [k for k in np.unique(labels[act]) if int(k) not in regular]
            per_sample.append([(labels == k) & act for k in singular])
        kmax = max(len(s) for s in per_sample)
        if kmax == 0:
            return None
        z = np.zeros((self.batch, kmax, *res))
        for b, comps in enumerate(per_sample):
            for k, m in enumerate(comps):
                z[b, k] = m / math.sqrt(m.sum())
        return torch.as_tensor(z, device=self.active.device)

    @property
    def singular(self) -> bool:
        """Whether some region has constants in its null space (no Dirichlet side reached)."""
        return self.null is not None

    def project(self, t: torch.Tensor) -> torch.Tensor:
        """Remove each closed region's mean from ``t`` ``(B, *res)`` (identity without null space)."""
        if self.null is None:
            return t
        z = self._cast("null", self.null, t.dtype).flatten(2)  # (B or 1, K, N)
        if z.shape[:2] == (1, 1):  # one region shared by the batch (a closed box): a product and a multiply-add
            z = z.view(-1)
            coef = torch.mv(t.reshape(t.shape[0], -1), z)
            return torch.addcmul(t, coef.view((-1,) + (1,) * (t.ndim - 1)), z.view(t.shape[1:]), value=-1)
        coef = torch.matmul(z, t.flatten(1).unsqueeze(-1))  # (B, K, 1): one pass, no full-size temporaries
        return t - torch.matmul(coef.transpose(1, 2), z).view(t.shape)

    def region_sums(self, t: torch.Tensor) -> torch.Tensor | None:
        """Per closed region, ``sum t`` over its cells ``(B, K)`` (None without null space)."""
        if self.null is None:
            return None
        z = (self.null > 0).to(t.dtype)
        return (z * t.unsqueeze(1)).flatten(2).sum(-1)

    # ---- operators ---------------------------------------------------------------------------------------

    def gradient(self, p: torch.Tensor) -> tuple[torch.Tensor, ...]:
        """Face gradient ``(p_k - p_{k-1}) / dx`` per axis, boundary faces by kind, shapes ``face_shape(a)``.

        Dirichlet sides use the ghost ``-p`` (value 0 on the face), Neumann sides give 0, periodic axes wrap
        (face ``n`` repeats face ``0``).
        """
        out = []
        for a in range(self.rank):
            dim, n, d = 1 + a, self.resolution[a], self.dx[a]
            lo_k, hi_k = self.kinds[a]
            if lo_k == "periodic":
                g0 = (p.narrow(dim, 0, 1) - p.narrow(dim, n - 1, 1)) / d
                inner = (p.narrow(dim, 1, n - 1) - p.narrow(dim, 0, n - 1)) / d
                out.append(torch.cat([g0, inner, g0], dim))
                continue
            inner = (p.narrow(dim, 1, n - 1) - p.narrow(dim, 0, n - 1)) / d
            first, last = p.narrow(dim, 0, 1), p.narrow(dim, n - 1, 1)
            lo = 2 * first / d if lo_k == "dirichlet" else torch.zeros_like(first)
            hi = -2 * last / d if hi_k == "dirichlet" else torch.zeros_like(last)
            out.append(torch.cat([lo, inner, hi], dim))
        return tuple(out)

    def divergence(self, flux) -> torch.Tensor:
        """MAC divergence ``sum_a (f_{k+1} - f_k) / dx_a`` of face values ``(B, *face_shape(a))``."""
        out = 0
        for a, f in enumerate(flux):
            dim, n = 1 + a, self.resolution[a]
            out = out + (f.narrow(dim, 1, n) - f.narrow(dim, 0, n)) / self.dx[a]
        return out

    def _cast(self, name: str, t: torch.Tensor, dtype: torch.dtype) -> torch.Tensor:
        """``t`` in ``dtype``, converted once per dtype (tensors that require grad are never cached)."""
        if t.dtype == dtype:
            return t
        if t.requires_grad:
            return t.to(dtype)
        key = (name, dtype)
        hit = self._casts.get(key)
        if hit is None:
            hit = self._casts[key] = t.to(dtype)
        return hit

    def _apply(self, p: torch.Tensor, *weights: torch.Tensor) -> torch.Tensor:
        g = self.gradient(p)
        flux = []
        for a, (w, gi) in enumerate(zip(weights, g)):
            w = self._cast(f"w{a}", w, p.dtype)
            if self.kinds[a][0] == "periodic":  # face n is face 0: read only faces 0..n-1
                dim, n = 1 + a, self.resolution[a]
                w = torch.cat([w.narrow(dim, 0, n), w.narrow(dim, 0, 1)], dim)
            flux.append(w * gi)
        return torch.where(self.active, -self.divergence(tuple(flux)), p)

    def apply(self, p: torch.Tensor) -> torch.Tensor:
        """``-div(w grad p)`` on active cells, ``p`` on inactive ones (the SPD system :meth:`solve` inverts)."""
        if any(w.requires_grad for w in self.weights):
            return self._apply(p, *self.weights)
        return self._apply_fixed(p)

    def _stencil(self, dtype: torch.dtype):
        """Diagonal and face couplings of the operator with fixed weights, in ``dtype`` (built once per dtype).

        ``diag`` is ``sum_a (w_lo + w_hi) / dx_a^2`` (Dirichlet faces twice, Neumann faces not at all) on the
        active cells and 1 on the inactive ones; ``couplings[a]`` are the weights of the interior faces along
        ``a`` over ``dx_a^2`` and ``wrap[a]`` that of the periodic wrap face (None on other axes).
        """
        key = ("stencil", dtype)
        hit = self._casts.get(key)
        if hit is None:
            w = tuple(wi.detach() for wi in self.weights)
            diag = torch.where(self.active, self._diagonal(w), torch.ones((), dtype=w[0].dtype))
            couplings, wrap = [], []
            for a, wa in enumerate(w):
                dim, n = 1 + a, self.resolution[a]
                couplings.append((wa.narrow(dim, 1, n - 1) / self.dx[a] ** 2).to(dtype).contiguous())
                periodic = self.kinds[a][0] == "periodic"
                wrap.append((wa.narrow(dim, 0, 1) / self.dx[a] ** 2).to(dtype).contiguous() if periodic else None)
            hit = self._casts[key] = (diag.to(dtype).contiguous(), tuple(couplings), tuple(wrap))
        return hit

    def _apply_fixed(self, p: torch.Tensor) -> torch.Tensor:
        # The operator as one diagonal product plus two shifted multiply-adds per axis: the same numbers as
        # ``_apply`` (gradient, weights, divergence, masking) in a third of the passes over memory.
        diag, couplings, wrap = self._stencil(p.dtype)
        out = diag * p
        for a, c in enumerate(couplings):
            dim, n = 1 + a, self.resolution[a]
            out.narrow(dim, 0, n - 1).addcmul_(c, p.narrow(dim, 1, n - 1), value=-1)
            out.narrow(dim, 1, n - 1).addcmul_(c, p.narrow(dim, 0, n - 1), value=-1)
            if wrap[a] is not None:
                out.narrow(dim, 0, 1).addcmul_(wrap[a], p.narrow(dim, n - 1, 1), value=-1)
                out.narrow(dim, n - 1, 1).addcmul_(wrap[a], p.narrow(dim, 0, 1), value=-1)
        return out

    def _leaves(self):
        """Weakly connected cells eliminated exactly in the preconditioner, or None.

        A *leaf* is an active cell whose diagonal is at most half the open-box one (mostly solid: a cell whose
        centre lies in a body but which a cut face still ties to the fluid) and which couples to no other
        leaf. Leaves only couple to non-leaves, so the leaf block of the operator is diagonal and they can be
        eliminated exactly (a block LDL^T step): see :meth:`_precondition`. Built once; shared layouts only
        (weights of batch 1).

        Returns:
            None, or ``(leaf, inv_d, src, dst, frac)``: flat leaf indices ``(L,)``, their inverse diagonal
            ``(L,)`` and the couplings leaf ``src`` -> neighbour ``dst`` with ``frac = c / d_leaf`` ``(P,)``.
        """
        hit = self._casts.get("leaves", False)
        if hit is not False:
            return hit
        out = None
        if self.batch == 1 and LEAF_THRESHOLD > 0:
            w = tuple(wi.detach()[:1].double() for wi in self.weights)
            diag = self._diagonal(w)[0].flatten()
            d0 = self._diagonal(tuple(torch.ones_like(wi) for wi in w))[0].flatten()
            cand = self.active[0].flatten() & (diag > 0) & (diag <= LEAF_THRESHOLD * d0)
            if bool(cand.any()):
                res, n_cells = self.resolution, math.prod(self.resolution)
                idx = torch.arange(n_cells, device=diag.device).view(res)
                src, dst, cpl = [], [], []
                for a, wa in enumerate(w):
                    n = res[a]
                    faces = [(wa[0].narrow(a, 1, n - 1), idx.narrow(a, 0, n - 1), idx.narrow(a, 1, n - 1))]
                    if self.kinds[a][0] == "periodic":
                        faces.append((wa[0].narrow(a, 0, 1), idx.narrow(a, n - 1, 1), idx.narrow(a, 0, 1)))
                    for c, lo, hi in faces:
                        c = c.flatten() / self.dx[a] ** 2
                        keep = c > 0
                        src += [lo.flatten()[keep], hi.flatten()[keep]]
                        dst += [hi.flatten()[keep], lo.flatten()[keep]]
                        cpl += [c[keep], c[keep]]
                src, dst, cpl = torch.cat(src), torch.cat(dst), torch.cat(cpl)
                touching = torch.zeros_like(cand)
                touching[src[cand[src] & cand[dst]]] = True
                leaf = cand & ~touching
                if bool(leaf.any()):
                    sel = leaf[src]
                    src, dst, cpl = src[sel], dst[sel], cpl[sel]
                    leaf_idx = torch.nonzero(leaf).flatten()
                    out = (leaf_idx, 1.0 / diag[leaf_idx], src, dst, cpl / diag[src], leaf.view(1, *res))
        self._casts["leaves"] = out
        return out

    def _precondition(self, r: torch.Tensor) -> torch.Tensor:
        # ``r`` is a CG residual, already projected onto the range (cg applies ``project`` to every residual
        # before the preconditioner), so only the output is projected.
        #
        # With leaves (see ``_leaves``) the preconditioner is the exact block elimination of the leaves around
        # an approximate inverse of the rest: ``M = D_L^-1 + R^T B R`` with the restriction ``R`` (identity on
        # the other cells; a leaf's residual is passed to its neighbours in proportion ``c / d_leaf``) and ``B``
        # the preconditioner below on the cells that are not leaves. ``M`` is the exact inverse when ``B`` is
        # the exact inverse of the Schur complement, and symmetric positive definite whenever ``B`` is.
        leaves = self._leaves()
        dtype = r.dtype
        if leaves is not None:
            leaf_idx, inv_d, src, dst, frac = (self._cast(f"leaf{k}", t, dtype) if t.is_floating_point() else t
                                               for k, t in enumerate(leaves[:5]))
            B = r.shape[0]
            r2 = r.reshape(B, -1)
            rt = _scatter_add(r2.index_fill(1, leaf_idx, 0.0), dst, r2.index_select(1, src) * frac).view_as(r)
            act = self._cast("act_nonleaf", self.active & ~leaves[5], dtype)
        else:
            rt = r
            act = self._cast("active", self.active, dtype)
        y = self._box_pinv(rt, act)
        # Without leaves: additive Jacobi on the cut cells (whose diagonal the unweighted box operator
        # overestimates): 58 -> 19 iterations at 128^2 with a disc and two boxes, still symmetric positive
        # definite. Inactive cells keep r: y * active + (inactive + 1 / diag on cut cells) * r.
        # With leaves the Jacobi term is left out: the elimination handles the weakly tied cells better, and
        # the term on the remaining cut cells slows warm-started solves (plume 4.8 -> 6.2 iterations at 128^2).
        key = ("rest", dtype)
        rest = self._casts.get(key)
        if rest is None:
            cut = self._cut_inv if leaves is None else torch.zeros_like(self._cut_inv)
            rest = self._casts[key] = ((~self.active).to(dtype) + cut.to(dtype)).contiguous()
        y = y.mul_(act).addcmul_(rest, rt) if not y.requires_grad else y * act + rest * rt
        if leaves is not None:
            y2 = y.view(B, -1)
            y2.index_copy_(1, leaf_idx, r2.index_select(1, leaf_idx) * inv_d)
            _scatter_add(y2, src, y2.index_select(1, dst) * frac)
        return self.project(y)

    # ---- direct solve of a layout that keeps coming back --------------------------------------------------

    def _box_pinv(self, f: torch.Tensor, pre: torch.Tensor | None = None) -> torch.Tensor:
        """``(-∇²_box)⁺ (pre f)``: the exact (pseudo-)inverse of the unweighted box, the constant mode dropped
        where the box is singular. Walls and open sides only, no autograd: mask, transform, multiply and
        transform back in one pass (:func:`phisim.spectral.fft.r2r_multiply`)."""
        r2r, per = _layout(self.kinds)
        if not per and not f.requires_grad:
            key = ("mult", f.dtype)
            mult = self._casts.get(key)
            if mult is None:
                mult = self._casts[key] = (-self._inv * _transform_scale(self.resolution, self.kinds)).to(f.dtype)
            fwd = tuple(_TRANSFORM[self.kinds[a]][0] for a in r2r)
            inv = tuple(_TRANSFORM[self.kinds[a]][1] for a in r2r)
            y = r2r_multiply(f, fwd, inv, tuple(1 + a for a in r2r), mult, pre=pre, engine=self.engine)
            if y is not None:
                return y
        return -_apply_multiplier(f if pre is None else f * pre, self.kinds, self._inv, self.engine)

    def _box_inverse(self, f: torch.Tensor) -> torch.Tensor:
        """``(-∇²_box)⁻¹ f`` of the unweighted box, exact. A singular box (no Dirichlet side) is made definite by
        ``β 11ᵀ / N`` with ``β`` its smallest non-zero eigenvalue: its pseudo-inverse plus ``mean(f) / β``."""
        y = self._box_pinv(f)
        if _singular(self.kinds):
            if self._beta_inv is None:
                self._beta_inv = float(self._inv.abs().max())
            y = y + f.mean(tuple(range(1, f.ndim)), keepdim=True) * self._beta_inv
        return y

    def _direct_solver(self, dtype: torch.dtype):
        """The factored direct solve of this operator, or None (PCG).

        It applies to one layout shared by the batch, weights without gradient, either a box with a Dirichlet
        side and no fluid region closed off from it (a definite system) or a closed box with one fluid region
        (the constants its only null space; the box operator is then regularised, see :meth:`_box_inverse`, and
        the answer projected), on the CPU, with at most
        :data:`phisim.solvers.direct.MAX_RANK` cut faces. It is built once the operator has been solved more
        than ``max(DIRECT_BUILD_AFTER, k / DIRECT_FACES_PER_REQUEST)`` times (its ``k`` box solves then cost
        about as much as the PCG solves so far), so a layout that changes every step never builds one.
        """
        if self._direct is False or not DIRECT:
            return None
        self._requests += 1
        if self._direct is None:
            one_closed_region = _singular(self.kinds) and self.null is not None and self.null.shape[1] == 1
            if (self.batch != 1 or self.rank < 2 or (self.null is not None and not one_closed_region)
                    or self.active.device.type != "cpu" or any(w.requires_grad for w in self.weights)
                    or dtype not in (torch.float32, torch.float64)):
                self._direct = False
                return None
            if self._requests <= DIRECT_BUILD_AFTER:  # a layout used once or twice (moving bodies) costs nothing
                return None
            self._direct = WoodburySolve(tuple(w[0] for w in self.weights), self.active[0], self.dx, self.kinds,
                                         self._box_inverse)
            k = self._direct.rank
            if k > MAX_RANK or k * k > MAX_RANK_SQUARED_PER_CELL * math.prod(self.resolution):
                self._direct = False
                return None
        if self._direct.lu is None:
            if self._requests <= max(DIRECT_BUILD_AFTER, self._direct.rank // DIRECT_FACES_PER_REQUEST):
                return None
            self._direct.factor()
        return self._direct

    def solve(self, rhs: torch.Tensor, *, solve: Solve, x0: torch.Tensor | None = None,
              preconditioned: bool = True) -> tuple[torch.Tensor, SolveInfo]:
        """Solve ``apply(p) = rhs`` on the active cells (``rhs`` is zeroed on inactive ones).

        In singular regions the right-hand side's mean is removed first (the caller checks compatibility
        when it matters) and the solution has zero mean per region.

        Args:
            rhs: ``(B, *resolution)``.
            solve: CG settings.
            x0: Optional warm start ``(B, *resolution)``.
            preconditioned: Use the preconditioner (spectral box inverse plus Jacobi on cut cells).

        Returns:
            ``(p, info)``; ``p`` is 0 on inactive cells. Differentiable w.r.t. ``rhs`` and the weights.
        """
        if tuple(rhs.shape[1:]) != self.resolution:
            raise ShapeError(f"rhs must have shape (B, *{self.resolution}), got {tuple(rhs.shape)}")
        act = self._cast("active", self.active, rhs.dtype)
        b = self.project(rhs * act)
        direct = self._direct_solver(rhs.dtype) if preconditioned else None
        if direct is not None:  # the exact answer as the start: CG checks it and polishes it if need be
            x0 = self.project(direct.solve(b.detach()) * act)
        elif x0 is not None:
            x0 = self.project(x0.detach().to(rhs.dtype) * act)
        params = tuple(w for w in self.weights if w.requires_grad)
        if params:
            fixed = [None if w.requires_grad else w for w in self.weights]

            def operator(x, *ps):
                it = iter(ps)
                return self._apply(x, *[next(it) if f is None else f for f in fixed])
        else:
            def operator(x):
                return self._apply_fixed(x)
        # Nothing to differentiate: skip autograd and cg's probe for captured grad-requiring tensors.
        with torch.set_grad_enabled(torch.is_grad_enabled() and (rhs.requires_grad or bool(params))):
            x, info = cg(operator, b, x0, solve=solve, preconditioner=self._precondition if preconditioned else None,
                     return_info=True, operator_params=params,
                     project=self.project if self.null is not None else None)
        return x * act, info
