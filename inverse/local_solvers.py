"""Generic local inverses for any differentiable batched forward process.

Each solver approximates the local inverse ``x = P⁻¹(y*; x0)`` of a forward process ``P`` by running a
few iterations of a classical optimiser on the per-sample y-space objective

    L_i(x_i) = ½ ‖P(x)_i − y*_i‖²,        i = 1 … B,

started from the current guess ``x0`` (Holl, Koltun, Thuerey, "Physical Gradients for Deep Learning",
section 2.2: ``P⁻¹_n(y* | x0)``, n iterations of an inverse-problem solver conditioned on ``x0``). The
samples of a batch are independent problems: ``P(x)_i`` must depend on ``x_i`` only (no batch coupling,
e.g. no BatchNorm in training mode inside ``P``).

Solvers are objects: settings go to ``__init__``, and ``solver(forward, y_target, x0) -> x`` runs them.
``forward`` is a callable ``(B, *x_shape) -> (B, *y_shape)`` or a
:class:`~inverse.operators.PhysicsOperator` (whose :meth:`~inverse.operators.PhysicsOperator.select` is
then used where a solver works sample by sample, so per-sample parameters stay aligned).
:class:`SolverOperator` turns any forward plus a solver into a :class:`~inverse.operators.PhysicsOperator`.

Solvers:

* :class:`GradientStepSolver`: ``x ← x − η ∂L/∂x``. With one step and ``η = 1`` physical-gradient
  training equals ordinary differentiable-physics training (theorem 1, appendix A.1).
* :class:`NewtonSolver`: ``x ← x − η H⁻¹ ∂L/∂x`` with the full per-sample Hessian of ``L``
  (torch.func), optionally saddle-free (``|λ|`` of the eigenvalues) and with the step clipped.
* :class:`InverseGradientSolver`: ``x ← x + η J⁺ (y* − P(x))`` (Newton-Raphson / Gauss-Newton on
  ``P(x) = y*``), ``J = ∂P/∂x`` per sample via torch.func (``vjp`` + ``vmap``).
* :class:`LBFGSBSolver`: ``scipy.optimize.minimize(method="L-BFGS-B")`` for ``max_iter`` iterations,
  per sample, in float64 on the CPU; the result is cast back to ``x0``'s device and dtype.

Newton and the inverse gradient build dense per-sample matrices (``n × n`` and ``m × n`` with ``n``, ``m``
the numbers of entries of one sample of ``x`` and ``y``): they are meant for small problems (E1, E2).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np
import scipy.optimize
import torch

from phisim.checks import (
    callable_name,
    check_batch_compatible,
    check_bool,
    check_callable,
    check_callable_output,
    check_int,
    check_number,
)
from phisim.errors import NonFiniteError, ParameterError, ShapeError

from .operators import PhysicsOperator, check_finite

__all__ = [
    "LocalSolver",
    "GradientStepSolver",
    "NewtonSolver",
    "InverseGradientSolver",
    "LBFGSBSolver",
    "SolverOperator",
    "batch_jacobian",
    "batch_hessian",
]

Forward = Callable[[torch.Tensor], torch.Tensor]


# --------------------------------------------------------------------------------------------------
# helpers
# --------------------------------------------------------------------------------------------------


def _evaluator(forward: Forward | PhysicsOperator) -> Forward:
    """The raw (unchecked) forward function of ``forward``."""
    if isinstance(forward, PhysicsOperator):
        return forward._forward
    return check_callable(forward, "forward (a callable or a PhysicsOperator)")


def _select(forward: Forward | PhysicsOperator, index: slice) -> Forward:
    """The forward restricted to the samples ``index`` (identity for plain callables)."""
    if isinstance(forward, PhysicsOperator):
        return forward.select(index)._forward
    return forward


def _per_sample_rows(fn: Forward, x: torch.Tensor, reverse_fn: Forward | None = None) -> torch.Tensor:
    """Per-sample Jacobian ``∂fn(x)_i/∂x_i`` of a batched, sample-independent ``fn``, shape ``(B, m, n)``.

    Uses one reverse-mode pass (``torch.func.vjp``) and ``torch.func.vmap`` over the ``m`` cotangents
    ``e_j`` (the same unit vector in every sample): since sample ``i`` of the output depends on sample
    ``i`` of the input only, the cotangent ``e_j`` broadcast over the batch returns row ``j`` of every
    sample's Jacobian at once. Falls back to a loop of ``torch.autograd.grad`` calls where ``fn`` is not
    supported by ``torch.func`` (e.g. a custom autograd Function without vmap support); in that case
    ``reverse_fn`` (an autograd-based equivalent of ``fn``, default ``fn``) is used.
    """
    b = x.shape[0]
    n = x[0].numel()
    try:
        y, vjp_fn = torch.func.vjp(fn, x)
        m = y[0].numel()
        eye = torch.eye(m, dtype=y.dtype, device=y.device)
        cot = eye[:, None, :].expand(m, b, m).reshape((m,) + tuple(y.shape))
        (rows,) = torch.func.vmap(vjp_fn)(cot)
    except (RuntimeError, NotImplementedError):
        fn_ag = reverse_fn or fn
        xg = x.detach().requires_grad_(True)
        with torch.enable_grad():
            y = fn_ag(xg)
            m = y[0].numel()
            rows_list = []
            for j in range(m):
                cot = torch.zeros_like(y).reshape(b, m)
                cot[:, j] = 1.0
                (g,) = torch.autograd.grad(y, xg, cot.reshape(y.shape), retain_graph=True, allow_unused=True)
                rows_list.append(torch.zeros_like(xg) if g is None else g)
        rows = torch.stack(rows_list, dim=0)
    return rows.reshape(m, b, n).permute(1, 0, 2).detach()


def batch_jacobian(forward: Forward | PhysicsOperator, x: torch.Tensor) -> torch.Tensor:
    """Per-sample Jacobians ``J_i = ∂P(x)_i / ∂x_i`` of a batched forward process.

    Args:
        forward: Callable ``(B, *x_shape) -> (B, *y_shape)`` (or a PhysicsOperator) whose sample ``i``
            depends on ``x_i`` only.
        x: ``(B, *x_shape)``.

    Returns:
        ``J``, ``(B, m, n)`` with ``m = prod(y_shape)``, ``n = prod(x_shape)``; rows index the flattened
        output, columns the flattened input. Detached.
    """
    fn = _evaluator(forward)
    return _per_sample_rows(fn, x.detach())


def batch_hessian(
    forward: Forward | PhysicsOperator, y_target: torch.Tensor, x: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-sample gradient and Hessian of ``L_i(x_i) = ½‖P(x)_i − y*_i‖²``.

    The Hessian is ``J_iᵀJ_i + Σ_k (P(x)_i − y*_i)_k ∂²P_k/∂x_i²`` (not the Gauss-Newton approximation),
    computed as the per-sample Jacobian of the gradient (reverse over reverse, torch.func).

    Args:
        forward: Callable ``(B, *x_shape) -> (B, *y_shape)`` or a PhysicsOperator.
        y_target: ``(B, *y_shape)``.
        x: ``(B, *x_shape)``.

    Returns:
        ``(g, H)``: ``g`` of shape ``(B, n)`` and ``H`` of shape ``(B, n, n)``, detached.
    """
    fn = _evaluator(forward)
    y_target = y_target.detach()

    def total(z: torch.Tensor) -> torch.Tensor:
        return 0.5 * ((fn(z) - y_target) ** 2).sum()

    def grad_func(z: torch.Tensor) -> torch.Tensor:
        return torch.func.grad(total)(z)

    def grad_autograd(z: torch.Tensor) -> torch.Tensor:
        with torch.enable_grad():
            z = z if z.requires_grad else z.requires_grad_(True)
            (g,) = torch.autograd.grad(total(z), z, create_graph=True)
        return g

    x = x.detach()
    try:
        g = grad_func(x)
    except (RuntimeError, NotImplementedError):
        g = grad_autograd(x.clone())
    hess = _per_sample_rows(grad_func, x, reverse_fn=grad_autograd)
    return g.reshape(x.shape[0], -1).detach(), hess


