"""phisim side of the benchmarks: one small function per case, timed in-process.

Every case takes ``(size, dtype, repeats, device)`` and returns a result dict like the PhiFlow
side's JSON line (``median_s``, ``repeats``, ``iterations`` ...). A case whose phisim module does
not exist yet (or lacks the function) returns ``{"error": "n/a: ..."}`` instead of raising, so
the runner can always produce its tables.

Inputs come from ``benchmarks/inputs.py``: the same numbers the PhiFlow side uses.
"""

from __future__ import annotations

import importlib
import os
import sys
import time
from collections.abc import Callable

import numpy as np
import torch

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import inputs  # noqa: E402
from timing import time_fn, time_steps  # noqa: E402

_DTYPES = {"float32": torch.float32, "float64": torch.float64}


class NotAvailable(Exception):
    """The phisim module or function a case needs does not exist (yet)."""


def _need(module: str, *names: str):
    """Import ``phisim.<module>`` and return the requested attributes, or raise NotAvailable."""
    try:
        mod = importlib.import_module(f"phisim.{module}")
    except ImportError as e:
        raise NotAvailable(f"phisim.{module} not available ({e})") from e
    out = []
    for n in names:
        if not hasattr(mod, n):
            raise NotAvailable(f"phisim.{module}.{n} not available")
        out.append(getattr(mod, n))
    return out[0] if len(out) == 1 else tuple(out)


def _grid(resolution):
    from phisim import Grid

    return Grid(resolution)  # bounds None: dx = 1, as inputs.py assumes


def _tensor(a, dtype, device):
    return torch.as_tensor(np.asarray(a), dtype=_DTYPES[dtype], device=device)


def _centered(arr, boundary, dtype, device):
    from phisim import CenteredGrid

    return CenteredGrid(_tensor(arr, dtype, device), _grid(arr.shape[1:]), boundary)


def _staggered(comps, resolution, boundary, dtype, device):
    from phisim import StaggeredGrid

    return StaggeredGrid([_tensor(c, dtype, device) for c in comps], _grid(resolution), boundary)


def _reps(size: str, repeats: int) -> int:
    res, b = inputs.parse_size(size)
    return 3 if int(np.prod(res)) * b >= 1024**2 else repeats


# ---- operators ----------------------------------------------------------------------------------


def laplace(size: str, dtype: str, repeats: int, device: str, boundary: str) -> dict:
    """``differential.laplace`` of a centred scalar with zero Dirichlet or periodic boundaries."""
    lap = _need("differential", "laplace")
    res, nb = inputs.parse_size(size)
    u = _centered(inputs.scalar_field(res, nb, dtype=dtype), boundary, dtype, device)
    return time_fn(lambda: lap(u), repeats=_reps(size, repeats), warmup=2, device=device, min_total_s=0.5)


def advect(size: str, dtype: str, repeats: int, device: str, scheme: str) -> dict:
    """Semi-Lagrangian or MacCormack advection of a centred scalar by a closed-box staggered velocity."""
    fn = _need("advection", scheme)
    res, nb = inputs.parse_size(size)
    u = _centered(inputs.scalar_field(res, nb, dtype=dtype), "dirichlet", dtype, device)
    v = _staggered(
        inputs.staggered_velocity(res, nb, amplitude=inputs.ADVECTION["velocity_amplitude"], dtype=dtype),
        res,
        "wall",
        dtype,
        device,
    )
    dt = inputs.ADVECTION["dt"]
    return time_fn(
        lambda: fn(u, v, dt), repeats=_reps(size, repeats), warmup=2, device=device, min_total_s=0.5
    )


# ---- Poisson ------------------------------------------------------------------------------------


