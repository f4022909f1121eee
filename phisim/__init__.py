"""phisim: differentiable PDE simulation on PyTorch (grids, fields, operators, solvers, fluids, I/O).

The package is one folder per layer; each layer imports only the layers listed before it:

==================  ==========================================================================================
``phisim``          errors, argument checks, ``Grid``, boundary conditions, padding, ``CenteredGrid`` /
                    ``StaggeredGrid`` (the vocabulary every layer shares)
``phisim.spectral`` FFT engines and plans, real-to-real transforms, box eigen-multipliers
``phisim.ops``      stencils, gradient / divergence / laplace / curl, advection
``phisim.solvers``  CG with ``Solve`` / ``SolveInfo``, Poisson (spectral, masked, direct), diffusion
``phisim.fluid``    geometry, bodies, projection, viscosity, forces, the ``FluidStepper``
``phisim.pde``      spectral (ETDRK) steppers of semi-linear PDEs
``phisim.io``       HDF5 in The Well's layout, training logs, journal and recovery, statistics
``phisim.viz``      pictures and animations (``phisim.show``: one call, inline in Jupyter or to a file)
``phisim.simulate`` initial states, scenarios and the parallel dataset writer
==================  ==========================================================================================

Old flat module paths (``phisim.poisson``, ``phisim.advection``, ...) still import; see :mod:`phisim.compat`.
"""


from phisim import compat as _compat
from phisim.boundary import (
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
from phisim.checks import (
    all_finite,
    check_device,
    check_dt,
    check_finite,
    check_finite_number,
    check_nonnegative,
    check_positive,
)
from phisim.compiled import compile  # noqa: A004 - phisim.compile mirrors torch.compile
from phisim.errors import (
    BoundaryError,
    FileFormatError,
    GridMismatchError,
    IncompleteFileWarning,
    NonFiniteError,
    ParameterError,
    PhisimError,
    ShapeError,
    SlowPathWarning,
    SolveError,
)
from phisim.field import CenteredGrid, Field, StaggeredGrid, sample_padded
from phisim.fluid import (
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
from phisim.grid import Grid
from phisim.io import (
    SimulationData,
    SimulationWriter,
    TrainingLog,
    read_simulation,
    read_training,
    recover_file,
    well_bc_type,
)
from phisim.ops.advection import advect, conservative, maccormack, semi_lagrangian
from phisim.ops.differential import curl, divergence, gradient, laplace, velocity_from_stream_function
from phisim.rollout import Trajectory, rollout
from phisim.simulate.noise import gaussian_vortex, random_rectangles, rectangles, spectral_noise, uniform_velocity
from phisim.solvers.diffusion import (
    diffuse,
    diffuse_staggered,
    diffuse_values,
    explicit_stability_limit,
    fourier_heat,
    heat_decay_factors,
)
from phisim.solvers.linalg import Solve, SolveInfo, cg, remove_mean
from phisim.solvers.poisson import masked_poisson_solve, solve_poisson, spectral_poisson_solve
from phisim.spectral.fft import FFTSettings, fft_settings, get_fft_settings, set_fft_settings

__all__ = [
    "PhisimError", "ShapeError", "GridMismatchError", "BoundaryError", "ParameterError",
    "NonFiniteError", "SolveError", "FileFormatError", "IncompleteFileWarning", "SlowPathWarning",
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
    "plot_field", "plot_vector_field", "plot_curves", "animate", "save_figure", "show",
    "Obstacle", "obstacle_mask", "make_incompressible", "relative_divergence", "buoyancy", "diffuse_velocity",
    "kinetic_energy", "normalize_energy", "cfl_dt", "navier_stokes_step", "navier_stokes_rk_step", "FluidState", "step",
    "compile", "rollout", "Trajectory",
]


_compat.install()

_PLOT_NAMES = ("plot_field", "plot_vector_field", "plot_curves", "animate", "save_figure", "show")


def __getattr__(name):
    """Import the pictures layer (and matplotlib) only when a plotting function is first used:
    ``phisim.show(obj)`` draws fields, states, trajectories and files inline in Jupyter or to a file."""
    if name in _PLOT_NAMES:
        from phisim import viz

        return getattr(viz, name)
    raise AttributeError(f"module 'phisim' has no attribute {name!r}")
