"""phisim: differentiable PDE simulation on PyTorch (grids, fields, operators, solvers, fluids, I/O)."""

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

__all__ = [
    "PhisimError", "ShapeError", "GridMismatchError", "BoundaryError", "ParameterError",
    "NonFiniteError", "SolveError", "FileFormatError",
]
