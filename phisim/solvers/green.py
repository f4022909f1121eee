"""Blocks of a box operator's Green's function between a few cells, from its separable eigen-decomposition
(internal).

The direct solves of static bodies (:mod:`phisim.solvers.direct` for the pressure, the viscous capacitance solves
of :mod:`phisim.solvers.mac_diffusion`) need ``G = A⁻¹`` of a box operator between the ``m`` cells next to a
body's surface: an ``m x m`` block. Built column by column that is ``m`` box solves of the whole grid (minutes on
millions of cells). The box operators are separable, ``A⁻¹ = (⊗_a L_a) diag(ψ(Σ_a λ_a)) (⊗_a R_a)`` with per axis
``R_a`` the forward transform (modes x cells), ``L_a`` its inverse (cells x modes) and ``λ_a`` the eigenvalues, so
the block can be contracted one axis at a time onto the window of rows the cells span (:func:`green_block`):
seconds instead of minutes.
"""

from __future__ import annotations

import numpy as np
import torch

__all__ = ["axis_operator", "symmetric_factors", "green_block", "box_green_block"]


def axis_operator(n: int, h: float, pair: tuple[str, str]) -> np.ndarray:
    """The box operator ``-d²/dx²`` of one axis on ``n`` cells, dense ``(n, n)``: ``(2 u_i - u_(i-1) - u_(i+1)) / h²``
    inside; a Neumann side drops its face, a Dirichlet side (zero half a cell beyond the last centre) adds ``2 / h²``
    to its cell, a periodic axis closes the ring."""
    m = np.zeros((n, n))
    i = np.arange(n - 1)
    m[i, i + 1] -= 1.0
    m[i + 1, i] -= 1.0
    m[i, i] += 1.0
    m[i + 1, i + 1] += 1.0
    if pair[0] == "periodic":
        if n > 1:
            m[0, n - 1] -= 1.0
            m[n - 1, 0] -= 1.0
            m[0, 0] += 1.0
            m[n - 1, n - 1] += 1.0
    else:
        m[0, 0] += 2.0 if pair[0] == "dirichlet" else 0.0
        m[n - 1, n - 1] += 2.0 if pair[1] == "dirichlet" else 0.0
    return m / (h * h)


def symmetric_factors(n: int, h: float, pair: tuple[str, str]) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``(μ, L, R)`` of :func:`axis_operator`: its eigenvalues (ascending; the constant mode of an axis without a
    Dirichlet side exactly 0, first) and orthonormal eigenvectors ``L`` (cells x modes), ``R = Lᵀ``."""
    mu, phi = np.linalg.eigh(axis_operator(n, h, pair))
    if "dirichlet" not in pair:
        mu[0] = 0.0
    phi = torch.as_tensor(phi)
    return torch.as_tensor(mu), phi, phi.T.contiguous()


def green_block(factors, inverse: torch.Tensor, coords) -> torch.Tensor:
    """``out[s, t] = (A⁻¹ e_(c_s))[c_t]`` for ``A⁻¹ = (⊗_a L_a) diag(inverse) (⊗_a R_a)``, float64 ``(m, m)``.

    Args:
        factors: Per axis ``(L_a, R_a)``: ``(n_a, K_a)`` and ``(K_a, n_a)`` float64.
        inverse: ``(K_0, ..., K_(d-1))`` float64, the operator's inverse eigenvalues.
        coords: Per axis the cells' integer coordinates ``(m,)``.

    The modes are contracted one axis at a time (the longest first) onto the window of rows the cells span, the
    cells grouped by the coordinates already contracted: about ``N w_1² + m (N / n_1) w_2 (w_3)`` operations for
    ``N`` cells and window widths ``w_a``, against ``m`` transforms of ``N`` cells column by column.
    """
    rank = len(factors)
    coords = [torch.as_tensor(c, dtype=torch.int64) for c in coords]
    m = int(coords[0].numel())
    res = [int(f[0].shape[0]) for f in factors]
    order = sorted(range(rank), key=lambda a: -res[a])
    lo = [int(c.min()) for c in coords]
    width = [int(c.max()) - lo[a] + 1 for a, c in enumerate(coords)]
    windows = [factors[a][0][lo[a]:lo[a] + width[a]] for a in range(rank)]  # (w_a, K_a)
    flat_local = coords[order[0]] - lo[order[0]]
    for a in order[1:]:
        flat_local = flat_local * width[a] + (coords[a] - lo[a])
    out = torch.empty(m, m, dtype=torch.float64)

    def descend(t: torch.Tensor, depth: int, members: torch.Tensor) -> None:
        a = order[depth]
        values = coords[a][members]
        for q in torch.unique(values).tolist():
            group = members[values == q]
            kernel = windows[a] * factors[a][1][:, q]  # the window's rows times the source's mode amplitudes
            u = torch.tensordot(kernel, t, dims=([1], [depth])).movedim(0, depth)
            if depth == rank - 1:
                out[group] = u.reshape(-1)[flat_local]
            else:
                descend(u, depth + 1, group)

    descend(inverse.permute(*order).contiguous(), 0, torch.arange(m))
    return out


def box_green_block(resolution, dx, kinds, coords, null_inverse: float | None = None) -> torch.Tensor:
    """The block of ``B⁻¹`` between the cells ``coords`` for the pressure's box operator ``B = Σ_a I ⊗ A_a ⊗ I``
    (:func:`axis_operator` per axis; ``kinds`` its ``(lower, upper)`` side pairs), float64 ``(m, m)``, symmetric.
    ``null_inverse``: the value of ``B⁻¹`` on the constant mode of a singular box (no Dirichlet side), where the box
    inverse makes the operator definite; required there."""
    res = tuple(int(n) for n in resolution)
    singular = all("dirichlet" not in pair for pair in kinds)
    if singular and null_inverse is None:
        raise ValueError("box_green_block: a singular box needs null_inverse")
    factors, lam = [], torch.zeros((), dtype=torch.float64)
    for a in range(len(res)):
        mu, left, right = symmetric_factors(res[a], float(dx[a]), kinds[a])
        factors.append((left, right))
        lam = lam.unsqueeze(-1) + mu
    if singular:
        lam = lam.clone()
        lam.reshape(-1)[0] = 1.0 / null_inverse
    return green_block(factors, 1.0 / lam, coords)