# --------------------------------------------------------------------------------------------------
# solvers
# --------------------------------------------------------------------------------------------------


def _check_positive(name: str, value: float) -> float:
    return check_number(value, name, minimum=0, min_open=True)


def _check_iterations(value: int, name: str = "max_iter") -> int:
    return check_int(value, name, minimum=1)


class LocalSolver:
    """Base class of the generic local inverses: ``solver(forward, y_target, x0) -> x``.

    Subclasses implement :meth:`_solve`; :meth:`__call__` validates the input (finite values, the
    target's shape against ``forward(x0)``), runs the solver with autograd enabled (also inside a
    ``torch.no_grad()`` block) and returns a detached result of ``x0``'s shape, device and dtype.
    """

    def __call__(
        self, forward: Forward | PhysicsOperator, y_target: torch.Tensor, x0: torch.Tensor
    ) -> torch.Tensor:
        """Runs the solver from ``x0`` towards ``P(x) = y_target``.

        Args:
            forward: Callable ``(B, *x_shape) -> (B, *y_shape)`` or a PhysicsOperator; differentiable.
            y_target: ``(B, *y_shape)``.
            x0: ``(B, *x_shape)``, the start (the guess the inverse is conditioned on).

        Returns:
            ``x``, ``(B, *x_shape)``, detached.

        Batch sizes: ``x0`` and ``y_target`` have the same batch size, or one of them 1 (shared by every sample
        of the other; the result has the common batch size).

        Raises:
            ShapeError: ``y_target``'s shape differs from ``forward(x0)``'s, the batch sizes differ (and neither
                is 1), ``forward`` does not keep the batch size, or the solver returns another shape than
                ``x0``'s (each naming the callable).
            NonFiniteError: ``x0``, ``y_target`` or ``forward(x0)`` contain NaN/Inf, or the solver's result does.
            ParameterError: ``forward`` is not callable (also a ``TypeError``).
        """
        x0 = torch.as_tensor(x0).detach()
        y_target = torch.as_tensor(y_target, device=x0.device).detach()
        if y_target.is_floating_point():
            y_target = y_target.to(x0.dtype)
        if x0.ndim < 1 or y_target.ndim < 1:
            raise ShapeError("x0 and y_target must be batch-first tensors with at least one dimension")
        batch = check_batch_compatible(x0, y_target, ("x0", "y_target"), "solve (batch sizes differ)")
        x0 = x0.expand(batch, *x0.shape[1:]).clone() if x0.shape[0] != batch else x0
        y_target = y_target.expand(batch, *y_target.shape[1:]) if y_target.shape[0] != batch else y_target
        check_finite("x0", x0)
        check_finite("y_target", y_target)
        fn = _evaluator(forward)
        with torch.no_grad():
            y0 = fn(x0)
        if not isinstance(y0, torch.Tensor) or y0.ndim < 1 or y0.shape[0] != batch:
            shape = tuple(y0.shape) if isinstance(y0, torch.Tensor) else type(y0).__name__
            raise ShapeError(f"forward {callable_name(forward)} returned {shape} for x0 of shape {tuple(x0.shape)}; "
                             f"it must keep the batch size {batch} on axis 0")
        if tuple(y0.shape) != tuple(y_target.shape):
            raise ShapeError(
                f"y_target has shape {tuple(y_target.shape)} but forward(x0) has shape {tuple(y0.shape)}"
            )
        if not bool(torch.isfinite(y0).all()):
            raise NonFiniteError("forward(x0) contains NaN/Inf; the start x0 is outside the forward's domain")
        with torch.enable_grad():
            x = self._solve(forward, y_target, x0)
        check_callable_output(x, x0.shape, None, f"local solver {type(self).__name__}")
        return x.detach().to(device=x0.device, dtype=x0.dtype)

    def _solve(
        self, forward: Forward | PhysicsOperator, y_target: torch.Tensor, x0: torch.Tensor
    ) -> torch.Tensor:
        raise NotImplementedError


