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

Direct solve. An operator solved again and again (a static body) is solved exactly by the box inverse and a
capacitance matrix on its cut faces (:mod:`phisim.solvers.direct`; two box solves per call, built at the first
solve). Whether an operator uses it is decided once, in its constructor (``direct=``), so every solve of one
operator takes the same path. Its answer is CG's start, so CG still checks it (zero iterations in float64, a
couple in float32) and provides the gradient. The fluid projection asks for it for static bodies only.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from phisim.errors import ParameterError, ShapeError
from phisim.ops.stencil import (
    coupled_sum,
    face_couplings,
    face_divergence,
    face_gradient,
    normalize_dx,
    normalize_kinds,
    weighted_diagonal,
)
from phisim.solvers.box import (
    TRANSFORMS,
    apply_multiplier,
    inverse_eigenvalues,
    is_singular,
    transform_layout,
    transform_scale,
)
from phisim.solvers.direct import MAX_RANK, MAX_RANK_SQUARED_PER_CELL, WoodburySolve
from phisim.solvers.linalg import Solve, SolveInfo, cg
from phisim.spectral.fft import r2r_multiply

__all__ = ["MaskedPoisson"]

#: Values of ``MaskedPoisson(direct=...)``.
DIRECT_CHOICES = ("auto", True, False)

#: Cells whose diagonal is at most this fraction of the open-box diagonal are eliminated exactly in the
#: preconditioner, the weakest of neighbouring ones first (0: off). 0.2 measured best over a cold solve with a
#: disc and two boxes and the warm-started plume and cylinder wake at 128^2 and 256^2 (0.4-0.5 leave the
#: warm solves as fast but double the cold iterations; 0.1 gains less).
LEAF_THRESHOLD = 0.2


def _weakest_first(cand: torch.Tensor, diag: torch.Tensor, src: torch.Tensor, dst: torch.Tensor) -> torch.Tensor:
    """A maximal set of candidate cells no two of which are neighbours, taken weakest first: in rounds, every
    remaining candidate whose diagonal (then flat index) is below that of each remaining candidate neighbour joins the
    set, and it and its neighbours leave the candidates. Every candidate left out thus has a neighbour in the set with
    a smaller diagonal, so the weakest cells of a layout (a face fraction of 1e-7 leaves a cell a diagonal that small)
    are always eliminated; leaving out every candidate that touches another one (the first rule) left such cells to
    the box preconditioner, whose eigenvalue there is their diagonal over the open one (CG of a moving free-slip
    sphere's layout stalled at 1.7e-4 after 1355 iterations; 19 with them eliminated and the Jacobi term on the weak
    cells left out, see :meth:`MaskedPoisson._precondition`). ``src -> dst`` lists each coupling both ways.
    Deterministic: no randomness, ties broken by index."""
    free = cand.clone()
    leaf = torch.zeros_like(cand)
    order = torch.arange(cand.numel(), device=cand.device)
    smaller = (diag[dst] < diag[src]) | ((diag[dst] == diag[src]) & (order[dst] < order[src]))
    while bool(free.any()):
        beaten = torch.zeros_like(cand)
        beaten[src[free[src] & free[dst] & smaller]] = True
        win = free & ~beaten  # the smallest free candidate always wins: every round adds at least one
        leaf |= win
        near = torch.zeros_like(cand)
        near[dst[win[src]]] = True
        free &= ~(win | near)
    return leaf


def scatter_rounds(index: torch.Tensor) -> tuple[tuple[torch.Tensor, torch.Tensor], ...]:
    """The rounds of a deterministic ``out[:, index] += values``: pairs ``(index_k, sel_k)``, the positions
    ``sel_k`` of the ``k``-th occurrence of each index and the indices there, so that no index repeats within a
    round. Built once per index (a sort and a host read of the largest repetition); :func:`_scatter_add` then adds
    without host synchronisation."""
    if not len(index):
        return ()
    order = torch.argsort(index, stable=True)
    sorted_index = index[order]
    first = torch.ones_like(sorted_index, dtype=torch.bool)
    first[1:] = sorted_index[1:] != sorted_index[:-1]
    start = torch.cummax(torch.where(first, torch.arange(len(index), device=index.device), 0), 0).values
    occurrence = torch.empty_like(index)
    occurrence[order] = torch.arange(len(index), device=index.device) - start
    rounds = []
    for k in range(int(occurrence.max()) + 1):
        sel = torch.nonzero(occurrence == k).flatten()
        rounds.append((index[sel], sel))
    return tuple(rounds)


