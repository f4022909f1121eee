"""Diffusion ``∂u/∂t = ν ∇²u``: explicit, implicit and spectral (exact per mode) time steps.

Space is discretised with the second-order cell-centred stencil and face boundary values of
:mod:`phisim.solvers.poisson` (``∇²_h u = L₀ u + b``, ``b`` from non-zero boundary values). The three methods
integrate this semi-discrete system in time:

* ``'explicit'``: forward Euler, first order in ``dt``; stable while
  ``dt/substeps ≤ 1 / (2 ν Σ_axes 1/dx²)`` (otherwise :class:`~phisim.errors.ParameterError`);
* ``'implicit'``: backward Euler ``(I - ν dt ∇²_h) u' = u``, first order, unconditionally stable;
  solved by :func:`phisim.solvers.linalg.cg` with the exact spectral inverse as preconditioner;
* ``'spectral'`` (default): exact in time, ``û(t) = e^{νtλ} û₀ + νt φ₁(νtλ) b̂`` per mode of the
  DST/DCT/FFT basis (``φ₁(z) = (e^z - 1)/z``), with ``λ`` the stencil eigenvalues; with
  ``spectrum='continuous'`` the continuous ``λ = -κ²`` (spectrally accurate in space for smooth
  data; zero boundary values only).

:func:`fourier_heat` is the periodic heat operator of the paper's heat experiment (E4):
``ŷ(k) = x̂(k) exp(-4π² |k|² ν t)`` with numpy's ``fftfreq`` wavenumbers in cycles per cell (dx = 1);
its decay factors are computed once per (resolution, ν t, dtype, device).

Reference for the time integrators: Hairer & Wanner, *Solving ODEs II* (stability of explicit and
implicit Euler); exponential integrator ``φ₁``: Hochbruck & Ostermann (2010), Acta Numerica 19.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from functools import lru_cache

import torch

from phisim.checks import check_dt, check_nonnegative
from phisim.errors import BoundaryError, NonFiniteError, ParameterError
from phisim.field import CenteredGrid, StaggeredGrid
from phisim.ops.stencil import boundary_source, check_rhs, laplace_zero, normalize_dx, normalize_kinds
from phisim.solvers import mac_diffusion as _mac
from phisim.solvers.box import spectral_apply
from phisim.solvers.linalg import Solve, cg
from phisim.solvers.poisson import field_kinds_and_values
from phisim.spectral import fft as _fft

__all__ = [
    "DIFFUSION_METHODS",
    "STAGGERED_METHODS",
    "diffuse_staggered",
    "staggered_laplace",
    "explicit_stability_limit",
    "diffuse_values",
    "diffuse",
    "fourier_k2",
    "heat_decay_factors",
    "fourier_heat",
]

DIFFUSION_METHODS = ("spectral", "implicit", "explicit")
#: Methods of :func:`diffuse_staggered`.
STAGGERED_METHODS = _mac.STAGGERED_METHODS


def explicit_stability_limit(dx, viscosity: float) -> float:
    """Largest stable forward-Euler step of the stencil diffusion, ``1 / (2 ν Σ 1/dx²)``.

    Args:
        dx: Spacing per axis (a sequence; a float means one axis).
        viscosity: Diffusivity ``ν >= 0``.

    Returns:
        The limit (``inf`` for ``ν = 0``).

    Raises:
        ParameterError: For a negative/non-finite viscosity or invalid dx.
    """
    nu = float(check_nonnegative(viscosity, "viscosity"))
    dx = (float(dx),) if isinstance(dx, (int, float)) else tuple(float(d) for d in dx)
    dx = normalize_dx(dx, len(dx))
    if nu == 0:
        return math.inf
    return 1.0 / (2.0 * nu * sum(1.0 / d**2 for d in dx))


def _check_product(tau) -> None:
    if not math.isfinite(float(tau.detach() if isinstance(tau, torch.Tensor) else tau)):
        raise ParameterError(
            f"viscosity * dt = {float(tau)} overflows: each factor is finite but their product is not; use a "
            "smaller time step or viscosity (the result would be NaN)"
        )


def _phi1(z: torch.Tensor) -> torch.Tensor:
    small = z.abs() < 1e-8
    safe = torch.where(small, torch.ones_like(z), z)
    return torch.where(small, 1.0 + z / 2, torch.expm1(safe) / safe)


def diffuse_values(
    u: torch.Tensor,
    dt,
    *,
    viscosity,
    dx=1.0,
    kinds="periodic",
    values=None,
    method: str = "spectral",
    substeps: int = 1,
    solve=None,
    spectrum: str = "stencil",
    engine: str | None = None,
) -> torch.Tensor:
    """Advance ``∂u/∂t = ν ∇²_h u`` by ``dt`` on a tensor ``(B, *resolution)``.

    Args:
        u: Values ``(B, *resolution)`` (1-3 spatial axes), float32/float64.
        dt: Time step ``>= 0`` (float or 0-d tensor; a tensor keeps gradients in the spectral method).
        viscosity: Diffusivity ``ν >= 0`` (float or 0-d tensor).
        dx: Cell spacing (float or one per axis).
        kinds: Boundary kinds per axis (see :func:`phisim.solvers.poisson.normalize_kinds`).
        values: Boundary values (see :func:`phisim.solvers.poisson.boundary_source`); fixed during the step.
        method: ``'spectral'`` (exact in time), ``'implicit'`` (backward Euler) or ``'explicit'``
            (forward Euler).
        substeps: Number of equal sub-steps for the explicit/implicit methods (ignored by spectral).
        solve: :class:`phisim.solvers.linalg.Solve` for the implicit method (default ``Solve(rtol=1e-10)``
            in float64, ``Solve()`` in float32).
        spectrum: Spectral method only: ``'stencil'`` (exact for the discrete operator; default) or
            ``'continuous'`` (exact Fourier/sine/cosine decay ``e^{-νκ²t}``; zero boundary values only).
        engine: FFT engine.

    Returns:
        ``u`` after ``dt``; same shape, dtype and device; differentiable.

    Raises:
        ParameterError: Negative/non-finite ``dt`` or ``viscosity``, unknown method, bad substeps, or
            an explicit step above the stability limit (the message gives the substeps needed).
        BoundaryError, ShapeError: Invalid kinds, values or shapes.
        NonFiniteError: NaN/Inf in ``u``.
    """
    rank = check_rhs(u, "u")
    dt = check_dt(dt)
    nu = check_nonnegative(viscosity, "viscosity")
    if method not in DIFFUSION_METHODS:
        raise ParameterError(f"method must be one of {DIFFUSION_METHODS}, got {method!r}")
    if not isinstance(substeps, int) or isinstance(substeps, bool) or substeps < 1:
        raise ParameterError(f"substeps must be an int >= 1, got {substeps!r}")
    if not bool(torch.isfinite(u).all()):
        raise NonFiniteError("diffuse: the state contains NaN or Inf")
    kinds = normalize_kinds(kinds, rank)
    dx = normalize_dx(dx, rank)
    tau = dt * nu  # ν t, a float or a 0-d tensor
    _check_product(tau)
    b = boundary_source(u, dx, kinds, values)
    if method == "spectral":
        if spectrum == "continuous" and b is not None:
            raise BoundaryError(
                "spectrum='continuous' supports zero boundary values only; use spectrum='stencil'"
            )

        def decay(lam):
            return torch.exp(lam * tau)

        out = spectral_apply(u, dx, kinds, decay, engine=engine, spectrum=spectrum)
        if b is not None:
            out = out + spectral_apply(b, dx, kinds, lambda lam: tau * _phi1(lam * tau), engine=engine)
        return out
    h = tau / substeps
    if method == "explicit":
        limit = explicit_stability_limit(dx, float(nu))
        step = float(dt) / substeps
        if step > limit * (1 + 1e-12):
            need = math.ceil(float(dt) / limit)
            raise ParameterError(
                f"explicit diffusion is unstable: dt/substeps = {step:g} exceeds the limit "
                f"1/(2 ν Σ 1/dx²) = {limit:g}; use substeps >= {need}, method='implicit' or "
                "method='spectral'"
            )
        for _ in range(substeps):
            lap = laplace_zero(u, dx, kinds)
            if b is not None:
                lap = lap + b
            u = u + h * lap
        return u
    # implicit

    if solve is None:
        solve = Solve(rtol=1e-10) if u.dtype == torch.float64 else Solve()

    def operator(x: torch.Tensor) -> torch.Tensor:
        return x - h * laplace_zero(x, dx, kinds)

    def precond(r: torch.Tensor) -> torch.Tensor:
        return spectral_apply(r, dx, kinds, lambda lam: 1.0 / (1.0 - lam * float(h)), engine=engine)

    for _ in range(substeps):
        rhs = u if b is None else u + h * b
        u = cg(operator, rhs, u.detach(), solve=solve, preconditioner=precond)
    return u


def diffuse(
    field,
    dt,
    *,
    viscosity,
    method: str = "spectral",
    substeps: int = 1,
    solve=None,
    spectrum: str = "stencil",
    engine: str | None = None,
):
    """Diffuse a field for a time ``dt``: ``∂u/∂t = ν ∇²u`` with the field's boundary.

    Boundary values sit on the cell face (see :mod:`phisim.boundary`). Vector fields diffuse each
    component with the condition its role implies (normal / tangential velocity at each side).
    A :class:`~phisim.field.StaggeredGrid` is passed on to :func:`diffuse_staggered` (methods
    ``'spectral'``, ``'implicit'``, ``'explicit'``; ``substeps`` and ``spectrum`` do not apply).

    Args:
        field: A :class:`phisim.field.CenteredGrid` (scalar ``(B, *res)`` or vector ``(B, C, *res)``) or a
            :class:`phisim.field.StaggeredGrid`.
        dt: Time step ``>= 0``.
        viscosity: Diffusivity ``ν >= 0``.
        method: ``'spectral'`` (default, exact in time), ``'implicit'`` or ``'explicit'``.
        substeps: Sub-steps for the explicit/implicit methods.
        solve: :class:`phisim.solvers.linalg.Solve` for the implicit method.
        spectrum: ``'stencil'`` or ``'continuous'`` (spectral method; see :func:`diffuse_values`).
        engine: FFT engine.

    Returns:
        A new field of the same kind on the same grid with the same boundary.

    Raises:
        ParameterError: Bad dt/viscosity/method, unstable explicit step, or a field that is neither a
            CenteredGrid nor a StaggeredGrid.
        BoundaryError, ShapeError, NonFiniteError: See :func:`diffuse_values`.
    """

    if isinstance(field, StaggeredGrid):
        if substeps != 1:
            raise ParameterError("diffuse: substeps is not supported for a StaggeredGrid")
        return diffuse_staggered(field, dt, viscosity=viscosity, method=method, solve=solve, engine=engine)
    if not isinstance(field, CenteredGrid):
        raise ParameterError(
            f"diffuse expects a CenteredGrid or StaggeredGrid, got {type(field).__name__}; diffuse raw "
            "values with diffuse_values"
        )
    grid = field.grid
    kw = dict(
        viscosity=viscosity,
        dx=grid.dx,
        method=method,
        substeps=substeps,
        solve=solve,
        spectrum=spectrum,
        engine=engine,
    )
    if not field.is_vector:
        kinds, values = field_kinds_and_values(field.boundary)
        return field.with_values(diffuse_values(field.values, dt, kinds=kinds, values=values, **kw))
    comps = []
    for c in range(field.values.shape[1]):
        kinds, values = field_kinds_and_values(field.boundary, c if field.values.shape[1] == grid.rank else None)
        values = tuple(tuple(_slice_channel(v, c) for v in pair) for pair in values)
        comps.append(diffuse_values(field.values[:, c], dt, kinds=kinds, values=values, **kw))
    return field.with_values(torch.stack(comps, dim=1))


def diffuse_staggered(
    velocity,
    dt,
    *,
    viscosity,
    method: str = "implicit",
    fixed=None,
    solve=None,
    engine: str | None = None,
    capacitance: dict | None = None,
    walls=None,
):
    """Viscous diffusion ``∂u/∂t = ν ∇²u`` of a MAC velocity over one step ``dt``, fast.

    Each component uses the (2d+1)-point Laplacian on its own faces with the ghost rules of the velocity
    boundary (walls and Dirichlet sides fix the normal velocity on boundary faces; a moving wall drags the
    tangential velocity; open sides leave boundary faces free with a mirrored ghost). In a box (no
    ``fixed`` faces) every implicit method is solved exactly by one forward and one inverse DST/DCT/FFT
    per component, chosen per axis by the component's boundary kinds (table in
    :mod:`phisim.solvers.mac_diffusion`). With ``fixed`` faces (bodies) the solve uses conjugate gradients
    preconditioned with the exact box solve, or, where the caller passes a ``capacitance`` dict (the solver
    cache of a body layout it reuses), a direct capacitance matrix on the body surface (built from the box's
    eigen-decomposition, kept in that dict; then two box solves per call, or, for a sharp surface where the Green's
    function of the box operator falls below round-off within a window around the body, one box solve and one on
    that window alone).

    Methods and their order in time:

    * ``'implicit'`` (default): backward Euler ``(I - ν dt L) u' = u``; first order, unconditionally
      stable, strongly damping (L-stable);
    * ``'crank_nicolson'``: ``(I - ν dt/2 L) u' = (I + ν dt/2 L) u``; second order, unconditionally
      stable (A-stable; the highest modes are damped weakly when ``ν dt / dx²`` is large);
    * ``'spectral'``: exact in time for the semi-discrete system, ``u' = e^{ν dt L} u`` (plus the exact
      response to boundary values); box only;
    * ``'explicit'``: forward Euler ``u' = u + ν dt L u``; first order, stable for
      ``ν dt Σ 2/dx² <= 1``.

    Args:
        velocity: MAC velocity (:class:`~phisim.field.StaggeredGrid`), batch ``B``, 1-3 axes.
        dt: Time step ``>= 0`` (float or 0-d tensor).
        viscosity: Kinematic viscosity ``ν >= 0`` (float or 0-d tensor).
        method: One of :data:`STAGGERED_METHODS`.
        fixed: Optional faces whose velocity is prescribed (solid or moving bodies): one mask per
            component, shape ``(1 or B, *face_shape(i))`` (bool or 0/1; None for a component without),
            1 where the face keeps the value it has in ``velocity``. Those faces act as Dirichlet samples
            in the stencil of their free neighbours.
        solve: :class:`phisim.solvers.linalg.Solve` of the CG solve with ``fixed`` faces (default rtol 1e-10 in
            float64, 1e-6 in float32); the direct capacitance solve does not use it.
        engine: FFT engine (see :func:`phisim.spectral.fft.resolve_engine`).
        capacitance: A dict owned by the caller in which direct solves for its ``fixed`` faces are kept (e.g.
            ``SolidLayout.solvers`` of a persistent layout); None: conjugate gradients.
        walls: Optional sharp no-slip surfaces, one ``(cut, coef, source)`` or None per component
            (:attr:`phisim.fluid.bodies.SolidLayout.walls`): the ``cut`` faces are held and their neighbours'
            stencil takes the surface velocity at the true surface (see :mod:`phisim.solvers.mac_diffusion`).

    Returns:
        The diffused StaggeredGrid (same grid and boundary; boundary faces re-imposed); differentiable
        w.r.t. the velocity, ``dt`` and ``viscosity``.

    Raises:
        ParameterError: Unknown method, negative/non-finite dt or viscosity, an unstable explicit step,
            ``'spectral'`` with ``fixed`` faces, or a field that is not a StaggeredGrid.
        ShapeError: For masks in ``fixed`` that do not fit the components.
        SolveError: If the CG solve with ``fixed`` faces does not converge.
    """
    return _mac.diffuse_staggered(velocity, dt, viscosity=viscosity, method=method, fixed=fixed, solve=solve,
                                  capacitance=capacitance, engine=engine, walls=walls)


def _slice_channel(v, c: int):
    if isinstance(v, torch.Tensor) and v.ndim >= 2 and v.shape[1] > 1:
        return v[:, c]
    return v


# ----------------------------------------------------------------------------------------------
# the periodic heat operator of E4


def staggered_laplace(velocity, walls=None):
    """The Laplacian of each MAC component with the velocity boundary's ghost rules, and with the sharp no-slip
    surfaces ``walls`` of :func:`diffuse_staggered` at their true position (``L_0 u - coef u + source`` on the free
    faces, 0 on the cut faces): the operator whose implicit steps :func:`diffuse_staggered` takes.

    Args:
        velocity: MAC velocity.
        walls: None, or one ``(cut, coef, source)`` or None per component.

    Returns:
        The Laplacian as a StaggeredGrid.
    """
    return _mac.staggered_laplace(velocity, walls)


def fourier_k2(
    resolution: Sequence[int], *, real: bool = True, dtype: torch.dtype = torch.float64, device=None
) -> torch.Tensor:
    """``|k|²`` with numpy's ``fftfreq`` wavenumbers in cycles per cell (dx = 1).

    Args:
        resolution: Cells per axis.
        real: rfft layout (last axis ``n//2 + 1`` bins, ``rfftfreq``) when True, full FFT layout otherwise.
        dtype: Output dtype.
        device: Output device.

    Returns:
        Tensor of shape ``resolution`` (last axis halved when ``real``).

    Raises:
        ParameterError: For a non-positive resolution.
    """
    resolution = tuple(int(n) for n in resolution)
    if not resolution or any(n < 1 for n in resolution):
        raise ParameterError(f"resolution must have positive entries, got {resolution}")
    return _k2_cached(resolution, real, dtype, torch.device(device or "cpu"))


@lru_cache(maxsize=64)
def _k2_cached(resolution, real, dtype, device) -> torch.Tensor:
    total = torch.zeros((), dtype=torch.float64)
    for a, n in enumerate(resolution):
        last = a == len(resolution) - 1
        k = (
            torch.fft.rfftfreq(n, dtype=torch.float64)
            if (real and last)
            else torch.fft.fftfreq(n, dtype=torch.float64)
        )
        shape = [1] * len(resolution)
        shape[a] = -1
        total = total + (k**2).reshape(shape)
    return total.to(dtype=dtype, device=device)


def heat_decay_factors(
    resolution: Sequence[int],
    dt: float,
    *,
    viscosity: float = 1.0,
    dtype: torch.dtype = torch.float64,
    device=None,
) -> torch.Tensor:
    """``exp(-4π² |k|² ν dt)`` in the rfft layout (cached per resolution, ν dt, dtype and device).

    Args:
        resolution: Cells per axis.
        dt: Time ``>= 0``.
        viscosity: Diffusivity ``ν >= 0`` (E4 uses ``ν dt = 8``).
        dtype: Output dtype (float64 recommended: factors underflow to 0 for high modes).
        device: Output device.

    Returns:
        Real tensor of shape ``resolution`` with the last axis halved.

    Raises:
        ParameterError: For negative/non-finite dt or viscosity.
    """
    t = float(check_dt(dt)) * float(check_nonnegative(viscosity, "viscosity"))
    _check_product(t)
    resolution = tuple(int(n) for n in resolution)
    return _decay_cached(resolution, t, dtype, torch.device(device or "cpu"))


@lru_cache(maxsize=64)
def _decay_cached(resolution, nu_t, dtype, device) -> torch.Tensor:
    k2 = _k2_cached(resolution, True, torch.float64, torch.device("cpu"))
    return torch.exp(-4 * math.pi**2 * k2 * nu_t).to(dtype=dtype, device=device)


def fourier_heat(
    x: torch.Tensor, dt: float, *, viscosity: float = 1.0, engine: str | None = None
) -> torch.Tensor:
    """Periodic heat operator of E4: ``ŷ(k) = x̂(k) exp(-4π² |k|² ν dt)``, batched.

    Wavenumbers are numpy's ``fftfreq`` in cycles per cell with dx = 1 (as PhiFlow's
    ``diffuse.fourier``); the decay factors are precomputed once per shape/dtype/device.

    Args:
        x: Tensor ``(B, *resolution)`` (1-3 spatial axes), float32/float64 (E4 uses float64).
        dt: Time ``>= 0`` (E4: ``ν dt = 8``).
        viscosity: Diffusivity ``ν >= 0``.
        engine: FFT engine.

    Returns:
        ``y`` with ``x``'s shape and dtype; linear, self-adjoint and differentiable in ``x``.

    Raises:
        ParameterError: Negative/non-finite dt or viscosity, or a non-float tensor.
        ShapeError: Wrong rank.
    """
    rank = check_rhs(x, "x")
    res = tuple(x.shape[1:])
    decay = heat_decay_factors(res, dt, viscosity=viscosity, dtype=x.dtype, device=x.device)
    return _fft.fourier_multiply(x, decay, tuple(range(1, rank + 1)), engine=engine)
