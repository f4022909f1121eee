"""Spectral PDEs of :mod:`phisim.pde` as physics for physical-gradient training: operator, local inverses, problem.

The forward process is ``steps`` time steps of one of the semi-linear equations ``u_t = L u + N(u)`` of
:mod:`phisim.pde` (an :class:`~phisim.pde.etdrk.ETDRKStepper`):

    y = P(x) = S^n(x),     x, y of shape (B, C, *resolution)  (the stepper's state layout).

Its **linear part** over the ``n`` steps is diagonal in the grid's spectral basis (Fourier on periodic axes, sine
or cosine on walls): ``ŷ(k) = g(k) x̂(k)`` with the transfer factor ``g(k) = exp(n·dt·L(k))`` (per channel), the
exact solution of ``u_t = L u`` that every ETDRK step applies to the state. :class:`PDEOperator` inverts it mode by
mode with a damping of the modes the equation all but erases (the *stiff* modes, where ``|g|`` is tiny):

    W(k) = 1 / g(k)                         where |g(k)|² ≥ eps   (exact),
    W(k) = conj(g(k)) / (|g(k)|² + eps)     where |g(k)|² < eps   (Wiener-damped).

``eps`` is the noise-to-signal power ratio of the Wiener filter (dimensionless, like ``g``): a mode is inverted
exactly while its signal power ``|g|²`` is at least the noise power ``eps``; below, the Wiener gain
``|g|/(|g|² + eps) < |g|/eps`` goes to zero with ``|g|``. No mode is amplified by more than ``1/sqrt(eps)``.
(:class:`~inverse.operators.Heat` damps its spectral inverse by a Bayes probability of signal against noise
instead; it has no ``eps``.) ``eps = 0`` is the exact inverse, refused where some mode is erased to 0.

The **local inverse** ``x = P⁻¹(y*; x0)`` (what physical gradients need; :mod:`inverse.physgrad`) handles the
nonlinear part in two stages:

1. ``linear_iterations`` fixed-point (Picard) steps ``x ← x + W (y* − P(x))``, i.e. ``x ← W (y* − N_n(x))`` where
   ``P = G + N_n`` (``G`` the linear part): exact in one step for a linear equation, a contraction where the
   nonlinear part is small over the horizon;
2. optionally a generic local inverse of :mod:`inverse.local_solvers` on the full operator (``solver``: inverse
   gradient, Newton or L-BFGS-B), started from the result of stage 1.

The same two stages are available separately as local solvers for :class:`~inverse.problem.Method`:
:class:`LinearPartSolver` (stage 1 alone).

:class:`PDEProblem` (registered as ``"pde"``; ``phisim train pde pg``) trains a small periodic convolutional ResNet
(:class:`ConvResNet`) to recover an earlier state ``x* = u(t0)`` of a 1-D or 2-D equation from a later one
``y* = u(t0 + n dt)``, with Adam through the solver, physical gradients (Wiener inverse of the linear part plus a
generic nonlinear inverse), HIG and the variants listed in its docstring. For a problem of your own (other data,
network or loss), :func:`inverse.custom.make_problem` takes ``physics=op.simulate`` and
``local_inverse=op.local_inverse`` of a :class:`PDEOperator` ``op`` and trains every method with it, HIG included.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import torch
from torch import nn

from phisim.checks import check_choice, check_int, check_number
from phisim.errors import ParameterError, ShapeError
from phisim.pde import EQUATIONS, ETDRKStepper, SpectralGrid, Wave, make_stepper

from .local_solvers import InverseGradientSolver, LBFGSBSolver, LocalSolver, NewtonSolver
from .operators import PhysicsOperator
from .problem import Batch, Method, Problem

__all__ = ["PDEOperator", "LinearPartSolver", "ConvResNet", "PDEProblem", "pde_transfer", "wiener_gain"]


# --------------------------------------------------------------------------------------------------
# the linear part and its damped inverse
# --------------------------------------------------------------------------------------------------


def _spectral_dtype(grid: SpectralGrid) -> torch.dtype:
    return grid.complex_dtype if grid.spectral_is_complex else grid.dtype


def pde_transfer(stepper: ETDRKStepper, steps: int) -> torch.Tensor:
    """The transfer factor ``g(k) = exp(steps·dt·L(k))`` of the linear part of ``steps`` steps of ``stepper``.

    Args:
        stepper: An :class:`~phisim.pde.etdrk.ETDRKStepper` (not :class:`~phisim.pde.Wave`, whose linear part is a
            2×2 block per mode; :class:`PDEOperator` treats it separately).
        steps: Number of steps (>= 1).

    Returns:
        complex128 (periodic axes or a complex symbol) or float64 tensor of shape ``(C or 1, *spectral_shape)``.

    Raises:
        ParameterError: ``steps < 1``, or ``g`` overflows float64 (a growing mode over too long a horizon).
    """
    steps = check_int(steps, "steps", minimum=1)
    lin = stepper.linear_symbol
    z = (steps * stepper.dt) * lin.to(torch.complex128 if lin.is_complex() else torch.float64)
    g = torch.exp(z)
    if not bool(torch.isfinite(g).all()):
        raise ParameterError(f"the linear part of {steps} steps of dt = {stepper.dt} overflows float64 (largest "
                             f"steps*dt*Re(L) = {float(z.real.max()):.4g}); shorten the horizon")
    return g


def wiener_gain(g: torch.Tensor, eps: float) -> torch.Tensor:
    """The damped inverse ``W`` of a diagonal transfer factor ``g``: ``1/g`` where ``|g|² ≥ eps``, else the Wiener
    value ``conj(g)/(|g|² + eps)`` (see the module docstring).

    Args:
        g: Transfer factors (real or complex), any shape.
        eps: Noise-to-signal power ratio ``>= 0``; ``0`` inverts every mode exactly.

    Returns:
        ``W``, same shape and dtype as ``g``.

    Raises:
        ParameterError: Negative or non-finite ``eps``, or ``eps = 0`` with a mode erased to ``g = 0`` (no exact
            inverse exists; use ``eps > 0``).
    """
    eps = check_number(eps, "eps", minimum=0)
    power = (g * g.conj()).real if g.is_complex() else g * g
    stiff = power < eps
    safe = torch.where(power > 0, g, torch.ones_like(g))
    exact = 1.0 / safe
    damped = g.conj() / (power + eps) if eps > 0 else torch.zeros_like(g)
    w = torch.where(stiff, damped, exact)
    if eps == 0 and bool((power == 0).any()):
        raise ParameterError(f"eps = 0 asks for the exact inverse, but {int((power == 0).sum())} mode(s) are erased "
                             "to g = 0 over this horizon (they cannot be recovered); use eps > 0")
    return w


def _wave_blocks(stepper: Wave, steps: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``(cos(wT), sin(wT)/w, w sin(wT))`` of the wave propagator over ``T = steps·dt`` (float64, spectral shape)."""
    w = stepper.speed * stepper.grid.wavenumber_squared().sqrt()
    t = steps * stepper.dt
    wt = w * t
    sinc = torch.where(w > 0, torch.sin(wt) / w.clamp_min(1e-300), torch.full_like(w, t))
    return torch.cos(wt), sinc, w * torch.sin(wt)


