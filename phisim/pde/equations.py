"""Ready-made steppers for the PDEs commonly used to train and test learned simulators.

Every class is an :class:`~phisim.pde.etdrk.ETDRKStepper` (or, for the wave equation, an exact linear stepper
with the same interface). Each takes its physical parameters in the equation's natural units, then the grid
settings shared by all of them:

``ndim`` (1, 2 or 3 where the equation allows), ``domain`` (axis length(s)), ``resolution`` (points per axis),
``dt``, ``order`` (ETDRK order, 1-4; linear equations are integrated exactly), ``boundaries`` (``"periodic"``,
``"dirichlet"``, ``"neumann"``, one or one per axis; walls only where the equation's linear operator is
diagonal in the sine/cosine basis and its nonlinear term needs no first derivative), ``dtype``, ``device`` and
``dealias`` (2/3 rule by default).

The defaults give a well-resolved, non-trivial trajectory from a random initial state
(:func:`random_field`) and are a reasonable starting point for a dataset.
"""

from __future__ import annotations

import inspect
import math
from collections.abc import Sequence

import torch

from ..errors import BoundaryError, ParameterError
from .etdrk import ETDRKStepper
from .transforms import SpectralGrid

__all__ = [
    "Advection", "Diffusion", "Dispersion", "HyperDiffusion", "Wave", "Burgers", "KortewegDeVries",
    "KuramotoSivashinsky", "AllenCahn", "CahnHilliard", "FisherKPP", "SwiftHohenberg", "GrayScott",
    "NavierStokesVorticity", "KolmogorovFlow", "DecayingTurbulence", "EQUATIONS", "make_stepper", "random_field",
]



def _param(value, name: str, *, positive: bool = False, nonnegative: bool = False) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ParameterError(f"{name} must be a number, got {value!r}")
    v = float(value)
    if not math.isfinite(v):
        raise ParameterError(f"{name} must be finite, got {v}")
    if positive and v <= 0:
        raise ParameterError(f"{name} must be > 0, got {v}")
    if nonnegative and v < 0:
        raise ParameterError(f"{name} must be >= 0, got {v}")
    return v


def _per_axis(value, ndim: int, name: str, **kw) -> tuple[float, ...]:
    if isinstance(value, (list, tuple)):
        if len(value) != ndim:
            raise ParameterError(f"{name} has {len(value)} entries for a {ndim}-D grid")
        return tuple(_param(v, name, **kw) for v in value)
    return (_param(value, name, **kw),) * ndim


def _grid(ndim, domain, resolution, boundaries, dtype, device) -> SpectralGrid:
    return SpectralGrid(domain=domain, resolution=resolution, ndim=ndim, boundaries=boundaries, dtype=dtype,
                        device=device)


def _periodic_only(grid: SpectralGrid, equation: str, why: str) -> None:
    if grid.wall_axes:
        raise BoundaryError(f"{equation} needs periodic boundaries on every axis ({why}); got {grid.boundaries}")


class Advection(ETDRKStepper):
    """Linear advection ``u_t + c . grad u = 0`` (exact in time; periodic axes only).

    Args:
        ndim: Spatial dimensions.
        velocity: Advection velocity ``c`` (one number for all axes or one per axis).
        domain: Axis length(s) ``> 0``.
        resolution: Points per axis.
        dt: Time step.
        boundaries: Must be periodic (a first derivative is not diagonal in the sine/cosine basis).
        dtype: Field dtype.
        device: Torch device.
    """

    def __init__(self, ndim: int = 1, velocity: float | Sequence[float] = 1.0, *, domain: float = 1.0,
                 resolution: int = 128, dt: float = 0.01, boundaries: str = "periodic",
                 dtype: torch.dtype = torch.float32, device: torch.device | str = "cpu"):
        grid = _grid(ndim, domain, resolution, boundaries, dtype, device)
        _periodic_only(grid, "Advection", "u_x is odd in the wavenumber")
        self.velocity = _per_axis(velocity, grid.ndim, "velocity")
        vel = self.velocity
        super().__init__(grid, dt, lambda g: -sum(c * g.derivative(a) for a, c in enumerate(vel)), order=0)


class Diffusion(ETDRKStepper):
    """Linear (possibly anisotropic) diffusion ``u_t = sum_a nu_a d^2u/dx_a^2`` (exact in time).

    Args:
        ndim: Spatial dimensions.
        diffusivity: ``nu > 0`` (one number or one per axis).
        domain, resolution, dt, boundaries, dtype, device: Grid settings (walls allowed).
    """

    def __init__(self, ndim: int = 1, diffusivity: float | Sequence[float] = 0.01, *, domain: float = 1.0,
                 resolution: int = 128, dt: float = 0.01, boundaries: str = "periodic",
                 dtype: torch.dtype = torch.float32, device: torch.device | str = "cpu"):
        grid = _grid(ndim, domain, resolution, boundaries, dtype, device)
        self.diffusivity = _per_axis(diffusivity, grid.ndim, "diffusivity", positive=True)
        nu = self.diffusivity
        super().__init__(grid, dt, lambda g: -sum(n * k * k for n, k in zip(nu, g.wavenumbers)), order=0)


