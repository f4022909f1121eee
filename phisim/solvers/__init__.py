"""Solvers layer: matrix-free CG with :class:`Solve` settings and :class:`SolveInfo` reports; Poisson (exact
spectral solves per boundary type, the masked cut-cell operator :class:`MaskedPoisson` with its PCG and direct
solves); diffusion of centred and staggered fields."""

from phisim.solvers.diffusion import (
    DIFFUSION_METHODS,
    STAGGERED_METHODS,
    diffuse,
    diffuse_staggered,
    diffuse_values,
    explicit_stability_limit,
    fourier_heat,
    fourier_k2,
    heat_decay_factors,
)
from phisim.solvers.heat import HEAT_METHODS, HeatStepper
from phisim.solvers.linalg import Solve, SolveInfo, cg, remove_mean
from phisim.solvers.masked import MaskedPoisson
from phisim.solvers.poisson import (
    AXIS_KINDS,
    Solved,
    boundary_source,
    field_kinds_and_values,
    laplacian_eigenvalues,
    masked_laplacian,
    masked_poisson_solve,
    masked_poisson_solve_with_info,
    normalize_kinds,
    solve_poisson,
    solve_poisson_with_info,
    spectral_apply,
    spectral_poisson_solve,
    stencil_laplacian,
)

__all__ = [
    "Solve", "SolveInfo", "cg", "remove_mean",
    "HeatStepper", "HEAT_METHODS",
    "MaskedPoisson",
    "AXIS_KINDS", "normalize_kinds", "laplacian_eigenvalues", "stencil_laplacian", "boundary_source",
    "spectral_poisson_solve", "spectral_apply", "masked_poisson_solve", "masked_laplacian", "solve_poisson",
    "Solved", "masked_poisson_solve_with_info", "solve_poisson_with_info",
    "field_kinds_and_values",
    "DIFFUSION_METHODS", "STAGGERED_METHODS", "diffuse_staggered", "explicit_stability_limit", "diffuse_values",
    "diffuse", "fourier_k2", "heat_decay_factors", "fourier_heat",
]