def poisson_cg(size: str, dtype: str, repeats: int, device: str) -> dict:
    """CG (``linalg.cg``) on phisim's zero-Dirichlet Laplacian, rtol 1e-5, with iteration count."""
    from phisim.solvers.linalg import Solve, cg

    lap = _need("differential", "laplace")
    res, nb = inputs.parse_size(size)
    f = _centered(inputs.poisson_rhs(res, nb, dtype=dtype), "dirichlet", dtype, device)
    grid, bc = f.grid, f.boundary
    from phisim import CenteredGrid

    def op(x):  # -laplace is SPD
        return -lap(CenteredGrid(x, grid, bc)).values

    p = inputs.POISSON
    solve = Solve(rtol=p["rtol"], atol=p["atol"], max_iter=p["max_iter"])
    info = {}

    def once():
        x, inf = cg(op, -f.values, solve=solve, return_info=True)
        info["iterations"] = int(torch.as_tensor(inf.iterations).max())
        return x

    from phisim.errors import SolveError

    t0 = time.perf_counter()
    try:
        once()
    except SolveError as e:  # e.g. float32 precision floor: report it with the time it took
        its = getattr(e, "iterations", None)
        out = {
            "error": f"SolveError: {str(e).splitlines()[0][:200]}",
            "time_to_error_s": time.perf_counter() - t0,
        }
        if its is not None:
            out["iterations"] = int(torch.as_tensor(its).max())
        return out
    r = time_fn(once, repeats=3 if int(np.prod(res)) >= 512**2 else repeats, warmup=0, device=device)
    r["iterations"] = info["iterations"]
    if dtype == "float32":
        r["note"] = "float32 CG with float64 residual refinement (phisim default)"
    return r


def poisson_direct(size: str, dtype: str, repeats: int, device: str) -> dict:
    """The fast direct (DST) zero-Dirichlet Poisson solve of ``phisim.solvers.poisson``."""
    solve = _need("poisson", "solve_poisson")
    res, nb = inputs.parse_size(size)
    f = _centered(inputs.poisson_rhs(res, nb, dtype=dtype), "dirichlet", dtype, device)
    return time_fn(lambda: solve(f), repeats=_reps(size, repeats), warmup=2, device=device, min_total_s=0.5)


# ---- heat ---------------------------------------------------------------------------------------


def heat_spectral(size: str, dtype: str, repeats: int, device: str) -> dict:
    """Exact periodic heat step ``diffusion.fourier_heat`` (PhiFlow's ``diffuse.fourier`` convention)."""
    fn = _need("diffusion", "fourier_heat")
    res, nb = inputs.parse_size(size)
    u = _tensor(inputs.periodic_scalar_field(res, nb, dtype=dtype), dtype, device)
    h = inputs.HEAT
    return time_fn(
        lambda: fn(u, h["dt"], viscosity=h["viscosity"]),
        repeats=_reps(size, repeats),
        warmup=2,
        device=device,
        min_total_s=0.5,
    )


# ---- fluid --------------------------------------------------------------------------------------


def _smoke_setup(size: str, dtype: str, device: str, method: str):
    """Inputs and a step function mirroring the PhiFlow side's step (see inputs.SMOKE)."""
    maccormack, semi_lagrangian = _need("advection", "maccormack", "semi_lagrangian")
    buoyancy, Projection = _need("fluid", "buoyancy", "Projection")
    from phisim.solvers.linalg import Solve

    res, nb = inputs.parse_size(size)
    init = inputs.smoke_initial(res, nb, dtype=dtype)
    smoke = _centered(init["smoke"], "neumann", dtype, device)
    inflow = _centered(init["inflow"], "neumann", dtype, device)
    v = _staggered(init["velocity"], res, "wall", dtype, device)
    s = inputs.SMOKE
    dt = s["dt"]
    solve = Solve(rtol=s["rtol"], atol=s["atol"], max_iter=s["max_iter"])

    info: dict = {}

    project = None

    def step(state):
        nonlocal project
        marker, vel, p = state
        marker = maccormack(marker, vel, dt) + inflow * dt
        vel = semi_lagrangian(vel, vel, dt)
        vel = buoyancy(vel, marker, dt, strength=s["buoyancy"])
        if project is None:
            project = Projection(vel.grid, vel.boundary, solve=solve, method=method, dtype=vel.dtype,
                                 device=vel.device)
        vel, p, si = project(vel, pressure_guess=p)
        if si is not None:
            info["iterations"] = int(torch.as_tensor(si.iterations).max())
        return marker, vel, p

    step.info = info
    return step, smoke, v