class Dispersion(ETDRKStepper):
    """Linear dispersion ``u_t = a sum_axes d^3u/dx^3`` (exact in time; periodic axes only).

    Args:
        ndim: Spatial dimensions.
        dispersivity: ``a`` (one number or one per axis).
        domain, resolution, dt, boundaries, dtype, device: Grid settings.
    """

    def __init__(self, ndim: int = 1, dispersivity: float | Sequence[float] = 0.01, *, domain: float = 1.0,
                 resolution: int = 128, dt: float = 0.01, boundaries: str = "periodic",
                 dtype: torch.dtype = torch.float32, device: torch.device | str = "cpu"):
        grid = _grid(ndim, domain, resolution, boundaries, dtype, device)
        _periodic_only(grid, "Dispersion", "u_xxx is odd in the wavenumber")
        self.dispersivity = _per_axis(dispersivity, grid.ndim, "dispersivity")
        disp = self.dispersivity
        super().__init__(grid, dt, lambda g: sum(a * g.derivative(i) ** 3 for i, a in enumerate(disp)), order=0)


class HyperDiffusion(ETDRKStepper):
    """Linear hyper-diffusion ``u_t = -nu Laplace^2 u`` (exact in time).

    Args:
        ndim: Spatial dimensions.
        hyperdiffusivity: ``nu > 0``.
        domain, resolution, dt, boundaries, dtype, device: Grid settings (walls allowed: the sine basis imposes
            ``u = u_xx = 0``, the cosine basis ``u_x = u_xxx = 0`` on the walls).
    """

    def __init__(self, ndim: int = 1, hyperdiffusivity: float = 1e-4, *, domain: float = 1.0, resolution: int = 128,
                 dt: float = 0.01, boundaries: str = "periodic", dtype: torch.dtype = torch.float32,
                 device: torch.device | str = "cpu"):
        grid = _grid(ndim, domain, resolution, boundaries, dtype, device)
        self.hyperdiffusivity = _param(hyperdiffusivity, "hyperdiffusivity", positive=True)
        nu = self.hyperdiffusivity
        super().__init__(grid, dt, lambda g: -nu * g.wavenumber_squared() ** 2, order=0)


class Wave(ETDRKStepper):
    """The wave equation ``u_tt = c^2 Laplace u`` as the first-order system ``(u, v = u_t)`` (exact in time).

    The state has two channels, displacement ``u`` and velocity ``v``. Per mode with frequency ``w = c |k|`` the
    step applies the exact propagator ``[[cos, sin/w], [-w sin, cos]](w dt)`` (``sin(w dt)/w -> dt`` at ``w = 0``):
    no dispersion or dissipation error. Walls are allowed (sine basis: fixed ends; cosine basis: free ends).

    Args:
        ndim: Spatial dimensions.
        speed: Wave speed ``c > 0``.
        domain, resolution, dt, boundaries, dtype, device: Grid settings.
    """

    def __init__(self, ndim: int = 1, speed: float = 1.0, *, domain: float = 1.0, resolution: int = 128,
                 dt: float = 0.01, boundaries: str = "periodic", dtype: torch.dtype = torch.float32,
                 device: torch.device | str = "cpu"):
        grid = _grid(ndim, domain, resolution, boundaries, dtype, device)
        self.speed = _param(speed, "speed", positive=True)
        super().__init__(grid, dt, None, order=0, channels=2)
        w = self.speed * grid.wavenumber_squared().sqrt()
        wt = w * self.dt
        cos = torch.cos(wt)
        sinc = torch.where(w > 0, torch.sin(wt) / w.clamp_min(1e-300), torch.full_like(w, self.dt))
        dtype = grid.complex_dtype if grid.spectral_is_complex else grid.dtype
        self._cos = cos.to(dtype)
        self._sinc = sinc.to(dtype)
        self._msin = (-w * torch.sin(wt)).to(dtype)

    def step_spectral(self, u_hat: torch.Tensor) -> torch.Tensor:
        """Exact step of ``(u, v)`` on the spectrum (see the class docstring)."""
        u, v = u_hat[:, 0], u_hat[:, 1]
        return torch.stack([self._cos * u + self._sinc * v, self._msin * u + self._cos * v], dim=1)


