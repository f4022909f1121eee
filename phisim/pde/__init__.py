"""Spectral PDE steppers: exponential time differencing Runge-Kutta (ETDRK0-4) for ``u_t = L u + N(u)``.

Quick start::

    import torch
    from phisim.pde import KuramotoSivashinsky, random_field

    stepper = KuramotoSivashinsky(ndim=1, domain=64.0, resolution=256, dt=0.1, dtype=torch.float64)
    u0 = random_field(stepper, batch=8, seed=0)          # (8, 1, 256)
    trajectory = stepper.rollout(u0, steps=500, every=5)  # (8, 101, 1, 256)

Custom equations: build a :class:`SpectralGrid`, give the symbol of ``L`` as a function of the grid's wavenumbers
and ``N`` as a function of the physical field (or of its spectrum) to :class:`ETDRKStepper`.
"""

from .equations import (
    EQUATIONS,
    Advection,
    AllenCahn,
    Burgers,
    CahnHilliard,
    DecayingTurbulence,
    Diffusion,
    Dispersion,
    FisherKPP,
    GrayScott,
    HyperDiffusion,
    KolmogorovFlow,
    KortewegDeVries,
    KuramotoSivashinsky,
    NavierStokesVorticity,
    SwiftHohenberg,
    Wave,
    make_stepper,
    random_field,
)
from .etdrk import ETDRKStepper, phi_functions
from .transforms import BOUNDARIES, SpectralGrid, dct2, dst2, idct2, idst2

__all__ = [
    "ETDRKStepper", "SpectralGrid", "phi_functions", "BOUNDARIES", "dct2", "idct2", "dst2", "idst2",
    "Advection", "Diffusion", "Dispersion", "HyperDiffusion", "Wave", "Burgers", "KortewegDeVries",
    "KuramotoSivashinsky", "AllenCahn", "CahnHilliard", "FisherKPP", "SwiftHohenberg", "GrayScott",
    "NavierStokesVorticity", "KolmogorovFlow", "DecayingTurbulence", "EQUATIONS", "make_stepper", "random_field",
]