# --------------------------------------------------------------------------------------------------
# the operator
# --------------------------------------------------------------------------------------------------


class PDEOperator(PhysicsOperator):
    """``steps`` time steps of a :mod:`phisim.pde` equation, with the Wiener-damped inverse of its linear part.

    ``x`` and ``y`` have the stepper's state layout ``(B, C, *resolution)``. The forward runs in the stepper's dtype
    (``compute_dtype``, float64 by default) and returns the input's dtype; gradients flow through the casts.
    Differentiable, batched, sample-independent.

    The local inverse (module docstring): ``linear_iterations`` steps ``x ← x + W (y* − P(x))`` from ``x0``, then
    ``solver`` (a :class:`~inverse.local_solvers.LocalSolver` on the full operator) if given. For the wave equation
    (exact, linear, a 2×2 block per mode: displacement and velocity) the linear part is the whole operator and
    its inverse is the propagator run backwards (determinant 1: exact for every mode, ``eps`` unused).

    Args:
        equation: An equation name of :data:`phisim.pde.EQUATIONS` (e.g. ``"kuramoto_sivashinsky"``,
            ``"burgers"``) or a ready :class:`~phisim.pde.etdrk.ETDRKStepper`.
        steps: Time steps of the forward process (>= 1).
        eps: Noise-to-signal power ratio of the damping (>= 0; see :func:`wiener_gain`).
        linear_iterations: Fixed-point steps with the linear inverse in :meth:`local_inverse` (>= 0).
        solver: Generic local inverse run after them (None: none). ``linear_iterations = 0`` needs one.
        compute_dtype: dtype of the stepper built from a name (default float64; a given stepper keeps its own).
        **settings: The equation's parameters and grid settings for :func:`phisim.pde.make_stepper` (``ndim``,
            ``domain``, ``resolution``, ``dt``, ``viscosity``, ...).

    Raises:
        ParameterError: Unknown equation or setting, non-positive ``dt``/``steps``, negative ``eps``, neither
            linear iterations nor a solver, ``eps = 0`` with erased modes, a horizon whose linear part overflows.
    """

    def __init__(self, equation: str | ETDRKStepper = "kuramoto_sivashinsky", steps: int = 1, *, eps: float = 1e-6,
                 linear_iterations: int = 1, solver: LocalSolver | None = None,
                 compute_dtype: torch.dtype = torch.float64, **settings):
        self.steps = check_int(steps, "steps", minimum=1)
        self.eps = check_number(eps, "eps", minimum=0)
        self.linear_iterations = check_int(linear_iterations, "linear_iterations", minimum=0)
        if solver is not None and not callable(solver):
            raise ParameterError(f"solver must be a LocalSolver (or a callable (forward, y_target, x0) -> x), got "
                                 f"{type(solver).__name__}")
        if self.linear_iterations == 0 and solver is None:
            raise ParameterError("the local inverse needs linear_iterations >= 1 or a solver")
        self.solver = solver
        if isinstance(equation, ETDRKStepper):
            if settings:
                raise ParameterError(f"settings {sorted(settings)} are for building a stepper by name; a given "
                                     "stepper keeps its own")
            stepper = equation
        elif isinstance(equation, str):
            if not (isinstance(compute_dtype, torch.dtype) and compute_dtype.is_floating_point):
                raise ParameterError(f"compute_dtype must be a floating torch.dtype, got {compute_dtype!r}")
            stepper = make_stepper(equation, dtype=compute_dtype, **settings)
        else:
            raise ParameterError(f"equation must be a name ({', '.join(sorted(EQUATIONS))}) or an ETDRKStepper, got "
                                 f"{type(equation).__name__}")
        self.stepper = stepper
        self.grid = stepper.grid
        self.shape = tuple(stepper.shape)  # (C, *resolution)
        spec = _spectral_dtype(self.grid)
        if isinstance(stepper, Wave):
            self._wave = tuple(t.to(spec) for t in _wave_blocks(stepper, self.steps))
            self.transfer = None
            self.gain = None
        else:
            self._wave = None
            g = pde_transfer(stepper, self.steps)
            w = wiener_gain(g, self.eps)
            if not self.grid.spectral_is_complex:
                g, w = g.real, w.real
            #: ``g(k)``, the linear part's factor per mode, ``(C or 1, *spectral_shape)`` (float64/complex128).
            self.transfer = g
            #: ``W(k)``, its damped inverse (same shape and dtype).
            self.gain = w
            self._g = g.to(spec)
            self._w = w.to(spec)

    # ----------------------------------------------------------------- helpers
    @property
    def dtype(self) -> torch.dtype:
        """The dtype the physics computes in (the stepper's)."""
        return self.grid.dtype

    def stiff_modes(self) -> torch.Tensor:
        """Boolean mask ``(C or 1, *spectral_shape)`` of the damped modes (``|g|² < eps``); all False for waves."""
        if self.transfer is None:
            return torch.zeros((1,) + self.grid.spectral_shape, dtype=torch.bool, device=self.grid.device)
        g = self.transfer
        power = (g * g.conj()).real if g.is_complex() else g * g
        return power < self.eps

    def _check_state(self, x: torch.Tensor, name: str) -> None:
        if x.ndim != len(self.shape) + 1 or tuple(x.shape[1:]) != self.shape:
            raise ShapeError(f"{name} has shape {tuple(x.shape)}; this {type(self.stepper).__name__} operator works on "
                             f"states (B, {', '.join(map(str, self.shape))}) = (batch, channels, *resolution)")

    def _to_compute(self, x: torch.Tensor) -> torch.Tensor:
        return x.to(device=self.grid.device, dtype=self.grid.dtype)

    def _apply_linear(self, x: torch.Tensor, inverse: bool) -> torch.Tensor:
        grid = self.grid
        u_hat = grid.to_spectral(x)
        if self._wave is not None:
            cos, sinc, wsin = self._wave
            u, v = u_hat[:, 0], u_hat[:, 1]
            if inverse:  # the propagator with -T: [[cos, -sin/w], [w sin, cos]]
                out = torch.stack([cos * u - sinc * v, wsin * u + cos * v], dim=1)
            else:
                out = torch.stack([cos * u + sinc * v, -wsin * u + cos * v], dim=1)
        else:
            out = (self._w if inverse else self._g) * u_hat
        return grid.to_physical(out)

    # ----------------------------------------------------------------- the linear part
    def linear_forward(self, x: torch.Tensor) -> torch.Tensor:
        """The linear part alone, ``ŷ = g x̂`` (``S^n`` without the nonlinear term): differentiable.

        Args:
            x: ``(B, C, *resolution)``.

        Returns:
            ``(B, C, *resolution)`` in ``x``'s dtype.

        Raises:
            ShapeError: ``x`` is not a state of this operator.
        """
        self._check_state(x, "x")
        return self._apply_linear(self._to_compute(x), inverse=False).to(device=x.device, dtype=x.dtype)

    def linear_inverse(self, y: torch.Tensor) -> torch.Tensor:
        """The damped inverse of the linear part, ``x̂ = W ŷ``: exact on modes with ``|g|² ≥ eps``.

        Args:
            y: ``(B, C, *resolution)``.

        Returns:
            ``(B, C, *resolution)`` in ``y``'s dtype.

        Raises:
            ShapeError: ``y`` is not a state of this operator.
        """
        self._check_state(y, "y")
        return self._apply_linear(self._to_compute(y), inverse=True).to(device=y.device, dtype=y.dtype)

    # ----------------------------------------------------------------- PhysicsOperator
    def _forward(self, x: torch.Tensor) -> torch.Tensor:
        self._check_state(x, "x")
        u = self._to_compute(x)
        if self._wave is not None:
            return self._apply_linear(u, inverse=False).to(device=x.device, dtype=x.dtype)
        return self.stepper.repeat(u, self.steps).to(device=x.device, dtype=x.dtype)

    def simulate(self, x: torch.Tensor) -> torch.Tensor:
        """The forward ``P(x)`` without the input checks of :meth:`forward` (no NaN test, no host reads).

        Traceable by ``torch.func`` (``vmap``/``jacrev``: what HIG differentiates) and ``torch.compile``; the
        ``physics`` to give :func:`inverse.custom.make_problem` (with ``local_inverse=op.local_inverse``).

        Args:
            x: ``(B, C, *resolution)``.

        Returns:
            ``P(x)``, same shape, device and dtype as ``x``.

        Raises:
            ShapeError: ``x`` is not a state of this operator.
        """
        return self._forward(x)

    def linear_step(self, y_target: torch.Tensor, x: torch.Tensor, y: torch.Tensor | None = None) -> torch.Tensor:
        """One fixed-point step ``x + W (y* − P(x))`` (no autograd history).

        Args:
            y_target: ``(B, C, *resolution)``.
            x: The current guess, same shape.
            y: ``P(x)`` if already known.

        Returns:
            The new guess, in ``x``'s dtype.
        """
        with torch.no_grad():
            xc = self._to_compute(x)
            yc = self._to_compute(self._forward(xc) if y is None else y)
            out = xc + self._apply_linear(self._to_compute(y_target) - yc, inverse=True)
        return out.to(device=x.device, dtype=x.dtype)

    def _local_inverse(self, y_target: torch.Tensor, x0: torch.Tensor, y0: torch.Tensor | None) -> torch.Tensor:
        self._check_state(x0, "x0")
        x = x0
        for i in range(self.linear_iterations):
            x = self.linear_step(y_target, x, y0 if i == 0 else None)
        if self.solver is not None:
            x = self.solver(self._forward, y_target, x)
        return x.to(x0.dtype)

    def __repr__(self) -> str:
        solver = type(self.solver).__name__ if self.solver is not None else None
        return (f"PDEOperator({type(self.stepper).__name__}, steps={self.steps}, dt={self.stepper.dt}, eps={self.eps}, "
                f"linear_iterations={self.linear_iterations}, solver={solver})")