class Burgers(ETDRKStepper):
    """Viscous Burgers ``u_t + b (u . grad) u = nu Laplace u`` (periodic axes only).

    In 1-D the state is scalar and the convection is written ``-(b/2) (u^2)_x``; in ``n`` dimensions the state
    is the velocity vector (``C = n`` channels) and the convection is ``-b u_j d_j u_i``.

    Args:
        ndim: Spatial dimensions.
        viscosity: ``nu > 0`` (the default 0.02 keeps unit-amplitude shocks resolved at N = 256 on ``2 pi``: the
            spectrum at the dealiasing cut-off stays ~1e-4 of its peak).
        convection: ``b`` (1 for the standard equation).
        domain: Axis length(s) (default ``2 pi``).
        resolution: Points per axis.
        dt: Time step.
        order: ETDRK order 1-4.
        boundaries: Must be periodic.
        dtype, device, dealias: As for :class:`ETDRKStepper`.
    """

    def __init__(self, ndim: int = 1, viscosity: float = 0.02, convection: float = 1.0, *,
                 domain: float = 2 * math.pi, resolution: int = 256, dt: float = 0.01, order: int = 4,
                 boundaries: str = "periodic", dtype: torch.dtype = torch.float32,
                 device: torch.device | str = "cpu", dealias: float = 2.0 / 3.0):
        grid = _grid(ndim, domain, resolution, boundaries, dtype, device)
        _periodic_only(grid, "Burgers", "its convection term needs first derivatives")
        self.viscosity = _param(viscosity, "viscosity", positive=True)
        self.convection = _param(convection, "convection")
        d = grid.ndim
        self._grad = torch.stack(torch.broadcast_tensors(*[grid.derivative(a, grid.complex_dtype)
                                                           for a in range(d)]))  # (d, *spec)
        b = self.convection
        if d == 1:
            factor = (-0.5 * b) * self._grad[0]  # N = -(b/2) i k F[u^2], the factor folded into the coefficients

            def nonlinear(u_hat, g):
                u = g.to_physical(u_hat)
                return g.to_spectral(u * u)
        else:
            factor = -b
            frac = dealias if isinstance(dealias, (int, float)) and not isinstance(dealias, bool) \
                and 0 < dealias <= 1 else 2.0 / 3.0
            cut = grid.dealias_cut(frac)  # u_hat arrives truncated: the transform reads the kept columns only
            grad = self._grad[..., :cut].contiguous()

            def nonlinear(u_hat, g):
                # channels: u_i (d) and d_j u_i (d*d) in one inverse transform
                u_hat = u_hat[..., :cut]
                du_hat = grad[None, None] * u_hat[:, :, None]  # (B, i, j, *spec)
                both = torch.cat([u_hat, du_hat.flatten(1, 2)], dim=1)
                phys = g.to_physical(both)
                u, du = phys[:, :d], phys[:, d:].unflatten(1, (d, d))
                conv = (u[:, None] * du).sum(2)  # sum_j u_j d_j u_i
                return g.to_spectral(conv)
        nu = self.viscosity
        super().__init__(grid, dt, lambda g: nu * g.laplacian(), nonlinear, order=order, channels=d, dealias=dealias,
                         nonlinear_factor=factor)


class KortewegDeVries(ETDRKStepper):
    """Korteweg-de Vries ``u_t + a u u_x + delta u_xxx = nu u_xx - mu u_xxxx`` in 1-D (periodic).

    With the defaults ``a = 6``, ``delta = 1`` a soliton is ``u = (c/2) sech^2(sqrt(c)/2 (x - c t))``. ``nu`` and
    ``mu`` (default 0) add optional (hyper-)viscous damping of the shortest scales.

    Args:
        alpha: Nonlinear coefficient ``a``.
        delta: Dispersion coefficient.
        viscosity: ``nu >= 0``.
        hyperviscosity: ``mu >= 0``.
        domain: Length (default 40).
        resolution: Points (default 256).
        dt: Time step.
        order: ETDRK order 1-4.
        boundaries: Must be periodic.
        dtype, device, dealias: As for :class:`ETDRKStepper`.
    """

    def __init__(self, alpha: float = 6.0, delta: float = 1.0, viscosity: float = 0.0, hyperviscosity: float = 0.0,
                 *, domain: float = 40.0, resolution: int = 256, dt: float = 1e-3, order: int = 4,
                 boundaries: str = "periodic", dtype: torch.dtype = torch.float32, device: torch.device | str = "cpu",
                 dealias: float = 2.0 / 3.0):
        grid = _grid(1, domain, resolution, boundaries, dtype, device)
        _periodic_only(grid, "KdV", "its terms u u_x and u_xxx are odd in the wavenumber")
        self.alpha = _param(alpha, "alpha")
        self.delta = _param(delta, "delta")
        self.viscosity = _param(viscosity, "viscosity", nonnegative=True)
        self.hyperviscosity = _param(hyperviscosity, "hyperviscosity", nonnegative=True)
        a, de, nu, mu = self.alpha, self.delta, self.viscosity, self.hyperviscosity
        half_dx = (-0.5 * a) * grid.derivative(0, grid.complex_dtype)

        def linear(g):
            k2 = g.wavenumber_squared()
            return -de * g.derivative(0) ** 3 - nu * k2 - mu * k2 * k2

        def nonlinear(u_hat, g):
            u = g.to_physical(u_hat)
            return g.to_spectral(u * u)

        super().__init__(grid, dt, linear, nonlinear, order=order, dealias=dealias, nonlinear_factor=half_dx)


