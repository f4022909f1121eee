"""Rollouts: many steps of a stepper, the trajectory stacked along a time axis, differentiable, checkpointed.

:func:`rollout` calls a stepper ``steps`` times and keeps every ``every``-th state (and the initial one), stacked
along a leading time axis. Gradients flow through the whole rollout; with ``checkpoint=L`` the steps run in
segments of ``L`` steps under :func:`torch.utils.checkpoint.checkpoint` (``use_reentrant=False``): the forward
pass keeps only the segments' boundary states (and the recorded states), and the backward pass recomputes
one segment at a time, so the memory of backpropagating through ``n`` steps grows with ``L`` (plus the
``n / L`` boundary states and the recorded trajectory), not with ``n``. Memory is lowest at ``L ~ sqrt(n)``.

Steppers: :class:`~phisim.fluid.FluidStepper` (state: :class:`~phisim.fluid.FluidState`), and steppers of
one :class:`~phisim.field.CenteredGrid` (:class:`~phisim.solvers.heat.HeatStepper`,
:class:`~phisim.fluid.BurgersStepper`, :class:`~phisim.fluid.AdvectionDiffusionStepper`, or any callable
``field -> field`` with a ``dt``). A compiled stepper (:func:`phisim.compile`) runs one compiled call per step.
"""

from __future__ import annotations

from dataclasses import dataclass, is_dataclass, replace

import torch
from torch.utils.checkpoint import checkpoint as _checkpoint

from phisim.errors import ParameterError
from phisim.field import CenteredGrid, StaggeredGrid

__all__ = ["Trajectory", "rollout"]


@dataclass(frozen=True, eq=False)
class Trajectory:
    """The states of a rollout stacked along a leading time axis ``T`` (the initial state first).

    Attributes:
        velocity: For a :class:`~phisim.fluid.FluidState`: per MAC component ``(T, B, *face_shape(i))``; else None.
        marker: ``(T, B, *res)`` for a FluidState with a marker; else None.
        pressure: ``(T, B, *res)`` for a FluidState (zeros where a state had no pressure yet, e.g. the initial
            one); else None.
        values: For a field stepper, the field's values ``(T, B, ...)``; else None.
        times: ``(T,)`` float64: the simulated time of each recorded state.
        final: The last state (to continue from), whether or not it was recorded.
    """

    velocity: tuple[torch.Tensor, ...] | None
    marker: torch.Tensor | None
    pressure: torch.Tensor | None
    values: torch.Tensor | None
    times: torch.Tensor
    final: object

    def __len__(self) -> int:
        return int(self.times.shape[0])


def _is_fluid(state) -> bool:
    """A :class:`~phisim.fluid.FluidState` (velocity, marker, pressure, time), recognised by its fields: this core
    module does not import the fluid layer."""
    return (is_dataclass(state) and isinstance(getattr(state, "velocity", None), StaggeredGrid)
            and all(hasattr(state, f) for f in ("marker", "pressure", "time")))


def _flatten(state) -> list[torch.Tensor | None]:
    if _is_fluid(state):
        return [*state.velocity.values,
                None if state.marker is None else state.marker.values,
                None if state.pressure is None else state.pressure.values]
    return [state.values]


def _unflatten(template, tensors, time, pressure_like):
    """A state like ``template`` holding ``tensors`` (as made by :func:`_flatten`) at ``time``."""
    if _is_fluid(template):
        d = template.velocity.rank
        v = template.velocity.with_values(tuple(tensors[:d]))
        m = None if tensors[d] is None else template.marker.with_values(tensors[d])
        p = None
        if tensors[d + 1] is not None:
            p = pressure_like.with_values(tensors[d + 1])
        return replace(template, velocity=v, marker=m, pressure=p, time=time)
    return template.with_values(tensors[0])


def _time_of(state, default: float) -> float:
    return float(state.time) if _is_fluid(state) else default