def _clip(step: torch.Tensor, clip: float | None) -> torch.Tensor:
    return step if clip is None else torch.clamp(step, -clip, clip)


class GradientStepSolver(LocalSolver):
    """Gradient descent on ``L_i = ½‖P(x)_i − y*_i‖²``: ``x ← x − η Jᵀ(P(x) − y*)``.

    One step with ``η = 1`` is the local inverse of theorem 1 (appendix A.1 of the paper): the
    physical-gradient proxy loss then gives exactly the gradient of ordinary backpropagation through
    ``P``.

    Args:
        step_size: ``η > 0``.
        max_iter: Number of steps (default 1).

    Raises:
        ParameterError: Non-positive or non-finite ``step_size``; ``max_iter < 1``.
    """

    def __init__(self, step_size: float = 1.0, max_iter: int = 1):
        self.step_size = _check_positive("step_size", step_size)
        self.max_iter = _check_iterations(max_iter)

    def _solve(self, forward, y_target, x0):
        fn = _evaluator(forward)
        x = x0.clone()
        for _ in range(self.max_iter):
            xg = x.detach().requires_grad_(True)
            loss = 0.5 * ((fn(xg) - y_target) ** 2).sum()
            (g,) = torch.autograd.grad(loss, xg)
            x = x - self.step_size * g
        return x