class KuramotoSivashinsky(ETDRKStepper):
    """Kuramoto-Sivashinsky ``u_t + Laplace u + Laplace^2 u + nonlinear = 0`` (periodic).

    ``form="conservative"`` (1-D only, the default there): nonlinear term ``u u_x`` (the form of the published
    Lyapunov spectra, e.g. ``lambda_1 ~ 0.043`` at ``L = 22``). ``form="combustion"`` (the default for 2-D/3-D):
    ``(1/2) |grad u|^2``; its spatial mean would drift, so the mean mode of the nonlinear term is removed
    (``remove_mean=True``), which leaves the dynamics of all other modes unchanged.

    Args:
        ndim: Spatial dimensions.
        form: ``"conservative"`` or ``"combustion"`` (default by ``ndim``).
        domain: Axis length(s) (default 64; 22 is the classic small chaotic box).
        resolution: Points per axis (default 256 in 1-D, 128 otherwise).
        dt: Time step.
        order: ETDRK order 1-4.
        remove_mean: Drop the mean mode of the combustion nonlinearity.
        boundaries: Must be periodic.
        dtype, device, dealias: As for :class:`ETDRKStepper`.
    """

    def __init__(self, ndim: int = 1, form: str | None = None, *, domain: float = 64.0, resolution: int | None = None,
                 dt: float = 0.1, order: int = 4, remove_mean: bool = True, boundaries: str = "periodic",
                 dtype: torch.dtype = torch.float32, device: torch.device | str = "cpu", dealias: float = 2.0 / 3.0):
        if resolution is None:
            resolution = 256 if ndim == 1 else 128
        grid = _grid(ndim, domain, resolution, boundaries, dtype, device)
        _periodic_only(grid, "Kuramoto-Sivashinsky", "its nonlinear term needs first derivatives")
        form = form or ("conservative" if grid.ndim == 1 else "combustion")
        if form not in ("conservative", "combustion"):
            raise ParameterError(f"form must be 'conservative' or 'combustion', got {form!r}")
        if form == "conservative" and grid.ndim != 1:
            raise ParameterError("the conservative form u u_x is 1-D; use form='combustion' in 2-D/3-D")
        self.form = form
        d = grid.ndim
        grads = [grid.derivative(a, grid.complex_dtype) for a in range(d)]
        if form == "conservative":
            factor = -0.5 * grads[0]  # N = -(1/2) i k F[u^2], the factor folded into the coefficients

            def nonlinear(u_hat, g):
                u = g.to_physical(u_hat)
                return g.to_spectral(u * u)
        else:
            frac = dealias if isinstance(dealias, (int, float)) and not isinstance(dealias, bool) \
                and 0 < dealias <= 1 else 2.0 / 3.0
            grad = torch.stack(torch.broadcast_tensors(*grads)) * grid.dealias_mask(frac)  # (d, *spec), masked
            cut = grid.dealias_cut(frac)  # the inverse transform reads only the kept columns of the half spectrum
            grad = grad[..., :cut].contiguous()
            keep = torch.ones(grid.spectral_shape, dtype=grid.complex_dtype, device=grid.device)
            if remove_mean:
                keep[(0,) * d] = 0.0
            factor = -0.5 * keep

            def nonlinear(u_hat, g):
                du = g.to_physical(grad * u_hat[..., :cut])  # (B, d, *res) since C == 1
                return g.to_spectral((du * du).sum(1, keepdim=True))

        def linear(g):
            k2 = g.wavenumber_squared()
            return k2 - k2 * k2

        super().__init__(grid, dt, linear, nonlinear, order=order, dealias=dealias, prefiltered=form == "combustion",
                         nonlinear_factor=factor)


