"""phisim: differentiable PDE simulation on PyTorch (grids, fields, operators, solvers, fluids, I/O)."""

from .advection import advect, conservative, maccormack, semi_lagrangian
from .boundary import (
    Boundary,
    BoundaryCondition,
    Dirichlet,
    FreeSlipWall,
    Inflow,
    Neumann,
    NoSlipWall,
    Open,
    Periodic,
    pad,
    pad_staggered_component,
    set_boundary_faces,
)
from .checks import (
    all_finite,
    check_device,
    check_dt,
    check_finite,
    check_finite_number,
    check_nonnegative,
    check_positive,
)
from .differential import curl, divergence, gradient, laplace, velocity_from_stream_function
from .diffusion import (
    diffuse,
    diffuse_staggered,
    diffuse_values,
    explicit_stability_limit,
    fourier_heat,
    heat_decay_factors,
)
from .errors import (
    BoundaryError,
    FileFormatError,
    GridMismatchError,
    IncompleteFileWarning,
    NonFiniteError,
    ParameterError,
    PhisimError,
    ShapeError,
    SolveError,
)
from .fft import FFTSettings, fft_settings, get_fft_settings, set_fft_settings
from .field import CenteredGrid, Field, StaggeredGrid, sample_padded
from .fluid import (
    FluidState,
    Obstacle,
    buoyancy,
    cfl_dt,
    diffuse_velocity,
    kinetic_energy,
    make_incompressible,
    navier_stokes_rk_step,
    navier_stokes_step,
    normalize_energy,
    obstacle_mask,
    relative_divergence,
    step,
)
from .grid import Grid
from .io import (
    SimulationData,
    SimulationWriter,
    TrainingLog,
    read_simulation,
    read_training,
    recover_file,
    well_bc_type,
)
from .linalg import Solve, SolveInfo, cg, remove_mean
from .noise import gaussian_vortex, random_rectangles, rectangles, spectral_noise, uniform_velocity
from .poisson import masked_poisson_solve, solve_poisson, spectral_poisson_solve
from .scenarios import e5_simulation

__all__ = [
    "PhisimError", "ShapeError", "GridMismatchError", "BoundaryError", "ParameterError",
    "NonFiniteError", "SolveError", "FileFormatError", "IncompleteFileWarning",
    "Grid",
    "Solve", "SolveInfo", "cg", "remove_mean",
    "Boundary", "BoundaryCondition", "Periodic", "Dirichlet", "Neumann", "NoSlipWall", "FreeSlipWall", "Open", "Inflow",
    "pad", "pad_staggered_component", "set_boundary_faces",
    "CenteredGrid", "StaggeredGrid", "Field", "sample_padded",
    "check_dt", "check_finite", "check_nonnegative", "check_positive", "all_finite", "check_device",
    "check_finite_number",
    "gradient", "divergence", "laplace", "curl", "velocity_from_stream_function",
    "FFTSettings", "fft_settings", "get_fft_settings", "set_fft_settings",
    "spectral_poisson_solve", "masked_poisson_solve", "solve_poisson",
    "diffuse", "diffuse_staggered", "diffuse_values", "explicit_stability_limit", "fourier_heat", "heat_decay_factors",
    "SimulationWriter", "SimulationData", "read_simulation", "TrainingLog", "read_training", "well_bc_type",
    "recover_file",
    "advect", "semi_lagrangian", "maccormack", "conservative",
    "spectral_noise", "rectangles", "random_rectangles", "gaussian_vortex", "uniform_velocity",
    "plot_field", "plot_vector_field", "plot_curves", "animate", "save_figure",
    "Obstacle", "obstacle_mask", "make_incompressible", "relative_divergence", "buoyancy", "diffuse_velocity",
    "kinetic_energy", "normalize_energy", "cfl_dt", "navier_stokes_step", "navier_stokes_rk_step", "FluidState", "step",
    "e5_simulation",
]


_PLOT_NAMES = ("plot_field", "plot_vector_field", "plot_curves", "animate", "save_figure")


def __getattr__(name):
    """Import the plotting functions (and matplotlib) only when first used."""
    if name in _PLOT_NAMES:
        from . import plot

        return getattr(plot, name)
    raise AttributeError(f"module 'phisim' has no attribute {name!r}")