class NewtonSolver(LocalSolver):
    """Newton's method on ``L_i = ½‖P(x)_i − y*_i‖²`` with the full per-sample Hessian.

    Update per sample: ``Δx = −η V f(Λ) Vᵀ g`` with ``H = V Λ Vᵀ`` (``torch.linalg.eigh``), ``g = ∂L/∂x``
    and ``f(λ) = 1/λ`` (plain Newton) or ``1/|λ|`` (``saddle_free=True``: always a descent direction,
    Dauphin et al. 2014); eigenvalues with ``|λ| ≤ rcond·max|λ|`` are dropped (pseudo-inverse). With
    ``clip`` the step is clipped elementwise to ``[−clip, clip]`` (the remedy of E2/E3 for the diverging
    Newton steps where the Hessian is singular).

    Args:
        max_iter: Newton iterations (default 1).
        step_size: ``η > 0`` (default 1).
        saddle_free: Use ``|λ|`` instead of ``λ``.
        clip: Elementwise bound of each step, or None.
        rcond: Relative eigenvalue cut-off.

    Raises:
        ParameterError: Invalid settings.
    """

    def __init__(
        self,
        max_iter: int = 1,
        step_size: float = 1.0,
        saddle_free: bool = False,
        clip: float | None = None,
        rcond: float = 1e-12,
    ):
        self.max_iter = _check_iterations(max_iter)
        self.step_size = _check_positive("step_size", step_size)
        self.saddle_free = check_bool(saddle_free, "saddle_free")
        self.clip = None if clip is None else _check_positive("clip", clip)
        self.rcond = check_number(rcond, "rcond", minimum=0)

    def _solve(self, forward, y_target, x0):
        x = x0.clone()
        for _ in range(self.max_iter):
            g, hess = batch_hessian(forward, y_target, x)
            lam, vec = torch.linalg.eigh(hess)
            mag = lam.abs()
            keep = mag > self.rcond * mag.amax(dim=-1, keepdim=True)
            denom = mag if self.saddle_free else lam
            safe = torch.where(keep, denom, torch.ones_like(denom))
            inv = torch.where(keep, 1.0 / safe, torch.zeros_like(lam))
            coeff = (vec.transpose(-1, -2) @ g.unsqueeze(-1)).squeeze(-1)
            step = -self.step_size * (vec @ (inv * coeff).unsqueeze(-1)).squeeze(-1)
            x = x + _clip(step, self.clip).reshape(x.shape)
        return x


