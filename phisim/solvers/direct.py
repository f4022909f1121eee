"""A direct solve of the weighted (cut-cell) Poisson system of one body layout (internal).

:class:`phisim.solvers.masked.MaskedPoisson` solves ``-div(w grad p) = f`` on the active cells by PCG. When
the same operator is solved again and again (a static body: one solve per step), it pays to solve it
directly instead. The operator differs from the unweighted box operator ``B`` (inverted exactly by one
spectral transform pair) only on the faces with weight ``w < 1`` that touch an active cell: there the box
face term ``c cᵀ`` (``c = (e_j - e_i) / h``; ``√2 e_0 / h`` on a Dirichlet side) enters with ``w`` instead of 1.
Faces between inactive cells (inside bodies) keep weight 1, so the inactive region decouples into blocks of
its own, and one pinned cell per block that reaches no Dirichlet side makes them definite. With ``U`` the
``k`` face vectors and pins and ``D = diag(w - 1, ..., 1, ...)``,

    ``A = B + U D Uᵀ``  and  ``A⁻¹ f = B⁻¹ f - B⁻¹ U C⁻¹ Uᵀ B⁻¹ f``,  ``C = D⁻¹ + Uᵀ B⁻¹ U``

(Sherman-Morrison-Woodbury; the capacitance matrix ``C`` is ``k x k``, built once and LU-factored in float64:
``Uᵀ B⁻¹ U`` is the box's Green's function between the few cells ``U`` touches, read from the box's separable
eigen-decomposition, :func:`box_green_block`, instead of ``k`` box solves of the whole grid). The active
block of ``A`` is exactly the masked operator, so its solution on the active cells is the masked solution; a solve
costs two box solves and one small triangular solve.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from phisim.errors import SlowPathWarning, warn_from_caller
from phisim.ops.tensors import unravel
from phisim.solvers.green import box_green_block

#: Largest rank ``k`` (faces with ``w < 1`` beside active cells, plus pins) for which the direct solve is built.
MAX_RANK = 4096
#: ... and largest ``k² / cells``: the triangular solves cost ``2 k²`` per call against two box solves. Measured:
#: 2-D discs and boxes at 128²-256² (``k² / cells`` 36-40) solve 6-9x faster than PCG from zero and make wake
#: steps 1.7-2.6x faster; a sphere in 32³ (170) only 2x faster than a cold PCG solve, less than warm ones.
MAX_RANK_SQUARED_PER_CELL = 64


class WoodburySolve:
    """``A⁻¹`` of one weighted Poisson operator by the box inverse and a capacitance matrix (see the module).

    Args:
        weights: Per axis the face weights ``(*face_shape(a))`` of one layout (float, no batch axis).
        active: ``(*resolution)`` bool, the active cells.
        dx: Cell size per axis.
        kinds: Box kinds per axis (``(lower, upper)`` pairs).
        box_inverse: ``f -> B⁻¹ f`` on ``(B, *resolution)`` tensors, in their dtype (the build passes float64;
            the solves run in the working dtype, ``C⁻¹`` in float64).
    """

    def __init__(self, weights, active: torch.Tensor, dx, kinds, box_inverse):
        self.box_inverse = box_inverse
        res = tuple(active.shape)
        self.dx = tuple(float(h) for h in dx)
        self.kinds = tuple(tuple(pair) for pair in kinds)
        self.resolution = res
        act = active.cpu().numpy()
        idx = np.arange(math.prod(res)).reshape(res)
        plus, minus, cp, cm, diag = [], [], [], [], []
        inactive_edges = ([], [])
        dirichlet_cells = []
        for a, w in enumerate(weights):
            w = w.detach().double().cpu().numpy()
            n, h = res[a], dx[a]
            lo_k, hi_k = kinds[a]
            take = np.take
            # interior faces 1..n-1 between cells k-1 and k (periodic: face 0 between n-1 and 0 as well)
            wi = take(w, np.arange(1, n), axis=a)
            ci, cj = take(idx, np.arange(0, n - 1), axis=a), take(idx, np.arange(1, n), axis=a)
            ai, aj = take(act, np.arange(0, n - 1), axis=a), take(act, np.arange(1, n), axis=a)
            if lo_k == "periodic":
                wi = np.concatenate([wi, take(w, [0], axis=a)], axis=a)
                ci = np.concatenate([ci, take(idx, [n - 1], axis=a)], axis=a)
                cj = np.concatenate([cj, take(idx, [0], axis=a)], axis=a)
                ai = np.concatenate([ai, take(act, [n - 1], axis=a)], axis=a)
                aj = np.concatenate([aj, take(act, [0], axis=a)], axis=a)
            sel = (wi < 1) & (ai | aj)
            plus.append(cj[sel])
            minus.append(ci[sel])
            cp.append(np.full(int(sel.sum()), 1.0 / h))
            cm.append(np.full(int(sel.sum()), -1.0 / h))
            diag.append(wi[sel] - 1.0)
            both = ~ai & ~aj  # faces inside the inactive region keep weight 1
            inactive_edges[0].append(ci[both])
            inactive_edges[1].append(cj[both])
            for side, kind in ((0, lo_k), (1, hi_k)):
                if kind != "dirichlet":
                    continue
                cell = 0 if side == 0 else n - 1
                wb = take(w, 0 if side == 0 else n, axis=a)
                cb, ab = take(idx, cell, axis=a), take(act, cell, axis=a)
                sel = (wb < 1) & ab
                plus.append(cb[sel])
                minus.append(cb[sel])
                cp.append(np.full(int(sel.sum()), math.sqrt(2.0) / h))
                cm.append(np.zeros(int(sel.sum())))
                diag.append(wb[sel] - 1.0)
                dirichlet_cells.append(cb[~ab])
        # one pin per block of the inactive region that reaches no Dirichlet side
        ncell = math.prod(res)
        r, c = np.concatenate(inactive_edges[0]), np.concatenate(inactive_edges[1])
        graph = coo_matrix((np.ones(len(r), dtype=np.int8), (r, c)), shape=(ncell, ncell))
        _, labels = connected_components(graph, directed=False)
        flat_act = act.reshape(-1)
        regular = set(labels[np.concatenate(dirichlet_cells)].tolist()) if dirichlet_cells else set()
        pins = [int(np.flatnonzero((labels == k) & ~flat_act)[0]) for k in np.unique(labels[~flat_act])
                if int(k) not in regular]
        plus.append(np.asarray(pins, dtype=np.int64))
        minus.append(np.asarray(pins, dtype=np.int64))
        cp.append(np.ones(len(pins)))
        cm.append(np.zeros(len(pins)))
        diag.append(np.ones(len(pins)))
        self.plus = torch.as_tensor(np.concatenate(plus).ravel(), dtype=torch.int64)
        self.minus = torch.as_tensor(np.concatenate(minus).ravel(), dtype=torch.int64)
        self.cp = torch.as_tensor(np.concatenate(cp).ravel())
        self.cm = torch.as_tensor(np.concatenate(cm).ravel())
        self.d = torch.as_tensor(np.concatenate(diag).ravel())
        self.rank = int(self.d.numel())
        self.lu = None

    def factor(self) -> None:
        """Build and LU-factor ``C = D⁻¹ + Uᵀ B⁻¹ U``.

        ``Uᵀ B⁻¹ U`` comes from the box's separable eigen-decomposition restricted to the cells ``U`` touches
        (:func:`box_green_block`; seconds where ``k`` box solves take minutes on millions of cells), checked
        against two exact box solves; where the check fails (a box inverse that is not this box's) it falls back
        to ``k`` box solves."""
        cap = self._coupling_by_spectrum()
        if cap is None:
            cap = self._coupling_by_box_solves()
        cap = cap + torch.diag(1.0 / self.d)
        self.lu, self.pivots = torch.linalg.lu_factor(cap)

    def _u_column(self, j: int) -> torch.Tensor:
        """Column ``j`` of ``U`` as a field ``(1, *resolution)``, float64."""
        src = torch.zeros(math.prod(self.resolution), dtype=torch.float64)
        src[self.plus[j]] += self.cp[j]
        src[self.minus[j]] += self.cm[j]
        return src.view(1, *self.resolution)

    def _coupling_by_box_solves(self) -> torch.Tensor:
        """``Uᵀ B⁻¹ U`` from ``k`` box solves (float64, in chunks of at most 32 MB)."""
        k, res = self.rank, self.resolution
        ncell = math.prod(res)
        cap = torch.zeros(k, k, dtype=torch.float64)
        chunk = max(1, (1 << 22) // ncell)
        for start in range(0, k, chunk):
            cols = torch.arange(start, min(k, start + chunk))
            m = cols.numel()
            src = torch.zeros(m, ncell, dtype=torch.float64)
            rows = torch.arange(m)
            src.index_put_((rows, self.plus[cols]), self.cp[cols], accumulate=True)
            src.index_put_((rows, self.minus[cols]), self.cm[cols], accumulate=True)
            z = self.box_inverse(src.view(m, *res)).reshape(m, ncell)
            cap[start:start + m] += z[:, self.plus] * self.cp + z[:, self.minus] * self.cm
        return cap

    def _coupling_by_spectrum(self) -> torch.Tensor | None:
        """``Uᵀ B⁻¹ U`` from the box's eigen-decomposition (None where it disagrees with ``box_inverse``)."""
        if self.rank == 0:
            return None
        res = self.resolution
        cells, pos = torch.unique(torch.cat([self.plus, self.minus]), return_inverse=True)
        pos_plus, pos_minus = pos[: self.rank], pos[self.rank:]
        null_inverse = None
        if all("dirichlet" not in pair for pair in self.kinds):  # the box inverse's constant mode
            null_inverse = float(self.box_inverse(torch.ones(1, *res, dtype=torch.float64)).mean())
        coords = unravel(cells, res)
        g = box_green_block(res, self.dx, self.kinds, coords, null_inverse)
        # Uᵀ G U with U = E_cells S: columns then rows of the sparse S
        gs = g[:, pos_plus] * self.cp + g[:, pos_minus] * self.cm
        cap = gs[pos_plus] * self.cp[:, None] + gs[pos_minus] * self.cm[:, None]
        # the check: two columns against exact box solves
        for j in sorted({0, self.rank - 1}):
            z = self.box_inverse(self._u_column(j)).reshape(-1)
            exact = z[self.plus] * self.cp + z[self.minus] * self.cm
            err = float((exact - cap[:, j]).abs().max())
            if err > 1e-9 * max(float(exact.abs().max()), 1e-300):
                warn_from_caller(f"direct pressure solve: the separable capacitance block differs from an exact box "
                                 f"solve by {err:.2e} (relative tolerance 1e-9); building it by {self.rank} box solves "
                                 "instead (the same factor, built more slowly)", SlowPathWarning)
                return None
        return cap

    def _gather(self, x: torch.Tensor) -> torch.Tensor:
        """``Uᵀ x`` per sample: ``(B, k)``."""
        flat = x.reshape(x.shape[0], -1)
        cp, cm = self.cp.to(x.dtype), self.cm.to(x.dtype)
        return flat[:, self.plus] * cp + flat[:, self.minus] * cm

    def _scatter(self, z: torch.Tensor, like: torch.Tensor) -> torch.Tensor:
        """``U z`` per sample, shaped like ``like``."""
        out = torch.zeros(like.shape[0], like[0].numel(), dtype=like.dtype, device=like.device)
        out.index_add_(1, self.plus, z * self.cp.to(like.dtype))
        out.index_add_(1, self.minus, z * self.cm.to(like.dtype))
        return out.view(like.shape)

    def solve(self, f: torch.Tensor) -> torch.Tensor:
        """``A⁻¹ f`` for ``f`` ``(B, *resolution)`` (CPU); two box solves and one ``k x k`` LU solve."""
        x = self.box_inverse(f)
        y = self._gather(x).to(torch.float64)
        z = torch.linalg.lu_solve(self.lu, self.pivots, y.T).T.to(f.dtype)
        return x - self.box_inverse(self._scatter(z, f))
