"""Batched, matrix-free, preconditioned conjugate gradient with implicit (adjoint) differentiation.

The entry point is :func:`cg`. It solves ``A x = b`` for a batch of independent right-hand sides
``b`` of shape ``(B, ...)`` where ``A`` is any linear, symmetric positive (semi-)definite function
acting on each sample independently (a stencil, a masked Laplacian, an implicit diffusion
operator). Policy lives in the frozen settings object :class:`Solve`; the outcome of a solve is a
:class:`SolveInfo`.

Behaviour in brief:

* **Per-sample convergence.** Sample ``b`` has converged when its *true* residual satisfies
  ``||rhs_b - A x_b|| <= max(rtol * ||rhs_b||, atol)`` (Euclidean norms over all non-batch
  axes). Converged samples are frozen (no further updates) while the others iterate; the loop
  ends when every sample is done. The recurrence residual drives the iteration; the true
  residual is recomputed at the end (one extra operator application) and is what
  :class:`SolveInfo` reports. When the two disagree (finite-precision drift) the residual is
  replaced by the true one and CG restarts from the current iterate; when such a restart does not
  improve the true residual the working precision's floor has been reached and the solve stops
  with a ``precision_floor`` failure instead of iterating on.
* **float32.** A float32 residual cannot get much below ``eps32 * ||A|| * ||x||``. With
  ``Solve.refine`` (the default for float32/float16/bfloat16 input whenever the operator accepts
  float64 input) the solve runs mixed-precision iterative refinement: the residual is computed in
  float64 on float64 copies, the correction is solved by float32 CG to a modest relative accuracy
  (``Solve.refine_rtol``), and the loop repeats until the float64 residual meets the tolerance.
  The returned solution has the input dtype; its residual is reported honestly (computed in
  float64): rounding a solution to float32 adds about ``eps32 * ||A|| * ||x||`` to it, so a
  tolerance below that is unreachable for *any* float32 vector. By default
  (``Solve.widen_tolerance``) such a solve succeeds: the float64 iterate meets the tolerance, the
  tolerance is widened by the measured rounding floor ``||A (fl32(x) - x)||``, and the widened
  threshold (which the returned solution's true residual provably meets) is what
  :attr:`SolveInfo.tolerance` reports, next to :attr:`SolveInfo.precision_floor`; the sample's status is
  then ``precision_floor``, not ``converged``, and :attr:`SolveInfo.achieved_rtol` gives the relative
  residual it has (:attr:`SolveInfo.met_requested` False). With
  ``widen_tolerance=False`` it is a ``precision_floor`` failure that suggests float64 input. So float32
  fields with default settings get a solution without any change by the user, the best one float32
  can hold. ``refine=True`` with float64 input
  gives the same scheme with float32 inner iterations and a float64 result.
* **Failures** (``raise_on_failure=True``) raise :class:`~phisim.errors.SolveError` carrying
  ``iterations`` and ``residual`` (per-sample tensors) and a message naming the cause: iteration
  limit, stagnation, precision floor, or breakdown (``p^T A p <= 0``: the operator is not SPD).
  NaN/Inf in the inputs or produced by the operator raise :class:`~phisim.errors.NonFiniteError`.
* **Gradients** never flow through the iterations. :func:`cg` is a ``torch.autograd.Function``
  whose backward solves the adjoint system ``A lambda = grad_x`` (``A`` symmetric: same operator,
  preconditioner, projection and :class:`Solve` settings, i.e. the same tolerances) with
  :func:`cg` itself. The gradient w.r.t. ``rhs`` is ``lambda``, w.r.t. ``x0`` it is zero, and w.r.t.
  each tensor in ``operator_params`` it is ``-d<lambda, A(theta) x>/d theta``, obtained by autograd
  on one operator application. Memory is independent of the iteration count. The backward is
  itself differentiable (double backward works through a second adjoint solve).
* **Singular operators** (pure Neumann or periodic Laplacian) are semi-definite. CG converges on
  the compatible subspace when the right-hand side is orthogonal to the null space. Pass a
  projector as ``project`` (e.g. :func:`remove_mean` for a constant null space): it is applied to
  ``rhs``, ``x0``, to the residual in every iteration and to the solution, so the returned
  solution is the minimum-norm one and the residual refers to the projected ``rhs``.

The algorithm is the preconditioned CG of Hestenes & Stiefel (1952) in the form given by
Saad, *Iterative Methods for Sparse Linear Systems* (2003), Alg. 9.1; the residual replacement
follows the idea of van der Vorst & Ye (2000); mixed-precision iterative refinement is classical
(Wilkinson 1963; Carson & Higham 2018).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import torch
from torch import Tensor

from phisim.allocator import keep_freed_memory
from phisim.checks import (
    callable_name,
    check_batch_compatible,
    check_bool,
    check_callable,
    check_callable_output,
    check_int,
    check_number,
)
from phisim.errors import NonFiniteError, ParameterError, ShapeError, SolveError

__all__ = ["Solve", "SolveInfo", "cg", "remove_mean"]

Operator = Callable[..., Tensor]
Preconditioner = Callable[[Tensor], Tensor]
Projector = Callable[[Tensor], Tensor]

#: Whether tensors on the CPU take the CPU's loops (a scalar loop for one sample, host reads where a sample
#: stopped); False runs the loop of other devices on the CPU too (no host reads but every ``check_every``
#: iterations), which the tests use to check that loop without a GPU.
_CPU_LOOPS = True

# Per-sample status codes used inside the iteration (int8 tensors on the solve's device).
_RUNNING = 0
_CONVERGED = 1
_MAX_ITER = 2
_STAGNATED = 3
_FLOOR = 4
_BREAKDOWN = 5
_NONFINITE = 6
_STATUS_NAMES = {
    _RUNNING: "running",
    _CONVERGED: "converged",
    _MAX_ITER: "max_iter",
    _STAGNATED: "stagnated",
    _FLOOR: "precision_floor",
    _BREAKDOWN: "breakdown",
    _NONFINITE: "non_finite",
}
_LOW_PRECISION = (torch.float32, torch.float16, torch.bfloat16)


@dataclass(frozen=True)
class Solve:
    """Settings of a conjugate-gradient solve (immutable; safe defaults).

    Attributes:
        rtol: Relative tolerance: sample ``b`` converges when ``||rhs_b - A x_b|| <= max(rtol *
            ||rhs_b||, atol)``. Default ``1e-5``.
        atol: Absolute tolerance on the residual norm (same units as ``rhs``). Default ``0``.
        max_iter: Limit on CG iterations per sample (all refinement rounds and restarts
            together). ``None`` means ``2 * N + 10`` with ``N`` the number of unknowns per sample:
            exact-arithmetic CG needs at most ``N``; the factor two allows for the delay caused by
            rounding. The stagnation and precision-floor detectors stop hopeless solves long
            before this limit.
        raise_on_failure: Raise :class:`~phisim.errors.SolveError` when a sample does not
            converge. With ``False`` the solve returns the last iterate and a :class:`SolveInfo`
            whose ``converged`` flags are False (request it with ``return_info=True``).
        refine: Mixed-precision iterative refinement (float64 residuals around float32 CG).
            ``None`` (default): on for float32/float16/bfloat16 input when the operator accepts
            float64 input, off otherwise. ``True``: always (float64 input then uses float32 inner
            iterations and returns float64); raises if the operator rejects float64 input.
            ``False``: plain CG in the input dtype, with the precision-floor detector.
        refine_rtol: Relative residual reduction asked of the float32 inner CG in each
            refinement round. It must be well above float32's own floor. Default ``1e-3``.
        max_refine: Limit on refinement rounds. Default ``20``.
        widen_tolerance: For float32/float16/bfloat16 output of a refined solve: when the float64
            iterate meets the tolerance but rounding it to the output dtype pushes the residual
            over (no vector of that dtype may meet it), accept the rounded solution against the
            tolerance widened by the rounding floor ``||A (fl(x) - x)||`` and report the widened
            threshold in :attr:`SolveInfo.tolerance` (and the floor in
            :attr:`SolveInfo.precision_floor`, the status ``'precision_floor'``, the relative residual met in
            :attr:`SolveInfo.achieved_rtol`). Default ``True``; ``False`` raises a
            ``precision_floor`` :class:`~phisim.errors.SolveError` instead.
        stagnation_window: A sample whose smallest recurrence residual has not decreased by at
            least 1 % within this many iterations is stopped as stagnated (an incompatible
            right-hand side for a singular operator, or a precision floor). Default ``500``.
        check_every: Iterations between host-side "all samples done?" checks (each check is a
            device synchronisation). Per-sample freezing happens on the device every iteration,
            so iteration counts and results do not depend on it; only up to ``check_every - 1``
            idle iterations may be spent after the last sample converges. ``None``: 1 on CPU,
            10 on other devices.
    """

    rtol: float = 1e-5
    atol: float = 0.0
    max_iter: int | None = None
    raise_on_failure: bool = True
    refine: bool | None = None
    refine_rtol: float = 1e-3
    max_refine: int = 20
    widen_tolerance: bool = True
    stagnation_window: int = 500
    check_every: int | None = None

    def __post_init__(self) -> None:
        # every field through the checks.py helpers: a string, None, a list, NaN, a bool or an out-of-range integer
        # is a ParameterError naming Solve.<field>; the checked values (floats, ints) are stored
        def put(name, value):
            object.__setattr__(self, name, value)

        for name in ("rtol", "atol"):
            put(name, check_number(getattr(self, name), f"Solve.{name}", minimum=0))
        if self.rtol == 0 and self.atol == 0:
            raise ParameterError("Solve(rtol=0, atol=0) can never be met; give rtol > 0 or atol > 0")
        put("refine_rtol", check_number(self.refine_rtol, "Solve.refine_rtol", minimum=0, maximum=1,
                                        min_open=True, max_open=True))
        for name, allow_none in (("max_iter", True), ("max_refine", False),
                                 ("stagnation_window", False), ("check_every", True)):
            put(name, check_int(getattr(self, name), f"Solve.{name}", minimum=1, allow_none=allow_none))
        if self.refine is not None:
            put("refine", check_bool(self.refine, "Solve.refine (None, True or False)"))
        for name in ("raise_on_failure", "widen_tolerance"):
            put(name, check_bool(getattr(self, name), f"Solve.{name}"))

    def resolved_max_iter(self, n: int) -> int:
        """The iteration limit for ``n`` unknowns per sample.

        Args:
            n: Number of unknowns per sample.

        Returns:
            ``max_iter`` if set, else ``2 * n + 10``.
        """
        return self.max_iter if self.max_iter is not None else 2 * n + 10


@dataclass
class SolveInfo:
    """Outcome of a :func:`cg` solve; all per-sample tensors have shape ``(B,)`` on the solve's device.

    Two questions have two answers: was the solution *accepted* (``converged``: no :class:`SolveError` was raised
    for it), and did it meet *what was asked* (``met_requested``, ``status == 'converged'``). They differ only for
    float32/float16/bfloat16 output of a refined solve whose requested tolerance lies below what that dtype can
    hold (``Solve.widen_tolerance``): such a sample is accepted against a widened threshold, and its status is
    ``'precision_floor'``, its ``achieved_rtol`` the relative residual it actually has.

    Attributes:
        iterations: CG iterations per sample (int64), all refinement rounds and restarts included.
        residual: True residual norm ``||rhs_b - A x_b||`` of the returned solution (float64 when
            the operator accepts float64 input, else the working dtype).
        converged: Whether the sample was accepted: ``residual <= tolerance`` (bool). ``tolerance`` is the
            requested threshold, widened by ``precision_floor`` where ``Solve.widen_tolerance`` applied.
        rtol: Relative tolerance requested (``Solve.rtol``).
        atol: Absolute tolerance requested (``Solve.atol``).
        tolerance: The per-sample absolute threshold the sample was accepted against:
            ``requested_tolerance``, plus ``precision_floor`` where the tolerance was widened.
        status: Per-sample outcome names: ``converged`` (the requested tolerance was met), ``precision_floor``
            (stopped at the working precision's floor above the requested tolerance: accepted at a widened
            tolerance when ``converged`` is True, a failure otherwise), ``max_iter``, ``stagnated``,
            ``breakdown`` or ``non_finite``.
        refined: Whether mixed-precision iterative refinement was used.
        refinements: Number of refinement rounds (0 without refinement).
        precision_floor: Per sample, the residual added by rounding the float64-refined solution
            to the output dtype, ``||A (fl(x) - x)||``, where it widened the tolerance (0 elsewhere);
            ``None`` when no tolerance was widened.
        requested_tolerance: Per sample, the threshold asked for, ``max(rtol * ||rhs_b||, atol)`` (float64).
        rhs_norm: Per sample, ``||rhs_b||`` (float64; of the projected right-hand side when a projector is given).
        achieved_rtol: Per sample, the relative residual actually met, ``residual / ||rhs_b||`` (float64; 0 for a
            zero right-hand side solved exactly, ``inf`` for a zero right-hand side with a nonzero residual).
        met_requested: Per sample, whether ``residual <= requested_tolerance`` (bool).

    The last four are filled by :func:`cg`; they default to None for reports built elsewhere, and
    :attr:`all_met_requested` then falls back on ``status``.
    """

    iterations: Tensor
    residual: Tensor
    converged: Tensor
    rtol: float
    atol: float
    tolerance: Tensor
    status: tuple[str, ...] = field(default_factory=tuple)
    refined: bool = False
    refinements: int = 0
    precision_floor: Tensor | None = None
    requested_tolerance: Tensor | None = None
    rhs_norm: Tensor | None = None
    achieved_rtol: Tensor | None = None
    met_requested: Tensor | None = None

    @property
    def all_converged(self) -> bool:
        """True when every sample was accepted (see ``converged``; :attr:`all_met_requested` is stricter)."""
        return bool(self.converged.all())

    @property
    def all_met_requested(self) -> bool:
        """True when every sample met the requested tolerance (no widening at the precision floor)."""
        if self.met_requested is not None:
            return bool(self.met_requested.all())
        return bool(self.status) and all(s == "converged" for s in self.status)

    def __repr__(self) -> str:
        its = self.iterations.tolist()
        res = [f"{v:.3g}" for v in self.residual.double().tolist()]
        n_ok = int(self.converged.sum())
        achieved = ("" if self.achieved_rtol is None else
                    f", achieved_rtol=[{', '.join(f'{v:.3g}' for v in self.achieved_rtol.double().tolist())}]")
        return (f"SolveInfo(converged={n_ok}/{len(its)}, iterations={its}, residual=[{', '.join(res)}], "
                f"rtol={self.rtol:g}, atol={self.atol:g}{achieved}, status={list(self.status)}, "
                f"refined={self.refined}, refinements={self.refinements})")


def remove_mean(t: Tensor) -> Tensor:
    """Subtract each sample's mean over all non-batch axes.

    It is the orthogonal projector onto the complement of the constant vector, i.e. the range of a
    pure-Neumann or periodic Laplacian on a uniform grid; pass it as ``cg(..., project=remove_mean)``.

    Args:
        t: Tensor of shape ``(B, ...)``.

    Returns:
        ``t - mean(t_b)`` per sample, same shape and dtype.
    """
    dims = tuple(range(1, t.ndim))
    return t - t.mean(dim=dims, keepdim=True)


# --------------------------------------------------------------------------------------------------
# helpers


def _all_finite(t: Tensor) -> bool:
    """Whether ``t`` holds no NaN/Inf: one reduction (NaN/Inf make the sum non-finite); only a sum that
    overflows from finite values falls through to the element-wise check."""
    t = t.detach()
    return bool(torch.isfinite(t.sum())) or bool(torch.isfinite(t).all())


_BLAS_DTYPES = (torch.float32, torch.float64)


#: Per-sample size from which a small batch takes one BLAS dot per sample instead of a product and a sum: the
#: product's temporary of the batch's size then costs more than the extra calls (measured in benchmarks/bench_cg.py).
_DOT_PER_SAMPLE_NUMEL = 1 << 16
_DOT_PER_SAMPLE_BATCH = 8


def _dot(u: Tensor, v: Tensor) -> Tensor:
    """Per-sample inner products ``(B,)``: BLAS dots (a single pass, no temporary) for a batch of one and for a few
    large samples, else a product and a sum."""
    B = u.shape[0]
    if u.dtype in _BLAS_DTYPES and u.dtype == v.dtype:
        if B == 1:
            return torch.dot(u.reshape(-1), v.reshape(-1)).reshape(1)
        if B <= _DOT_PER_SAMPLE_BATCH and u[0].numel() >= _DOT_PER_SAMPLE_NUMEL:
            uf, vf = u.reshape(B, -1), v.reshape(B, -1)
            return torch.stack([torch.dot(uf[i], vf[i]) for i in range(B)])
    return (u * v).flatten(1).sum(1)


def _dot1(u: Tensor, v: Tensor) -> float:
    """The inner product of a batch of one as a Python number (the CPU's single-sample iteration)."""
    if u.dtype in _BLAS_DTYPES and u.dtype == v.dtype:
        return float(torch.dot(u.reshape(-1), v.reshape(-1)))
    return float((u * v).sum())


def _norm(u: Tensor) -> Tensor:
    return torch.linalg.vector_norm(u.flatten(1), dim=1)


def _bcast(s: Tensor, like: Tensor) -> Tensor:
    return s.view((-1,) + (1,) * (like.ndim - 1))


def _apply(op: Operator, x: Tensor, params: Sequence[Tensor]) -> Tensor:
    y = op(x, *params)
    if not isinstance(y, Tensor) or y.shape != x.shape:
        check_callable_output(y, x.shape, op, "cg: the operator (which must keep the shape)", finite=False)
    return y


class _CheckedCallable:
    """A user preconditioner or projection whose every output is checked for the input's exact shape (nothing is
    broadcast: a flat tensor or a batch of 1 is a :class:`ShapeError` naming the callable), and whose first output
    of a solve for NaN/Inf (:class:`NonFiniteError`; one reduction per solve)."""

    def __init__(self, fn: Callable[[Tensor], Tensor], role: str):
        self.fn = fn
        self.role = role
        self.first = True

    def __call__(self, r: Tensor) -> Tensor:
        out = self.fn(r)
        if not isinstance(out, Tensor) or out.shape != r.shape:
            check_callable_output(out, r.shape, self.fn, self.role, finite=False)
        if self.first and not (torch.jit.is_tracing() or torch.compiler.is_compiling()):
            self.first = False
            check_callable_output(out, r.shape, self.fn, self.role, finite=True)
        return out

    def __repr__(self) -> str:
        return callable_name(self.fn)


def _checked(fn, role: str):
    if fn is None or isinstance(fn, _CheckedCallable):
        return fn
    return _CheckedCallable(check_callable(fn, role), role)


def _accepts_float64(op: Operator, x64: Tensor, params: Sequence[Tensor]) -> Tensor | None:
    """``op(x64)`` if the operator runs in float64 and returns float64, else None."""
    try:
        y = op(x64, *params)
    except (RuntimeError, TypeError):
        return None
    if not isinstance(y, Tensor) or y.dtype != torch.float64 or y.shape != x64.shape:
        return None
    return y


# --------------------------------------------------------------------------------------------------
# the iteration


def _cg_core(A: Callable[[Tensor], Tensor], M: Preconditioner | None, P: Projector | None,
             x: Tensor, r: Tensor, tol: Tensor, active: Tensor, budget: Tensor,
             window: int, check_every: int) -> tuple[Tensor, Tensor, Tensor]:
    """Preconditioned CG from iterate ``x`` with residual ``r`` on the samples flagged ``active``.

    Args:
        A: Linear operator (batched, per sample).
        M: Preconditioner ``M^-1`` or None.
        P: Projector applied to every residual, or None.
        x: Start iterate ``(B, ...)``; updated in place.
        r: Its residual ``b - A x`` ``(B, ...)``; updated in place.
        tol: Per-sample absolute tolerance on the recurrence residual norm ``(B,)``.
        active: Samples to iterate ``(B,)`` bool.
        budget: Per-sample iteration limit ``(B,)`` int64.
        window: Stagnation window in iterations.
        check_every: Iterations between host-side termination checks.

    Returns:
        ``(x, iterations, status)``; status is ``_RUNNING`` for samples that were not active.

    Per iteration the bookkeeping is a handful of ``(B,)`` operations: one "keeps going" flag combines
    convergence, stagnation, budget and the finite/positive-curvature checks. A sample that stops keeps the
    iteration, residual norm and curvature it stopped with (in an iteration where some sample stopped on the
    CPU, where asking the host is free; every iteration, without a host synchronisation, on other devices);
    the reasons are worked out once, after the loop (a stopped sample's ``alpha`` is zero, so its
    ``last_improved`` no longer changes).
    """
    B = x.shape[0]
    dev = x.device
    on_cpu = dev.type == "cpu" and _CPU_LOOPS
    if B == 1 and on_cpu:
        return _cg_single(A, M, P, x, r, tol, active, budget, window)
    iters = torch.zeros(B, dtype=torch.int64, device=dev)
    status = torch.full((B,), _RUNNING, dtype=torch.int8, device=dev)
    rnorm = _norm(r)
    status = torch.where(active & (rnorm <= tol), _CONVERGED, status)
    status = torch.where(active & ~torch.isfinite(rnorm), _NONFINITE, status)
    status = torch.where(active & (status == _RUNNING) & (budget <= 0), _MAX_ITER, status)
    active = active & (status == _RUNNING)
    if not bool(active.any()):
        return x, iters, status
    z = M(r) if M is not None else r
    rz = _dot(r, z)
    p = z * _bcast(active.to(z.dtype), z)
    spare = torch.empty_like(p)
    zero = torch.zeros((), dtype=x.dtype, device=dev)
    best = rnorm.clone()
    # Every active sample has run all k iterations so far (a sample that stops leaves ``active`` for good), so the
    # iteration number is the Python counter k; a sample's count is recorded when it stops (k, or k - 1 when
    # that iteration broke down), and k for the samples still active at the end.
    last_improved = torch.zeros(B, dtype=torch.int64, device=dev)
    # what a sample stopped with: the iteration (0: has not stopped in the loop), whether its curvature broke
    # down there (and the curvature), its residual norm
    stop_at = torch.zeros(B, dtype=torch.int64, device=dev)
    broke = torch.zeros(B, dtype=torch.bool, device=dev)
    pq_stop = torch.zeros(B, dtype=rnorm.dtype, device=dev)
    rnorm_stop = rnorm.clone()
    n_max = int(budget.max())
    k = 0
    while k < n_max:
        q = A(p)
        pq = _dot(p, q)
        ok = active & (pq > 0)  # False for p^T A p <= 0 (breakdown) and for NaN
        alpha = _bcast(torch.where(ok, rz / pq, zero), x)
        x.addcmul_(alpha, p)
        r.addcmul_(alpha, q, value=-1)
        if P is not None:
            r.copy_(P(r))
        k += 1
        z = M(r) if M is not None else r
        rz_new = _dot(r, z)
        rnorm = _norm(r) if M is not None else rz_new.clamp_min(0).sqrt()
        improved = rnorm < 0.99 * best
        best = torch.where(improved, rnorm, best)
        last_improved = torch.where(improved, k, last_improved)
        # NaN fails every comparison: a non-finite residual stops the sample (its reason is set below)
        going = ok & (rnorm > tol) & (last_improved > k - window) & (budget > k)
        # going implies active: some sample stopped iff the two differ (one host read on the CPU)
        if not on_cpu or not torch.equal(going, active):
            stopped = active & ~going
            broken = active & ~ok  # a breakdown stops its sample in the same iteration
            stop_at = torch.where(stopped, k, stop_at)
            rnorm_stop = torch.where(stopped, rnorm, rnorm_stop)
            pq_stop = torch.where(broken, pq, pq_stop)
            broke |= broken
            active = going
            if (on_cpu or k % check_every == 0) and not bool(active.any()):
                break
        beta = _bcast(torch.where(going, rz_new / rz, zero), p)
        # stopped samples get p = z, which alpha = 0 keeps from acting; written into the second buffer
        p, spare = torch.addcmul(z, beta, p, out=spare), p
        rz = rz_new
    ended = stop_at > 0
    reason = torch.where(
        broke, torch.where(torch.isfinite(pq_stop), _BREAKDOWN, _NONFINITE),
        torch.where(rnorm_stop <= tol, _CONVERGED,
                    torch.where(~torch.isfinite(rnorm_stop), _NONFINITE,
                                torch.where(stop_at - last_improved >= window, _STAGNATED, _MAX_ITER))))
    status = torch.where(ended, reason.to(torch.int8), status)
    iters = torch.where(ended, stop_at - broke.to(torch.int64), iters)
    iters = torch.where(active, k, iters)
    status = torch.where(active, _MAX_ITER, status)
    return x, iters, status


def _cg_single(A: Callable[[Tensor], Tensor], M: Preconditioner | None, P: Projector | None,
               x: Tensor, r: Tensor, tol: Tensor, active: Tensor, budget: Tensor,
               window: int) -> tuple[Tensor, Tensor, Tensor]:
    """:func:`_cg_core` for a single sample on the CPU: the same iteration and stopping rules, with the
    scalars (``alpha``, ``beta``, norms, counters) as Python numbers instead of ``(1,)`` tensors (on the CPU
    reading a number is no synchronisation; it saves about twenty tensor operations per iteration). Per
    iteration: the operator, two BLAS dots, ``x += alpha p`` and ``r -= alpha q`` in place, and
    ``p = z + beta p`` written into a second buffer (one pass each, no allocation)."""

    def done(iterations: int, status: int) -> tuple[Tensor, Tensor, Tensor]:
        return (x, torch.tensor([iterations], dtype=torch.int64, device=x.device),
                torch.tensor([status], dtype=torch.int8, device=x.device))

    if not bool(active[0]):
        return done(0, _RUNNING)
    tol_, budget_ = float(tol[0]), int(budget[0])
    rnorm = float(_norm(r)[0])
    if rnorm <= tol_:
        return done(0, _CONVERGED)
    if not math.isfinite(rnorm):
        return done(0, _NONFINITE)
    if budget_ <= 0:
        return done(0, _MAX_ITER)
    z = M(r) if M is not None else r
    rz = _dot1(r, z)
    p = z.clone(memory_format=torch.contiguous_format)
    spare = torch.empty_like(p)
    # flat views for BLAS dots: r is updated in place; p alternates between two buffers (views of both kept)
    blas = r.dtype in _BLAS_DTYPES and r.is_contiguous()
    rf = r.view(-1) if blas else None
    pf, spare_f = p.view(-1), spare.view(-1)
    best, last, k = rnorm, 0, 0
    while k < budget_:
        q = A(p)
        pq = float(torch.dot(pf, q.reshape(-1))) if blas and q.dtype == p.dtype else _dot1(p, q)
        if not pq > 0:  # p^T A p <= 0 (breakdown) or NaN
            return done(k, _BREAKDOWN if math.isfinite(pq) else _NONFINITE)
        alpha = rz / pq
        x.add_(p, alpha=alpha)
        r.add_(q, alpha=-alpha)
        if P is not None:
            r.copy_(P(r))
        k += 1
        if M is None:
            rz_new = float(torch.dot(rf, rf)) if blas else _dot1(r, r)
            rnorm = math.sqrt(max(rz_new, 0.0))
        else:
            z = M(r)
            rz_new = _dot1(r, z)
            rnorm = float(_norm(r)[0])
        if rnorm < 0.99 * best:
            best, last = rnorm, k
        if rnorm <= tol_:
            return done(k, _CONVERGED)
        if not math.isfinite(rnorm):
            return done(k, _NONFINITE)
        if k - last >= window:
            return done(k, _STAGNATED)
        if k >= budget_:
            return done(k, _MAX_ITER)
        p, spare = torch.add(z, p, alpha=rz_new / rz, out=spare), p
        pf, spare_f = spare_f, pf
        rz = rz_new
    return done(k, _MAX_ITER)


class _Setup:
    """Everything a solve needs besides the tensors, shared by forward and backward."""

    def __init__(self, op: Operator, params: Sequence[Tensor], solve: Solve,
                 M: Preconditioner | None, P: Projector | None):
        self.op = op
        self.params = tuple(params)
        self.solve = solve
        self.M = M
        self.P = P


def _tolerance(solve: Solve, b: Tensor) -> Tensor:
    bn = _norm(b).double()
    return torch.clamp(solve.rtol * bn, min=solve.atol)


def _solve(s: _Setup, b: Tensor, x0: Tensor | None) -> tuple[Tensor, SolveInfo]:
    """Run a solve (no autograd); returns the solution in ``b``'s dtype and its info."""
    solve = s.solve
    params = s.params
    dtype = b.dtype
    B = b.shape[0]
    n = b[0].numel() if B else 0
    max_iter = solve.resolved_max_iter(n)
    check_every = solve.check_every or (1 if b.device.type == "cpu" else 10)
    if s.P is not None:
        b = s.P(b)
        if x0 is not None:
            x0 = s.P(x0)
    tol = _tolerance(solve, b)  # float64 (B,)
    b64 = b.double()
    x64_start = x0.double() if x0 is not None else torch.zeros_like(b64)

    # Decide whether the operator runs in float64 (needed for refinement and the float64 residual).
    refine = solve.refine
    if dtype == torch.float64 and not refine:
        op64 = True
        Ax64 = None
    else:
        Ax64 = _accepts_float64(s.op, x64_start, params)
        op64 = Ax64 is not None
    if refine is None:
        refine = dtype in _LOW_PRECISION and op64
    if refine and not op64:
        raise ParameterError("Solve(refine=True) needs an operator that accepts float64 input and returns "
                             "float64; this one does not (cast its coefficients inside, or use refine=False)")
    budget = torch.full((B,), max_iter, dtype=torch.int64, device=b.device)

    if refine:
        assert Ax64 is not None
        x, iters, status, rounds, x64_ref = _refine(s, b64, x64_start, Ax64, tol, budget, check_every, dtype)
        res = None
    else:
        x, iters, status, res = _plain(s, b, x0, tol, budget, check_every, dtype)
        rounds = 0

    # True residual of the returned solution, in float64 when the operator allows it (a float64 plain solve
    # has just computed it for this iterate).
    if res is None or dtype != torch.float64:
        if op64:
            res = _norm(b64 - _apply(s.op, x.double(), params))
        else:
            res = _norm(b - _apply(s.op, x, params)).double()
    floor = None
    requested = tol
    if refine and op64 and dtype in _LOW_PRECISION and solve.widen_tolerance:
        # The float64 iterate met the tolerance but its rounding to the output dtype may not: no
        # vector of that dtype need meet it. Widen by the rounding floor ||A (fl(x) - x)||; then
        # ||b - A fl(x)|| <= ||b - A x|| + ||A (fl(x) - x)|| <= tol + floor holds for the returned x.
        rounded = (status == _CONVERGED) & (res > tol)
        if bool(rounded.any()):
            delta = x.double() - x64_ref
            Ad = _apply(s.op, delta, params)
            if s.P is not None:
                Ad = s.P(Ad)
            floor = torch.where(rounded, _norm(Ad), torch.zeros_like(tol))
            tol = tol + floor
    converged = res <= tol
    met = res <= requested
    # Status names what was met: the requested tolerance ('converged'), or only a threshold widened by the
    # precision floor (accepted) or nothing (an iteration that ended converged but whose returned solution
    # misses the tolerance after rounding to the output dtype): both 'precision_floor'.
    status = torch.where(met, _CONVERGED,
                         torch.where(converged | (status == _CONVERGED), _FLOOR, status))
    bn = _norm(b).double()
    res64 = res.double()
    achieved = torch.where(bn > 0, res64 / torch.where(bn > 0, bn, 1.0),
                           torch.where(res64 > 0, math.inf, 0.0))
    info = SolveInfo(iterations=iters, residual=res, converged=converged, rtol=solve.rtol, atol=solve.atol,
                     tolerance=tol, status=tuple(_STATUS_NAMES[int(c)] for c in status.tolist()),
                     refined=bool(refine), refinements=rounds, precision_floor=floor,
                     requested_tolerance=requested, rhs_norm=bn, achieved_rtol=achieved, met_requested=met)
    if solve.raise_on_failure and not bool(converged.all()):
        _raise(info, dtype, refine)
    return x, info


def _plain(s: _Setup, b: Tensor, x0: Tensor | None, tol64: Tensor, budget: Tensor, check_every: int,
           dtype: torch.dtype) -> tuple[Tensor, Tensor, Tensor, Tensor | None]:
    """Plain CG in the working dtype with residual replacement and the precision-floor detector.

    Returns ``(x, iterations, status, residual)``; ``residual`` is the true residual norm of the returned
    ``x`` (float64) when the last check computed it for that iterate, else None.
    """
    solve = s.solve
    B = b.shape[0]
    eps = torch.finfo(dtype).eps

    def A(v: Tensor) -> Tensor:
        return _apply(s.op, v, s.params)

    tol = tol64.to(dtype) if dtype == torch.float64 else tol64.float().to(dtype)
    bn = _norm(b).double()
    # A tolerance below the working precision's unit roundoff is unreachable: fail at once.
    hopeless = (tol64 < eps * bn) & (bn > 0)
    if x0 is None:
        x = torch.zeros_like(b)
        r = b.clone()
    else:
        x = x0.clone()
        r = b - A(x)
    if s.P is not None:
        r = s.P(r)
    active = ~hopeless
    x, iters, status = _cg_core(A, s.M, s.P, x, r, tol, active, budget, solve.stagnation_window, check_every)
    status = torch.where(hopeless, _FLOOR, status)
    prev = None
    for _ in range(4):
        r = b - A(x)
        if s.P is not None:
            r = s.P(r)
        tn = _norm(r).double()
        fix = (status == _CONVERGED) & (tn > tol64)
        if prev is not None:
            floor = fix & (tn > 0.5 * prev)
            status = torch.where(floor, _FLOOR, status)
            fix = fix & ~floor
        if not bool(fix.any()):
            return x, iters, status, tn
        prev = tn
        x, it2, st2 = _cg_core(A, s.M, s.P, x, r, tol, fix, budget - iters, solve.stagnation_window,
                               check_every)
        iters = iters + it2
        status = torch.where(fix, st2, status)
    del B
    return x, iters, status, None


def _refine(s: _Setup, b64: Tensor, x64: Tensor, Ax64: Tensor, tol64: Tensor, budget: Tensor,
            check_every: int, out_dtype: torch.dtype) -> tuple[Tensor, Tensor, Tensor, int, Tensor]:
    """Mixed-precision iterative refinement: float64 residuals, float32 CG corrections."""
    solve = s.solve
    B = b64.shape[0]
    dev = b64.device
    inner = torch.float32

    def A32(v: Tensor) -> Tensor:
        return _apply(s.op, v, s.params)

    # Rounding the result to a low-precision dtype adds to its residual; aim the float64 iterate at a
    # quarter of the tolerance so that the rounded solution keeps the headroom.
    target = tol64 * (0.25 if out_dtype != torch.float64 else 1.0)
    x64 = x64.clone()
    r64 = b64 - Ax64
    if s.P is not None:
        r64 = s.P(r64)
    iters = torch.zeros(B, dtype=torch.int64, device=dev)
    status = torch.full((B,), _RUNNING, dtype=torch.int8, device=dev)
    rn = _norm(r64)
    rounds = 0
    for _ in range(solve.max_refine):
        ok = rn <= target
        status = torch.where(ok, _CONVERGED, status)
        active = (status == _RUNNING) & ~ok
        if not bool(active.any()):
            break
        rounds += 1
        rhs = r64.to(inner)
        inner_tol = torch.maximum(solve.refine_rtol * rn, 0.5 * target).to(inner)
        d, it, st = _cg_core(A32, s.M, s.P, torch.zeros_like(rhs), rhs.clone(), inner_tol, active,
                             budget - iters, solve.stagnation_window, check_every)
        iters = iters + it
        hard_fail = active & ((st == _BREAKDOWN) | (st == _NONFINITE))
        status = torch.where(hard_fail, st, status)
        take = active & ~hard_fail
        x64 = x64 + d.double() * _bcast(take.double(), x64)
        r64 = b64 - _apply(s.op, x64, s.params)
        if s.P is not None:
            r64 = s.P(r64)
        rn_new = _norm(r64)
        no_progress = take & (rn_new > 0.9 * rn) & (rn_new > target)
        status = torch.where(no_progress, torch.where(st == _MAX_ITER, _MAX_ITER, _STAGNATED), status)
        out = take & (iters >= budget) & (rn_new > target)
        status = torch.where(out & (status == _RUNNING), _MAX_ITER, status)
        rn = rn_new
    ok = rn <= target
    status = torch.where(ok, _CONVERGED, torch.where(status == _RUNNING, _MAX_ITER, status))
    if s.P is not None:
        x64 = s.P(x64)
    return x64.to(out_dtype), iters, status, rounds, x64


def _raise(info: SolveInfo, dtype: torch.dtype, refined: bool) -> None:
    failed = [i for i, ok in enumerate(info.converged.tolist()) if not ok]
    reasons = sorted({info.status[i] for i in failed})
    rel = (info.residual / torch.clamp(info.tolerance, min=torch.finfo(torch.float64).tiny)).tolist()
    detail = ", ".join(f"sample {i}: {info.status[i]}, {int(info.iterations[i])} iterations, "
                       f"residual {float(info.residual[i]):.3g} = {rel[i]:.3g} x tolerance"
                       for i in failed[:4])
    if len(failed) > 4:
        detail += f", ... ({len(failed)} of {len(info.converged)} samples failed)"
    hints = []
    name = str(dtype).replace("torch.", "")
    if "breakdown" in reasons:
        hints.append("p^T A p <= 0 was met: the operator (or the preconditioner) is not symmetric positive "
                     "definite; CG needs an SPD operator (check signs, e.g. solve -laplace(x) = -b), or it is "
                     "singular and the right-hand side has a part in its null space (pass "
                     "project=remove_mean for a pure Neumann/periodic Laplacian)")
    if "non_finite" in reasons:
        hints.append("the operator or preconditioner produced NaN/Inf")
    if "precision_floor" in reasons:
        if dtype in _LOW_PRECISION:
            how = ("even the float64-refined solution, rounded to " + name + ", misses it; "
                   "pass float64 input (optionally Solve(refine=True) for float32 inner iterations)"
                   if refined else
                   "use float64 input or Solve(refine=True) (needs an operator that accepts float64)")
            hints.append(f"the {name} precision floor was reached: the tolerance is below what {name} "
                         f"arithmetic can resolve for this problem (about eps*||A||*||x||); {how}, "
                         "or loosen rtol")
        else:
            hints.append(f"the {name} precision floor was reached: the true residual stopped improving; "
                         "loosen rtol/atol")
    if "stagnated" in reasons:
        hints.append("the residual stopped decreasing: the right-hand side may be incompatible with a "
                     "singular operator (pass project=remove_mean for a pure Neumann/periodic Laplacian), "
                     "or the precision floor was reached")
    if "max_iter" in reasons:
        hints.append("the iteration limit was hit: raise Solve.max_iter or use a preconditioner")
    msg = (f"CG did not converge (rtol={info.rtol:g}, atol={info.atol:g}, dtype={name}): {detail}. "
           + "; ".join(hints) + ".")
    if "non_finite" in reasons:
        err = NonFiniteError(msg)
        err.iterations, err.residual, err.info = info.iterations, info.residual, info  # type: ignore[attr-defined]
        raise err
    err = SolveError(msg, iterations=info.iterations, residual=info.residual)
    err.info = info  # type: ignore[attr-defined]
    raise err


# --------------------------------------------------------------------------------------------------
# autograd


class _CG(torch.autograd.Function):
    """x = A(theta)^-1 b with the adjoint-solve backward (see module docstring)."""

    @staticmethod
    def forward(ctx, setup: _Setup, info_box: list, b: Tensor, x0: Tensor | None,  # type: ignore[override]
                *params: Tensor) -> Tensor:
        x, info = _solve(setup, b, x0)
        info_box.append(info)
        ctx.setup = setup
        ctx.save_for_backward(x, *params)
        return x

    @staticmethod
    def backward(ctx, grad_x: Tensor):  # type: ignore[override]
        x, *params = ctx.saved_tensors
        s: _Setup = ctx.setup
        # Adjoint solve; A is symmetric, so the same operator, preconditioner and settings apply.
        # Calling the differentiable cg keeps the backward differentiable (double backward).
        lam = cg(s.op, grad_x, solve=s.solve, preconditioner=s.M, operator_params=tuple(params), project=s.P)
        grads_p: list[Tensor | None] = [None] * len(params)
        need = [i for i, p in enumerate(params) if ctx.needs_input_grad[4 + i]]
        if need:
            # -d<lam, A(theta) x>/d theta with x and lam held fixed: torch.func.vjp differentiates only
            # w.r.t. the parameters it is given, while staying connected to x and lam for double backward.
            def apply_params(*ps: Tensor) -> Tensor:
                full = list(params)
                for i, p in zip(need, ps):
                    full[i] = p
                return s.op(x, *full)

            _, vjp_fn = torch.func.vjp(apply_params, *[params[i] for i in need])
            for i, gi in zip(need, vjp_fn(lam)):
                grads_p[i] = -gi
        return (None, None, lam, None, *grads_p)


def cg(operator: Operator, rhs: Tensor, x0: Tensor | None = None, *, solve: Solve = Solve(),
       preconditioner: Preconditioner | None = None, return_info: bool = False,
       operator_params: Sequence[Tensor] = (), project: Projector | None = None
       ) -> Tensor | tuple[Tensor, SolveInfo]:
    """Solve ``A x = rhs`` per sample with preconditioned conjugate gradient; differentiable implicitly.

    Args:
        operator: Linear function ``A(x, *operator_params) -> Tensor``; maps ``(B, ...)`` to the same
            shape, acts on each sample independently and is symmetric positive (semi-)definite.
            With refinement it is also called with float64 input.
        rhs: Right-hand sides, shape ``(B, ...)`` (batch first), floating point.
        x0: Optional start iterate of ``rhs``'s shape (warm start), or of batch size 1 (one start shared by
            every sample); its gradient is zero.
        solve: Settings (tolerances, limits, refinement); see :class:`Solve`.
        preconditioner: Optional ``M^-1``: a symmetric positive definite function on ``(B, ...)``
            tensors approximating ``A^-1``, per sample. It must return its input's exact shape (nothing is
            broadcast) and finite values (checked on its first call of a solve).
        return_info: Also return a :class:`SolveInfo`.
        operator_params: Tensors the operator depends on (a coefficient field, a mask); gradients
            w.r.t. them are ``-d<lambda, A(theta) x>/d theta``. A tensor that requires grad must be
            passed here rather than captured by the operator, else ``ParameterError``.
        project: Optional orthogonal projector onto the range of a singular operator (e.g.
            :func:`remove_mean`), applied to ``rhs``, ``x0``, the residuals and the solution.

    Returns:
        The solution ``x`` (``rhs``'s shape, dtype and device), and the :class:`SolveInfo` when
        ``return_info`` is set.

    Raises:
        SolveError: A sample did not converge (with ``raise_on_failure``); carries per-sample
            ``iterations`` and ``residual`` and the :class:`SolveInfo` as ``info``.
        NonFiniteError: NaN/Inf in ``rhs`` or ``x0``, or produced by the operator.
        ParameterError: Invalid inputs (non-tensor operator_params, grad-requiring tensors captured
            by the operator, ``refine=True`` with an operator that rejects float64).
        ShapeError: ``rhs`` has no batch axis, ``x0`` has another shape (or a batch size other than ``B`` or 1),
            or the operator, the preconditioner or the projection changes shape (naming the callable).
        NonFiniteError: Also when the preconditioner or the projection returns NaN/Inf (naming it).

    On the CPU the first solve of a process calls :func:`phisim.allocator.keep_freed_memory` (glibc keeps freed
    memory for the next iteration's arrays; the user's ``MALLOC_*`` settings and ``PHISIM_KEEP_FREED_MEMORY=0``
    win).
    """
    if not isinstance(rhs, Tensor) or not rhs.is_floating_point():
        raise ParameterError(f"cg: rhs must be a floating-point torch.Tensor, got {type(rhs).__name__}"
                             + (f" of dtype {rhs.dtype}" if isinstance(rhs, Tensor) else ""))
    if rhs.ndim < 1:
        raise ShapeError("cg: rhs needs a leading batch axis, shape (B, ...)")
    if not isinstance(solve, Solve):
        raise ParameterError(f"cg: solve must be a phisim.solvers.linalg.Solve, got {type(solve).__name__}")
    if not _all_finite(rhs):
        raise NonFiniteError("cg: rhs contains NaN or Inf")
    if x0 is not None:
        if isinstance(x0, Tensor) and x0.ndim == rhs.ndim and x0.shape[1:] == rhs.shape[1:]:
            check_batch_compatible(rhs, x0, ("rhs", "x0"), "solve")
            if x0.shape[0] == 1 and rhs.shape[0] != 1:
                x0 = x0.expand(rhs.shape)
        if not isinstance(x0, Tensor) or x0.shape != rhs.shape:
            raise ShapeError(f"cg: x0 must have rhs's shape {tuple(rhs.shape)}, got "
                             f"{tuple(getattr(x0, 'shape', ()))}")
        x0 = x0.detach().to(rhs.dtype)
        if not _all_finite(x0):
            raise NonFiniteError("cg: x0 contains NaN or Inf")
    params = tuple(operator_params)
    for p in params:
        if not isinstance(p, Tensor):
            raise ParameterError(f"cg: operator_params must be tensors, got {type(p).__name__}")
    if torch.is_grad_enabled():
        with torch.enable_grad():
            probe = operator(rhs.detach(), *[p.detach() for p in params])
        if isinstance(probe, Tensor) and probe.requires_grad:
            raise ParameterError("cg: the operator depends on tensors that require grad but are not passed "
                                 "as operator_params; pass them as cg(..., operator_params=(k,)) with "
                                 "operator(x, k), else their gradients would be silently missing")
    check_callable(operator, "cg: operator")
    if rhs.device.type == "cpu":
        # the iterations allocate the operator's output every time: keep freed memory for the next one (arrays of a
        # few MiB would otherwise be handed back to the system and fault in again; see phisim.allocator)
        keep_freed_memory()
    setup = _Setup(operator, params, solve, _checked(preconditioner, "cg: preconditioner"),
                   _checked(project, "cg: projection"))
    box: list[SolveInfo] = []
    x = _CG.apply(setup, box, rhs, x0, *params)
    if return_info:
        return x, box[0]
    return x