class AllenCahn(ETDRKStepper):
    """Allen-Cahn ``u_t = D Laplace u + r (u - u^3)`` (phases ``u = +-1``, interface width ``~ sqrt(D / r)``).

    Args:
        ndim: Spatial dimensions.
        diffusivity: ``D > 0``.
        reactivity: ``r > 0``.
        domain, resolution, dt, order, boundaries, dtype, device, dealias: Grid/stepper settings (walls allowed).
    """

    def __init__(self, ndim: int = 1, diffusivity: float = 1e-3, reactivity: float = 1.0, *, domain: float = 1.0,
                 resolution: int = 128, dt: float = 0.05, order: int = 4, boundaries: str = "periodic",
                 dtype: torch.dtype = torch.float32, device: torch.device | str = "cpu", dealias: float = 2.0 / 3.0):
        grid = _grid(ndim, domain, resolution, boundaries, dtype, device)
        self.diffusivity = _param(diffusivity, "diffusivity", positive=True)
        self.reactivity = _param(reactivity, "reactivity", positive=True)
        dd, r = self.diffusivity, self.reactivity
        super().__init__(grid, dt, lambda g: dd * g.laplacian() + r, nonlinear_physical=lambda u: -r * u * u * u,
                         order=order, dealias=dealias)


class CahnHilliard(ETDRKStepper):
    """Cahn-Hilliard ``u_t = M Laplace(u^3 - u - gamma Laplace u)`` (mass-conserving phase separation).

    With periodic or Neumann (cosine basis) boundaries the mass ``int u`` is conserved exactly by the scheme.
    The nonlinear term ``M Laplace(u^3)`` is integrated explicitly, so ``dt`` must resolve its stiffness
    (roughly ``dt < 1 / (M k_max^2)`` with ``k_max`` the largest kept wavenumber; the defaults are stable).

    Args:
        ndim: Spatial dimensions.
        gamma: Interface energy ``gamma > 0`` (interface width ``~ sqrt(gamma)``).
        mobility: ``M > 0``.
        domain, resolution, dt, order, boundaries, dtype, device, dealias: Grid/stepper settings (walls allowed).
    """

    def __init__(self, ndim: int = 1, gamma: float = 2.5e-3, mobility: float = 1.0, *, domain: float = 1.0,
                 resolution: int = 64, dt: float = 1e-4, order: int = 4, boundaries: str = "periodic",
                 dtype: torch.dtype = torch.float32, device: torch.device | str = "cpu", dealias: float = 2.0 / 3.0):
        grid = _grid(ndim, domain, resolution, boundaries, dtype, device)
        self.gamma = _param(gamma, "gamma", positive=True)
        self.mobility = _param(mobility, "mobility", positive=True)
        gm, m = self.gamma, self.mobility
        lap = (m * grid.laplacian()).to(grid.complex_dtype if grid.spectral_is_complex else grid.dtype)

        def nonlinear(u_hat, g):
            u = g.to_physical(u_hat)
            return g.to_spectral(u * u * u)

        def linear(g):
            k2 = g.wavenumber_squared()
            return m * (k2 - gm * k2 * k2)

        super().__init__(grid, dt, linear, nonlinear, order=order, dealias=dealias, nonlinear_factor=lap)


class FisherKPP(ETDRKStepper):
    """Fisher-KPP ``u_t = D Laplace u + r u (1 - u)`` (travelling fronts with speed ``2 sqrt(D r)``).

    Args:
        ndim: Spatial dimensions.
        diffusivity: ``D > 0``.
        reactivity: ``r > 0``.
        domain, resolution, dt, order, boundaries, dtype, device, dealias: Grid/stepper settings (walls allowed).
    """

    def __init__(self, ndim: int = 1, diffusivity: float = 1e-3, reactivity: float = 10.0, *, domain: float = 1.0,
                 resolution: int = 128, dt: float = 5e-3, order: int = 4, boundaries: str = "periodic",
                 dtype: torch.dtype = torch.float32, device: torch.device | str = "cpu", dealias: float = 2.0 / 3.0):
        grid = _grid(ndim, domain, resolution, boundaries, dtype, device)
        self.diffusivity = _param(diffusivity, "diffusivity", positive=True)
        self.reactivity = _param(reactivity, "reactivity", positive=True)
        dd, r = self.diffusivity, self.reactivity
        super().__init__(grid, dt, lambda g: dd * g.laplacian() + r, nonlinear_physical=lambda u: -r * u * u,
                         order=order, dealias=dealias)


