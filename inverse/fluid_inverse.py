"""E5: the incompressible-fluid marker pair (forward simulation, reverse-simulation local inverse), problem.

Paper: Holl, Koltun, Thuerey, "Physical Gradients for Deep Learning", section 3.4 and appendix B.4
(``EXPERIMENTS.md``, E5). The state ``x`` is the initial velocity ``v0`` at the cell centres
``(B, 2, nx, ny)`` (the network output), ``y`` the marker ``m_t`` after ``t = steps * dt`` ``(B, nx, ny)``.
The initial marker ``m0`` is a per-sample parameter of the operator.

Forward (:class:`FluidMarkerOperator`): ``v0`` is resampled to the MAC faces (average of the two adjacent
cells), projected to be divergence-free (as the reference does before simulating a prediction), and then
``steps`` E5 steps (:func:`inverse.fluid_scene.e5_step`: MacCormack self-advection, projection, energy rescale,
MacCormack marker advection) carry ``m0`` to ``m_t``.

Local inverse (the reference's ``estimate_v0``): the solution is assumed to lie on the low-dimensional prior
manifold "uniform velocity + one Gaussian vortex at the domain centre c"
``v(r) = u + s exp(-|r - c|^2 / (2 sigma^2)) (-(r - c)_y, (r - c)_x)``.

* ``u = (c - com(m0)) / t``: the uniform velocity that carries the centre of mass of ``m0`` to the domain
  centre at time ``t`` (fixed by the data, as in the data generator);
* ``s = s0 + ds``: ``s0 = mean_cells((r - c) x x0) / C`` projects the guess ``x0`` on the vortex
  (``C = mean_cells(f(r) |r - c|^2)``, 120.52 for E5, the reference hard-codes 120.5; the uniform part
  contributes nothing on the symmetric grid), and ``ds`` comes from a reverse simulation: starting from the
  target marker ``y*`` with the negated final velocity of the forward run of ``x0``, ``steps`` steps are
  simulated (time reversal). At each reverse step (and at ``t`` itself) the centre of mass of the forward
  marker ``com_f`` is compared with that of the reverse marker ``com_r`` at the same time ``tau``:
  ``d = (com_f - com_r) x (com_r - p(tau))`` with the vortex position ``p(tau) = c + u tau``; ``d`` is the
  torque-like misfit: a too strong counter-clockwise vortex turns the forward marker further around ``p``
  and makes ``d`` negative. ``ds = delta_scale * mean(d)`` with the reference's ``delta_scale = 1e-3`` (for
  other domain sizes scaled by ``(128 / size)^2``, since ``d`` grows like ``size^2``).

The result ``x~ = u + vortex(s)`` ignores the small-scale part of ``v0``, which limits the achievable
accuracy (the paper says so; appendix B.4).

Deviations from the reference code (``tum-pbs/SIP``, ``fluid/fluid_base.py``), all documented here:

* the reference places the vortex at reverse step ``i`` at ``c + u (steps - 1 - i)``, without the factor
  ``dt`` (so up to ``4x`` too far along ``u``, while its first entry at ``tau = t`` uses ``c + u t``); we use
  ``c + u tau`` throughout. ``reference_vortex_track=True`` reproduces the reference.
* the reference's ground-truth simulation runs on a centred velocity without the initial projection; here the
  ground truth ``y* = P(x*)`` uses the same operator as the predictions (staggered, projected), so ``x*``
  is an exact solution.
* the fill fraction is drawn per sample (the reference draws one per batch) and exactly
  ``round(f * cells)`` cells inside the box are marked (the reference marks the top fraction of
  ``noise * box`` over the whole domain and then masks with the box, which caps the fill at the positive part
  of the noise inside the box).

Objective (:func:`frequency_loss`, PhiFlow's ``frequency_loss(m - m*, n=1, frequency_falloff=80,
ignore_mean=True)``): per sample ``sum_k sqrt(max(|F(D - mean D)(k) w(k)|^2, 1e-5))`` with the unnormalised
2-D FFT ``F``, ``D = y - y*``, ``w(k) = exp(-1/2 |k|^2 falloff^2)`` and ``k`` the numpy ``fftfreq``
wavenumbers in cycles per cell (``|k| = 1/64`` for the lowest mode of E5). The reference's physical gradient
does not take a Newton step of this loss: the local inverse is given the target ``y*`` itself, which is what
``QuadraticLoss()`` (identity) with ``eta = 1`` yields in :func:`inverse.physgrad.physical_update`.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import torch
from torch import nn

from inverse.fluid_scene import E5_DT, E5_STEPS, e5_grid, e5_step
from phisim.errors import ParameterError, ShapeError
from phisim.field import CenteredGrid, StaggeredGrid
from phisim.fluid import make_incompressible
from phisim.grid import Grid
from phisim.simulate.noise import gaussian_vortex, spectral_noise

from .nets import UNet
from .operators import PhysicsOperator
from .problem import Batch, Method, Problem

__all__ = [
    "FluidMarkerOperator",
    "FluidProblem",
    "frequency_weights",
    "frequency_loss",
    "center_of_mass",
    "vortex_velocity",
    "vortex_strength",
]

#: Reference falloff of the frequency loss for 64 cells per axis.
E5_FREQUENCY_FALLOFF = 80.0
#: Reference scale of the vortex-strength update.
E5_DELTA_SCALE = 1e-3


# ---- helpers ---------------------------------------------------------------------------------------------


def _check_marker(marker: torch.Tensor, name: str) -> None:
    if marker.ndim != 3:
        raise ShapeError(f"{name} must have shape (B, nx, ny), got {tuple(marker.shape)}")


def center_of_mass(marker: torch.Tensor, grid: Grid) -> torch.Tensor:
    """Centre of mass ``sum(m r) / sum(m)`` of scalar fields over the cell centres (no periodic wrapping).

    Args:
        marker: ``(B, nx, ny)`` values on ``grid``.
        grid: The 2-D grid.

    Returns:
        ``(B, 2)`` physical coordinates; samples whose total mass is not positive get the domain centre.

    Raises:
        ShapeError: For a marker that is not ``(B, *grid.resolution)``.
    """
    _check_marker(marker, "marker")
    if tuple(marker.shape[1:]) != tuple(grid.resolution):
        raise ShapeError(f"marker has spatial shape {tuple(marker.shape[1:])}, the grid {grid.resolution}")
    points = grid.cell_centers(marker.dtype, marker.device)  # (nx, ny, 2)
    mass = marker.sum(dim=(1, 2))
    moment = torch.einsum("bij,ijd->bd", marker, points)
    centre = torch.tensor(
        [lo + 0.5 * s for (lo, _), s in zip(grid.bounds, grid.size)], dtype=marker.dtype, device=marker.device
    )
    ok = mass > 0
    safe = torch.where(ok, mass, torch.ones_like(mass))
    return torch.where(ok[:, None], moment / safe[:, None], centre.expand_as(moment))


def _domain_centre(grid: Grid, dtype, device) -> torch.Tensor:
    return torch.tensor(
        [lo + 0.5 * s for (lo, _), s in zip(grid.bounds, grid.size)], dtype=dtype, device=device
    )


def _cross(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """z-component of the 2-D cross product over the last axis."""
    return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]


def vortex_velocity(
    grid: Grid, strength: torch.Tensor, sigma: float, centre: torch.Tensor | None = None
) -> torch.Tensor:
    """Centred velocity of one Gaussian vortex per sample (the prior's vortex; PhiFlow's ``AngularVelocity``).

    ``v(r) = s exp(-|r - c|^2 / (2 sigma^2)) (-(r - c)_y, (r - c)_x)``, no periodic wrapping.

    Args:
        grid: The 2-D grid.
        strength: ``(B,)`` vortex strengths ``s``.
        sigma: Falloff length.
        centre: ``(2,)`` vortex centre (default: the domain centre).

    Returns:
        ``(B, 2, nx, ny)``.
    """
    c = _domain_centre(grid, strength.dtype, strength.device) if centre is None else centre
    v = gaussian_vortex(
        grid,
        c,
        strength,
        sigma,
        staggered=False,
        batch_size=strength.shape[0],
        dtype=strength.dtype,
        device=strength.device,
    )
    return v.values


def _vortex_norm(grid: Grid, sigma: float, dtype, device) -> torch.Tensor:
    """``C = mean_cells(f(r) |r - c|^2)`` with ``f = exp(-|r - c|^2 / (2 sigma^2))``."""
    r = grid.cell_centers(torch.float64, device) - _domain_centre(grid, torch.float64, device)
    d2 = (r**2).sum(-1)
    return (torch.exp(-0.5 * d2 / sigma**2) * d2).mean().to(dtype)


def vortex_strength(velocity: torch.Tensor, grid: Grid, sigma: float) -> torch.Tensor:
    """Projection of a centred velocity onto the centred Gaussian vortex: ``mean((r - c) x v) / C``.

    Exact for a pure vortex of :func:`vortex_velocity` (``C = mean(f |r - c|^2)``); a uniform velocity adds
    nothing on a grid symmetric about its centre.

    Args:
        velocity: ``(B, 2, nx, ny)`` at the cell centres of ``grid``.
        grid: The 2-D grid.
        sigma: The vortex falloff length.

    Returns:
        ``(B,)``.
    """
    r = grid.cell_centers(velocity.dtype, velocity.device) - _domain_centre(
        grid, velocity.dtype, velocity.device
    )
    ang = r[..., 0] * velocity[:, 1] - r[..., 1] * velocity[:, 0]
    return ang.mean(dim=(1, 2)) / _vortex_norm(grid, sigma, velocity.dtype, velocity.device)


def frequency_weights(
    resolution: Sequence[int],
    falloff: float = E5_FREQUENCY_FALLOFF,
    dtype: torch.dtype | None = None,
    device=None,
) -> torch.Tensor:
    """``w(k) = exp(-1/2 |k|^2 falloff^2)`` with ``k`` in cycles per cell (numpy ``fftfreq``), FFT layout.

    ``QuadraticLoss(weights=frequency_weights(...)**2, transform=FourierTransform(2))`` is the squared
    (``n = 2``) variant of :func:`frequency_loss` up to the FFT normalisation and the mean removal.

    Args:
        resolution: ``(nx, ny)``.
        falloff: The falloff (80 in E5 at 64 cells).
        dtype: Floating dtype (default: torch's default).
        device: Device.

    Returns:
        ``(nx, ny)``.

    Raises:
        ParameterError: For a non-positive or non-finite falloff.
    """
    if not (math.isfinite(falloff) and falloff > 0):
        raise ParameterError(f"falloff must be finite and > 0, got {falloff}")
    dtype = dtype or torch.get_default_dtype()
    k2 = torch.zeros(tuple(resolution), dtype=torch.float64, device=device)
    for a, n in enumerate(resolution):
        view = [1] * len(resolution)
        view[a] = n
        k2 = k2 + torch.fft.fftfreq(n, dtype=torch.float64, device=device).reshape(view) ** 2
    return torch.exp(-0.5 * k2 * falloff**2).to(dtype)


def frequency_loss(
    y: torch.Tensor,
    y_target: torch.Tensor,
    falloff: float = E5_FREQUENCY_FALLOFF,
    *,
    n: int = 1,
    threshold: float = 1e-5,
    ignore_mean: bool = True,
) -> torch.Tensor:
    """Per-sample frequency-weighted marker mismatch of E5 (PhiFlow's ``frequency_loss``, ``n = 1``).

    ``L = sum_k a_k^n / n`` with ``a_k = sqrt(max(|F(D)(k) w(k)|^2, threshold))``, ``D = y - y*`` (minus its
    mean when ``ignore_mean``), ``F`` the unnormalised 2-D FFT over the last two axes and ``w`` from
    :func:`frequency_weights`. The threshold keeps the gradient of ``|.|`` finite at zero.

    Args:
        y: ``(B, nx, ny)``.
        y_target: ``(B, nx, ny)``.
        falloff: Weight falloff (80 in E5 at 64 cells).
        n: 1 (the E5 loss) or 2.
        threshold: Floor of the squared weighted amplitudes.
        ignore_mean: Remove the mean of ``D`` (the ``k = 0`` mode) first.

    Returns:
        ``(B,)``, differentiable.

    Raises:
        ShapeError: For mismatched or non-3-D inputs.
        ParameterError: For ``n`` not in ``(1, 2)``, a negative threshold or a bad falloff.
    """
    if tuple(y.shape) != tuple(y_target.shape):
        raise ShapeError(f"y {tuple(y.shape)} and y_target {tuple(y_target.shape)} differ in shape")
    _check_marker(y, "y")
    if n not in (1, 2):
        raise ParameterError(f"n must be 1 or 2, got {n!r}")
    if not (math.isfinite(threshold) and threshold >= 0):
        raise ParameterError(f"threshold must be finite and >= 0, got {threshold}")
    d = y - y_target.to(y.dtype)
    if ignore_mean:
        d = d - d.mean(dim=(1, 2), keepdim=True)
    w = frequency_weights(tuple(y.shape[1:]), falloff, dtype=y.dtype, device=y.device)
    c = torch.fft.fft2(d) * w
    a2 = c.real**2 + c.imag**2
    a = torch.sqrt(torch.clamp(a2, min=threshold))
    return (a**n).sum(dim=(1, 2)) / n


# ---- the operator ----------------------------------------------------------------------------------------


@dataclass
class _Trajectory:
    x: torch.Tensor  # the initial velocity simulated (detached)
    marker: torch.Tensor  # final marker (B, nx, ny)
    coms: list[torch.Tensor]  # centres of mass at steps 0..S, each (B, 2)
    velocity: StaggeredGrid  # final velocity


class FluidMarkerOperator(PhysicsOperator):
    """E5 pair: initial velocity -> final marker, with the reverse-simulation prior-fit local inverse.

    See the module docstring for the forward process, the local inverse and the deviations from the reference.

    Args:
        marker0: Initial markers ``(B, nx, ny)`` (one per sample; the grid is
            :func:`inverse.fluid_scene.e5_grid`, ``dx = 2``, periodic).
        steps: Simulation steps (8 in E5).
        dt: Time step (0.25 in E5).
        sigma: Falloff length of the prior's vortex (default ``20 * size / 128``: 20 in E5).
        project_initial: Project the staggered initial velocity before simulating (the reference does).
        delta_scale: Scale of the vortex-strength update (default: the reference's ``1e-3`` times
            ``(128 / size)^2``, which keeps the relative step independent of the domain size: the misfit ``d``
            grows like ``size^2``).
        reference_vortex_track: Use the reference's vortex positions ``c + u (steps - 1 - i)`` in the reverse
            pass instead of ``c + u tau`` (see the module docstring).

    Raises:
        ShapeError: ``marker0`` is not ``(B, nx, ny)``.
        ParameterError: Non-positive ``steps``/``dt``/``sigma`` or a non-finite ``delta_scale``.
    """

    def __init__(
        self,
        marker0: torch.Tensor,
        *,
        steps: int = E5_STEPS,
        dt: float = E5_DT,
        sigma: float | None = None,
        project_initial: bool = True,
        delta_scale: float | None = None,
        reference_vortex_track: bool = False,
    ):
        m = torch.as_tensor(marker0)
        if not m.is_floating_point():
            m = m.to(torch.get_default_dtype())
        _check_marker(m, "marker0")
        if isinstance(steps, bool) or int(steps) != steps or steps < 1:
            raise ParameterError(f"steps must be a positive integer, got {steps!r}")
        if not (math.isfinite(dt) and dt > 0):
            raise ParameterError(f"dt must be finite and > 0, got {dt}")
        self.marker0 = m.detach()
        self.grid = e5_grid(tuple(m.shape[1:]))
        self.steps = int(steps)
        self.dt = float(dt)
        self.sigma = 20.0 * self.grid.size[0] / 128.0 if sigma is None else float(sigma)
        if not (math.isfinite(self.sigma) and self.sigma > 0):
            raise ParameterError(f"sigma must be finite and > 0, got {sigma}")
        self.project_initial = bool(project_initial)
        if delta_scale is None:
            delta_scale = E5_DELTA_SCALE * (128.0 / self.grid.size[0]) ** 2
        if not math.isfinite(delta_scale):
            raise ParameterError(f"delta_scale must be finite, got {delta_scale}")
        self.delta_scale = float(delta_scale)
        self.reference_vortex_track = bool(reference_vortex_track)
        self._cache: _Trajectory | None = None

    @property
    def time(self) -> float:
        """Simulated time ``steps * dt``."""
        return self.steps * self.dt

    def select(self, index: slice | torch.Tensor | Sequence[int]) -> FluidMarkerOperator:
        """The operator for the samples ``index`` (restricts ``marker0``).

        Args:
            index: A slice or integer index tensor into the batch dimension.

        Returns:
            A new :class:`FluidMarkerOperator` with the same settings.
        """
        if not isinstance(index, slice):
            index = torch.as_tensor(index)
            if index.dtype != torch.bool:
                index = index.long()
        return FluidMarkerOperator(
            self.marker0[index],
            steps=self.steps,
            dt=self.dt,
            sigma=self.sigma,
            project_initial=self.project_initial,
            delta_scale=self.delta_scale,
            reference_vortex_track=self.reference_vortex_track,
        )

    def output_shape(self, x_shape: Sequence[int]) -> torch.Size:
        """``(B, nx, ny)`` for ``x`` of shape ``(B, 2, nx, ny)``.

        Args:
            x_shape: Shape of ``x``.

        Returns:
            The marker shape.
        """
        return torch.Size((x_shape[0],) + tuple(self.marker0.shape[1:]))

    def _check_x(self, x: torch.Tensor, name: str) -> None:
        expected = (self.marker0.shape[0], 2) + tuple(self.marker0.shape[1:])
        if tuple(x.shape) != expected:
            raise ShapeError(
                f"{name} must be the centred initial velocity of shape {expected} (the operator holds "
                f"{self.marker0.shape[0]} markers of {tuple(self.marker0.shape[1:])}), got "
                f"{tuple(x.shape)}"
            )

    def initial_velocity(self, x: torch.Tensor) -> StaggeredGrid:
        """The staggered (and, with ``project_initial``, projected) velocity the simulation starts from.

        Args:
            x: ``(B, 2, nx, ny)`` centred velocity.

        Returns:
            The MAC velocity (differentiable).
        """
        self._check_x(x, "x")
        v = CenteredGrid(x, self.grid, "periodic").to_staggered()
        if self.project_initial:
            v, _ = make_incompressible(v)
        return v

    def _simulate(self, x: torch.Tensor, record: bool) -> _Trajectory:
        marker = CenteredGrid(self.marker0.to(device=x.device, dtype=x.dtype), self.grid, "periodic")
        velocity = self.initial_velocity(x)
        coms = [center_of_mass(marker.values.detach(), self.grid)] if record else []
        pressure = None
        for _ in range(self.steps):
            marker, velocity, pressure = e5_step(marker, velocity, pressure, self.dt)
            if record:
                coms.append(center_of_mass(marker.values.detach(), self.grid))
        return _Trajectory(x.detach(), marker.values, coms, velocity)

    def _forward(self, x: torch.Tensor) -> torch.Tensor:
        self._check_x(x, "x")
        if torch.is_grad_enabled() and x.requires_grad:
            return self._simulate(x, record=False).marker
        traj = self._simulate(x, record=True)
        self._cache = traj  # reused by the local inverse of the same x (physical_update runs forward first)
        return traj.marker

    def _trajectory(self, x0: torch.Tensor) -> _Trajectory:
        c = self._cache
        if (
            c is not None
            and c.x.shape == x0.shape
            and c.x.dtype == x0.dtype
            and c.x.device == x0.device
            and torch.equal(c.x, x0)
        ):
            return c
        with torch.no_grad():
            traj = self._simulate(x0, record=True)
        self._cache = traj
        return traj

    def prior_velocity(self, strength: torch.Tensor, dtype=None, device=None) -> torch.Tensor:
        """The prior ``u + vortex(strength)`` with ``u = (c - com(m0)) / t``, centred ``(B, 2, nx, ny)``.

        Args:
            strength: ``(B,)`` vortex strengths.
            dtype: Result dtype (default ``strength``'s).
            device: Result device (default ``strength``'s).

        Returns:
            The centred velocity.
        """
        dtype = dtype or strength.dtype
        device = device or strength.device
        u = self.uniform_velocity(dtype, device)
        vort = vortex_velocity(self.grid, strength.to(device=device, dtype=dtype), self.sigma)
        return vort + u[:, :, None, None]

    def uniform_velocity(self, dtype=None, device=None) -> torch.Tensor:
        """``u = (c - com(m0)) / t`` per sample, ``(B, 2)``.

        Args:
            dtype: Result dtype (default the marker's).
            device: Result device (default the marker's).

        Returns:
            The uniform velocities.
        """
        m0 = self.marker0.to(device=device or self.marker0.device, dtype=dtype or self.marker0.dtype)
        c = _domain_centre(self.grid, m0.dtype, m0.device)
        return (c - center_of_mass(m0, self.grid)) / self.time

    def strength_update(self, y_target: torch.Tensor, x0: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The prior fit ``(s0, ds)``: ``s0`` the vortex strength of ``x0``, ``ds`` the reverse-pass update.

        Args:
            y_target: ``(B, nx, ny)`` target markers ``m_t``.
            x0: ``(B, 2, nx, ny)`` the current guess.

        Returns:
            ``(s0, ds)``, each ``(B,)``.
        """
        self._check_x(x0, "x0")
        traj = self._trajectory(x0)
        grid, dt, S = self.grid, self.dt, self.steps
        with torch.no_grad():
            s0 = vortex_strength(x0, grid, self.sigma)
            c = _domain_centre(grid, x0.dtype, x0.device)
            u = self.uniform_velocity(x0.dtype, x0.device)
            target = y_target.to(dtype=x0.dtype)
            rev_com = center_of_mass(target, grid)
            d = [_cross(traj.coms[S] - rev_com, rev_com - (c + u * self.time))]
            marker = CenteredGrid(target, grid, "periodic")
            velocity = -traj.velocity
            pressure = None
            for i in range(S):
                marker, velocity, pressure = e5_step(marker, velocity, pressure, dt)
                rev_com = center_of_mass(marker.values, grid)
                tau = (S - 1 - i) if self.reference_vortex_track else (S - 1 - i) * dt
                d.append(_cross(traj.coms[S - 1 - i] - rev_com, rev_com - (c + u * tau)))
            ds = torch.stack(d, 0).mean(0) * self.delta_scale
        return s0, ds

    def _local_inverse(
        self, y_target: torch.Tensor, x0: torch.Tensor, y0: torch.Tensor | None
    ) -> torch.Tensor:
        self._check_x(x0, "x0")
        s0, ds = self.strength_update(y_target, x0)
        return self.prior_velocity(s0 + ds, x0.dtype, x0.device)


# ---- the problem -----------------------------------------------------------------------------------------


@dataclass
class FluidProblem(Problem):
    """E5: infer the initial velocity from the markers ``(m0, m_t)`` (see ``EXPERIMENTS.md``).

    Data on the fly (lengths scale with the domain size ``L = 2 * resolution``; E5: ``L = 128``): a box of
    ``56/128 L`` at a centre uniform in ``[L/4, 3L/4]^2``; the marker marks the ``round(f * cells)`` box cells
    of largest spectral noise (:func:`phisim.simulate.noise.spectral_noise`, the E3/PhiFlow recipe), ``f`` uniform in
    ``fill_range`` per sample; ``v0* = u + vortex(s) + 0.1 * noise`` with ``u = (c - com(m0)) / t``, ``s``
    uniform in ``strength_range``, the vortex falloff ``sigma = 20/128 L``, and unit-std spectral noise per
    component; ``m_t = P(v0*)``. Network: U-net 5 levels, 16 filters, circular padding, input
    ``(m0, m_t)``, output ``v0`` at the cell centres (49,570 parameters). Methods: ``adam`` (Adam through the
    simulation on the frequency loss, batch mean) and ``pg`` (Adam on ``1/2 |v0 - v~|^2`` with the
    reverse-simulation local inverse). Metric: ``sum_cells |v0 - v0*|_2`` per sample (the reference's
    ``l1_loss(vec_abs(v - v*))``), batch mean. The frequency-loss falloff scales with the resolution
    (``80 * nx / 64``) so that the weights depend on the physical wavenumber only.

    Attributes:
        resolution: Cells per axis (multiples of 16; E5: 64x64 on a 128x128 domain).
        steps: Simulation steps (8).
        dt: Time step (0.25).
        fill_range: Range of the marker's fill fraction of the domain (0.05 to 0.15).
        strength_range: Range of the vortex strength (-2 to 2).
        noise_amplitude: Factor of the small-scale noise velocity (0.1).
        lr: Adam learning rate of both methods (0.005).
        reference_vortex_track: Passed to :class:`FluidMarkerOperator`.
        delta_factor: Factor on the operator's vortex-strength update scale (1: the reference's
            ``1e-3 (128 / L)^2``; larger values move the strength further towards the truth per step).
    """

    name: str = "fluid"
    batch_size: int = 64
    reduction: str = "mean"
    loss_name: str = "marker frequency loss per sample"
    metric_name: str = "v0 error per sample (sum over cells of |v0−v0*|₂)"
    resolution: tuple[int, int] = (64, 64)
    steps: int = E5_STEPS
    dt: float = E5_DT
    fill_range: tuple[float, float] = (0.05, 0.15)
    strength_range: tuple[float, float] = (-2.0, 2.0)
    noise_amplitude: float = 0.1
    lr: float = 0.005
    reference_vortex_track: bool = False
    delta_factor: float = 1.0

    def __post_init__(self):
        self.resolution = tuple(int(n) for n in self.resolution)
        if len(self.resolution) != 2 or any(n < 16 or n % 16 for n in self.resolution):
            raise ParameterError(
                f"resolution must be two multiples of 16 (the 5-level U-net), got {self.resolution}"
            )
        lo, hi = self.fill_range
        if not (0 < lo <= hi <= 1):
            raise ParameterError(f"fill_range must satisfy 0 < lo <= hi <= 1, got {self.fill_range}")
        self.methods = {
            "adam": Method("adam", "physics", lr=self.lr),
            "pg": Method("pg", "physgrad", lr=self.lr),
        }

    @property
    def grid(self) -> Grid:
        """The E5 grid at this resolution (``dx = 2``, periodic)."""
        return e5_grid(self.resolution)

    @property
    def sigma(self) -> float:
        """Vortex falloff length (20 for a 128 domain)."""
        return 20.0 * self.grid.size[0] / 128.0

    @property
    def falloff(self) -> float:
        """Frequency-loss falloff (80 at 64 cells)."""
        return E5_FREQUENCY_FALLOFF * self.resolution[0] / 64.0

    def operator(self, marker0: torch.Tensor) -> FluidMarkerOperator:
        """The physics pair for these initial markers.

        Args:
            marker0: ``(B, nx, ny)``.

        Returns:
            The operator.
        """
        return FluidMarkerOperator(
            marker0,
            steps=self.steps,
            dt=self.dt,
            sigma=self.sigma,
            reference_vortex_track=self.reference_vortex_track,
            delta_scale=E5_DELTA_SCALE * (128.0 / self.grid.size[0]) ** 2 * self.delta_factor,
        )

    def make_network(self) -> nn.Module:
        """U-net, 5 levels, 16 filters, 2 -> 2 channels, circular padding (49,570 parameters)."""
        return UNet(2, 2, levels=5, filters=16, padding_mode="circular")

    def sample_markers(
        self, batch_size: int, generator: torch.Generator
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Initial markers and their fill fractions (float64, CPU).

        Args:
            batch_size: ``B``.
            generator: CPU generator.

        Returns:
            ``(marker (B, nx, ny), fill fraction (B,))``.
        """
        grid = self.grid
        L = torch.tensor(grid.size, dtype=torch.float64)
        pos = (torch.rand(batch_size, 2, generator=generator, dtype=torch.float64) * 0.5 + 0.25) * L
        half = 0.5 * 56.0 / 128.0 * L
        noise = spectral_noise(grid, batch_size, generator=generator, dtype=torch.float64).values
        pts = grid.cell_centers(torch.float64)  # (nx, ny, 2)
        inside = ((pts[None] >= pos[:, None, None] - half) & (pts[None] <= pos[:, None, None] + half)).all(-1)
        lo, hi = self.fill_range
        frac = lo + (hi - lo) * torch.rand(batch_size, generator=generator, dtype=torch.float64)
        k = torch.round(frac * grid.num_cells).long()
        k = torch.minimum(torch.maximum(k, torch.ones_like(k)), inside.flatten(1).sum(1))
        score = torch.where(inside, noise, torch.full_like(noise, -math.inf)).flatten(1)
        ordered = torch.sort(score, dim=1, descending=True).values
        thr = ordered.gather(1, (k - 1)[:, None])
        marker = (
            ((score >= thr) & torch.isfinite(score)).to(torch.float64).reshape(batch_size, *grid.resolution)
        )
        return marker, marker.flatten(1).mean(1)

    def sample(self, batch_size: int, generator: torch.Generator, device=None) -> Batch:
        """Markers, ground-truth initial velocities and the simulated targets (see the class docstring).

        Args:
            batch_size: ``B``.
            generator: CPU generator of this batch.
            device: Torch device.

        Returns:
            The batch: ``inputs (B, 2, nx, ny) = (m0, m_t)``, ``y_target = m_t``, ``x_true = v0*``.
        """
        grid = self.grid
        marker, _ = self.sample_markers(batch_size, generator)
        lo, hi = self.strength_range
        strength = lo + (hi - lo) * torch.rand(batch_size, generator=generator, dtype=torch.float64)
        fluct = spectral_noise(grid, batch_size, channels=2, generator=generator, dtype=torch.float64).values
        marker = marker.to(device=device, dtype=self.dtype)
        op = self.operator(marker)
        x = op.prior_velocity(strength.to(device=device, dtype=self.dtype))
        x = x + self.noise_amplitude * fluct.to(device=device, dtype=self.dtype)
        with torch.no_grad():
            y = op.forward(x)
        return Batch(torch.stack([marker, y], dim=1), y, x, op)

    def predict(self, model: nn.Module, batch: Batch) -> torch.Tensor:
        """``v0 = net(m0, m_t)``, ``(B, 2, nx, ny)``."""
        return model(batch.inputs)

    def loss(self, y: torch.Tensor, y_target: torch.Tensor) -> torch.Tensor:
        """Per-sample :func:`frequency_loss` (``n = 1``, falloff :attr:`falloff`)."""
        return frequency_loss(y, y_target, self.falloff)

    def metric(self, x: torch.Tensor, batch: Batch) -> torch.Tensor:
        """Per-sample ``sum_cells |v0 - v0*|_2``."""
        diff = x - batch.x_true.to(x.dtype)
        return torch.sqrt((diff**2).sum(1)).flatten(1).sum(1)
