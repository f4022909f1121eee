"""Print the validation figures of docs/VALIDATION_SPECTRAL.md (run: ``python -m tests.phisim.pde.validation_report``).

The same set-ups as the tests, with the measured numbers printed instead of asserted.
"""

from __future__ import annotations

import math
import time

import torch

from phisim.pde import (
    AllenCahn,
    Burgers,
    CahnHilliard,
    FisherKPP,
    KortewegDeVries,
    KuramotoSivashinsky,
    NavierStokesVorticity,
    random_field,
)

from ._exact import burgers_cole_hopf, empirical_order, kdv_soliton, kdv_two_soliton
from .test_long_validation import leading_lyapunov_ks
from .test_nonlinear_validation import _initial

F64 = torch.float64


def orders() -> None:
    """Errors against a dt/8 ETDRK4 reference and the fitted order, per scheme and set-up."""
    setups = {
        "Burgers, periodic, nu=0.1, N=64, T=1": (
            lambda o, dt: Burgers(viscosity=0.1, resolution=64, dt=dt, order=o, dtype=F64), 1.0,
            [0.1, 0.05, 0.025, 0.0125]),
        "Allen-Cahn, Neumann, D=0.01, N=48, T=2": (
            lambda o, dt: AllenCahn(diffusivity=0.01, resolution=48, dt=dt, order=o, boundaries="neumann",
                                    dtype=F64), 2.0, [0.2, 0.1, 0.05, 0.025]),
        "Fisher-KPP, Dirichlet, D=0.01, r=2, N=48, T=1": (
            lambda o, dt: FisherKPP(diffusivity=0.01, reactivity=2.0, resolution=48, dt=dt, order=o,
                                    boundaries="dirichlet", dtype=F64), 1.0, [0.1, 0.05, 0.025, 0.0125]),
        "KS, L=22, N=64, T=2 (random state)": (
            lambda o, dt: KuramotoSivashinsky(domain=22.0, resolution=64, dt=dt, order=o, dtype=F64), 2.0,
            [0.05, 0.025, 0.0125, 0.00625]),
    }
    for name, (make, t_end, dts) in setups.items():
        ref = make(4, dts[-1] / 8)
        if name.startswith("KS"):
            u0 = random_field(ref, 1, amplitude=1.0, max_wavenumber=3, seed=1)
        else:
            u0 = _initial(ref.grid)
        u_ref = ref.repeat(u0, int(round(t_end / ref.dt)))
        print(f"\n{name}; dt = {dts}")
        for order in (1, 2, 3, 4):
            errs = [float((make(order, dt).repeat(u0, int(round(t_end / dt))) - u_ref).abs().max()) for dt in dts]
            text = ", ".join(f"{e:.2e}" for e in errs)
            print(f"  ETDRK{order}: errors {text}; order {empirical_order(dts, errs):.2f}")


def solutions() -> None:
    """Errors against the analytic solutions and conservation figures."""
    nu = 0.1
    for n in (64, 128, 256):
        s = Burgers(viscosity=nu, resolution=n, dt=1e-3, dtype=F64)
        (x,) = s.grid.coordinates()
        err = float((s.repeat(torch.sin(x)[None, None], 1000)[0, 0] - burgers_cole_hopf(x, 1.0, nu)).abs().max())
        print(f"Burgers vs Cole-Hopf, nu=0.1, t=1, N={n}, dt=1e-3, ETDRK4: max error {err:.2e}")

    length = 40.0
    s = KortewegDeVries(domain=length, resolution=256, dt=2e-3, dtype=F64)
    (x,) = s.grid.coordinates()
    u0 = kdv_soliton(x, 0.0, 1.0, 10.0, length)[None, None]
    u = s.repeat(u0, 1250)
    dx = length / 256
    err = float((u[0, 0] - kdv_soliton(x, 2.5, 1.0, 10.0, length)).abs().max())
    m0, p0 = float(u0.sum()) * dx, float((u0 ** 2).sum()) * dx
    print(f"KdV soliton kappa=1 (speed 4, amplitude 2), L=40, N=256, dt=2e-3, t=2.5: max error {err:.2e}; "
          f"mass drift {float(u.sum()) * dx - m0:.1e} (of {m0:.3f}); momentum drift "
          f"{(float((u ** 2).sum()) * dx - p0) / p0:.1e} (relative)")

    k1, k2, n, dt, th = 1.0, 0.6, 512, 2e-3, 5.0
    s = KortewegDeVries(domain=80.0, resolution=n, dt=dt, dtype=F64)
    (x,) = s.grid.coordinates()
    u0 = kdv_two_soliton(x, -th, k1, k2, 40.0, 40.0)
    u = s.repeat(u0[None, None], int(round(2 * th / dt)))[0, 0]
    err = float((u - kdv_two_soliton(x, th, k1, k2, 40.0, 40.0)).abs().max())

    def peak(field, lo, hi, refine=64):
        fine = torch.fft.irfft(torch.fft.rfft(field), n=refine * n) * refine
        xf = torch.arange(refine * n, dtype=F64) * 80.0 / (refine * n)
        return float(xf[torch.argmax(torch.where((xf > lo) & (xf < hi), fine, torch.full_like(fine, -1e9)))])

    sf = peak(u, 52, 70) - peak(u0, 10, 30) - 4 * k1 ** 2 * 2 * th
    ss = peak(u, 38, 50) - peak(u0, 30, 40) - 4 * k2 ** 2 * 2 * th
    lr = math.log((k1 + k2) / (k1 - k2))
    print(f"KdV two solitons k=(1, 0.6), L=80, N=512, dt=2e-3, t=-5..5: max error vs Hirota {err:.2e}; phase shifts "
          f"{sf:+.4f} (exact {lr / k1:+.4f}), {ss:+.4f} (exact {-lr / k2:+.4f})")

    s = NavierStokesVorticity(viscosity=0.02, resolution=32, dt=0.05, dtype=F64)
    xx, yy = s.grid.coordinates()
    w0 = (2 * torch.sin(xx) * torch.sin(yy))[None, None]
    err = float((s.repeat(w0, 20) - w0 * math.exp(-0.04)).abs().max())
    print(f"Taylor-Green vorticity, nu=0.02, 32^2, dt=0.05, t=1: max error {err:.2e}")

    for b in ("periodic", "neumann"):
        s = CahnHilliard(ndim=2, resolution=32, dt=2e-4, boundaries=b, dtype=F64)
        u0 = random_field(s, 2, amplitude=0.3, mean=0.1, max_wavenumber=8, seed=3)
        u = s.repeat(u0, 300)
        drift = float((u.mean((2, 3)) - u0.mean((2, 3))).abs().max())
        print(f"Cahn-Hilliard 2-D {b}, 32^2, 300 steps: mean drift {drift:.1e}, max change of u "
              f"{float((u - u0).abs().max()):.2f}")


def lyapunov() -> None:
    """KS L=22 leading Lyapunov exponent for a few resolutions and time steps."""
    for kw in (dict(), dict(resolution=32), dict(resolution=128), dict(dt=0.1, renormalise_every=25),
               dict(seed=5)):
        t0 = time.time()
        lam, err = leading_lyapunov_ks(**kw)
        print(f"KS L=22 leading Lyapunov exponent {kw or 'N=64, dt=0.25'}: {lam:.4f} +- {err:.4f} "
              f"({time.time() - t0:.1f} s)")


if __name__ == "__main__":
    torch.set_num_threads(1)
    solutions()
    orders()
    lyapunov()