class SwiftHohenberg(ETDRKStepper):
    """Swift-Hohenberg ``u_t = r u - (k0^2 + Laplace)^2 u + g u^2 - u^3`` (stripes; hexagons for ``g > 0`` in 2-D).

    Args:
        ndim: Spatial dimensions.
        reactivity: ``r`` (the control parameter; patterns for ``r > 0``).
        critical_wavenumber: ``k0 > 0`` (pattern wavelength ``2 pi / k0``).
        quadratic: ``g``.
        domain: Axis length(s) (default ``20 pi``: ten wavelengths at ``k0 = 1``).
        resolution, dt, order, boundaries, dtype, device, dealias: Grid/stepper settings (walls allowed).
    """

    def __init__(self, ndim: int = 1, reactivity: float = 0.7, critical_wavenumber: float = 1.0,
                 quadratic: float = 0.0, *, domain: float = 20 * math.pi, resolution: int = 128, dt: float = 0.1,
                 order: int = 4, boundaries: str = "periodic", dtype: torch.dtype = torch.float32,
                 device: torch.device | str = "cpu", dealias: float = 2.0 / 3.0):
        grid = _grid(ndim, domain, resolution, boundaries, dtype, device)
        self.reactivity = _param(reactivity, "reactivity")
        self.critical_wavenumber = _param(critical_wavenumber, "critical_wavenumber", positive=True)
        self.quadratic = _param(quadratic, "quadratic")
        r, k0, gq = self.reactivity, self.critical_wavenumber, self.quadratic
        super().__init__(grid, dt, lambda g: r - (k0 * k0 - g.wavenumber_squared()) ** 2,
                         nonlinear_physical=lambda u: u * u * (gq - u), order=order, dealias=dealias)


class GrayScott(ETDRKStepper):
    """Gray-Scott reaction-diffusion (two channels ``u, v``; Pearson 1993 units).

    ``u_t = D_u Laplace u - u v^2 + F (1 - u)``, ``v_t = D_v Laplace v + u v^2 - (F + k) v``.

    Args:
        ndim: Spatial dimensions.
        feed: ``F > 0``.
        kill: ``k > 0``.
        diffusivity_u: ``D_u > 0``.
        diffusivity_v: ``D_v > 0``.
        domain: Axis length(s) (default 2.5, as in Pearson's patterns).
        resolution, dt, order, boundaries, dtype, device, dealias: Grid/stepper settings (walls allowed; Neumann is
            the usual choice).
    """

    def __init__(self, ndim: int = 2, feed: float = 0.04, kill: float = 0.06, diffusivity_u: float = 2e-5,
                 diffusivity_v: float = 1e-5, *, domain: float = 2.5, resolution: int = 128, dt: float = 1.0,
                 order: int = 4, boundaries: str = "periodic", dtype: torch.dtype = torch.float32,
                 device: torch.device | str = "cpu", dealias: float = 2.0 / 3.0):
        grid = _grid(ndim, domain, resolution, boundaries, dtype, device)
        self.feed = _param(feed, "feed", positive=True)
        self.kill = _param(kill, "kill", positive=True)
        self.diffusivity_u = _param(diffusivity_u, "diffusivity_u", positive=True)
        self.diffusivity_v = _param(diffusivity_v, "diffusivity_v", positive=True)
        f, k, du, dv = self.feed, self.kill, self.diffusivity_u, self.diffusivity_v

        def linear(g):
            lap = g.laplacian()
            return torch.stack([du * lap - f, dv * lap - (f + k)])

        def nonlinear(u):
            a, b = u[:, :1], u[:, 1:]
            r = a * b * b
            return torch.cat([f - r, r], dim=1)

        super().__init__(grid, dt, linear, nonlinear_physical=nonlinear, order=order, channels=2, dealias=dealias)