class InverseGradientSolver(LocalSolver):
    """Inverse-gradient iterations ``x ← x + η J⁺ (y* − P(x))`` (Newton-Raphson on ``P(x) = y*``).

    ``J = ∂P/∂x`` per sample (:func:`batch_jacobian`), ``J⁺`` its pseudo-inverse
    (``torch.linalg.pinv`` with relative cut-off ``rcond``; the plain inverse for a square, regular
    ``J``). This is the inverse gradient ``Δx = (∂x/∂y) Δy`` of the physgrad chapter, iterated.

    Args:
        max_iter: Iterations (default 1).
        step_size: ``η > 0`` (default 1).
        clip: Elementwise bound of each step, or None (E2 clips the diverging inverse gradients).
        rcond: Relative singular-value cut-off of the pseudo-inverse.

    Raises:
        ParameterError: Invalid settings.
    """

    def __init__(
        self, max_iter: int = 1, step_size: float = 1.0, clip: float | None = None, rcond: float = 1e-12
    ):
        self.max_iter = _check_iterations(max_iter)
        self.step_size = _check_positive("step_size", step_size)
        self.clip = None if clip is None else _check_positive("clip", clip)
        self.rcond = check_number(rcond, "rcond", minimum=0)

    def _solve(self, forward, y_target, x0):
        fn = _evaluator(forward)
        x = x0.clone()
        b = x.shape[0]
        for _ in range(self.max_iter):
            with torch.no_grad():
                r = (y_target - fn(x)).reshape(b, -1)
            jac = batch_jacobian(forward, x)
            step = self.step_size * (torch.linalg.pinv(jac, rtol=self.rcond) @ r.unsqueeze(-1)).squeeze(-1)
            x = x + _clip(step, self.clip).reshape(x.shape)
        return x


class LBFGSBSolver(LocalSolver):
    """L-BFGS-B (``scipy.optimize.minimize``) on ``L_i = ½‖P(x)_i − y*_i‖²``, per sample, from ``x0``.

    Each sample is optimised separately in float64 on the CPU (the forward is evaluated on float64 CPU
    tensors of batch size 1, via ``select`` for operators with per-sample parameters); the result is cast
    back to ``x0``'s device and dtype. Gradients come from autograd.

    Args:
        max_iter: L-BFGS-B iterations (scipy's ``maxiter``; default 32 as in E4).
        ftol: scipy's relative function-decrease tolerance (default tiny, so that ``max_iter`` rules).
        gtol: scipy's projected-gradient tolerance.
        maxcor: Number of stored correction pairs.
        bounds: Optional ``(lower, upper)`` bounds on every entry of ``x`` (None: unbounded side).

    Attributes:
        last_results: The ``scipy.optimize.OptimizeResult`` of each sample of the last call.

    Raises:
        ParameterError: Invalid settings.
    """

    def __init__(
        self,
        max_iter: int = 32,
        ftol: float = 1e-15,
        gtol: float = 1e-12,
        maxcor: int = 10,
        bounds: tuple[float | None, float | None] | None = None,
    ):
        self.max_iter = _check_iterations(max_iter)
        self.ftol = _check_positive("ftol", ftol)
        self.gtol = _check_positive("gtol", gtol)
        self.maxcor = _check_iterations(maxcor, "maxcor")
        if bounds is not None:
            if isinstance(bounds, (str, bytes)) or not hasattr(bounds, "__len__") or len(bounds) != 2:
                raise ParameterError(f"bounds must be None or a pair (lower, upper), got {bounds!r}")
            lo = check_number(bounds[0], "bounds[0] (lower)", allow_none=True, finite=False)
            hi = check_number(bounds[1], "bounds[1] (upper)", allow_none=True, finite=False)
            if lo is not None and hi is not None and not lo < hi:
                raise ParameterError(f"bounds must satisfy lower < upper, got {bounds}")
            bounds = (lo, hi)
        self.bounds = bounds
        self.last_results: list[scipy.optimize.OptimizeResult] = []

    def _solve(self, forward, y_target, x0):
        cpu64 = {"device": "cpu", "dtype": torch.float64}
        out = torch.empty(x0.shape, **cpu64)
        self.last_results = []
        for i in range(x0.shape[0]):
            fn = _select(forward, slice(i, i + 1))
            shape = x0[i : i + 1].shape
            target = y_target[i : i + 1].to(**cpu64)

            def fun(v: np.ndarray, fn=fn, shape=shape, target=target) -> tuple[float, np.ndarray]:
                xt = torch.from_numpy(np.asarray(v, dtype=np.float64).reshape(shape)).requires_grad_(True)
                loss = 0.5 * ((fn(xt) - target) ** 2).sum()
                (g,) = torch.autograd.grad(loss, xt)
                return float(loss.detach()), g.detach().numpy().ravel().astype(np.float64)

            start = x0[i : i + 1].to(**cpu64).numpy().ravel()
            bounds = None if self.bounds is None else [self.bounds] * start.size
            res = scipy.optimize.minimize(
                fun, start, jac=True, method="L-BFGS-B", bounds=bounds,
                options={
                    "maxiter": self.max_iter, "ftol": self.ftol, "gtol": self.gtol, "maxcor": self.maxcor,
                },
            )
            self.last_results.append(res)
            out[i] = torch.from_numpy(np.asarray(res.x, dtype=np.float64).reshape(shape[1:]))
        return out