class LinearPartSolver(LocalSolver):
    """The fixed-point local inverse of a :class:`PDEOperator` alone: ``iterations`` steps ``x ← x + W (y* − P(x))``.

    A :class:`~inverse.local_solvers.LocalSolver` for :class:`~inverse.problem.Method` (``local_solver=``), so a
    problem can offer the linear-part inverse beside the operator's own combined one.

    Args:
        iterations: Fixed-point steps (>= 1).

    Raises:
        ParameterError: ``iterations < 1``; a forward that is not a :class:`PDEOperator` (on call).
    """

    def __init__(self, iterations: int = 1):
        self.iterations = check_int(iterations, "iterations", minimum=1)

    def _solve(self, forward, y_target, x0):
        if not isinstance(forward, PDEOperator):
            raise ParameterError(f"LinearPartSolver needs a PDEOperator forward (it uses the linear part's inverse), "
                                 f"got {type(forward).__name__}")
        x = x0
        for _ in range(self.iterations):
            x = forward.linear_step(y_target, x)
        return x


# --------------------------------------------------------------------------------------------------
# network
# --------------------------------------------------------------------------------------------------


class ConvResNet(nn.Module):
    """A small convolutional ResNet for 1-D or 2-D fields: ``x = input + out(blocks(in(input)))``.

    ``in``: a convolution ``channels -> width``; ``blocks`` residual blocks ``h + conv(act(conv(act(h))))`` whose
    convolutions have the dilation ``2^i`` in block ``i`` (the receptive field doubles per block); ``out``: a
    convolution ``width -> channels`` initialised to zero, so the untrained network is the identity (the guess
    "nothing changed"). No normalisation layers: every sample is independent (as HIG's per-sample Jacobians need).

    Args:
        ndim: Spatial dimensions (1 or 2).
        channels: Field channels in and out.
        width: Hidden channels.
        blocks: Residual blocks.
        kernel_size: Odd kernel size.
        padding_mode: ``"circular"`` (periodic axes), ``"zeros"``, ``"reflect"`` or ``"replicate"``.

    Raises:
        ParameterError: Bad sizes or padding mode.
    """

    def __init__(self, ndim: int = 1, channels: int = 1, width: int = 16, blocks: int = 3, kernel_size: int = 5,
                 padding_mode: str = "circular"):
        super().__init__()
        self.ndim = check_int(ndim, "ndim", minimum=1, maximum=2)
        self.channels = check_int(channels, "channels", minimum=1, maximum=2**20)
        width = check_int(width, "width", minimum=1, maximum=2**20)
        blocks = check_int(blocks, "blocks", minimum=0, maximum=16)
        k = check_int(kernel_size, "kernel_size", minimum=1, maximum=1025)
        if k % 2 == 0:
            raise ParameterError(f"kernel_size must be odd (a centred stencil), got {k}")
        check_choice(padding_mode, "padding_mode", ("circular", "zeros", "reflect", "replicate"))
        conv = nn.Conv1d if self.ndim == 1 else nn.Conv2d

        def layer(c_in, c_out, dilation=1):
            return conv(c_in, c_out, k, padding=dilation * (k // 2), dilation=dilation, padding_mode=padding_mode)

        self.inp = layer(self.channels, width)
        self.blocks = nn.ModuleList([nn.ModuleList([layer(width, width, 2**i), layer(width, width, 2**i)])
                                     for i in range(blocks)])
        self.act = nn.GELU()
        self.out = layer(width, self.channels)
        nn.init.zeros_(self.out.weight)
        nn.init.zeros_(self.out.bias)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Applies the network.

        Args:
            x: ``(B, channels, *resolution)`` with ``ndim`` spatial axes.

        Returns:
            Same shape.

        Raises:
            ShapeError: Wrong rank or channels.
        """
        if x.ndim != self.ndim + 2 or x.shape[1] != self.channels:
            raise ShapeError(f"ConvResNet({self.ndim}-D) expects (B, {self.channels}, *resolution) with {self.ndim} "
                             f"spatial axes, got {tuple(x.shape)}")
        h = self.inp(x)
        for c1, c2 in self.blocks:
            h = h + c2(self.act(c1(self.act(h))))
        return x + self.out(self.act(h))


# --------------------------------------------------------------------------------------------------
# the problem
# --------------------------------------------------------------------------------------------------

_NONLINEAR_SOLVERS = ("inverse_gradient", "newton", "lbfgsb", "none")
_NAVIER_STOKES = ("navier_stokes", "kolmogorov", "decaying_turbulence")  # 2-D only


@dataclass
class PDEProblem(Problem):
    """Recover an earlier state of a :mod:`phisim.pde` equation from a later one (registered as ``"pde"``).

    Data (drawn from the training generator): a band-limited random field (Gaussian noise low-passed to the modes
    ``|m| <= max_wavenumber``, each sample scaled to the standard deviation ``amplitude``, mean removed), advanced
    ``warmup_steps`` steps by the equation (so that ``x*`` is a state the dynamics produces, e.g. on the chaotic
    attractor of Kuramoto–Sivashinsky), is ``x*``; ``y* = P(x*)`` after ``steps`` more steps. The network
    (:class:`ConvResNet`, identity at initialisation) maps ``y*`` to ``x`` (both ``(B, C, *resolution)``).
    Loss ``½ Σ_cells (P(x) − y*)²`` and metric ``Σ_cells |x − x*|`` per sample; batch ``reduction='mean'``.

    Defaults (those of ``docs/RESULTS_PDE.md``): Kuramoto–Sivashinsky on the chaotic box ``L = 22`` with 64 points,
    ``dt = 0.25``, horizon 2 steps (``T = 0.5``), warm-up 200 steps (``t = 50``), batch 8, float32 network (4,525
    parameters), float64 physics; ``eps = rcond = 1e-2``, Adam ``lr = 1e-3``, HIG ``lr = 1``, ``rcond = 1e-4``.

    Methods:

    * ``adam``: Adam through the solver; ``sgd``: SGD with momentum 0.9.
    * ``pg``: physical gradients with the operator's local inverse: ``linear_iterations`` Wiener-damped linear-part
      steps, then the generic nonlinear inverse ``nonlinear_solver`` (``"inverse_gradient"`` by default,
      ``solver_iterations`` iterations with relative cut-off ``rcond``).
    * ``pg_linear``: the Wiener-damped linear-part steps alone (:class:`LinearPartSolver`).
    * ``pg_inverse_gradient``, ``pg_lbfgsb``: a generic local inverse alone.
    * ``hig``: half-inverse gradients (``hig_lr``, ``hig_rcond``).
    * ``supervised``: regress ``x*``.

    Attributes (settings, all keyword arguments of the constructor / ``--setting`` on the command line):
        equation: Equation name (:data:`phisim.pde.EQUATIONS`).
        ndim: Spatial dimensions (1 or 2; None: 2 for the Navier–Stokes equations, else 1).
        domain: Domain length(s).
        resolution: Points per axis (an int, or one per axis).
        dt: Time step.
        steps: Steps of the forward process ``P``.
        warmup_steps: Steps from the random field to ``x*`` (0: ``x*`` is the random field).
        amplitude: Standard deviation of the random field.
        max_wavenumber: Largest mode number of the random field.
        eps: Damping of the linear inverse (:func:`wiener_gain`).
        linear_iterations: Wiener fixed-point steps of ``pg`` and ``pg_linear``.
        nonlinear_solver: Generic stage of ``pg``: ``"inverse_gradient"``, ``"newton"``, ``"lbfgsb"`` or ``"none"``.
        solver_iterations: Iterations of the generic inverses (L-BFGS-B gets four times as many).
        rcond: Relative singular-value cut-off of the generic inverses.
        lr: Adam learning rate (all Adam-based methods).
        hig_lr: HIG learning rate.
        hig_rcond: HIG truncation.
        width, blocks, kernel_size: :class:`ConvResNet` sizes.
        equation_settings: Further parameters of the equation (e.g. ``{"viscosity": 0.05}``).
    """

    name: str = "pde"
    batch_size: int = 8
    reduction: str = "mean"
    equation: str = "kuramoto_sivashinsky"
    ndim: int | None = None
    domain: float | Sequence[float] = 22.0
    resolution: int | Sequence[int] = 64
    dt: float = 0.25
    steps: int = 2
    warmup_steps: int = 200
    amplitude: float = 1.0
    max_wavenumber: float = 4.0
    eps: float = 1e-2
    linear_iterations: int = 1
    nonlinear_solver: str = "inverse_gradient"
    solver_iterations: int = 1
    rcond: float = 1e-2
    lr: float = 1e-3
    hig_lr: float = 1.0
    hig_rcond: float = 1e-4
    width: int = 12
    blocks: int = 3
    kernel_size: int = 5
    equation_settings: dict = field(default_factory=dict)

    def __post_init__(self):
        self.batch_size = check_int(self.batch_size, "batch_size", minimum=1)
        if not isinstance(self.equation, str):
            raise ParameterError(f"equation must be a name ({', '.join(sorted(EQUATIONS))}), got {self.equation!r}")
        self.equation = self.equation.strip().lower().replace("-", "_").replace(" ", "_")
        check_choice(self.reduction, "reduction", ("mean", "sum"))
        if self.ndim is None:
            self.ndim = 2 if self.equation in _NAVIER_STOKES else 1
        self.ndim = check_int(self.ndim, "ndim", minimum=1, maximum=2)
        res = self.resolution
        if isinstance(res, (list, tuple)):
            if len(res) == 1:
                res = res[0]
            elif len(res) != self.ndim:
                raise ParameterError(f"resolution has {len(res)} entries for ndim = {self.ndim}")
        self.resolution = (tuple(check_int(n, "resolution", minimum=2) for n in res) if isinstance(res, (list, tuple))
                           else check_int(res, "resolution", minimum=2))
        self.steps = check_int(self.steps, "steps", minimum=1)
        self.warmup_steps = check_int(self.warmup_steps, "warmup_steps", minimum=0)
        self.amplitude = check_number(self.amplitude, "amplitude", minimum=0, min_open=True)
        self.max_wavenumber = check_number(self.max_wavenumber, "max_wavenumber", minimum=0, min_open=True)
        self.linear_iterations = check_int(self.linear_iterations, "linear_iterations", minimum=0)
        check_choice(self.nonlinear_solver, "nonlinear_solver", _NONLINEAR_SOLVERS)
        self.solver_iterations = check_int(self.solver_iterations, "solver_iterations", minimum=1)
        self.rcond = check_number(self.rcond, "rcond", minimum=0)
        if not isinstance(self.equation_settings, dict):
            raise ParameterError(f"equation_settings must be a dict of the equation's parameters, got "
                                 f"{type(self.equation_settings).__name__}")
        generic = self._generic_solver(self.nonlinear_solver)
        # the physics: float64 stepper; built here so that bad settings fail at once (linear_iterations = 0 with
        # nonlinear_solver = 'none' leaves pg without a local inverse: a ParameterError of PDEOperator)
        self._operator = PDEOperator(self.equation, self.steps, eps=self.eps,
                                     linear_iterations=self.linear_iterations, solver=generic,
                                     **self._stepper_settings())
        lr = check_number(self.lr, "lr", minimum=0, min_open=True)
        methods = {
            "adam": Method("adam", "physics", lr=lr),
            "sgd": Method("sgd", "physics", optimizer="sgd", lr=lr, momentum=0.9),
            "pg": Method("pg", "physgrad", lr=lr),
            "pg_linear": Method("pg_linear", "physgrad", lr=lr,
                                local_solver=LinearPartSolver(max(1, self.linear_iterations))),
            "pg_inverse_gradient": Method("pg_inverse_gradient", "physgrad", lr=lr,
                                          local_solver=self._generic_solver("inverse_gradient")),
            "pg_lbfgsb": Method("pg_lbfgsb", "physgrad", lr=lr, local_solver=self._generic_solver("lbfgsb")),
            "hig": Method("hig", "hig", optimizer="hig", lr=self.hig_lr, rcond=self.hig_rcond),
            "supervised": Method("supervised", "supervised", lr=lr),
        }
        self.methods = methods
        self.hig_physics = self._operator.simulate  # unchecked forward: traceable by torch.func (no host syncs)

    def _stepper_settings(self) -> dict:
        settings = dict(self.equation_settings)
        for key in ("ndim", "domain", "resolution", "dt"):
            if key in settings:
                raise ParameterError(f"give {key} as a problem setting, not in equation_settings")
        grid = {"domain": self.domain, "resolution": self.resolution, "dt": self.dt}
        if self.equation not in _NAVIER_STOKES + ("kdv",):
            grid["ndim"] = self.ndim
        elif self.equation == "kdv" and self.ndim != 1 or self.equation != "kdv" and self.ndim != 2:
            raise ParameterError(f"{self.equation} is {'1' if self.equation == 'kdv' else '2'}-D; set ndim accordingly")
        return {**grid, **settings}

    def _generic_solver(self, name: str) -> LocalSolver | None:
        it = self.solver_iterations
        if name == "inverse_gradient":
            return InverseGradientSolver(max_iter=it, rcond=self.rcond)
        if name == "newton":
            return NewtonSolver(max_iter=it, rcond=self.rcond, saddle_free=True)
        if name == "lbfgsb":
            return LBFGSBSolver(max_iter=4 * it)
        return None

    def operator(self) -> PDEOperator:
        """The physics pair (built once)."""
        return self._operator

    @property
    def state_shape(self) -> tuple[int, ...]:
        """``(C, *resolution)`` of one sample."""
        return self._operator.shape

    def make_network(self) -> nn.Module:
        """A :class:`ConvResNet` (identity at initialisation; circular padding on periodic grids)."""
        periodic = all(b == "periodic" for b in self._operator.grid.boundaries)
        return ConvResNet(self.ndim, self.state_shape[0], self.width, self.blocks, self.kernel_size,
                          "circular" if periodic else "replicate").to(self.dtype)

    def draw_states(self, batch_size: int, generator: torch.Generator) -> torch.Tensor:
        """``x*``: band-limited random fields advanced ``warmup_steps`` steps, float64 ``(B, C, *resolution)``.

        Args:
            batch_size: Samples.
            generator: CPU generator all randomness is drawn from.

        Returns:
            The states on the physics' device.
        """
        op = self._operator
        grid = op.grid
        noise = torch.randn((batch_size,) + op.shape, generator=generator, dtype=torch.float64)
        g64 = SpectralGrid(grid.domain, grid.resolution, boundaries=grid.boundaries, dtype=torch.float64)
        keep = torch.ones(g64.spectral_shape, dtype=torch.float64)
        for a, k in enumerate(g64.wavenumbers):
            unit = (2 * math.pi if grid.boundaries[a] == "periodic" else math.pi) / grid.domain[a]
            keep = keep * (k.abs() / unit <= self.max_wavenumber)
        u = g64.to_physical(g64.to_spectral(noise) * keep)
        dims = tuple(range(2, u.dim()))
        u = u - u.mean(dims, keepdim=True)
        u = self.amplitude * u / u.std(dims, keepdim=True).clamp_min(1e-300)
        u = u.to(device=grid.device, dtype=op.dtype)
        with torch.no_grad():
            if self.warmup_steps:
                u = op.stepper.repeat(u, self.warmup_steps)
        return u

    def sample(self, batch_size: int, generator: torch.Generator, device=None) -> Batch:
        """``x*`` from :meth:`draw_states`, ``y* = P(x*)`` (float64), the network input ``y*`` in the network dtype."""
        op = self._operator
        x = self.draw_states(batch_size, generator)
        with torch.no_grad():
            y = op.forward(x)
        x = x.to(device=device, dtype=self.dtype)
        y = y.to(device=device, dtype=self.dtype)
        return Batch(y, y, x, op, labels=x)

    def predict(self, model: nn.Module, batch: Batch) -> torch.Tensor:
        """``x = net(y*)``, ``(B, C, *resolution)``."""
        return model(batch.inputs)