class NavierStokesVorticity(ETDRKStepper):
    """2-D incompressible Navier-Stokes in vorticity form on a periodic box.

    ``w_t + u . grad w = nu Laplace w - alpha w + f``, velocity ``u = (psi_y, -psi_x)`` from ``Laplace psi = -w``.
    The optional Kolmogorov forcing is the curl of the body force ``(A sin(k_f y), 0)``:
    ``f = -A k_f cos(k_f y)``. The state is the vorticity (one channel).

    Args:
        viscosity: ``nu > 0`` (``Re = 1/nu`` for unit velocity and length scales).
        drag: Linear drag ``alpha >= 0``.
        forcing: ``None`` or ``"kolmogorov"``.
        forcing_wavenumber: ``k_f`` (an integer number of periods over the domain for a periodic forcing).
        forcing_amplitude: ``A``.
        domain: Box length(s) (default ``2 pi``).
        resolution: Points per axis.
        dt: Time step (explicit in the convection: keep ``max|u| dt / dx`` below ~1).
        order: ETDRK order 1-4.
        boundaries: Must be periodic.
        dtype, device, dealias: As for :class:`ETDRKStepper`.
    """

    def __init__(self, viscosity: float = 1e-3, drag: float = 0.0, forcing: str | None = None,
                 forcing_wavenumber: int = 4, forcing_amplitude: float = 1.0, *, domain: float = 2 * math.pi,
                 resolution: int = 128, dt: float = 5e-3, order: int = 4, boundaries: str = "periodic",
                 dtype: torch.dtype = torch.float32, device: torch.device | str = "cpu", dealias: float = 2.0 / 3.0):
        grid = _grid(2, domain, resolution, boundaries, dtype, device)
        _periodic_only(grid, "Navier-Stokes (vorticity)", "the stream function/velocity coupling needs them")
        self.viscosity = _param(viscosity, "viscosity", positive=True)
        self.drag = _param(drag, "drag", nonnegative=True)
        if forcing not in (None, "kolmogorov"):
            raise ParameterError(f"forcing must be None or 'kolmogorov', got {forcing!r}")
        self.forcing = forcing
        self.forcing_wavenumber = _param(forcing_wavenumber, "forcing_wavenumber", positive=True)
        self.forcing_amplitude = _param(forcing_amplitude, "forcing_amplitude")
        cd = grid.complex_dtype
        dx, dy = grid.derivative(0, cd), grid.derivative(1, cd)
        k2 = grid.wavenumber_squared()
        inv = torch.where(k2 > 0, 1.0 / k2.clamp_min(1e-300), torch.zeros_like(k2)).to(grid.dtype)
        # spectra of (u, v, w_x, w_y) from w_hat: u = psi_y = dy w / k^2, v = -psi_x = -dx w / k^2
        ops = torch.stack(torch.broadcast_tensors(dy * inv, -dx * inv, dx, dy))  # (4, *spec)
        frac = dealias if isinstance(dealias, (int, float)) and not isinstance(dealias, bool) and 0 < dealias <= 1 \
            else 2.0 / 3.0
        # the input truncation and the sign of -u . grad w, folded into the operators: (-u, -v, w_x, w_y)
        sign = torch.tensor([-1.0, -1.0, 1.0, 1.0], dtype=torch.float64, device=grid.device).reshape(
            (4,) + (1,) * grid.ndim)
        ops_in = (ops * sign * grid.dealias_mask(frac)).to(cd)
        cut = grid.dealias_cut(frac)  # the transform reads only the kept columns of the half spectrum
        ops_in = ops_in[..., :cut].contiguous()
        force_hat = None
        if forcing == "kolmogorov":
            _, y = grid.coordinates(torch.float64)
            kf, amp = self.forcing_wavenumber, self.forcing_amplitude
            f = (-amp * kf * torch.cos(kf * y)).expand(grid.resolution)
            g64 = SpectralGrid(grid.domain, grid.resolution, dtype=torch.float64, device=grid.device)
            force_hat = g64.to_spectral(f.to(grid.device)).to(cd)
        self._ops = ops
        self._force_hat = force_hat

        def nonlinear(w_hat, g):
            phys = g.to_physical(ops_in * w_hat[..., :cut])  # (B, 4, *res) since C == 1
            mu, mv, wx, wy = phys.split(1, dim=1)
            out = g.to_spectral(torch.addcmul(mu * wx, mv, wy))  # -u . grad w
            return out if force_hat is None else out + force_hat

        nu, al = self.viscosity, self.drag
        super().__init__(grid, dt, lambda g: nu * g.laplacian() - al, nonlinear, order=order, dealias=dealias,
                         prefiltered=True)

    def velocity(self, w: torch.Tensor) -> torch.Tensor:
        """The velocity ``(u, v)`` of a vorticity field.

        Args:
            w: Vorticity ``(B, 1, Nx, Ny)``.

        Returns:
            Velocity ``(B, 2, Nx, Ny)``.
        """
        self.check_state(w)
        return self.grid.to_physical(self._ops[:2] * self.grid.to_spectral(w))


def KolmogorovFlow(viscosity: float = 1e-3, drag: float = 0.1, forcing_wavenumber: int = 4,
                   forcing_amplitude: float = 1.0, **kwargs) -> NavierStokesVorticity:
    """Forced 2-D turbulence (Kolmogorov flow) with the settings of the jax-cfd benchmarks (``Re = 1000``).

    Args:
        viscosity: ``nu`` (default 1e-3).
        drag: Linear drag (default 0.1).
        forcing_wavenumber: ``k_f`` (default 4).
        forcing_amplitude: ``A`` (default 1).
        **kwargs: Grid/stepper settings passed to :class:`NavierStokesVorticity`.

    Returns:
        The stepper.
    """
    return NavierStokesVorticity(viscosity, drag, "kolmogorov", forcing_wavenumber, forcing_amplitude, **kwargs)


def DecayingTurbulence(viscosity: float = 1e-3, **kwargs) -> NavierStokesVorticity:  # noqa: N802
    """Freely decaying 2-D turbulence (no forcing, no drag).

    Args:
        viscosity: ``nu`` (default 1e-3).
        **kwargs: Grid/stepper settings passed to :class:`NavierStokesVorticity`.

    Returns:
        The stepper.
    """
    return NavierStokesVorticity(viscosity, 0.0, None, **kwargs)


