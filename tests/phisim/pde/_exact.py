"""Analytic reference solutions shared by the spectral-stepper tests."""

from __future__ import annotations

import math

import torch


def burgers_cole_hopf(x: torch.Tensor, t: float, nu: float, modes: int = 4096) -> torch.Tensor:
    """Periodic viscous Burgers ``u_t + u u_x = nu u_xx`` from ``u(x, 0) = sin x`` via the Cole-Hopf transform.

    ``u = -2 nu phi_x / phi`` with ``phi`` solving the heat equation from ``phi_0 = exp((cos x - 1) / (2 nu))``;
    the heat equation is solved exactly on ``modes`` Fourier modes and evaluated at ``x`` by trigonometric sums.
    """
    xf = torch.arange(modes, dtype=torch.float64) * 2 * math.pi / modes
    ph = torch.fft.rfft(torch.exp((torch.cos(xf) - 1) / (2 * nu)))
    k = torch.arange(modes // 2 + 1, dtype=torch.float64)
    c = ph * torch.exp(-nu * k * k * t) / modes
    c[1:] *= 2
    c[-1] /= 2
    waves = torch.exp(1j * k[None] * x.reshape(-1, 1))
    phi = (c * waves).sum(-1).real
    phi_x = (c * 1j * k * waves).sum(-1).real
    return (-2 * nu * phi_x / phi).reshape(x.shape)


def kdv_two_soliton(x: torch.Tensor, t: float, k1: float, k2: float, x1: float, x2: float) -> torch.Tensor:
    """Hirota's two-soliton solution of ``u_t + 6 u u_x + u_xxx = 0`` on the line.

    ``u = 2 (log F)_xx``, ``F = 1 + e^{a} + e^{b} + A e^{a + b}``, ``a = 2 k1 (x - 4 k1^2 t - x1)``,
    ``b = 2 k2 (x - 4 k2^2 t - x2)``, ``A = ((k1 - k2) / (k1 + k2))^2``.
    """
    a1, a2 = 2 * k1, 2 * k2
    e1 = torch.exp(a1 * (x - 4 * k1 ** 2 * t - x1))
    e2 = torch.exp(a2 * (x - 4 * k2 ** 2 * t - x2))
    big_a = ((k1 - k2) / (k1 + k2)) ** 2
    f = 1 + e1 + e2 + big_a * e1 * e2
    fx = a1 * e1 + a2 * e2 + big_a * (a1 + a2) * e1 * e2
    fxx = a1 ** 2 * e1 + a2 ** 2 * e2 + big_a * (a1 + a2) ** 2 * e1 * e2
    return 2 * (fxx / f - (fx / f) ** 2)


def kdv_soliton(x: torch.Tensor, t: float, kappa: float, x0: float, length: float) -> torch.Tensor:
    """One soliton ``2 kappa^2 sech^2(kappa (x - 4 kappa^2 t - x0))`` of ``u_t + 6 u u_x + u_xxx = 0``,
    wrapped onto a periodic domain of the given length (nearest image)."""
    s = torch.remainder(x - 4 * kappa ** 2 * t - x0 + length / 2, length) - length / 2
    return 2 * kappa ** 2 / torch.cosh(kappa * s) ** 2


def empirical_order(dts, errors) -> float:
    """Least-squares slope of ``log(error)`` over ``log(dt)``."""
    lx = torch.log(torch.tensor(dts, dtype=torch.float64))
    ly = torch.log(torch.tensor(errors, dtype=torch.float64))
    lx = lx - lx.mean()
    return float((lx * (ly - ly.mean())).sum() / (lx * lx).sum())
