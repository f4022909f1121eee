"""Compiled steps: :func:`compile` (``phisim.compile``) runs a stepper's step through ``torch.compile`` (inductor).

A stepper's step (``stepper.advance``: :class:`~phisim.fluid.FluidStepper`, :class:`~phisim.solvers.heat.HeatStepper`,
:class:`~phisim.fluid.BurgersStepper`, :class:`~phisim.fluid.AdvectionDiffusionStepper`) reads nothing back to the
host and branches on no tensor value, so it traces as one graph (``fullgraph=True``); inside the graph the
transforms are ``torch.fft``. The validation of each call (types, grids, dtypes: Python-level checks) stays
outside the compiled function.

* CPU: inductor needs a working C++ compiler. :func:`inductor_available` compiles a one-line function once per
  process to find out; without one, :func:`compile` says so in one warning and the stepper runs eager.
* CUDA: ``mode='reduce-overhead'`` (CUDA graphs) unless another mode is asked for. A CUDA graph writes its
  outputs into memory of its own that its next replay overwrites, so the compiled step copies its result out
  (:func:`own_memory`, one copy of the state per step): states can be kept, fed back step after step (rollouts)
  and backpropagated through many steps.

Shapes and dtypes are static (``dynamic=False``): a new resolution, batch size or grad mode compiles anew, new
values of the state do not (the stepper hands its step neither the time nor a pressure it does not use, and builds
its caches before the first trace). Steps that depend on the time (moving bodies, time-dependent inflows) are not
worth compiling: the time is a constant of the graph, so each step traces anew; moving bodies and PCG pressure
solves (``direct=False`` or where the direct solve does not apply) do not trace as one graph at all.

Example:
    >>> import phisim
    >>> from phisim.fluid import FluidStepper
    >>> stepper = phisim.compile(FluidStepper(grid, "periodic", viscosity=1e-3, dt=0.01))  # doctest: +SKIP
"""

from __future__ import annotations

import builtins
import dataclasses
import functools
import itertools
import types
import warnings
from typing import Any

import torch

from phisim.errors import ParameterError

__all__ = ["compile", "compile_function", "inductor_available", "is_compiling", "own_memory"]

#: Whether the code runs inside ``torch.compile``'s tracing (a constant there): steps skip checks that read a value
#: back to the host while traced, where the stepper made them once before.
is_compiling = getattr(torch.compiler, "is_compiling", None) or torch._dynamo.is_compiling


@functools.cache
def inductor_available(device_type: str = "cpu") -> bool:
    """Whether ``torch.compile``'s inductor backend works for tensors on ``device_type`` (checked once per process
    by compiling and running a one-line function; on the CPU this needs a working C++ compiler)."""
    try:
        fn = torch.compile(lambda x: x * 2.0 + 1.0, backend="inductor", fullgraph=True, dynamic=False)
        return bool(fn(torch.ones(4, device=device_type)).sum() == 12.0)
    except Exception:  # noqa: BLE001 - any failure of the toolchain means: run eager
        return False


def compile_function(fn, *, device_type: str = "cpu", mode: str | None = None):
    """``torch.compile(fn, fullgraph=True, dynamic=False)`` with inductor, or ``fn`` itself (and a one-line warning)
    where inductor does not work here. On CUDA the default mode is ``'reduce-overhead'`` (CUDA graphs)."""
    if not inductor_available(device_type):
        warnings.warn("phisim.compile: torch.compile (inductor) does not work here (no working C++ compiler for "
                      f"{device_type}); the step runs eager", RuntimeWarning, stacklevel=3)
        return fn
    if mode is None and device_type == "cuda":
        mode = "reduce-overhead"
    compiled = torch.compile(_own_code(fn), fullgraph=True, dynamic=False, mode=mode)
    if device_type != "cuda" or mode not in ("reduce-overhead", "max-autotune"):
        return compiled

    @functools.wraps(fn)
    def step_out_of_the_graph_pool(*args, **kwargs):
        return own_memory(compiled(*args, **kwargs))

    return step_out_of_the_graph_pool


def own_memory(out: Any) -> Any:
    """``out`` with every tensor in it copied (``clone``, differentiable): tensors, tuples and lists of them, fields
    (:class:`~phisim.field.CenteredGrid`, :class:`~phisim.field.StaggeredGrid`) and dataclasses (a
    :class:`~phisim.fluid.FluidState`); anything else as it is. A CUDA-graph step's result so no longer lies in the
    graph's memory, which its next replay overwrites."""
    if isinstance(out, torch.Tensor):
        return out.clone()
    if isinstance(out, (tuple, list)):
        return type(out)(own_memory(o) for o in out)
    trusted = getattr(type(out), "_trusted", None)  # a field: same shapes, so no second validation
    if trusted is not None:
        return trusted(own_memory(out.values), out.grid, out.boundary)
    if dataclasses.is_dataclass(out) and not isinstance(out, type):
        return dataclasses.replace(out, **{f.name: own_memory(getattr(out, f.name))
                                           for f in dataclasses.fields(out) if f.init})
    return out


_serial = itertools.count()


def _own_code(fn):
    """``fn`` (a function or bound method) with a code object of its own.

    ``torch.compile`` keeps its graphs per code object, with a limit on how many (``recompile_limit``, 8) before a
    ``fullgraph`` compile fails. Every stepper's ``advance`` is the same code: without a copy, the ninth stepper
    compiled in a process (another resolution, dtype or setting) would fail. A copy per compiled step gives each
    its own graphs and its own limit.
    """
    func, owner = (fn.__func__, fn.__self__) if isinstance(fn, types.MethodType) else (fn, None)
    if not isinstance(func, types.FunctionType):
        return fn
    name = f"{func.__name__}_compiled_{next(_serial)}"
    code = func.__code__.replace(co_name=name, co_qualname=name) if hasattr(func.__code__, "co_qualname") else (
        func.__code__.replace(co_name=name))
    copy = types.FunctionType(code, func.__globals__, name, func.__defaults__, func.__closure__)
    copy.__kwdefaults__ = func.__kwdefaults__
    copy.__dict__.update(func.__dict__)
    copy.__doc__ = func.__doc__
    return copy if owner is None else types.MethodType(copy, owner)


def compile(stepper, *, mode: str | None = None):  # noqa: A001 - phisim.compile mirrors torch.compile
    """Run ``stepper``'s step through ``torch.compile`` (inductor) from now on; returns the stepper.

    Args:
        stepper: A stepper with an ``advance`` method (the fluid, heat, Burgers and advection-diffusion steppers).
        mode: ``torch.compile``'s mode (default: None on the CPU, ``'reduce-overhead'`` on CUDA).

    Returns:
        The same stepper; its calls validate as before and then run the compiled step.

    Raises:
        ParameterError: For an object without a traceable step.
    """
    advance = getattr(stepper, "advance", None)
    if not builtins.callable(advance):
        raise ParameterError(f"phisim.compile needs a stepper with an advance() step, got {type(stepper).__name__}")
    device = getattr(stepper, "device", None)
    device_type = torch.device(device).type if device is not None else "cpu"
    stepper._advance = compile_function(advance, device_type=device_type, mode=mode)
    return stepper
