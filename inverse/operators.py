"""Forward-physics / local-inverse operator pairs for physical-gradient training.

A :class:`PhysicsOperator` bundles a differentiable forward process ``y = P(x)`` with a *local inverse*
``x = P⁻¹(y*; x0)``: a solution of ``P(x) = y*`` (or of ``min_x ½‖P(x) − y*‖²``) that is conditioned on a
current guess ``x0`` and, where ``P`` is not injective, prefers the solution closest to ``x0``
(Holl, Koltun, Thuerey, "Physical Gradients for Deep Learning", section 2.2 and appendix A.2; the
physgrad chapter of the Physics-based Deep Learning book, "Global and local inverse simulators").

All arrays are torch tensors, batch first: ``x`` has shape ``(B, *x_shape)``, ``y`` ``(B, *y_shape)``.
Every sample is an independent problem: sample ``i`` of ``P(x)`` depends on sample ``i`` of ``x`` only.
Device and dtype follow the input; float64 works everywhere.

This module holds the base class and the analytic pairs of the reference experiments E1 (the two
optimizer toys), E2 (``sin(a/x)``), E3 (Poisson: CG forward, Laplacian inverse) and E4 (heat: spectral
forward, Wiener/Bayes-damped spectral inverse). Generic local inverses for any differentiable forward live in
:mod:`inverse.local_solvers`.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch

from phisim.checks import callable_name, check_batch_compatible, check_callable_output, check_choice, check_number
from phisim.errors import NonFiniteError, ParameterError, ShapeError
from phisim.solvers.diffusion import fourier_heat, fourier_k2
from phisim.solvers.linalg import Solve, cg, remove_mean
from phisim.solvers.poisson import negative_laplacian, normalize_kinds, spectral_poisson_solve, stencil_laplacian
from phisim.spectral.fft import r2rn

__all__ = [
    "PhysicsOperator",
    "ScaleToy",
    "SquareToy",
    "Sine",
    "Poisson",
    "Heat",
    "check_finite",
    "ghost_dirichlet_laplacian",
    "ghost_dirichlet_solve",
]


def check_finite(name: str, value: torch.Tensor) -> None:
    """Raises :class:`~phisim.errors.NonFiniteError` if ``value`` holds NaN or Inf.

    Args:
        name: What the tensor is, for the message (e.g. ``"x0"``).
        value: Any tensor.

    Raises:
        NonFiniteError: ``value`` contains a NaN or an infinite entry.
    """
    if value.is_floating_point() or value.is_complex():
        if not bool(torch.isfinite(value).all()):
            n_bad = int((~torch.isfinite(value)).sum())
            raise NonFiniteError(
                f"{name} contains {n_bad} non-finite value(s) (NaN or Inf) out of {value.numel()}; "
                "check the network output / the simulation state before calling the operator."
            )


def _as_tensor(value, like: torch.Tensor | None = None) -> torch.Tensor:
    """Converts numpy arrays / numbers to a tensor on ``like``'s device and dtype (if given)."""
    t = torch.as_tensor(value)
    if like is not None:
        t = t.to(device=like.device, dtype=like.dtype)
    return t