#: Equation names accepted by :func:`make_stepper`.
EQUATIONS = {
    "advection": Advection, "diffusion": Diffusion, "dispersion": Dispersion, "hyper_diffusion": HyperDiffusion,
    "wave": Wave, "burgers": Burgers, "kdv": KortewegDeVries, "kuramoto_sivashinsky": KuramotoSivashinsky,
    "allen_cahn": AllenCahn, "cahn_hilliard": CahnHilliard, "fisher_kpp": FisherKPP,
    "swift_hohenberg": SwiftHohenberg, "gray_scott": GrayScott, "navier_stokes": NavierStokesVorticity,
    "kolmogorov": KolmogorovFlow, "decaying_turbulence": DecayingTurbulence,
}


def make_stepper(name: str, **kwargs) -> ETDRKStepper:
    """Build an equation's stepper by name (see :data:`EQUATIONS`).

    Args:
        name: Equation name, e.g. ``"kuramoto_sivashinsky"`` (case-insensitive; ``-`` and spaces read as ``_``).
        **kwargs: The equation's parameters and grid settings.

    Returns:
        The stepper.

    Raises:
        ParameterError: Unknown name (the message lists the known ones) or a parameter the equation does not take
            (e.g. ``order`` for the linear equations, which are integrated exactly).
    """
    key = str(name).strip().lower().replace("-", "_").replace(" ", "_")
    if key not in EQUATIONS:
        raise ParameterError(f"unknown equation {name!r}; known: {', '.join(sorted(EQUATIONS))}")
    factory = EQUATIONS[key]
    target = NavierStokesVorticity if factory in (KolmogorovFlow, DecayingTurbulence) else factory
    accepted = set(inspect.signature(factory).parameters) | set(inspect.signature(target).parameters)
    accepted.discard("kwargs")
    unknown = sorted(set(kwargs) - accepted)
    if unknown:
        raise ParameterError(f"{key} does not take {', '.join(unknown)}; its parameters: {', '.join(sorted(accepted))}")
    return factory(**kwargs)


def random_field(stepper: ETDRKStepper, batch: int = 1, *, amplitude: float = 1.0, max_wavenumber: float = 4.0,
                 mean: float | Sequence[float] = 0.0, seed: int | None = None) -> torch.Tensor:
    """A smooth random initial state for ``stepper``: Gaussian noise low-passed to the modes ``|m| <= max_wavenumber``.

    ``m`` counts periods (periodic axes) or half-periods (wall axes) over the domain. Each sample and channel is
    scaled to the standard deviation ``amplitude`` (mean removed), then ``mean`` is added.

    Args:
        stepper: The stepper whose grid, channels, dtype and device the state takes.
        batch: Number of samples.
        amplitude: Standard deviation of each sample and channel.
        max_wavenumber: Largest mode number kept (``> 0``).
        mean: Mean value(s) (one or one per channel).
        seed: Seed of a private generator (``None``: torch's global generator).

    Returns:
        Tensor ``(batch, C, *resolution)``.
    """
    _param(amplitude, "amplitude", nonnegative=True)
    _param(max_wavenumber, "max_wavenumber", positive=True)
    if isinstance(batch, bool) or not isinstance(batch, int) or batch < 1:
        raise ParameterError(f"batch must be an int >= 1, got {batch!r}")
    grid = stepper.grid
    gen = torch.Generator().manual_seed(seed) if seed is not None else None
    noise = torch.randn((batch, stepper.channels) + grid.resolution, generator=gen, dtype=torch.float64)
    g64 = SpectralGrid(grid.domain, grid.resolution, boundaries=grid.boundaries, dtype=torch.float64)
    keep = torch.ones(g64.spectral_shape, dtype=torch.float64)
    for a, k in enumerate(g64.wavenumbers):
        unit = (2 * math.pi if grid.boundaries[a] == "periodic" else math.pi) / grid.domain[a]
        keep = keep * (k.abs() / unit <= max_wavenumber)
    u = g64.to_physical(g64.to_spectral(noise) * keep)
    dims = tuple(range(2, u.dim()))
    u = u - u.mean(dims, keepdim=True)
    u = amplitude * u / u.std(dims, keepdim=True).clamp_min(1e-300)
    means = torch.as_tensor(mean, dtype=torch.float64).reshape(-1)
    if means.numel() not in (1, stepper.channels):
        raise ParameterError(f"mean has {means.numel()} entries for {stepper.channels} channels")
    u = u + means.reshape((1, -1) + (1,) * grid.ndim)
    return u.to(device=grid.device, dtype=grid.dtype)
