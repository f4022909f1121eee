"""Exponential time differencing Runge-Kutta steppers (ETDRK0-4) for semi-linear PDEs ``u_t = L u + N(u)``.

The linear part ``L`` must be diagonal in the grid's spectral basis (a function of the wavenumbers, one value per
mode and channel); it is integrated exactly. The nonlinear part ``N`` is integrated with the exponential
Runge-Kutta schemes of Cox & Matthews (2002): order 1 (exponential Euler), 2 (ETD2RK), 3 (ETD3RK) and 4 (ETD4RK);
order 0 is the exact linear exponential alone. The phi-functions ``phi_1..phi_3`` of ``z = dt L`` are evaluated
once, on construction, with the contour-integral method of Kassam & Trefethen (2005): the mean of ``phi(z + R
e^{i theta_j})`` over ``M`` points of a circle around each ``z``, computed in complex128 and then cast to the
stepper's precision. This keeps the coefficients accurate where the closed formulas cancel catastrophically
(``|z|`` small).

Nonlinear terms are dealiased with the 2/3 rule (by default): the spectrum is truncated before the nonlinear
term is evaluated, and the nonlinear term's spectrum is truncated again. Both masks are folded into the
precomputed coefficients: each step multiplies the state once by a stack of coefficients (giving the truncated
state and the linear parts of every stage in one pass), so that a stage is one fused multiply-add per nonlinear
term. A diagonal factor of the nonlinear term (``nonlinear_factor``, e.g. the ``-ik/2`` of ``-(u^2)_x / 2``) is
folded into the coefficients as well.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Callable
from typing import Union

import torch

from ..allocator import keep_freed_memory
from ..errors import BoundaryError, NonFiniteError, ParameterError, ShapeError
from .transforms import SpectralGrid

__all__ = ["ETDRKStepper", "phi_functions", "LinearOperator", "SpectralNonlinear", "PhysicalNonlinear"]

#: ``L``: a tensor broadcastable to ``(C, *grid.spectral_shape)`` or a function ``grid -> tensor``.
LinearOperator = Union[torch.Tensor, Callable[[SpectralGrid], torch.Tensor]]  # noqa: UP007
#: ``N`` given on the spectrum: ``(u_hat, grid) -> N_hat`` with ``u_hat`` already dealiased.
SpectralNonlinear = Callable[[torch.Tensor, SpectralGrid], torch.Tensor]
#: ``N`` given in physical space: ``u -> N(u)`` (pointwise or any other function of the real field).
PhysicalNonlinear = Callable[[torch.Tensor], torch.Tensor]

_CHUNK = 1 << 15


def _check_number(value, name: str, positive: bool = True) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) and not (
            isinstance(value, torch.Tensor) and value.numel() == 1):
        raise ParameterError(f"{name} must be a number, got {value!r}")
    v = float(value)
    if not math.isfinite(v):
        raise ParameterError(f"{name} must be finite, got {v}")
    if positive and v <= 0:
        raise ParameterError(f"{name} must be > 0, got {v}")
    return v


def _phi_direct(z: torch.Tensor, order: int) -> torch.Tensor:
    """Closed formulas of phi_0..phi_order (accurate only away from ``z = 0``); stacked on a new first axis."""
    ez = torch.exp(z)
    out = [ez]
    term = ez
    fact = 1.0
    for k in range(1, order + 1):
        term = (term - 1.0 / fact) / z  # phi_k = (phi_{k-1} - 1/(k-1)!) / z
        fact *= k
        out.append(term)
    return torch.stack(out)


def phi_functions(z: torch.Tensor, order: int = 3, points: int = 64, radius: float = 1.0) -> torch.Tensor:
    """``phi_0(z) .. phi_order(z)`` by the contour-integral method of Kassam & Trefethen (2005).

    ``phi_0 = e^z``, ``phi_1 = (e^z - 1)/z``, ``phi_2 = (e^z - 1 - z)/z^2``, ``phi_3 = (e^z - 1 - z - z^2/2)/z^3``.
    Each value is the mean of the closed formula over ``points`` points ``z + radius e^{i theta_j}``,
    ``theta_j = 2 pi (j + 1/2) / points`` (a trapezoidal rule of Cauchy's integral, spectrally accurate since the
    functions are entire), evaluated in complex128, once per distinct value and in chunks to bound the memory.

    Args:
        z: Tensor of (real or complex) arguments, any shape.
        order: Highest phi index (0..3).
        points: Contour points ``M`` (>= 8).
        radius: Contour radius ``R`` (> 0).

    Returns:
        complex128 tensor of shape ``(order + 1, *z.shape)``.
    """
    zc = z.to(torch.complex128).reshape(-1)
    # operators built from |k|^2 repeat the same value many times: evaluate each distinct z once
    if bool((zc.imag == 0).all()):
        distinct, inverse = torch.unique(zc.real, return_inverse=True)
        zu = distinct.to(torch.complex128)
    else:
        distinct, inverse = torch.unique(torch.view_as_real(zc), dim=0, return_inverse=True)
        zu = torch.view_as_complex(distinct.contiguous())
    theta = 2 * math.pi * (torch.arange(points, dtype=torch.float64) + 0.5) / points
    circle = (radius * torch.polar(torch.ones_like(theta), theta)).to(zc.device)
    out = torch.empty((order + 1, zu.numel()), dtype=torch.complex128, device=zc.device)
    for start in range(0, zu.numel(), _CHUNK):
        r = zu[start:start + _CHUNK, None] + circle
        out[:, start:start + _CHUNK] = _phi_direct(r, order).mean(dim=-1)
    return out[:, inverse].reshape((order + 1,) + tuple(z.shape))


def _mirror_walls(grid: SpectralGrid) -> SpectralGrid:
    """A shallow copy of ``grid`` whose wall-axis wavenumbers have the opposite sign (for the evenness test)."""
    g = copy.copy(grid)
    g.wavenumbers = tuple(-k if a in grid.wall_axes else k for a, k in enumerate(grid.wavenumbers))
    return g


class ETDRKStepper:
    """One time step of ``u_t = L u + N(u)`` with an exponential Runge-Kutta scheme (exponax-style).

    Settings and coefficients are fixed on construction; ``stepper(u)`` advances a batch of states by ``dt``.
    The state has shape ``(B, C, *grid.resolution)``, the grid's dtype and device. The step is differentiable
    with respect to the state and traceable by ``torch.compile(fullgraph=True)``.

    Defining an equation takes a few lines (here 1-D Burgers, ``u_t = nu u_xx - (u^2/2)_x``)::

        grid = SpectralGrid(domain=2 * math.pi, resolution=256, dtype=torch.float64)
        dx = grid.derivative(0)                                   # i k
        stepper = ETDRKStepper(grid, dt=0.01, order=4,
                               linear=lambda g: 0.01 * g.laplacian(),            # L(k) = -nu k^2
                               nonlinear=lambda u_hat, g: -0.5 * dx * g.to_spectral(g.to_physical(u_hat) ** 2))
        u1 = stepper(u0)                                          # u0: (B, 1, 256)

    or with a pointwise physical nonlinearity: ``nonlinear_physical=lambda u: u - u**3``.

    Args:
        grid: The :class:`~phisim.pde.transforms.SpectralGrid` (domain, resolution, boundaries, dtype, device).
        dt: Time step (> 0).
        linear: The symbol of ``L``: a tensor broadcastable to ``(C, *grid.spectral_shape)`` or a function
            ``grid -> tensor`` (built from ``grid.wavenumbers``, ``grid.laplacian()``, ``grid.derivative(axis)``).
            Evaluated in float64/complex128. On wall axes it must be even in the wavenumber (a function of
            ``k^2``), or it would not be diagonal in the sine/cosine basis; a function is checked by evaluating it
            a second time with the wall wavenumbers negated (a tensor is taken as given).
        nonlinear: ``N`` on the spectrum, ``(u_hat, grid) -> N_hat``; it receives the dealiased spectrum
            ``(B, C, *spectral_shape)`` and returns a spectrum of the same shape (or broadcastable to it).
        nonlinear_physical: ``N`` in physical space, ``u -> N(u)`` on the dealiased field ``(B, C, *resolution)``.
            Give at most one of ``nonlinear`` and ``nonlinear_physical``.
        order: 0 (linear exponential only, no nonlinear term allowed), 1, 2, 3 or 4.
        channels: Number of channels ``C`` of the state.
        dealias: Kept fraction of the modes per axis in nonlinear terms (2/3 rule; 1.0 disables dealiasing).
        contour_points: Points of the Kassam-Trefethen contour.
        contour_radius: Radius of the contour.
        check_finite: If True, ``__call__`` raises :class:`NonFiniteError` on non-finite input (a host sync, so
            off by default and incompatible with ``fullgraph`` compilation).
        prefiltered: If True, ``nonlinear`` receives the spectrum without the 2/3-rule truncation because it
            applies the mask itself (e.g. folded into its derivative operators, saving one pass over the spectrum;
            the mask is ``grid.dealias_mask(dealias)``). The output truncation is applied in any case.
        nonlinear_factor: Optional diagonal factor ``D`` of the nonlinear term (a number or a tensor broadcastable to
            ``(C, *spectral_shape)``): the nonlinear term is ``D * nonlinear(...)`` (or ``D * F[nonlinear_physical]``).
            ``D`` is folded into the precomputed coefficients, which saves one pass over the spectrum per stage.

    Raises:
        ParameterError: Bad ``dt``/order/channels/dealias/contour settings, a non-finite ``L``, or a ``dt`` for which
            the contour evaluation is inaccurate or overflows the stepper's precision.
        BoundaryError: ``L`` is not diagonal in the sine/cosine basis of a wall axis.
        ShapeError: ``L`` does not broadcast to ``(C, *spectral_shape)``.
    """

    def __init__(self, grid: SpectralGrid, dt: float, linear, nonlinear: SpectralNonlinear | None = None, *,
                 nonlinear_physical: PhysicalNonlinear | None = None, order: int = 4, channels: int = 1,
                 dealias: float = 2.0 / 3.0, contour_points: int = 64, contour_radius: float = 1.0,
                 check_finite: bool = False, prefiltered: bool = False,
                 nonlinear_factor: torch.Tensor | float | None = None):
        if not isinstance(grid, SpectralGrid):
            raise ParameterError(f"grid must be a SpectralGrid, got {type(grid).__name__}")
        self.grid = grid
        if grid.device.type == "cpu":  # one step's freed arrays are reused by the next (phisim.allocator)
            keep_freed_memory()
        self.dt = _check_number(dt, "dt")
        if isinstance(order, bool) or order not in (0, 1, 2, 3, 4):
            raise ParameterError(f"order must be one of 0, 1, 2, 3, 4, got {order!r}")
        if isinstance(channels, bool) or not isinstance(channels, int) or channels < 1:
            raise ParameterError(f"channels must be an int >= 1, got {channels!r}")
        if nonlinear is not None and nonlinear_physical is not None:
            raise ParameterError("give at most one of nonlinear (spectral) and nonlinear_physical")
        if order == 0 and (nonlinear is not None or nonlinear_physical is not None):
            raise ParameterError("order 0 is the exact linear exponential and ignores N; use order >= 1 for a "
                                 "nonlinear term")
        if isinstance(contour_points, bool) or not isinstance(contour_points, int) or contour_points < 8:
            raise ParameterError(f"contour_points must be an int >= 8, got {contour_points!r}")
        contour_radius = _check_number(contour_radius, "contour_radius")
        if isinstance(dealias, bool) or not isinstance(dealias, (int, float)) or not 0 < dealias <= 1:
            raise ParameterError(f"dealias must be a fraction in (0, 1], got {dealias!r}")
        self.order = order
        self.channels = channels
        self.dealias = float(dealias)
        self.check_finite = bool(check_finite)
        self.prefiltered = bool(prefiltered)
        self.shape = (channels,) + grid.resolution
        self._nonlinear = nonlinear
        self._nonlinear_physical = nonlinear_physical
        self.has_nonlinear = nonlinear is not None or nonlinear_physical is not None
        self.nonlinear_factor = self._evaluate_factor(nonlinear_factor)

        lin = self._evaluate_linear(linear)
        self.linear_symbol = lin  # complex128 or float64, shape (C or 1, *spectral_shape)
        self._build_coefficients(lin, contour_points, contour_radius)

    # ------------------------------------------------------------------ construction
    def _evaluate_linear(self, linear) -> torch.Tensor:
        grid = self.grid
        if linear is None:
            lin = torch.zeros(grid.spectral_shape, dtype=torch.float64, device=grid.device)
        elif callable(linear):
            lin = linear(grid)
        else:
            lin = linear
        if not isinstance(lin, torch.Tensor):
            lin = torch.as_tensor(lin, dtype=torch.float64)
        lin = lin.to(grid.device)
        lin = lin.to(torch.complex128) if lin.is_complex() else lin.to(torch.float64)
        target = (self.channels,) + grid.spectral_shape
        try:
            lin = torch.broadcast_to(lin, torch.broadcast_shapes(lin.shape, (1,) + grid.spectral_shape))
        except RuntimeError as exc:
            raise ShapeError(f"the linear operator of shape {tuple(lin.shape)} does not broadcast to the spectral "
                             f"shape (C, *spectral_shape) = {target}") from exc
        if lin.dim() != len(target) or lin.shape[0] not in (1, self.channels):
            raise ShapeError(f"the linear operator has shape {tuple(lin.shape)}; expected {target} or a shape "
                             "broadcastable to it")
        if not bool(torch.isfinite(lin).all()):
            raise ParameterError("the linear operator has non-finite entries (a NaN or infinite parameter?)")
        if grid.wall_axes and callable(linear):
            mirrored = linear(_mirror_walls(grid))
            mirrored = torch.as_tensor(mirrored).to(device=grid.device, dtype=lin.dtype)
            scale = float(lin.abs().max()) + 1e-300
            if float((mirrored - lin).abs().max()) > 1e-12 * scale:
                axes = ", ".join(f"{a} ({grid.boundaries[a]})" for a in grid.wall_axes)
                raise BoundaryError(f"the linear operator is not even in the wavenumber along the wall axes {axes}: "
                                    "odd derivatives (advection, dispersion) are not diagonal in the sine/cosine "
                                    "basis; use periodic boundaries on those axes")
        if lin.is_complex() and not grid.spectral_is_complex:
            if float(lin.imag.abs().max()) > 0:
                raise BoundaryError("a complex linear operator needs a periodic axis; with walls on every axis the "
                                    "sine/cosine spectrum is real")
            lin = lin.real
        return lin.contiguous()

    def _evaluate_factor(self, factor) -> torch.Tensor | None:
        if factor is None:
            return None
        if isinstance(factor, bool) or not isinstance(factor, (int, float, complex, torch.Tensor)):
            raise ParameterError(f"nonlinear_factor must be a number or a tensor, got {type(factor).__name__}")
        f = torch.as_tensor(factor).to(self.grid.device)
        f = f.to(torch.complex128) if f.is_complex() else f.to(torch.float64)
        try:
            torch.broadcast_shapes(f.shape, (self.channels,) + self.grid.spectral_shape)
        except RuntimeError as exc:
            raise ShapeError(f"nonlinear_factor of shape {tuple(f.shape)} does not broadcast to (C, *spectral_shape) "
                             f"= {(self.channels,) + self.grid.spectral_shape}") from exc
        if not bool(torch.isfinite(f).all()):
            raise ParameterError("nonlinear_factor has non-finite entries")
        if f.is_complex() and not self.grid.spectral_is_complex and float(f.imag.abs().max()) > 0:
            raise BoundaryError("a complex nonlinear_factor needs a periodic axis; with walls on every axis the "
                                "sine/cosine spectrum is real")
        return f

    def _build_coefficients(self, lin: torch.Tensor, points: int, radius: float) -> None:
        """Precompute the stacked state coefficients ``self._state_coef`` and the nonlinear coefficients.

        With ``m`` the input truncation (1 where the nonlinear term masks its input itself or there is no
        dealiasing) and ``M`` the output truncation, the schemes are rewritten so that every stage input is a
        linear combination of ``u`` and earlier nonlinear terms (``n_x = D N_raw(x)``)::

            order 1: out = e u + M dt phi1 n_u
            order 2: a = m e u + M dt phi1 n_u;  out = e u + M dt (phi1 - phi2) n_u + M dt phi2 n_a
            order 3: a = m e2 u + q n_u;  b = m e u - M dt phi1 n_u + 2 M dt phi1 n_a;
                     out = e u + f1 n_u + 4 f2 n_a + f3 n_b
            order 4: a = m e2 u + q n_u;  b = m e2 u + q n_a;  c = m e u + (e2 - 1) q n_u + 2 q n_b;
                     out = e u + f1 n_u + f2 (n_a + n_b) + f3 n_c

        (``e = exp(dt L)``, ``e2 = exp(dt L / 2)``, ``q = M dt/2 phi1(dt L / 2)``); ``D`` and ``M`` are folded into
        every coefficient of a nonlinear term.
        """
        grid, dt, order = self.grid, self.dt, self.order
        cdtype = grid.complex_dtype if (grid.spectral_is_complex or lin.is_complex()) else grid.dtype
        mask = grid.dealias_mask(self.dealias) if self.dealias < 1 else None
        # in the spectrum's dtype: a complex-by-complex product is about twice as fast as a mixed one
        spec_dtype = grid.complex_dtype if grid.spectral_is_complex else grid.dtype
        self.dealias_mask = None if mask is None else mask.to(spec_dtype)
        mask_in = mask is not None and (self._nonlinear_physical is not None or not self.prefiltered)
        self._mask_input = mask_in
        factor = self.nonlinear_factor
        if factor is not None and factor.is_complex():
            cdtype = grid.complex_dtype
        z = dt * lin

        def cast(t: torch.Tensor, name: str, nonlinear: bool = False, masked_input: bool = False) -> torch.Tensor:
            t = t if (lin.is_complex() or (factor is not None and factor.is_complex() and nonlinear)) else t.real
            if nonlinear:
                if factor is not None:
                    t = t * factor
                if mask is not None:
                    t = t * mask
            if masked_input and mask_in:
                t = t * mask
            out = t.to(cdtype)
            if not bool(torch.isfinite(out).all()):
                zmax = float(z.real.max())
                raise ParameterError(f"the ETDRK coefficient {name} overflows {cdtype} at dt = {dt} (largest "
                                     f"dt*Re(L) = {zmax:.4g}); the linear operator grows too fast for this dt: "
                                     "reduce dt")
            return out

        def stack(*coefs: torch.Tensor) -> torch.Tensor:
            shape = torch.broadcast_shapes(*(c.shape for c in coefs))
            return torch.stack([c.expand(shape) for c in coefs]).unsqueeze(1).contiguous()  # (k, 1, C, *spec)

        one = torch.ones((), dtype=torch.float64, device=grid.device)
        with torch.no_grad():
            if order == 0:
                self._state_coef = cast(torch.exp(z.to(torch.complex128)), "exp(dt L)").contiguous()
                self._coef = ()
                return
            full = phi_functions(z, 3 if order >= 3 else order, points, radius)
            self._check_contour(z, full)
            e = full[0]
            p1 = dt * full[1]
            # the stacked coefficients of the state: (truncated u,) then the linear parts of the stages
            state = []
            if mask_in:
                state.append(cast(one.expand(z.shape), "mask", masked_input=True))
            if order == 1:
                state.append(cast(e, "exp(dt L)"))
                self._coef = (cast(p1, "dt phi1", True),)
            elif order == 2:
                p2 = dt * full[2]
                if mask_in:
                    state.append(cast(e, "exp(dt L)", masked_input=True))
                state.append(cast(e, "exp(dt L)"))
                self._coef = (cast(p1, "dt phi1", True), cast(p1 - p2, "dt (phi1 - phi2)", True),
                              cast(p2, "dt phi2", True))
            else:
                half = phi_functions(z / 2, 1, points, radius)
                self._check_contour(z / 2, half)
                ph1, ph2, ph3 = full[1], full[2], full[3]
                e2, q = half[0], 0.5 * dt * half[1]
                f1 = dt * (ph1 - 3 * ph2 + 4 * ph3)
                f2 = dt * (ph2 - 2 * ph3)
                f3 = dt * (4 * ph3 - ph2)
                state.append(cast(e2, "exp(dt L / 2)", masked_input=True))
                if mask_in:
                    state.append(cast(e, "exp(dt L)", masked_input=True))
                state.append(cast(e, "exp(dt L)"))
                if order == 3:
                    self._coef = (cast(q, "dt/2 phi1(dt L / 2)", True), cast(-p1, "-dt phi1", True),
                                  cast(2 * p1, "2 dt phi1", True), cast(f1, "f1", True), cast(4 * f2, "4 f2", True),
                                  cast(f3, "f3", True))
                else:
                    self._coef = (cast(q, "dt/2 phi1(dt L / 2)", True), cast((e2 - 1) * q, "(e2 - 1) q", True),
                                  cast(2 * q, "dt phi1(dt L / 2)", True), cast(f1, "f1", True),
                                  cast(2 * f2, "2 f2", True), cast(f3, "f3", True))
            self._state_coef = stack(*state)

    def _check_contour(self, z: torch.Tensor, phis: torch.Tensor) -> None:
        """Compare the contour values with the closed formulas where those are well conditioned (|z| >= 2)."""
        if not bool(torch.isfinite(phis).all()):
            raise ParameterError(f"the contour evaluation of the phi-functions overflows at dt = {self.dt} (largest "
                                 f"dt*Re(L) = {float(z.real.max()):.4g}): reduce dt")
        zc = z.to(torch.complex128).reshape(-1)
        far = zc[zc.abs() >= 2]
        if far.numel() == 0:
            return
        ref = _phi_direct(far, phis.shape[0] - 1)
        got = phis.reshape(phis.shape[0], -1)[:, zc.abs() >= 2]
        rel = ((got - ref).abs() / ref.abs().clamp_min(1e-300)).max()
        if not bool(rel <= 1e-6):
            worst = far[((got - ref).abs() / ref.abs().clamp_min(1e-300)).amax(0).argmax()]
            raise ParameterError(f"the contour evaluation of the phi-functions is inaccurate at dt = {self.dt} "
                                 f"(relative error {float(rel):.2e} at dt*L = {complex(worst):.4g}); the linear "
                                 "operator is too large for this dt: reduce dt (or raise contour_points)")

    # ------------------------------------------------------------------ stepping
    def _nonlinear_raw(self, u_hat: torch.Tensor) -> torch.Tensor:
        """``N`` without its diagonal factor, on an already truncated spectrum."""
        if self._nonlinear is not None:
            return self._nonlinear(u_hat, self.grid)
        return self.grid.to_spectral(self._nonlinear_physical(self.grid.to_physical(u_hat)))

    def nonlinear_spectral(self, u_hat: torch.Tensor) -> torch.Tensor:
        """``N`` on the spectrum, after the 2/3-rule truncation of ``u_hat`` (the output truncation is folded into
        the step's coefficients).

        Args:
            u_hat: Spectrum ``(B, C, *spectral_shape)``.

        Returns:
            The spectrum of ``N(u)`` (including ``nonlinear_factor``).
        """
        if self._mask_input:
            u_hat = u_hat * self.dealias_mask
        out = self._nonlinear_raw(u_hat)
        if self.nonlinear_factor is not None:
            out = out * self.nonlinear_factor.to(out.dtype if out.is_complex() else self.grid.dtype)
        return out

    def step_spectral(self, u_hat: torch.Tensor) -> torch.Tensor:
        """One step on the spectrum (no transforms, no input checks).

        Args:
            u_hat: Spectrum ``(B, C, *spectral_shape)`` (see :meth:`SpectralGrid.to_spectral`).

        Returns:
            The spectrum one ``dt`` later.
        """
        if self.order == 0:
            return self._state_coef * u_hat
        c = self._coef
        nl = self._nonlinear_raw
        # one pass: (truncated u,) and the linear part of every stage, stacked on a new first axis
        lin = (self._state_coef * u_hat).unbind(0)
        if self._mask_input:
            u_in, lin = lin[0], lin[1:]
        else:
            u_in = u_hat
        if self.order == 1:
            return torch.addcmul(lin[-1], c[0], nl(u_in))
        if self.order == 2:
            n_u = nl(u_in)
            n_a = nl(torch.addcmul(lin[0], c[0], n_u))
            return torch.addcmul(torch.addcmul(lin[-1], c[1], n_u), c[2], n_a)
        e2u, eu = lin[0], lin[-1]
        meu = lin[1] if len(lin) == 3 else eu
        if self.order == 3:
            q, mp1, p1x2, f1, f2, f3 = c
            n_u = nl(u_in)
            n_a = nl(torch.addcmul(e2u, q, n_u))
            n_b = nl(torch.addcmul(torch.addcmul(meu, mp1, n_u), p1x2, n_a))
            return torch.addcmul(torch.addcmul(torch.addcmul(eu, f1, n_u), f2, n_a), f3, n_b)
        q, qc, q2, f1, f2, f3 = c
        n_u = nl(u_in)
        n_a = nl(torch.addcmul(e2u, q, n_u))
        n_b = nl(torch.addcmul(e2u, q, n_a))
        n_c = nl(torch.addcmul(torch.addcmul(meu, qc, n_u), q2, n_b))
        out = torch.addcmul(torch.addcmul(eu, f1, n_u), f2, n_a + n_b)
        return torch.addcmul(out, f3, n_c)

    def check_state(self, u: torch.Tensor) -> None:
        """Raise a clear error unless ``u`` has the stepper's shape ``(B, C, *resolution)``, dtype and device.

        Args:
            u: The state to check.

        Raises:
            ShapeError: Wrong rank, channels or resolution.
            ParameterError: Wrong dtype or device.
        """
        if not isinstance(u, torch.Tensor):
            raise ShapeError(f"the state must be a torch.Tensor of shape (B, {', '.join(map(str, self.shape))}), "
                             f"got {type(u).__name__}")
        if u.dim() != len(self.shape) + 1 or tuple(u.shape[1:]) != self.shape:
            raise ShapeError(f"the state has shape {tuple(u.shape)}; this stepper expects (B, "
                             f"{', '.join(map(str, self.shape))}) = (batch, channels, *resolution)")
        if u.dtype != self.grid.dtype:
            raise ParameterError(f"the state has dtype {u.dtype}; this stepper was built for {self.grid.dtype} "
                                 "(build another stepper or cast the state)")
        if u.device.type != self.grid.device.type or (
                self.grid.device.index is not None and u.device.index != self.grid.device.index):
            raise ParameterError(f"the state is on device {u.device}; this stepper was built on device "
                                 f"{self.grid.device} (build another stepper or move the state)")

    def __call__(self, u: torch.Tensor) -> torch.Tensor:
        """Advance ``u`` by one time step ``dt``.

        Args:
            u: State ``(B, C, *resolution)`` in the stepper's dtype and on its device.

        Returns:
            The state at ``t + dt``, same shape.

        Raises:
            ShapeError: Wrong shape.
            ParameterError: Wrong dtype or device.
            NonFiniteError: Non-finite input when ``check_finite`` is set.
        """
        self.check_state(u)
        if self.check_finite and not bool(torch.isfinite(u).all()):
            raise NonFiniteError("the state contains NaN or Inf")
        return self.grid.to_physical(self.step_spectral(self.grid.to_spectral(u)))

    def repeat(self, u: torch.Tensor, steps: int) -> torch.Tensor:
        """Advance ``u`` by ``steps`` time steps, staying on the spectrum in between (two transforms in all).

        Args:
            u: State ``(B, C, *resolution)``.
            steps: Number of steps (>= 0).

        Returns:
            The state at ``t + steps * dt``.
        """
        if isinstance(steps, bool) or not isinstance(steps, int) or steps < 0:
            raise ParameterError(f"steps must be an int >= 0, got {steps!r}")
        self.check_state(u)
        u_hat = self.grid.to_spectral(u)
        for _ in range(steps):
            u_hat = self.step_spectral(u_hat)
        return self.grid.to_physical(u_hat)

    def rollout(self, u: torch.Tensor, steps: int, every: int = 1) -> torch.Tensor:
        """The trajectory ``u(t), u(t + every dt), ...`` over ``steps`` steps, stacked on a time axis.

        Args:
            u: State ``(B, C, *resolution)``.
            steps: Number of steps (>= 0).
            every: Keep every ``every``-th state (>= 1).

        Returns:
            Tensor ``(B, T, C, *resolution)`` with ``T = steps // every + 1`` (the initial state first).
        """
        if isinstance(every, bool) or not isinstance(every, int) or every < 1:
            raise ParameterError(f"every must be an int >= 1, got {every!r}")
        if isinstance(steps, bool) or not isinstance(steps, int) or steps < 0:
            raise ParameterError(f"steps must be an int >= 0, got {steps!r}")
        self.check_state(u)
        out = [u]
        u_hat = self.grid.to_spectral(u)
        for i in range(1, steps + 1):
            u_hat = self.step_spectral(u_hat)
            if i % every == 0:
                out.append(self.grid.to_physical(u_hat))
        return torch.stack(out, dim=1)

    def __repr__(self) -> str:
        return (f"{type(self).__name__}(order={self.order}, dt={self.dt}, channels={self.channels}, "
                f"grid={self.grid!r})")