class PhysicsOperator:
    """A differentiable forward process ``P`` paired with a local inverse ``P⁻¹(·; x0)``.

    Subclasses implement :meth:`_forward` (differentiable with autograd, batched) and
    :meth:`_local_inverse`; the public :meth:`forward` and :meth:`local_inverse` validate their input
    (finite values, batch sizes and shapes) and then call them. Calling the operator is the same as
    :meth:`forward`.

    Per-sample parameters (e.g. the ``a`` of :class:`Sine`, one per sample) are supported: operators
    holding them override :meth:`select`, which returns the operator restricted to some samples; the
    generic solvers of :mod:`inverse.local_solvers` use it when they work sample by sample.

    Attributes:
        check_inputs: If True (default), :meth:`forward` and :meth:`local_inverse` check their inputs
            for NaN/Inf (one device synchronisation per call). Set False in tight GPU loops.
    """

    check_inputs: bool = True

    def _callable_name(self, role: str) -> str:
        """The user callable behind ``role`` (``'forward'`` or ``'local inverse'``), for error messages: a wrapped
        function (``physics``, ``inverse_fn``, ``solver``) by its name, else the operator's method."""
        attrs = ("physics",) if role == "forward" else ("inverse_fn", "solver")
        for attr in attrs:
            fn = self.__dict__.get(attr)
            if fn is not None:
                return callable_name(fn)
        return f"{type(self).__name__}.{'_forward' if role == 'forward' else '_local_inverse'}"

    # ----------------------------------------------------------------- to implement in subclasses
    def _forward(self, x: torch.Tensor) -> torch.Tensor:
        raise NotImplementedError

    def _local_inverse(
        self, y_target: torch.Tensor, x0: torch.Tensor, y0: torch.Tensor | None
    ) -> torch.Tensor:
        raise NotImplementedError

    def output_shape(self, x_shape: Sequence[int]) -> torch.Size | None:
        """Shape of ``forward(x)`` for an ``x`` of shape ``x_shape``, or None where it is not known.

        The default says the output has the input's shape. Operators for which this does not hold
        override it (returning None makes :meth:`local_inverse` evaluate ``forward(x0)`` to check the
        target's shape when no ``y0`` is given).

        Args:
            x_shape: ``(B, *x_shape)``.

        Returns:
            ``(B, *y_shape)``, or None.
        """
        return torch.Size(x_shape)

    def select(self, index: slice | torch.Tensor | Sequence[int]) -> PhysicsOperator:
        """The operator restricted to the samples ``index`` of the batch.

        Operators without per-sample parameters return ``self`` (the default).

        Args:
            index: A slice or integer index tensor into the batch dimension.

        Returns:
            An operator acting on ``x[index]``.
        """
        return self

    # ----------------------------------------------------------------- public interface
    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Simulates ``y = P(x)`` (differentiable, batched).

        Args:
            x: ``(B, *x_shape)``, floating point.

        Returns:
            ``y``, ``(B, *y_shape)``, same device and dtype as ``x``.

        Raises:
            ShapeError: ``x`` has no batch dimension or a shape the operator does not accept, or the forward
                returns another batch size than ``x``'s (or another shape than :meth:`output_shape` says),
                naming the forward callable.
            NonFiniteError: ``x`` contains NaN/Inf (when :attr:`check_inputs`).
        """
        x = _as_tensor(x)
        if x.ndim < 1:
            raise ShapeError("x must be batch-first with at least one dimension, got a 0-d tensor")
        if not x.is_floating_point():
            raise ShapeError(f"x must be a floating-point tensor, got dtype {x.dtype}")
        if self.check_inputs:
            check_finite("x", x)
        y = self._forward(x)
        if not isinstance(y, torch.Tensor) or y.ndim < 1 or y.shape[0] != x.shape[0]:
            shape = tuple(y.shape) if isinstance(y, torch.Tensor) else type(y).__name__
            raise ShapeError(f"forward {self._callable_name('forward')} returned {shape} for x of shape "
                             f"{tuple(x.shape)}; it must keep the batch size {x.shape[0]} on axis 0")
        return y

    __call__ = forward

    def local_inverse(
        self, y_target: torch.Tensor, x0: torch.Tensor, y0: torch.Tensor | None = None
    ) -> torch.Tensor:
        """Local inverse ``x = P⁻¹(y_target; x0)``: a solution of ``P(x) = y_target`` near ``x0``.

        Where several solutions exist the one closest to ``x0`` is preferred; where none exists the
        operator returns (an approximation of) a minimiser of ``½‖P(x) − y_target‖²`` reached from
        ``x0``. The result carries no autograd history (it is a target, used as ``stopgrad(x̃)``).

        Args:
            y_target: ``(B, *y_shape)``, the desired output.
            x0: ``(B, *x_shape)``, the current guess the inverse is conditioned on.
            y0: Optional ``P(x0)``, ``(B, *y_shape)``, if already computed (saves a forward pass for
                inverses that use it).

        Returns:
            ``x``, ``(B, *x_shape)``, detached, same device and dtype as ``x0``.

        Batch sizes: ``x0`` and ``y_target`` have the same batch size, or one of them has 1 (a shared start or
        a shared target), which is broadcast to the other's.

        Raises:
            ShapeError: ``y_target`` does not have the shape of ``P(x0)`` (or of ``y0``), the batch sizes
                differ (and neither is 1), or the local inverse returns another shape than ``x0``'s (naming
                the callable).
            NonFiniteError: an input, or the local inverse's result, contains NaN/Inf (when
                :attr:`check_inputs`).
        """
        x0 = _as_tensor(x0).detach()
        y_target = torch.as_tensor(y_target, device=x0.device).detach()
        if y_target.is_floating_point():
            y_target = y_target.to(dtype=x0.dtype)
        if x0.ndim < 1 or y_target.ndim < 1:
            raise ShapeError("x0 and y_target must be batch-first tensors with at least one dimension")
        batch = check_batch_compatible(x0, y_target, ("x0", "y_target"), "invert (batch sizes differ)")
        x0 = x0.expand(batch, *x0.shape[1:]) if x0.shape[0] != batch else x0
        y_target = y_target.expand(batch, *y_target.shape[1:]) if y_target.shape[0] != batch else y_target
        if y0 is not None:
            y0 = _as_tensor(y0)
            y0 = y0.expand(batch, *y0.shape[1:]) if y0.ndim >= 1 and y0.shape[0] == 1 != batch else y0
        if self.check_inputs:
            check_finite("x0", x0)
            check_finite("y_target", y_target)
        if y0 is not None:
            y0 = _as_tensor(y0).detach()
            if self.check_inputs:
                check_finite("y0", y0)
            expected = y0.shape
            source = "y0"
        else:
            expected = self.output_shape(x0.shape)
            source = "forward(x0)"
            if expected is None:
                with torch.no_grad():
                    y0 = self._forward(x0)
                expected = y0.shape
        if tuple(y_target.shape) != tuple(expected):
            raise ShapeError(
                f"y_target has shape {tuple(y_target.shape)} but {source} has shape {tuple(expected)}; "
                "the target must have the shape of the forward output for the given x0"
            )
        x = self._local_inverse(y_target, x0, y0)
        if not isinstance(x, torch.Tensor) or x.shape != x0.shape:
            check_callable_output(x, x0.shape, None, "local inverse " + self._callable_name("local inverse"),
                                  finite=False)
        if self.check_inputs and not bool(torch.isfinite(x.detach()).all()):
            raise NonFiniteError(f"local inverse {self._callable_name('local inverse')} returned NaN/Inf for "
                                 "finite inputs")
        return x.detach()


# --------------------------------------------------------------------------------------------------
# E1: optimizer toys
# --------------------------------------------------------------------------------------------------


def _check_last_dim_two(x: torch.Tensor, name: str) -> None:
    if x.ndim != 2 or x.shape[-1] != 2:
        raise ShapeError(f"{name} must have shape (B, 2), got {tuple(x.shape)}")


class ScaleToy(PhysicsOperator):
    """E1 toy with anisotropic scaling: ``P(x1, x2) = (x1, α·x2)``, exact inverse ``(y1, y2/α)``.

    With ``L = |P(x)|²`` gradient descent's trajectory depends on ``α`` while the physical-gradient
    trajectory does not (scale invariance; physgrad chapter, "The crux of the matter").

    Args:
        alpha: The scale ``α`` of the second component; finite and non-zero.

    Raises:
        ParameterError: ``alpha`` is zero or not finite.
    """

    def __init__(self, alpha: float = 1.0):
        alpha = check_number(alpha, "alpha")
        if alpha == 0.0:
            raise ParameterError(f"alpha must be finite and non-zero, got {alpha}")
        self.alpha = alpha

    def _forward(self, x: torch.Tensor) -> torch.Tensor:
        _check_last_dim_two(x, "x")
        scale = torch.tensor([1.0, self.alpha], dtype=x.dtype, device=x.device)
        return x * scale

    def _local_inverse(
        self, y_target: torch.Tensor, x0: torch.Tensor, y0: torch.Tensor | None
    ) -> torch.Tensor:
        _check_last_dim_two(x0, "x0")
        return torch.stack([y_target[:, 0], y_target[:, 1] / self.alpha], dim=-1)


class SquareToy(PhysicsOperator):
    """E1 toy ``P(x1, x2) = (x1, x2²)`` with the closest-solution analytic inverse.

    ``P`` is not injective: ``(x1, ±x2)`` give the same output. The local inverse conditioned on ``x0``
    returns ``(y1, s·sqrt(y2))`` with ``s = sign(x0_2)`` (``+1`` where ``x0_2 = 0``), the preimage on
    ``x0``'s side. For ``y2 < 0`` no preimage exists and ``x2 = 0`` (the minimiser of ``|x2² − y2|``)
    is returned.
    """

    def _forward(self, x: torch.Tensor) -> torch.Tensor:
        _check_last_dim_two(x, "x")
        return torch.stack([x[:, 0], x[:, 1] ** 2], dim=-1)

    def _local_inverse(
        self, y_target: torch.Tensor, x0: torch.Tensor, y0: torch.Tensor | None
    ) -> torch.Tensor:
        _check_last_dim_two(x0, "x0")
        sign = torch.where(x0[:, 1] < 0, -1.0, 1.0).to(x0.dtype)
        x2 = sign * torch.sqrt(torch.clamp(y_target[:, 1], min=0.0))
        return torch.stack([y_target[:, 0], x2], dim=-1)


# --------------------------------------------------------------------------------------------------
# E2: sin(a / x)
# --------------------------------------------------------------------------------------------------


class Sine(PhysicsOperator):
    """E2 forward ``y = sin(a/x)`` with the analytic closest-solution inverse.

    The solutions of ``sin(a/x) = t`` (``t ∈ [−1, 1]``) are ``x = a/u`` for the phases
    ``u ∈ {θ₁ + 2πn} ∪ {θ₂ + 2πn}``, ``n ∈ ℤ``, with ``θ₁ = arcsin t`` and ``θ₂ = π − θ₁``. For the
    E2 target ``t = −1`` both families coincide with the minima ``u = 3π/2 + 2πn`` of the paper
    (appendix B.1: ``n = round(a/(2π x0) − 3/4)``, ``x* = a/(3π/2 + 2πn)``).

    The local inverse returns the solution **closest to x0 in x**, exactly:

    * ``x = a/u`` is monotone on each sign of ``u``, so the closest solution on ``x0``'s side is the
      image of one of the two phase neighbours of ``u0 = a/x0`` in each family (``floor`` and ``ceil`` of
      ``(u0 − θ)/(2π)``); the four candidates are compared by ``|x − x0|``. Rounding the phase, as in the
      paper, picks the closest solution in ``u`` which can differ from the closest in ``x``.
    * The outermost solutions need the special handling the paper mentions: a phase neighbour on the
      other side of ``u = 0`` (e.g. ``n = −1`` for ``t = −1`` when ``x0 > 2a/π``, which rounding would
      choose) is a solution of the opposite sign of ``x`` and never the closest one; such candidates
      (and ``u = 0``, i.e. ``x = ∞``) are excluded. For ``x0 > 0, a > 0`` the result is therefore at most
      the outermost positive solution ``a/θ_min``.
    * Targets outside ``[−1, 1]`` have no solution; they are clamped to ``[−1, 1]`` (the closest
      attainable output). ``x0 = 0`` is treated as ``+tiny`` (the solution closest to 0 on the positive
      side, which is ``≈ 0``).

    With ``closest="phase"`` the candidate closest to ``x0`` in the phase ``u = a/x`` is returned instead:
    for ``t = −1`` this is the paper's rule ``n = round(a/(2π x0) − 3/4)`` (with the same outermost-minimum
    handling). E2's training needs it: the closest-in-x choice is biased towards ``x → 0`` (the boundary
    between two neighbouring solutions lies at the harmonic, not the arithmetic, mean of their phases),
    and a network trained with it can drift into the ever denser solutions near ``x = 0``.

    Args:
        a: The parameter ``a``: a number (shared by all samples) or a tensor of shape ``(B,)`` with one
            value per sample (numpy arrays are accepted). Must be finite and non-zero.
        closest: ``"x"`` (default) or ``"phase"``: the distance that selects the solution.

    Raises:
        ParameterError: ``a`` contains zero or a non-finite value, or has more than one dimension;
            unknown ``closest``.
    """

    def __init__(self, a: float | torch.Tensor, closest: str = "x"):
        self.closest = check_choice(closest, "closest", ("x", "phase"))
        if isinstance(a, (str, bytes)) or a is None:
            raise ParameterError(f"a must be a number or a (B,) tensor, got {a!r}")
        try:
            a_t = torch.as_tensor(a)
        except (TypeError, ValueError, RuntimeError) as exc:
            raise ParameterError(f"a must be a number or a (B,) tensor, got {a!r}") from exc
        if a_t.is_complex() or a_t.dtype == torch.bool:
            raise ParameterError(f"a must be real, got dtype {a_t.dtype}")
        if not a_t.is_floating_point():
            a_t = a_t.to(torch.get_default_dtype())
        if a_t.ndim > 1:
            raise ParameterError(f"a must be a number or a (B,) tensor, got shape {tuple(a_t.shape)}")
        if not bool(torch.isfinite(a_t).all()) or bool((a_t == 0).any()):
            raise ParameterError("a must be finite and non-zero everywhere")
        self.a = a_t

    def _a_like(self, x: torch.Tensor) -> torch.Tensor:
        a = self.a.to(device=x.device, dtype=x.dtype)
        if a.ndim == 1:
            if a.shape[0] != x.shape[0]:
                raise ShapeError(f"Sine holds {a.shape[0]} values of a but x has batch size {x.shape[0]}")
            a = a.reshape((x.shape[0],) + (1,) * (x.ndim - 1))
        return a

    def select(self, index: slice | torch.Tensor | Sequence[int]) -> Sine:
        """Restricts the per-sample ``a`` to the samples ``index`` (see :meth:`PhysicsOperator.select`).

        Args:
            index: A slice or integer index tensor into the batch dimension.

        Returns:
            A :class:`Sine` for those samples (``self`` when ``a`` is shared).
        """
        if self.a.ndim == 0:
            return self
        return Sine(self.a[index], closest=self.closest)

    def _forward(self, x: torch.Tensor) -> torch.Tensor:
        return torch.sin(self._a_like(x) / x)

    def _local_inverse(
        self, y_target: torch.Tensor, x0: torch.Tensor, y0: torch.Tensor | None
    ) -> torch.Tensor:
        a = self._a_like(x0)
        tiny = torch.finfo(x0.dtype).tiny ** 0.5
        x0s = torch.where(x0.abs() < tiny, torch.full_like(x0, tiny) * torch.where(x0 < 0, -1.0, 1.0), x0)
        u0 = a / x0s
        t = torch.clamp(y_target, -1.0, 1.0)
        theta1 = torch.asin(t)
        theta2 = math.pi - theta1
        two_pi = 2.0 * math.pi
        candidates = []
        for theta in (theta1, theta2):
            n_lo = torch.floor((u0 - theta) / two_pi)
            for n in (n_lo, n_lo + 1.0):
                candidates.append(theta + two_pi * n)
        u = torch.stack(candidates, dim=0)  # (4, B, ...)
        valid = (u * u0.unsqueeze(0)) > 0  # same side of u = 0 as u0; excludes u = 0
        x_cand = a.unsqueeze(0) / torch.where(valid, u, torch.ones_like(u))
        gap = (u - u0.unsqueeze(0)) if self.closest == "phase" else (x_cand - x0s.unsqueeze(0))
        dist = torch.where(valid, gap.abs(), torch.full_like(u, math.inf))
        best = dist.argmin(dim=0, keepdim=True)
        return torch.gather(x_cand, 0, best).squeeze(0)


# --------------------------------------------------------------------------------------------------
# E3: Poisson
# --------------------------------------------------------------------------------------------------


def _check_compute_dtype(dtype: torch.dtype | None) -> torch.dtype | None:
    if dtype is not None and not (isinstance(dtype, torch.dtype) and dtype.is_floating_point):
        raise ParameterError(f"compute_dtype must be a floating torch.dtype or None, got {dtype!r}")
    return dtype


class Poisson(PhysicsOperator):
    """E3 pair: forward ``y = ∇⁻²x`` by conjugate gradients, local inverse the 5-point Laplacian ``x = ∇²y``.

    The forward solves ``∇²_h y = x`` with :func:`phisim.solvers.linalg.cg` on the SPD system ``−∇²_h y = −x``
    (start ``y = 0``; tolerance from ``solve``, E3 uses ``rtol = 1e-5``); its gradient is the implicit
    adjoint solve of :func:`~phisim.solvers.linalg.cg` (no backpropagation through the iterations). ``∇²_h`` is
    :func:`phisim.solvers.poisson.stencil_laplacian`: the second-order cell-centred stencil with boundary values
    on the cell faces (phisim's convention; the reference code puts the zero Dirichlet value in the ghost
    cell instead). The local inverse is the exact inverse of the discrete forward (``∇²_h``), independent
    of ``x0``; it recovers ``x`` from ``P(x)`` to the CG tolerance.

    For boundaries without a Dirichlet side (periodic / Neumann everywhere) the operator is singular: the
    forward projects out the mean (zero-mean ``x`` required for an exact solve, the returned ``y`` has
    zero mean) and the inverse returns a zero-mean ``x``.

    Args:
        dx: Cell spacing (float or one per axis; E3: 1).
        kinds: Boundary kinds per axis (see :func:`phisim.solvers.poisson.normalize_kinds`); E3: ``"dirichlet"``
            (zero values).
        solve: CG settings (default ``Solve(rtol=1e-5)`` as in E3).
        preconditioner: ``None`` (plain CG, as the reference) or ``"spectral"`` (the exact fast solver as
            preconditioner: converges in one iteration).
        convention: Where the zero Dirichlet value sits: ``"face"`` (phisim's convention, on the cell faces:
            ghost ``-u``) or ``"ghost"`` (the reference code's, in the ghost cell: ghost ``0``, a stencil whose
            boundary cells lose the ``-1`` of the face convention; eigenvectors of DST type I). ``"ghost"``
            needs zero Dirichlet on every side.
        compute_dtype: dtype the solve and the inverse run in (default float64; results are cast back to
            the input's dtype and gradients flow through the casts). A float32 CG cannot reach
            ``rtol = 1e-5`` on 64×64 grids (its precision floor); None computes in the input dtype.

    Raises:
        ParameterError: Unknown preconditioner or a non-Solve ``solve``.
        BoundaryError: Invalid ``kinds`` (on first use).
    """

    def __init__(
        self,
        dx=1.0,
        kinds="dirichlet",
        solve: Solve | None = None,
        preconditioner: str | None = None,
        compute_dtype: torch.dtype | None = torch.float64,
        convention: str = "face",
    ):
        check_choice(preconditioner, "preconditioner", (None, "spectral"))
        check_choice(convention, "convention", ("face", "ghost"))
        if convention == "ghost" and kinds != "dirichlet":
            raise ParameterError("convention='ghost' is the zero-Dirichlet-everywhere box of E3: use kinds='dirichlet'")
        self.convention = convention
        solve = Solve(rtol=1e-5) if solve is None else solve
        if not isinstance(solve, Solve):
            raise ParameterError(f"solve must be a phisim.solvers.linalg.Solve, got {type(solve).__name__}")
        self.dx = dx
        self.kinds = kinds
        self.solve = solve
        self.preconditioner = preconditioner
        self.compute_dtype = _check_compute_dtype(compute_dtype)

    def _singular(self, rank: int) -> bool:
        return all("dirichlet" not in pair for pair in normalize_kinds(self.kinds, rank))

    def _forward(self, x: torch.Tensor) -> torch.Tensor:
        if x.ndim < 2 or x.ndim > 4:
            raise ShapeError(f"Poisson expects (B, *resolution) with 1-3 spatial axes, got {tuple(x.shape)}")
        singular = self._singular(x.ndim - 1)
        dtype = x.dtype
        x = x.to(self.compute_dtype or dtype)

        def neg_laplace(u: torch.Tensor) -> torch.Tensor:
            if self.convention == "ghost":
                return -ghost_dirichlet_laplacian(u, self.dx)
            return negative_laplacian(u, self.dx, self.kinds)  # the sign folded into the stencil: one pass less

        pre = None
        if self.preconditioner == "spectral":
            def pre(r: torch.Tensor) -> torch.Tensor:
                if self.convention == "ghost":
                    return -ghost_dirichlet_solve(r, self.dx)
                return -spectral_poisson_solve(r, self.dx, self.kinds, incompatible="project")

        project = remove_mean if singular else None
        y = cg(neg_laplace, -x, solve=self.solve, preconditioner=pre, project=project)
        return y.to(dtype)

    def _local_inverse(
        self, y_target: torch.Tensor, x0: torch.Tensor, y0: torch.Tensor | None
    ) -> torch.Tensor:
        x = self._laplace(y_target.to(self.compute_dtype or x0.dtype))
        x = remove_mean(x) if self._singular(x.ndim - 1) else x
        return x.to(x0.dtype)

    def _laplace(self, u: torch.Tensor) -> torch.Tensor:
        if self.convention == "ghost":
            return ghost_dirichlet_laplacian(u, self.dx)
        return stencil_laplacian(u, self.dx, self.kinds)

    def exact_solve(self, x: torch.Tensor) -> torch.Tensor:
        """``y = ∇⁻²x`` by the exact spectral solver of the operator's convention (float64, no CG)."""
        x64 = x.to(torch.float64)
        if self.convention == "ghost":
            return ghost_dirichlet_solve(x64, self.dx).to(x.dtype)
        return spectral_poisson_solve(x64, self.dx, self.kinds).to(x.dtype)


def _boundary_cells(shape: Sequence[int], dx, dtype, device) -> torch.Tensor:
    """``Σ_axes (number of box sides beside the cell) / dx_a²`` per cell ``(*shape)``."""
    rank = len(shape)
    dx = (float(dx),) * rank if isinstance(dx, (int, float)) else tuple(float(d) for d in dx)
    out = torch.zeros(tuple(shape), dtype=dtype, device=device)
    for a, n in enumerate(shape):
        edge = torch.zeros(n, dtype=dtype, device=device)
        edge[0] += 1.0
        edge[-1] += 1.0
        view = [1] * rank
        view[a] = n
        out = out + edge.view(view) / dx[a] ** 2
    return out


def ghost_dirichlet_laplacian(u: torch.Tensor, dx=1.0) -> torch.Tensor:
    """The 5-point Laplacian with zero Dirichlet values in the ghost cells (ghost ``0``), ``(B, *res)``.

    The convention of the reference code of E3: the face convention's stencil (ghost ``-u``) plus ``u / dx²``
    for every box side beside a cell. Differentiable.
    """
    return stencil_laplacian(u, dx, "dirichlet") + u * _boundary_cells(u.shape[1:], dx, u.dtype, u.device)


def ghost_dirichlet_solve(x: torch.Tensor, dx=1.0) -> torch.Tensor:
    """Exact inverse of :func:`ghost_dirichlet_laplacian` by DST type I on every axis (``(B, *res)``)."""

    res = tuple(x.shape[1:])
    rank = len(res)
    dxs = (float(dx),) * rank if isinstance(dx, (int, float)) else tuple(float(d) for d in dx)
    lam = torch.zeros(res, dtype=torch.float64, device=x.device)
    for a, n in enumerate(res):
        k = torch.arange(1, n + 1, dtype=torch.float64, device=x.device)
        view = [1] * rank
        view[a] = n
        lam = lam + (-4.0 * torch.sin(math.pi * k / (2 * (n + 1))) ** 2 / dxs[a] ** 2).view(view)
    axes = tuple(range(1, rank + 1))
    scale = math.prod(2 * (n + 1) for n in res)
    y = r2rn(x, ("dst1",) * rank, axes)
    return r2rn(y / (lam.to(x.dtype) * scale), ("dst1",) * rank, axes)


# --------------------------------------------------------------------------------------------------
# E4: heat
# --------------------------------------------------------------------------------------------------


class Heat(PhysicsOperator):
    """E4 pair: exact periodic diffusion ``ŷ(k) = x̂(k)·exp(−4π²|k|²·νt)`` and its Bayes-damped inverse.

    Forward: :func:`phisim.solvers.diffusion.fourier_heat` (numpy's ``fftfreq`` wavenumbers in cycles per cell,
    dx = 1, periodic; E4: 64×64, ``νt = 8``, float64).

    Local inverse (paper appendix B.3, as written in EXPERIMENTS.md E4), per sample: residual
    ``r = y* − P(x0)``, ``A = FFT(r)`` (unnormalised, numpy's convention), ``ℓ(k) = 4π²|k|²·νt``;
    noise scale ``σ_n = noise_scale·‖r‖₂``, signal scale ``σ_s(k) = signal_scale·exp(−ℓ(k))``;
    ``p_s = ½ exp(−½(|A|/σ_s)²)``, ``p_n = ½ exp(−½(|A|/σ_n)²)``, ``P = p_s/(p_s + p_n)`` (0/0 → 0);
    action ``a = 2(P − ½)`` where ``P ≤ ½`` or ``P ≥ threshold``, else 0;
    ``x = x0 + Re IFFT(A·exp(a·ℓ))``. ``a = 1`` inverts the mode fully (a mode that is clearly signal),
    ``a = 0`` leaves it, ``a < 0`` diffuses it further (a mode dominated by noise). The amplification
    ``exp(a·ℓ)`` only reaches ``exp(ℓ)`` where ``|A| ≲ σ_s(k)``, so the result stays bounded
    (``≲ signal_scale`` per mode) whatever the noise in ``y*``.

    Args:
        nu_t: ``ν·t`` (E4: 8).
        noise_scale: Relative noise level of the residual (E4: 1e-6).
        signal_scale: Prior amplitude of the signal's Fourier coefficients (E4: 64).
        threshold: ``P`` above which a mode is (partly) inverted (E4: 0.68).
        noise_floor: Optional lower bound of ``σ_n`` relative to ``‖y*‖₂`` (not part of E4; default 0).
            ``σ_n`` is proportional to the residual, so once the residual is at round-off level, iterating
            the inverse treats round-off as signal and amplifies it (bounded by the prior, about
            ``signal_scale`` per Fourier coefficient). A floor such as ``1e-6`` (the noise of ``y*``)
            avoids that when the inverse is iterated to convergence on one problem.
        compute_dtype: dtype forward and inverse run in (default float64, as E4; results are cast back to
            the input's dtype). The inverse needs float64: ``exp(ℓ)`` reaches ``e^158`` on 64×64 grids.

    Raises:
        ParameterError: Non-finite or non-positive settings, ``threshold`` outside ``[0.5, 1]``.
    """

    def __init__(self, nu_t: float = 8.0, noise_scale: float = 1e-6, signal_scale: float = 64.0,
                 threshold: float = 0.68, noise_floor: float = 0.0,
                 compute_dtype: torch.dtype | None = torch.float64):
        self.nu_t = check_number(nu_t, "nu_t", minimum=0, min_open=True)
        self.noise_scale = check_number(noise_scale, "noise_scale", minimum=0, min_open=True)
        self.signal_scale = check_number(signal_scale, "signal_scale", minimum=0, min_open=True)
        self.noise_floor = check_number(noise_floor, "noise_floor", minimum=0)
        self.compute_dtype = _check_compute_dtype(compute_dtype)
        self.threshold = check_number(threshold, "threshold", minimum=0.5, maximum=1.0)

    def _forward(self, x: torch.Tensor) -> torch.Tensor:
        if x.ndim < 2 or x.ndim > 4:
            raise ShapeError(f"Heat expects (B, *resolution) with 1-3 spatial axes, got {tuple(x.shape)}")
        return fourier_heat(x.to(self.compute_dtype or x.dtype), self.nu_t).to(x.dtype)

    def exponent(self, resolution: Sequence[int], dtype: torch.dtype, device) -> torch.Tensor:
        """``ℓ(k) = 4π²|k|²·νt`` in the full FFT layout.

        Args:
            resolution: Cells per axis.
            dtype: Real dtype.
            device: Device.

        Returns:
            Tensor of shape ``resolution``.
        """
        return 4 * math.pi**2 * self.nu_t * fourier_k2(resolution, real=False, dtype=dtype, device=device)

    def _local_inverse(
        self, y_target: torch.Tensor, x0: torch.Tensor, y0: torch.Tensor | None
    ) -> torch.Tensor:
        out_dtype = x0.dtype
        dtype = self.compute_dtype or x0.dtype
        x0 = x0.to(dtype)
        y0 = self._forward(x0) if y0 is None else y0.to(dtype)
        r = y_target.to(dtype) - y0
        axes = tuple(range(1, r.ndim))
        amp = torch.fft.fftn(r, dim=axes)
        ell = self.exponent(r.shape[1:], r.dtype, r.device)
        bshape = (r.shape[0],) + (1,) * (r.ndim - 1)
        tiny = torch.finfo(r.dtype).tiny
        norm = torch.linalg.vector_norm(r.reshape(r.shape[0], -1), dim=1).reshape(bshape)
        sigma_n = self.noise_scale * norm
        if self.noise_floor > 0:
            t_norm = torch.linalg.vector_norm(y_target.reshape(r.shape[0], -1), dim=1).reshape(bshape)
            sigma_n = torch.maximum(sigma_n, self.noise_floor * t_norm)
        sigma_n = sigma_n.clamp_min(tiny)
        sigma_s = (self.signal_scale * torch.exp(-ell)).clamp_min(tiny)
        mag = amp.abs()
        p_s = 0.5 * torch.exp(-0.5 * (mag / sigma_s) ** 2)
        p_n = 0.5 * torch.exp(-0.5 * (mag / sigma_n) ** 2)
        denom = p_s + p_n
        prob = torch.where(denom > 0, p_s / torch.where(denom > 0, denom, 1.0), torch.zeros_like(denom))
        act = (prob <= 0.5) | (prob >= self.threshold)
        action = torch.where(act, 2 * (prob - 0.5), torch.zeros_like(prob))
        dx = torch.fft.ifftn(amp * torch.exp(action * ell), dim=axes).real
        return (x0 + dx).to(out_dtype)