def _scatter_add(out: torch.Tensor, index: torch.Tensor, values: torch.Tensor,
                 in_rounds: bool | None = None, rounds=None) -> torch.Tensor:
    """``out[:, index] += values`` in place, in a fixed order on every device.

    On the CPU ``index_add_`` accumulates repeated indices in order. Elsewhere it uses atomic additions whose
    order varies between runs, so the values are added in rounds in which no index repeats (each element then
    gets one addition per round, a result that does not depend on scheduling): ``rounds`` from
    :func:`scatter_rounds` (built here when not given). ``in_rounds`` forces either way.
    """
    if not (out.device.type != "cpu" if in_rounds is None else in_rounds):
        return out.index_add_(1, index, values)
    for index_k, sel_k in (scatter_rounds(index) if rounds is None else rounds):
        out.index_add_(1, index_k, values.index_select(1, sel_k))
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
        direct: Whether :meth:`solve` starts from the exact direct solve (box inverse plus a capacitance matrix
            on the cut faces, :mod:`phisim.solvers.direct`; CG then only checks and polishes it). ``'auto'``
            (default): where it applies (one layout shared by the batch, weights without gradient, a box with a
            Dirichlet side or a closed box with one fluid region, 2-D or 3-D, CPU, at most
            :data:`~phisim.solvers.direct.MAX_RANK` cut faces) and pays (``k² <= MAX_RANK_SQUARED_PER_CELL``
            cells for ``k`` cut faces). ``False``: always PCG. ``True``: wherever it applies, paying or not, and an
            error where it does not apply. The choice is made here, once, so every solve of an operator takes the
            same path. Building it costs one box solve per cut face at the first solve: worth it for an operator solved
            many times (a static body), not for one used once (a moving body's layout at one instant).

    Raises:
        ShapeError: For weights that do not fit one grid.
        ParameterError: For weights outside ``[0, 1]`` or non-finite, or a ``direct`` that cannot apply.
    """

    def __init__(self, weights, dx, kinds, *, engine: str | None = None, direct: bool | str = "auto"):
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
        self.dx = normalize_dx(dx, rank)
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
        self._inv = inverse_eigenvalues(res, self.dx, self.kinds, active.device)
        dw = self._diagonal(tuple(w.detach() for w in weights))
        d0 = self._diagonal(tuple(torch.ones_like(w[:1]) for w in weights))
        frac = tuple(((w.detach() > 0) & (w.detach() < 1)).to(w.dtype) for w in weights)
        cut = active & (dw < d0 * (1 - 1e-9)) & (dw > 0) & (self._diagonal(frac) > 0)  # cells with cut faces
        self._cut_inv = torch.where(cut, 1.0 / torch.where(cut, dw, torch.ones_like(dw)), torch.zeros_like(dw))
        self._scale2 = tuple(1.0 / d**2 for d in self.dx)
        self._beta_inv = None  # 1 / smallest non-zero box eigenvalue (singular boxes, see _box_inverse)
        self._direct_pending = None
        if not any(direct is c for c in DIRECT_CHOICES):
            raise ParameterError(f"direct must be 'auto', True or False, got {direct!r}")
        self._direct = self._direct_applies(direct is True) if direct is not False else False
        if direct is True and self._direct is False:
            raise ParameterError("direct=True: the direct solve does not apply to this operator (it needs one layout "
                                 "shared by the batch, weights without gradient, 2-D or 3-D, the CPU, a Dirichlet "
                                 "side or one closed fluid region, and few enough cut faces)")

    # ---- structure ---------------------------------------------------------------------------------------

    def _diagonal(self, weights) -> torch.Tensor:
        """Diagonal of ``-div(w grad)`` per cell (see :func:`phisim.ops.stencil.weighted_diagonal`)."""
        return weighted_diagonal(weights, self.dx, self.kinds)

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
        """Face gradient ``(p_k - p_{k-1}) / dx`` per axis, boundary faces by kind, shapes ``face_shape(a)``
        (:func:`phisim.ops.stencil.face_gradient`: Dirichlet sides use the ghost ``-p``, Neumann sides give 0,
        periodic axes wrap)."""
        return face_gradient(p, self.dx, self.kinds)

    def divergence(self, flux) -> torch.Tensor:
        """MAC divergence ``sum_a (f_{k+1} - f_k) / dx_a`` of face values ``(B, *face_shape(a))``."""
        return face_divergence(flux, self.dx)

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
            couplings, wrap = face_couplings(w, self.dx, self.kinds, dtype)
            hit = self._casts[key] = (diag.to(dtype).contiguous(), couplings, wrap)
        return hit

    def _apply_fixed(self, p: torch.Tensor) -> torch.Tensor:
        # The operator in fused form (phisim.ops.stencil.coupled_sum): the same numbers as ``_apply``
        # (gradient, weights, divergence, masking) in a third of the passes over memory.
        diag, couplings, wrap = self._stencil(p.dtype)
        return coupled_sum(p, diag, couplings, wrap, -1.0)

    def _leaves(self):
        """Weakly connected cells eliminated exactly in the preconditioner, or None.

        A *leaf* is an active cell whose diagonal is at most :data:`LEAF_THRESHOLD` of the open-box one (mostly
        solid: a cell whose centre lies in a body but which a cut face still ties to the fluid) and which couples
        to no other leaf; among neighbouring candidates the weakest are taken (:func:`_weakest_first`). Leaves only
        couple to non-leaves, so the leaf block of the operator is diagonal and they can be eliminated exactly (a
        block LDL^T step): see :meth:`_precondition`. The candidates left out (``weak``) take the additive Jacobi
        term there instead. Built once; shared layouts only (weights of batch 1).

        Returns:
            None, or ``(leaf, inv_d, src, dst, frac, mask, weak)``: flat leaf indices ``(L,)``, their inverse
            diagonal ``(L,)``, the couplings leaf ``src`` -> neighbour ``dst`` with ``frac = c / d_leaf`` ``(P,)``,
            and the leaves and the candidates left out as masks ``(1, *res)``.
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
                        lo, hi = lo.flatten(), hi.flatten()
                        keep = (c > 0) & (cand[lo] | cand[hi])  # the couplings of candidates: all that is used
                        src += [lo[keep], hi[keep]]
                        dst += [hi[keep], lo[keep]]
                        cpl += [c[keep], c[keep]]
                src, dst, cpl = torch.cat(src), torch.cat(dst), torch.cat(cpl)
                among = cand[src] & cand[dst]  # the rounds read the couplings between candidates only
                leaf = _weakest_first(cand, diag, src[among], dst[among])
                if bool(leaf.any()):
                    sel = leaf[src]
                    src, dst, cpl = src[sel], dst[sel], cpl[sel]
                    leaf_idx = torch.nonzero(leaf).flatten()
                    out = (leaf_idx, 1.0 / diag[leaf_idx], src, dst, cpl / diag[src], leaf.view(1, *res),
                           (cand & ~leaf).view(1, *res))
        self._casts["leaves"] = out
        return out

    #: Whether the leaves' scatter-adds run in rounds without repeated indices (deterministic, see
    #: :func:`_scatter_add`); None: on devices other than the CPU, where ``index_add_`` uses atomic additions.
    deterministic_rounds: bool | None = None

    def _rounds(self, device: torch.device):
        """The rounds (:func:`scatter_rounds`) of the leaves' two scatter-adds, to ``dst`` and to ``src``, built once
        per layout; None where ``index_add_`` is used as it is."""
        use = device.type != "cpu" if self.deterministic_rounds is None else self.deterministic_rounds
        if not use:
            return None
        hit = self._casts.get("rounds")
        if hit is None:
            leaves = self._leaves()
            hit = self._casts["rounds"] = (scatter_rounds(leaves[3]), scatter_rounds(leaves[2]))
        return hit

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
            rounds = self._rounds(r.device)
            rt = _scatter_add(r2.index_fill(1, leaf_idx, 0.0), dst, r2.index_select(1, src) * frac,
                              rounds is not None, None if rounds is None else rounds[0]).view_as(r)
            act = self._cast("act_nonleaf", self.active & ~leaves[5], dtype)
        else:
            rt = r
            act = self._cast("active", self.active, dtype)
        y = self._box_pinv(rt, act)
        # Without leaves: additive Jacobi on the cut cells (whose diagonal the unweighted box operator
        # overestimates): 58 -> 19 iterations at 128^2 with a disc and two boxes, still symmetric positive
        # definite. Inactive cells keep r: y * active + (inactive + 1 / diag on cut cells) * r.
        # With leaves the Jacobi term is kept only on the weak cells that are not leaves (neighbours of a weaker
        # leaf, ``_leaves``): the elimination handles the weakly tied cells better, and the term on every other
        # cut cell slows warm-started solves (plume 4.8 -> 6.2 iterations at 128^2); without it a weak cell left
        # out keeps an eigenvalue of the preconditioned operator near its diagonal over the open one (1.8e-3
        # measured in a 3-D layout: 117 iterations instead of 19). M stays D_L^-1 + R^T (B + J) R: symmetric.
        key = ("rest", dtype)
        rest = self._casts.get(key)
        if rest is None:
            cut = self._cut_inv if leaves is None else self._cut_inv * leaves[6]
            rest = self._casts[key] = ((~self.active).to(dtype) + cut.to(dtype)).contiguous()
        y = y.mul_(act).addcmul_(rest, rt) if not y.requires_grad else y * act + rest * rt
        if leaves is not None:
            # the box inverse's transforms may return a strided result (on CUDA, with a periodic axis in 3-D);
            # the leaves are written into y in place through its flat view
            y = y.contiguous()
            y2 = y.view(B, -1)
            y2.index_copy_(1, leaf_idx, r2.index_select(1, leaf_idx) * inv_d)
            _scatter_add(y2, src, y2.index_select(1, dst) * frac, rounds is not None,
                         None if rounds is None else rounds[1])
        return self.project(y)

    # ---- direct solve of a layout that keeps coming back --------------------------------------------------

    def _box_pinv(self, f: torch.Tensor, pre: torch.Tensor | None = None) -> torch.Tensor:
        """``(-∇²_box)⁺ (pre f)``: the exact (pseudo-)inverse of the unweighted box, the constant mode dropped
        where the box is singular. Walls and open sides only, no autograd: mask, transform, multiply and
        transform back in one pass (:func:`phisim.spectral.fft.r2r_multiply`)."""
        r2r, per = transform_layout(self.kinds)
        if not per and not f.requires_grad:
            key = ("mult", f.dtype)
            mult = self._casts.get(key)
            if mult is None:
                mult = self._casts[key] = (-self._inv * transform_scale(self.resolution, self.kinds)).to(f.dtype)
            fwd = tuple(TRANSFORMS[self.kinds[a]][0] for a in r2r)
            inv = tuple(TRANSFORMS[self.kinds[a]][1] for a in r2r)
            y = r2r_multiply(f, fwd, inv, tuple(1 + a for a in r2r), mult, pre=pre, engine=self.engine)
            if y is not None:
                return y
        return -apply_multiplier(f if pre is None else f * pre, self.kinds, self._inv, self.engine)

    def _box_inverse(self, f: torch.Tensor) -> torch.Tensor:
        """``(-∇²_box)⁻¹ f`` of the unweighted box, exact. A singular box (no Dirichlet side) is made definite by
        ``β 11ᵀ / N`` with ``β`` its smallest non-zero eigenvalue: its pseudo-inverse plus ``mean(f) / β``."""
        y = self._box_pinv(f)
        if is_singular(self.kinds):
            if self._beta_inv is None:
                self._beta_inv = float(self._inv.abs().max())
            y = y + f.mean(tuple(range(1, f.ndim)), keepdim=True) * self._beta_inv
        return y

    def _direct_applies(self, always: bool):
        """None where the direct solve applies (built at the first solve), else False; ``always``: also where it
        may not pay (``k² > MAX_RANK_SQUARED_PER_CELL`` cells)."""
        one_closed_region = is_singular(self.kinds) and self.null is not None and self.null.shape[1] == 1
        if (self.batch != 1 or self.rank < 2 or (self.null is not None and not one_closed_region)
                or self.active.device.type != "cpu" or any(w.requires_grad for w in self.weights)):
            return False
        solver = WoodburySolve(tuple(w[0] for w in self.weights), self.active[0], self.dx, self.kinds,
                               self._box_inverse)
        k = solver.rank
        if k > MAX_RANK or (not always and k * k > MAX_RANK_SQUARED_PER_CELL * math.prod(self.resolution)):
            return False
        self._direct_pending = solver
        return None

    @property
    def uses_direct_solve(self) -> bool:
        """Whether :meth:`solve` starts from the direct solve (float32/float64 right-hand sides)."""
        return self._direct is not False

    def _direct_solver(self, dtype: torch.dtype):
        """The factored direct solve of this operator (factored at the first request), or None (PCG)."""
        if self._direct is False or dtype not in (torch.float32, torch.float64):
            return None
        if self._direct is None:
            self._direct = self._direct_pending
            self._direct_pending = None
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
