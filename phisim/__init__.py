"""phisim: differentiable PDE simulation on PyTorch (grids, fields, operators, solvers, fluids, I/O)."""

from .boundary import (
    Boundary,
    BoundaryCondition,
    Dirichlet,
    FreeSlipWall,
    Neumann,
    NoSlipWall,
    Open,
    Periodic,
    pad,
    pad_staggered_component,
    set_boundary_faces,
)
from .checks import check_dt, check_finite, check_nonnegative, check_positive
from .errors import (
    BoundaryError,
    FileFormatError,
    GridMismatchError,
    NonFiniteError,
    ParameterError,
    PhisimError,
    ShapeError,
    SolveError,
)
from .differential import curl, divergence, gradient, laplace, velocity_from_stream_function
from .field import CenteredGrid, Field, StaggeredGrid, sample_padded
from .grid import Grid

__all__ = [
    "PhisimError", "ShapeError", "GridMismatchError", "BoundaryError", "ParameterError",
    "NonFiniteError", "SolveError", "FileFormatError",
    "Grid",
    "Boundary", "BoundaryCondition", "Periodic", "Dirichlet", "Neumann", "NoSlipWall", "FreeSlipWall", "Open",
    "pad", "pad_staggered_component", "set_boundary_faces",
    "CenteredGrid", "StaggeredGrid", "Field", "sample_padded",
    "check_dt", "check_finite", "check_nonnegative", "check_positive",
    "gradient", "divergence", "laplace", "curl", "velocity_from_stream_function",
]