def rollout(stepper, state, steps: int, *, every: int = 1, checkpoint: int | None = None, dt=None) -> Trajectory:
    """Advance ``state`` by ``steps`` calls of ``stepper``; return every ``every``-th state stacked in time.

    Args:
        stepper: A :class:`~phisim.fluid.FluidStepper` (``state`` a FluidState), or a stepper of a
            :class:`~phisim.field.CenteredGrid` (heat, Burgers, advection-diffusion; a callable ``field -> field``).
        state: The initial state (recorded first).
        steps: Number of steps ``>= 0``.
        every: Record the state after every ``every`` steps (``T = 1 + steps // every`` records).
        checkpoint: ``None`` (default): autograd keeps every step's intermediates. ``L > 0``: segments of ``L``
            steps are checkpointed (recomputed in the backward pass); same values and gradients, memory of the
            backward pass growing with ``L`` instead of ``steps``. Only used when gradients are recorded.
        dt: Time step of a FluidStepper call (default: the stepper's).

    Returns:
        A :class:`Trajectory`.

    Raises:
        ParameterError: For a negative ``steps``, ``every < 1``, ``checkpoint < 1``, or a FluidStepper without a
            time step.
    """
    for name, value, low in (("steps", steps, 0), ("every", every, 1)):
        if isinstance(value, bool) or not isinstance(value, int) or value < low:
            raise ParameterError(f"{name} must be an int >= {low}, got {value!r}")
    if checkpoint is not None and (isinstance(checkpoint, bool) or not isinstance(checkpoint, int) or checkpoint < 1):
        raise ParameterError(f"checkpoint must be None or an int >= 1, got {checkpoint!r}")
    fluid = _is_fluid(state)
    if not fluid and not isinstance(state, CenteredGrid):
        raise ParameterError(f"rollout advances a FluidState or a CenteredGrid, got {type(state).__name__}")
    if fluid:
        dt = getattr(stepper, "dt", None) if dt is None else dt
        if dt is None:
            raise ParameterError("no dt: pass one to rollout or to the FluidStepper")
        step_dt = float(dt)

        def one(s):
            return stepper(s, dt)
    else:
        if dt is not None:
            raise ParameterError("dt= applies to a FluidStepper; a field stepper steps by its own dt")
        step_dt = float(getattr(stepper, "dt", 0.0) or 0.0)
        one = stepper

    records = [_flatten(state)]
    times = [_time_of(state, 0.0)]
    current = state
    count = 0
    use_checkpoint = checkpoint is not None and torch.is_grad_enabled()
    while count < steps:
        n = min(steps - count, checkpoint if use_checkpoint else steps - count)
        # the states recorded inside this segment: after steps count + k, k in 1..n, with (count + k) % every == 0
        marks = [k for k in range(1, n + 1) if (count + k) % every == 0]
        if use_checkpoint:
            current, recorded = _segment_checkpointed(one, current, n, marks, step_dt)
        else:
            current, recorded = _segment(one, current, n, marks)
        for k, (rec, time) in zip(marks, recorded):
            records.append(rec)
            times.append(time if time is not None else times[0] + (count + k) * step_dt)
        count += n
    return _stack(records, times, current, fluid, state)


def _segment(one, state, n, marks):
    """``n`` steps; the flattened states (and their times, None for fields) after the steps in ``marks``."""
    recorded = []
    for k in range(1, n + 1):
        state = one(state)
        if k in marks:
            recorded.append((_flatten(state), state.time if _is_fluid(state) else None))
    return state, recorded


def _segment_checkpointed(one, state, n, marks, step_dt):
    """``n`` steps under one non-reentrant checkpoint: only the inputs and the outputs are kept."""
    template = state
    structure: dict = {}

    def run(*flat):
        s = _unflatten(template, list(flat), template.time if _is_fluid(template) else None,
                       template.pressure if _is_fluid(template) else None)
        s, recorded = _segment(one, s, n, marks)
        structure["final"] = s  # the metadata of the result (grids, boundaries, time); its tensors come back out
        out = _flatten(s)
        structure["final_none"] = [t is None for t in out]
        structure["rec_none"] = [[t is None for t in r] for r, _ in recorded]
        structure["rec_time"] = [time for _, time in recorded]
        return tuple(t for t in out if t is not None) + tuple(t for r, _ in recorded for t in r if t is not None)

    flat = _flatten(state)
    outputs = _checkpoint(run, *flat, use_reentrant=False)
    it = iter(outputs)
    final_tensors = [None if none else next(it) for none in structure["final_none"]]
    recorded = [([None if none else next(it) for none in rec], time)
                for rec, time in zip(structure["rec_none"], structure["rec_time"])]
    meta = structure["final"]
    final = _unflatten(meta, final_tensors, meta.time if _is_fluid(meta) else None,
                       meta.pressure if _is_fluid(meta) else None)
    return final, recorded


def _stack(records, times, final, fluid, initial) -> Trajectory:
    t = torch.tensor(times, dtype=torch.float64)
    if not fluid:
        return Trajectory(None, None, None, torch.stack([r[0] for r in records]), t, final)
    d = initial.velocity.rank
    velocity = tuple(torch.stack([r[i] for r in records]) for i in range(d))
    marker = None
    if records[0][d] is not None:
        marker = torch.stack([r[d] for r in records])
    like = next((r[d + 1] for r in records if r[d + 1] is not None), None)
    pressure = None
    if like is not None:
        pressure = torch.stack([r[d + 1] if r[d + 1] is not None else torch.zeros_like(like) for r in records])
    return Trajectory(velocity, marker, pressure, None, t, final)