def smoke_step(size: str, dtype: str, repeats: int, device: str, method: str = "auto") -> dict:
    """One smoke step (MacCormack smoke, semi-Lagrangian velocity, buoyancy, closed-box projection).

    ``method='auto'`` is phisim's default projection (direct spectral solve in an obstacle-free box);
    ``'cg'`` uses masked CG (spectral preconditioner) with the PhiFlow side's tolerances and warm start.
    """
    step, smoke, v = _smoke_setup(size, dtype, device, method)
    timing, _ = time_steps(
        step, (smoke, v, None), repeats=_reps(size, max(repeats, 5)), warmup=2, device=device
    )
    if "iterations" in step.info:
        timing["iterations"] = step.info["iterations"]  # pressure CG, last timed step
    return timing


def smoke_backward8(size: str, dtype: str, repeats: int, device: str) -> dict:
    """Forward and backward through 8 smoke steps; gradient of sum(smoke^2)/2 w.r.t. the initial velocity."""
    step, smoke, v = _smoke_setup(size, dtype, device, "auto")

    def once():
        vv = v.with_values([c.detach().requires_grad_(True) for c in v.values])
        state = (smoke, vv, None)
        for _ in range(8):
            state = step(state)
        loss = 0.5 * (state[0].values ** 2).sum()
        return torch.autograd.grad(loss, vv.values)

    return time_fn(once, repeats=3, warmup=1, device=device)


def smoke_check(size: str, dtype: str, repeats: int, device: str) -> dict:
    """20 smoke steps, then :func:`inputs.smoke_stats` (compared with PhiFlow's in the docs)."""
    step, smoke, v = _smoke_setup(size, dtype, device, "auto")
    state = (smoke, v, None)
    t0 = time.perf_counter()
    for _ in range(20):
        state = step(state)
    elapsed = time.perf_counter() - t0
    vel = state[1].values[-1]  # faces normal to the last axis -> centres
    vc = 0.5 * (vel.narrow(-1, 0, vel.shape[-1] - 1) + vel.narrow(-1, 1, vel.shape[-1] - 1))
    stats = inputs.smoke_stats(state[0].values[0].cpu().numpy(), vc[0].cpu().numpy())
    return {"median_s": elapsed, "repeats": 1, "stats": stats}


#: case name -> function(size, dtype, repeats, device); names match ``peer_phiflow.CASES``.
CASES: dict[str, Callable[..., dict]] = {
    "laplace_dirichlet": lambda *a: laplace(*a, boundary="dirichlet"),
    "laplace_periodic": lambda *a: laplace(*a, boundary="periodic"),
    "advect_semi_lagrangian": lambda *a: advect(*a, scheme="semi_lagrangian"),
    "advect_maccormack": lambda *a: advect(*a, scheme="maccormack"),
    "poisson_cg": poisson_cg,
    "poisson_direct": poisson_direct,
    "heat_fourier": heat_spectral,
    "smoke_step": smoke_step,
    "smoke_step_cg": lambda *a: smoke_step(*a, method="cg"),
    "smoke_backward8": smoke_backward8,
    "smoke_check": smoke_check,
}


def run_case(case: str, size: str, dtype: str, repeats: int = 5, device: str = "cpu") -> dict:
    """Run one phisim case; never raises (missing modules give ``n/a``, failures an ``error``)."""
    base = {"case": case, "size": size, "dtype": dtype, "device": device}
    if case not in CASES:
        return {**base, "error": "n/a: no phisim case"}
    try:
        res = CASES[case](size, dtype, repeats, device)
    except NotAvailable as e:
        return {**base, "error": f"n/a: {e}"}
    except Exception as e:  # report, do not crash the run
        return {**base, "error": f"{type(e).__name__}: {str(e).splitlines()[0][:300] if str(e) else ''}"}
    res.pop("times_s", None)
    return {**base, **res}
