"""Peer driver of the periodic fluid benchmark: jax-cfd 0.2.1 (JAX, CPU) in its own virtual environment.

Run by ``benchmarks/bench_jaxcfd.py`` as a child process with the interpreter of ``benchmarks/.venv-jax`` (made by
``benchmarks/setup_jaxpeers.sh``). One JSON request per line on stdin, one JSON answer per line on stdout:

* ``{"cmd": "info"}`` -> versions and XLA flags;
* ``{"cmd": "time", "case": {...}, "reps": k}`` -> ``{"times": [s, ...], "compile_s": s}``; the first request of a
  case builds and jit-compiles it (``compile_s``, not timed again); every timed call ends with
  ``block_until_ready``;
* ``{"cmd": "energy", "case": {...}}`` -> ``{"energy": [...]}``: mean of ``u² + v²`` per sample after the case's
  steps (the like-for-like check);
* ``{"cmd": "quit"}``.

The scheme is the pairing ``../shared/PEERS.md`` names: ``equations.semi_implicit_navier_stokes`` (forward Euler,
explicit viscosity) with semi-Lagrangian convection (``advection.advect_step_semilagrangian`` wrapped as the
term ``(advected - u) / dt``) and the fast-diagonalisation pressure solve, on the periodic square
``[0, 2π)²``. Cases: ``mode`` ``"step"`` (one step), ``"rollout"`` (``steps`` steps under ``funcutils.repeated``),
``"grad"`` (gradient of the final energy w.r.t. the initial velocity through ``steps`` steps); ``batch`` > 1 uses
``jax.vmap``; ``dim`` 3 (default 2) is the periodic cube ``[0, 2π)³``.
"""

from __future__ import annotations

import json
import os
import sys
import time

import numpy as np

TWO_PI = 2 * np.pi


def initial_velocity(x: np.ndarray, y: np.ndarray, component: int, shift: float, z: np.ndarray | None = None
                     ) -> np.ndarray:
    """The analytic initial velocity shared with the phisim side (a Taylor-Green vortex plus a few modes; in 3-D
    the vortex varies along z as ``cos z`` and the third component is ``0.2 sin(2x) cos y``)."""
    xs = x - shift
    cz = 1.0 if z is None else np.cos(z)
    if component == 0:
        return np.sin(xs) * np.cos(y) * cz + 0.3 * np.sin(2 * y + 0.5)
    if component == 1:
        return -np.cos(xs) * np.sin(y) * cz + 0.2 * np.cos(3 * xs)
    return 0.2 * np.sin(2 * xs) * np.cos(y)


def build(case: dict):
    """The jitted function of ``case`` and its input state."""
    import jax
    import jax.numpy as jnp
    from jax_cfd.base import advection, boundaries, equations, funcutils, grids, pressure

    dtype = jnp.float64 if case["dtype"] == "float64" else jnp.float32
    n, batch, dt, nu = case["n"], case["batch"], case["dt"], case["viscosity"]
    dim = case.get("dim", 2)
    grid = grids.Grid((n,) * dim, domain=((0.0, TWO_PI),) * dim)
    bc = boundaries.periodic_boundary_conditions(dim)

    def convect(v):
        return tuple(grids.GridArray((advection.advect_step_semilagrangian(u, v, dt).data - u.data) / dt,
                                     u.offset, u.grid) for u in v)

    step = equations.semi_implicit_navier_stokes(density=1.0, viscosity=nu, dt=dt, grid=grid, convect=convect,
                                                 pressure_solve=pressure.solve_fast_diag)

    def state_of(datas):
        return tuple(grids.GridVariable(grids.GridArray(d, off, grid), bc) for d, off in zip(datas, grid.cell_faces))

    def datas_of(state):
        return tuple(u.array.data for u in state)

    def one(datas):
        return datas_of(step(state_of(datas)))

    if case["mode"] == "step":
        fn = one
    elif case["mode"] == "rollout":
        many = funcutils.repeated(step, case["steps"])

        def fn(datas):
            return datas_of(many(state_of(datas)))
    else:  # grad of the final energy
        many = funcutils.repeated(step, case["steps"])

        def energy(datas):
            out = datas_of(many(state_of(datas)))
            return sum(jnp.mean(d**2) for d in out)

        fn = jax.grad(energy)
    if batch > 1:
        fn = jax.vmap(fn)
    fn = jax.jit(fn)
    datas = []
    for c, off in enumerate(grid.cell_faces):
        mesh = [np.asarray(m) for m in grid.mesh(off)]
        comps = [initial_velocity(mesh[0], mesh[1], c, b * TWO_PI / batch, mesh[2] if dim == 3 else None)
                 for b in range(batch)]
        arr = np.stack(comps) if batch > 1 else comps[0]
        datas.append(jnp.asarray(arr, dtype=dtype))
    return fn, tuple(datas)


def main() -> None:
    """Serve requests on stdin until ``quit``."""
    import jax

    jax.config.update("jax_enable_x64", True)
    built: dict[str, tuple] = {}
    for line in sys.stdin:
        req = json.loads(line)
        cmd = req["cmd"]
        if cmd == "quit":
            break
        if cmd == "info":
            import jax_cfd

            out = {"jax": jax.__version__, "jax_cfd": getattr(jax_cfd, "__version__", "0.2.1"),
                   "xla_flags": os.environ.get("XLA_FLAGS", ""), "devices": [str(d) for d in jax.devices()]}
        else:
            case = req["case"]
            key = json.dumps(case, sort_keys=True)
            compile_s = None
            if key not in built:
                fn, x = build(case)
                t = time.perf_counter()
                jax.block_until_ready(fn(x))
                compile_s = time.perf_counter() - t
                built[key] = (fn, x)
            fn, x = built[key]
            if cmd == "time":
                times = []
                for _ in range(req.get("reps", 5)):
                    t = time.perf_counter()
                    jax.block_until_ready(fn(x))
                    times.append(time.perf_counter() - t)
                out = {"times": times, "compile_s": compile_s}
            elif cmd == "energy":
                datas = fn(x)
                dim = case.get("dim", 2)
                axes = tuple(range(datas[0].ndim - dim, datas[0].ndim))
                e = sum(np.mean(np.asarray(d, dtype=np.float64) ** 2, axis=axes) for d in datas)
                out = {"energy": np.atleast_1d(e).tolist()}
            else:
                out = {"error": f"unknown command {cmd!r}"}
        sys.stdout.write(json.dumps(out) + "\n")
        sys.stdout.flush()


if __name__ == "__main__":
    main()
