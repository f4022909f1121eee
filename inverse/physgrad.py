"""The physical-gradient (scale-invariant physics, SIP) layer.

Training a network ``x = f_θ(y*)`` through a physics process ``y = P(x)`` normally backpropagates the
y-space loss through ``P``. Physical-gradient training (Holl, Koltun, Thuerey, "Physical Gradients for
Deep Learning", eq. 5 and algorithm 1) replaces the gradient of ``P`` by a local inverse:

1. ``y = P(x)`` (forward simulation),
2. ``Δy`` = a Newton step of the y-space loss ``L(y)`` (for ``½‖y − y*‖²``: ``Δy = η (y* − y)``),
3. ``x̃ = P⁻¹(y + Δy; x)`` (local inverse conditioned on the prediction),
4. proxy loss ``½‖x − stopgrad(x̃)‖²``, backpropagated through ``f_θ`` only, any torch optimizer.

The gradient the network receives at ``x`` is the physical gradient ``x − x̃``. If ``P⁻¹`` is one
gradient-descent step on ``½‖P(x) − (y + Δy)‖²`` with step 1 and ``η = 1``, then
``x − x̃ = Jᵀ(P(x) − y − Δy) = Jᵀ(y − y*)`` is exactly the backpropagated gradient (theorem 1,
appendix A.1). With an exact inverse and ``η = 1``, ``x̃`` solves ``P(x̃) = y*`` (scale invariance:
reparametrising ``x`` or ``y`` by an invertible map leaves the trajectory unchanged).

Two entry points:

* :func:`physical_gradient_loss` (and :func:`physical_update`): the proxy loss, for training loops
  where the network output ``x`` and the target ``y*`` are at hand.
* :class:`PhysicalGradient` / :func:`physgrad`: an autograd Function whose forward returns ``P(x)`` and
  whose backward returns the physical gradient, for users who put ``P`` inside a bigger graph.

Quadratic y-space losses :class:`QuadraticLoss` ``L(y) = ½ Σ_k w_k |(T(y − y*))_k|²`` with a unitary
linear transform ``T`` (identity, or the orthonormal FFT via :class:`FourierTransform`) supply the Newton
step ``Δy``. Since the Hessian is ``Tᴴ W T``, the Newton step is ``Δy = η Tᴴ M T (y* − y)`` with
``M_k = w_k/(w_k + λ)`` (``λ``: Levenberg damping, default 0, i.e. ``M_k = 1`` where ``w_k > 0``): the
weights cancel, apart from modes the loss ignores (``w_k = 0``, or below ``rcond·max w``), which the step
leaves alone. A frequency-weighted loss such as E5's is
``QuadraticLoss(weights=w(k), transform=FourierTransform(2))``.
"""

from __future__ import annotations

from collections.abc import Callable

import torch

from phisim.checks import (
    check_batch_compatible,
    check_callable_output,
    check_choice,
    check_int,
    check_number,
    check_positive,
)
from phisim.errors import ParameterError, ShapeError

from .operators import PhysicsOperator, check_finite

__all__ = [
    "QuadraticLoss",
    "FourierTransform",
    "physical_update",
    "physical_gradient_loss",
    "PhysicalGradient",
    "physgrad",
]


def _check_eta(eta: float) -> float:
    return check_number(eta, "eta (a finite positive number, typically in (0, 1])", minimum=0, min_open=True)


class FourierTransform:
    """Orthonormal (unitary) discrete Fourier transform over the last ``ndim`` axes.

    ``T(y) = fftn(y, norm="ortho")``; the inverse returns the real part of ``ifftn(·, norm="ortho")``
    (exact for real signals when the weights used between the two are symmetric, ``w(k) = w(−k)``, e.g.
    functions of ``|k|``). Differentiable (torch.fft).

    Args:
        ndim: Number of trailing (spatial) axes transformed, e.g. 2 for ``(B, X, Y)`` fields.

    Raises:
        ParameterError: ``ndim < 1``.
    """

    def __init__(self, ndim: int):
        self.ndim = check_int(ndim, "ndim", minimum=1)

    def __call__(self, y: torch.Tensor) -> torch.Tensor:
        """Forward transform.

        Args:
            y: ``(..., *spatial)`` real or complex.

        Returns:
            Complex coefficients of the same shape.
        """
        return torch.fft.fftn(y, dim=tuple(range(-self.ndim, 0)), norm="ortho")

    def inverse(self, c: torch.Tensor) -> torch.Tensor:
        """Inverse transform (real part).

        Args:
            c: ``(..., *spatial)`` complex coefficients.

        Returns:
            Real tensor of the same shape.
        """
        return torch.fft.ifftn(c, dim=tuple(range(-self.ndim, 0)), norm="ortho").real


