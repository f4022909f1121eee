"""The heat equation as a stepper: ``∂u/∂t = ν ∇²u`` with settings checked and the step's operator built once.

:class:`HeatStepper` precomputes, in its constructor, the per-mode multiplier of one step (``exp(ν dt λ)`` for
the exact ``'spectral'`` method, ``1 / (1 - ν dt λ)`` for backward Euler, ``1 + ν dt λ`` for forward Euler, with
``λ`` the eigenvalues of the boundary-aware 5/7-point Laplacian, :mod:`phisim.solvers.box`); a call applies it
with one forward and one inverse transform. Boundaries with non-zero values (a heated wall) are stepped by
:func:`~phisim.solvers.diffusion.diffuse`, which adds their exact response.
"""

from __future__ import annotations

import torch

from phisim.checks import check_dt, check_nonnegative
from phisim.errors import GridMismatchError, ParameterError
from phisim.field import CenteredGrid
from phisim.grid import Grid
from phisim.solvers.box import apply_multiplier, eigenvalues_cached, transform_scale
from phisim.solvers.diffusion import diffuse
from phisim.solvers.poisson import field_kinds_and_values, normalize_kinds

__all__ = ["HeatStepper", "HEAT_METHODS"]

#: Time discretisations of :class:`HeatStepper`.
HEAT_METHODS = ("spectral", "implicit", "explicit")


class HeatStepper:
    """One heat step ``u <- u + ∫ ν ∇²u dt`` of a scalar :class:`~phisim.field.CenteredGrid`, built once.

    Args:
        grid: The grid.
        boundary: The scalar boundary (periodic, Dirichlet or Neumann sides; a specification as accepted by
            :class:`~phisim.field.CenteredGrid`).
        diffusivity: ``ν >= 0``.
        dt: Time step ``>= 0``.
        method: ``'spectral'`` (default; exact in time for the semi-discrete system), ``'implicit'`` (backward
            Euler, first order, unconditionally stable) or ``'explicit'`` (forward Euler, first order, stable
            for ``ν dt Σ 4/dx² <= 2``).
        dtype, device: Of the fields this stepper advances.

    Raises:
        ParameterError: For a negative diffusivity or dt, an unknown method, an unstable explicit step, or a
            dtype that is not floating point.
        BoundaryError: For an unknown boundary specification.

    Example:
        >>> from phisim import Grid, CenteredGrid
        >>> from phisim.solvers.heat import HeatStepper
        >>> grid = Grid((32, 32), bounds=[(0, 1), (0, 1)])
        >>> heat = HeatStepper(grid, "periodic", diffusivity=0.01, dt=0.1)
        >>> u = heat(CenteredGrid.zeros(grid, "periodic"))
    """

    def __init__(self, grid: Grid, boundary, *, diffusivity: float, dt, method: str = "spectral",
                 dtype: torch.dtype = torch.float32, device=None):
        if not isinstance(grid, Grid):
            raise ParameterError(f"grid must be a phisim.Grid, got {type(grid).__name__}")
        if method not in HEAT_METHODS:
            raise ParameterError(f"unknown heat method {method!r}; choose one of {HEAT_METHODS}")
        if dtype not in (torch.float32, torch.float64):
            raise ParameterError(f"dtype must be torch.float32 or torch.float64, got {dtype!r}")
        template = CenteredGrid.zeros(grid, boundary, 1, dtype=dtype, device=device)
        self.grid, self.boundary, self.method = grid, template.boundary, method
        self.dtype, self.device = dtype, template.values.device
        self.diffusivity = check_nonnegative(diffusivity, "diffusivity")
        self.dt = check_dt(dt)
        kinds, values = field_kinds_and_values(self.boundary)
        self.kinds = normalize_kinds(kinds, grid.rank)
        nu_dt = float(self.diffusivity) * float(self.dt)
        if method == "explicit" and nu_dt * sum(4.0 / d**2 for d in grid.dx) > 2.0 * (1 + 1e-12):
            raise ParameterError(f"explicit heat step unstable: ν dt Σ 4/dx² = "
                                 f"{nu_dt * sum(4.0 / d**2 for d in grid.dx):.3g} > 2; use method='spectral' or "
                                 "'implicit', or a smaller dt")
        #: Whether the boundary holds non-zero values (then each step goes through ``diffuse``).
        self.inhomogeneous = any(v is not None and not (isinstance(v, (int, float)) and v == 0)
                                 for pair in values for v in pair)
        lam = eigenvalues_cached(grid.resolution, tuple(grid.dx), self.kinds, torch.float64, self.device, True)
        mult = {"spectral": lambda: torch.exp(nu_dt * lam), "implicit": lambda: 1.0 / (1.0 - nu_dt * lam),
                "explicit": lambda: 1.0 + nu_dt * lam}[method]()
        self._multiplier = (mult * transform_scale(grid.resolution, self.kinds)).to(dtype)
        self._advance = self.advance

    def __call__(self, u: CenteredGrid) -> CenteredGrid:
        """Advance ``u`` by one step.

        Raises:
            GridMismatchError: For a field on another grid or with another boundary.
            ParameterError: For a field of another dtype or device, or a vector field.
        """
        if not isinstance(u, CenteredGrid) or u.is_vector:
            raise ParameterError(f"a HeatStepper advances a scalar CenteredGrid, got {type(u).__name__}")
        if u.grid != self.grid or u.boundary != self.boundary:
            raise GridMismatchError("the field's grid or boundary differs from the HeatStepper's")
        if u.dtype != self.dtype or u.values.device.type != self.device.type:
            raise ParameterError(f"this stepper was built for {self.dtype} on {self.device}; got {u.dtype} on "
                                 f"{u.values.device}")
        return self._advance(u)

    def advance(self, u: CenteredGrid) -> CenteredGrid:
        """The step on a validated field: no host read, no branch on tensor values (what :func:`torch.compile`
        traces as one graph; see :func:`phisim.compile`)."""
        if self.inhomogeneous:
            return diffuse(u, self.dt, viscosity=self.diffusivity, method=self.method)
        return u.with_values(apply_multiplier(u.values, self.kinds, self._multiplier, None, prescaled=True))

    def __repr__(self) -> str:
        return f"HeatStepper({self.grid}, diffusivity={self.diffusivity}, dt={self.dt}, method={self.method!r})"