# --------------------------------------------------------------------------------------------------
# adapter
# --------------------------------------------------------------------------------------------------


class SolverOperator(PhysicsOperator):
    """A :class:`~inverse.operators.PhysicsOperator` made of any forward and a generic local solver.

    ``forward(x)`` evaluates the given forward; ``local_inverse(y*, x0)`` runs ``solver(forward, y*, x0)``.
    Wrapping a PhysicsOperator keeps its forward (and its per-sample :meth:`select`) and replaces its
    local inverse, e.g. ``SolverOperator(Sine(a), NewtonSolver(saddle_free=True, clip=1.0))`` or the
    E3/E4 "PG with L-BFGS-B" variants.

    Args:
        forward: Callable ``(B, *x_shape) -> (B, *y_shape)`` or a PhysicsOperator.
        solver: A :class:`LocalSolver` (or any callable ``(forward, y_target, x0) -> x``).
        output_shape: Optional function ``x_shape -> y_shape`` (full shapes incl. batch); when not given
            the output shape is taken from the wrapped operator, or is unknown for a plain callable.

    Raises:
        ParameterError: ``forward`` or ``solver`` is not callable (also a ``TypeError``).
    """

    def __init__(
        self,
        forward: Forward | PhysicsOperator,
        solver: LocalSolver | Callable,
        output_shape: Callable[[Sequence[int]], Sequence[int]] | None = None,
    ):
        check_callable(forward, "forward")
        check_callable(solver, "solver")
        self.inner = forward
        self.solver = solver
        self._output_shape = output_shape
        if isinstance(forward, PhysicsOperator):
            self.check_inputs = forward.check_inputs

    def output_shape(self, x_shape: Sequence[int]) -> torch.Size | None:
        """Shape of ``forward(x)`` for ``x`` of shape ``x_shape`` (None if unknown).

        Args:
            x_shape: ``(B, *x_shape)``.

        Returns:
            ``(B, *y_shape)`` or None.
        """
        if self._output_shape is not None:
            return torch.Size(self._output_shape(x_shape))
        if isinstance(self.inner, PhysicsOperator):
            return self.inner.output_shape(x_shape)
        return None

    def select(self, index: slice | torch.Tensor | Sequence[int]) -> SolverOperator:
        """The operator restricted to the samples ``index`` (delegates to the wrapped operator).

        Args:
            index: A slice or integer index tensor into the batch dimension.

        Returns:
            A :class:`SolverOperator` for those samples.
        """
        if isinstance(self.inner, PhysicsOperator):
            return SolverOperator(self.inner.select(index), self.solver, self._output_shape)
        return self

    def _forward(self, x: torch.Tensor) -> torch.Tensor:
        return _evaluator(self.inner)(x)

    def _local_inverse(
        self, y_target: torch.Tensor, x0: torch.Tensor, y0: torch.Tensor | None
    ) -> torch.Tensor:
        return self.solver(self.inner, y_target, x0)