class QuadraticLoss:
    """Diagonal weighted quadratic y-space loss ``L(y) = ½ Σ_k w_k |(T(y − y*))_k|²`` per sample.

    ``T`` is the identity (weights applied elementwise) or a unitary linear transform with an
    ``inverse`` method (e.g. :class:`FourierTransform`). ``QuadraticLoss()`` is the plain
    ``½‖y − y*‖²`` of the paper ("l2_loss" of the reference code: a sum over cells and channels).

    Args:
        weights: ``w_k ≥ 0``, broadcastable to ``T(y)``'s shape ``(B, *y_shape)`` (usually
            ``y_shape``), or None for all ones.
        transform: None (identity) or a callable unitary transform with an ``inverse`` method.
        damping: Levenberg damping ``λ ≥ 0`` of the Newton step (``M_k = w_k/(w_k + λ)``).
        rcond: Weights ``w_k ≤ rcond·max(w)`` count as zero in the Newton step.

    Raises:
        ParameterError: Negative or non-finite weights, negative damping/rcond, or a transform without
            ``inverse``.
    """

    def __init__(
        self,
        weights: torch.Tensor | None = None,
        transform: Callable[[torch.Tensor], torch.Tensor] | None = None,
        damping: float = 0.0,
        rcond: float = 0.0,
    ):
        if weights is not None:
            if isinstance(weights, (str, bytes)):
                raise ParameterError(f"weights must be a tensor of numbers >= 0, got {weights!r}")
            try:
                weights = torch.as_tensor(weights)
            except (TypeError, ValueError, RuntimeError) as exc:
                raise ParameterError(f"weights must be a tensor of numbers >= 0, got {weights!r}") from exc
            if weights.is_complex() or weights.dtype == torch.bool:
                raise ParameterError(f"weights must be real, got dtype {weights.dtype}")
            if not bool(torch.isfinite(weights).all()) or bool((weights < 0).any()):
                raise ParameterError("weights must be finite and non-negative")
        if transform is not None and not (callable(transform) and callable(getattr(transform, "inverse", None))):
            raise ParameterError("transform must be callable with an inverse(c) method (unitary transform)")
        self.weights = weights
        self.transform = transform
        self.damping = check_number(damping, "damping", minimum=0)
        self.rcond = check_number(rcond, "rcond", minimum=0)

    def _fwd(self, r: torch.Tensor) -> torch.Tensor:
        if self.transform is None:
            return r
        return check_callable_output(self.transform(r), r.shape, self.transform, "transform", finite=False)

    def _inv(self, c: torch.Tensor) -> torch.Tensor:
        if self.transform is None:
            return c
        return check_callable_output(self.transform.inverse(c), c.shape, self.transform.inverse, "transform.inverse",
                                     finite=False)

    def _weights_like(self, c: torch.Tensor) -> torch.Tensor | None:
        if self.weights is None:
            return None
        real_dtype = c.real.dtype if c.is_complex() else c.dtype
        return self.weights.to(device=c.device, dtype=real_dtype)

    def value(self, y: torch.Tensor, y_target: torch.Tensor) -> torch.Tensor:
        """Per-sample loss ``½ Σ_k w_k |(T(y − y*))_k|²`` (differentiable).

        Args:
            y: ``(B, *y_shape)``.
            y_target: ``(B, *y_shape)``.

        Returns:
            ``(B,)``.
        """
        c = self._fwd(y - y_target)
        sq = c.real**2 + c.imag**2 if c.is_complex() else c**2
        w = self._weights_like(c)
        if w is not None:
            sq = sq * w
        return 0.5 * sq.reshape(sq.shape[0], -1).sum(dim=1)

    def newton_step(self, y: torch.Tensor, y_target: torch.Tensor, eta: float = 1.0) -> torch.Tensor:
        """Newton step ``Δy = −η H⁺ ∇L = η Tᴴ M T (y* − y)`` of the loss at ``y``.

        Args:
            y: ``(B, *y_shape)``.
            y_target: ``(B, *y_shape)``.
            eta: Step size ``η > 0`` (1: the full Newton step, which reaches ``y*`` in the kept modes).

        Returns:
            ``Δy``, ``(B, *y_shape)``.

        Raises:
            ParameterError: Invalid ``eta``.
        """
        eta = _check_eta(eta)
        c = self._fwd(y_target - y)
        w = self._weights_like(c)
        if w is not None:
            cutoff = self.rcond * float(w.max()) if w.numel() else 0.0
            w_eff = torch.where(w > cutoff, w, torch.zeros_like(w))
            if self.damping > 0:
                mask = w_eff / (w_eff + self.damping)
            else:
                mask = (w_eff > 0).to(w.dtype)
            c = c * mask
        elif self.damping > 0:
            c = c / (1.0 + self.damping)
        return eta * self._inv(c)


_L2 = QuadraticLoss()


def physical_update(
    x: torch.Tensor,
    y_target: torch.Tensor,
    operator: PhysicsOperator,
    eta: float = 1.0,
    loss: QuadraticLoss | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """One physical-gradient correction: ``x̃ = P⁻¹(y + Δy; x)`` with ``y = P(x)``.

    Args:
        x: ``(B, *x_shape)``, the prediction (its autograd graph is not used).
        y_target: ``(B, *y_shape)``, the target ``y*``.
        operator: The forward/local-inverse pair.
        eta: y-space step size ``η > 0``: ``Δy = loss.newton_step(y, y*, η)`` (``η (y* − y)`` for L2).
        loss: The y-space loss supplying the Newton step (default ``½‖y − y*‖²``).

    Returns:
        ``(x̃, y)``: the corrected state ``(B, *x_shape)`` and ``P(x)`` ``(B, *y_shape)``, both detached.

    Batch sizes: ``x`` and ``y_target`` have the same batch size, or ``y_target`` has 1 (one target shared by
    every sample).

    Raises:
        ParameterError: Invalid ``eta``.
        ShapeError: ``y_target``'s shape differs from ``P(x)``'s, or its batch size is neither ``x``'s nor 1.
        NonFiniteError: ``x`` or ``y_target`` contain NaN/Inf.
    """
    eta = _check_eta(eta)
    loss = _L2 if loss is None else loss
    xd = x.detach()
    y_target = torch.as_tensor(y_target, device=xd.device).detach()
    if xd.ndim >= 1 and y_target.ndim >= 1:
        check_batch_compatible(xd, y_target, ("x", "y_target"), "compute a physical update")
        if y_target.shape[0] == 1 != xd.shape[0]:
            y_target = y_target.expand(xd.shape[0], *y_target.shape[1:])
    check_finite("x", xd)
    check_finite("y_target", y_target)
    with torch.no_grad():
        y = operator.forward(xd)
    if tuple(y.shape) != tuple(y_target.shape):
        raise ShapeError(
            f"y_target has shape {tuple(y_target.shape)} but P(x) has shape {tuple(y.shape)}"
        )
    with torch.no_grad():
        dy = loss.newton_step(y, y_target.to(y.dtype), eta)
    x_tilde = operator.local_inverse(y + dy, xd, y0=y)
    return x_tilde.detach(), y.detach()


def physical_gradient_loss(
    x: torch.Tensor,
    y_target: torch.Tensor,
    operator: PhysicsOperator,
    eta: float = 1.0,
    reduction: str = "sum",
    loss: QuadraticLoss | None = None,
) -> torch.Tensor:
    """Proxy loss ``½‖x − stopgrad(x̃)‖²`` whose gradient at ``x`` is the physical gradient ``x − x̃``.

    ``x̃ = P⁻¹(y + Δy; x)``, ``y = P(x)``, ``Δy`` the Newton step of the y-space loss (see
    :func:`physical_update`). Backpropagating this loss trains the network producing ``x`` with physical
    gradients (paper eq. 5, algorithm 1) using any torch optimizer. The loss *value* is not the y-space
    loss; report that separately.

    Args:
        x: ``(B, *x_shape)``, the network prediction (with autograd history).
        y_target: ``(B, *y_shape)``.
        operator: The forward/local-inverse pair.
        eta: y-space step size ``η > 0``.
        reduction: ``"sum"``: ``½ Σ_{i,cells} (x − x̃)²`` (the batch sum, as Poisson/heat in the
            reference); ``"mean"``: the per-sample sums averaged over the batch (as sine/fluid).
        loss: The y-space loss supplying ``Δy`` (default ``½‖y − y*‖²``).

    Returns:
        A scalar tensor, differentiable with respect to ``x``.

    Raises:
        ParameterError: Invalid ``eta`` or ``reduction``.
        ShapeError: ``y_target``'s shape differs from ``P(x)``'s.
        NonFiniteError: ``x`` or ``y_target`` contain NaN/Inf.
    """
    check_choice(reduction, "reduction", ("sum", "mean"))
    x_tilde, _ = physical_update(x, y_target, operator, eta=eta, loss=loss)
    per_sample = 0.5 * ((x - x_tilde) ** 2).reshape(x.shape[0], -1).sum(dim=1)
    return per_sample.sum() if reduction == "sum" else per_sample.mean()


class PhysicalGradient(torch.autograd.Function):
    """Autograd Function: forward ``y = P(x)``, backward the physical gradient instead of ``Jᵀ g``.

    Backward, given the incoming gradient ``g = ∂ℒ/∂y`` of the downstream loss ``ℒ``: the Newton step of
    a downstream loss with identity Hessian (``ℒ = ½‖y − y*‖²``, for which ``g = y − y*``) is
    ``Δy = −η s g``, the local inverse gives ``x̃ = P⁻¹(y + Δy; x)``, and the returned gradient is
    ``(x − x̃)/s``. ``s`` (``grad_scale``) undoes an overall factor of the downstream loss, e.g. ``s = B``
    for a batch mean, so the local inverse sees the full-size step; the division keeps the returned
    gradient in the loss's own scale. For a one-gradient-step inverse with step 1 and ``η = 1`` the result
    is ``Jᵀ g`` exactly, the ordinary gradient (theorem 1), for any ``s``.

    Use ``PhysicalGradient.apply(x, operator, eta, grad_scale)`` or :func:`physgrad`. Not twice
    differentiable.
    """

    @staticmethod
    def forward(ctx, x: torch.Tensor, operator: PhysicsOperator, eta: float = 1.0, grad_scale: float = 1.0):
        """Evaluates ``P(x)`` and stores what backward needs.

        Args:
            ctx: Autograd context.
            x: ``(B, *x_shape)``.
            operator: The forward/local-inverse pair.
            eta: y-step size ``η > 0``.
            grad_scale: ``s > 0``.

        Returns:
            ``y = P(x)``, ``(B, *y_shape)``.

        Raises:
            ParameterError: Invalid ``eta`` or ``grad_scale``.
        """
        eta = _check_eta(eta)
        scale = float(check_positive(grad_scale, "grad_scale"))
        y = operator.forward(x.detach())
        ctx.operator = operator
        ctx.eta = eta
        ctx.scale = scale
        ctx.save_for_backward(x.detach(), y.detach())
        return y

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad_y: torch.Tensor):
        """Returns ``(x − P⁻¹(y − η s g; x))/s`` for ``x``.

        Args:
            ctx: Autograd context.
            grad_y: ``g``, ``(B, *y_shape)``.

        Returns:
            Gradients for ``(x, operator, eta, grad_scale)``; only the first is not None.
        """
        x, y = ctx.saved_tensors
        target = y - ctx.eta * ctx.scale * grad_y.to(y.dtype)
        x_tilde = ctx.operator.local_inverse(target, x, y0=y)
        return (x - x_tilde) / ctx.scale, None, None, None


def physgrad(
    operator: PhysicsOperator, eta: float = 1.0, grad_scale: float = 1.0
) -> Callable[[torch.Tensor], torch.Tensor]:
    """Wraps ``operator`` as a differentiable function ``x -> P(x)`` with physical-gradient backward.

    Args:
        operator: The forward/local-inverse pair.
        eta: y-step size ``η > 0``.
        grad_scale: ``s > 0``, see :class:`PhysicalGradient` (use the batch size for a batch-mean loss).

    Returns:
        A function ``x -> PhysicalGradient.apply(x, operator, eta, grad_scale)``.

    Raises:
        ParameterError: Invalid ``eta`` or ``grad_scale``.
    """
    eta = _check_eta(eta)
    check_positive(grad_scale, "grad_scale")

    def apply(x: torch.Tensor) -> torch.Tensor:
        return PhysicalGradient.apply(x, operator, eta, grad_scale)

    return apply
