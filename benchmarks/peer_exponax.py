"""Peer driver of the ETDRK benchmark: exponax 0.2.0 (JAX, CPU) in its own virtual environment.

Run by ``benchmarks/bench_etdrk.py`` as a child process with the interpreter of ``benchmarks/.venv-jax`` (see
``benchmarks/setup_jaxpeers.sh``). It reads one JSON request per line on stdin and answers each with one JSON line
on stdout:

* ``{"cmd": "info"}`` -> versions and XLA flags.
* ``{"cmd": "time", "case": {...}, "reps": k}`` -> ``{"times": [seconds, ...], "cpu": [seconds, ...]}`` (wall time
  and CPU time of the whole process, all threads); the first request of a case builds, jit-compiles and warms it up
  (not timed). Every call ends with ``block_until_ready``.
* ``{"cmd": "result", "case": {...}, "path": "x.npy"}`` -> writes the case's output to ``path``.
* ``{"cmd": "quit"}``.

A case: ``eq`` (``"ks1d"``: conservative Kuramoto-Sivashinsky; ``"burgers1d"``: viscous Burgers in the conservative
form ``-(u^2/2)_x``; ``"ns2d"``: 2-D Navier-Stokes in vorticity form; ``"heat2d"``: 2-D diffusion, exact in time),
``n`` (points per axis), ``batch``, ``mode`` (``"step"`` or ``"rollout"``), ``steps``, ``dt``, ``domain``,
``viscosity`` (burgers1d, ns2d, heat2d), ``order`` (ETDRK order), ``dtype`` (``"float32"`` or ``"float64"``; the
latter needs ``JAX_ENABLE_X64=1``); ``"fft1d"``/``"fft2d"`` time one forward and one inverse real FFT of the state
(the transform floor). The initial state is the analytic field of :func:`initial_state`, which ``bench_etdrk.py``
builds identically.
"""

from __future__ import annotations

import json
import math
import sys
import time

import numpy as np

# jax and exponax are imported inside build()/main() so that bench_etdrk.py can import initial_state with numpy only


def initial_state(case: dict) -> np.ndarray:
    """The deterministic initial state ``(batch, 1, n[, n])`` (float32) shared with the phisim side.

    Args:
        case: The benchmark case.

    Returns:
        The state (``case["dtype"]``, default float32); sample ``b`` is shifted by ``b / batch`` of the domain.
    """
    n, length, batch = case["n"], case["domain"], case["batch"]
    x = np.arange(n) * length / n
    out = []
    for b in range(batch):
        s = 2 * math.pi / length
        shift = b * length / max(batch, 1)
        if case["eq"] in ("ks1d", "burgers1d", "fft1d"):
            u = np.cos(3 * s * (x - shift)) + 0.5 * np.sin(7 * s * (x - shift)) + 0.2 * np.cos(11 * s * x)
            out.append(u[None])
        else:
            xx, yy = np.meshgrid(x - shift, x, indexing="ij")
            w = np.sin(s * xx) * np.cos(2 * s * yy) + 0.5 * np.cos(3 * s * xx) * np.sin(s * yy) \
                + 0.3 * np.sin(s * (xx + 2 * yy))
            out.append(w[None])
    return np.stack(out).astype(case.get("dtype", "float32"))


def build(case: dict):
    """A jitted function of the batched state for ``case`` and its input (on the JAX device)."""
    import exponax as ex
    import jax
    import jax.numpy as jnp

    n, dt, length, order = case["n"], case["dt"], case["domain"], case["order"]
    if case["eq"] == "fft2d":  # the FFT floor: one forward and one inverse real 2-D transform
        return jax.jit(jax.vmap(lambda u: jnp.fft.irfft2(jnp.fft.rfft2(u), s=(n, n)))), jnp.asarray(initial_state(case))
    if case["eq"] == "fft1d":
        return jax.jit(jax.vmap(lambda u: jnp.fft.irfft(jnp.fft.rfft(u), n=n))), jnp.asarray(initial_state(case))
    if case["eq"] == "ks1d":
        stepper = ex.stepper.KuramotoSivashinskyConservative(1, length, n, dt, order=order)
    elif case["eq"] == "burgers1d":
        stepper = ex.stepper.Burgers(1, length, n, dt, diffusivity=case["viscosity"], conservative=True, order=order)
    elif case["eq"] == "heat2d":
        stepper = ex.stepper.Diffusion(2, length, n, dt, diffusivity=case["viscosity"])
    elif case["eq"] == "ns2d":
        stepper = ex.stepper.NavierStokesVorticity(2, length, n, dt, diffusivity=case["viscosity"], order=order)
    else:
        raise ValueError(f"unknown equation {case['eq']!r}")
    fn = stepper if case["mode"] == "step" else ex.repeat(stepper, case["steps"])
    return jax.jit(jax.vmap(fn)), jnp.asarray(initial_state(case))


def main() -> None:
    """Serve the requests on stdin until ``quit`` or end of input."""
    import jax

    cache: dict[str, tuple] = {}

    def get(case):
        key = json.dumps(case, sort_keys=True)
        if key not in cache:
            fn, u0 = build(case)
            for _ in range(2):
                fn(u0).block_until_ready()
            cache[key] = (fn, u0)
        return cache[key]

    for line in sys.stdin:
        req = json.loads(line)
        cmd = req.get("cmd")
        if cmd == "quit":
            break
        if cmd == "info":
            import os

            out = {"jax": jax.__version__, "exponax": "0.2.0", "devices": [str(d) for d in jax.devices()],
                   "xla_flags": os.environ.get("XLA_FLAGS", ""), "x64": bool(jax.config.jax_enable_x64)}
        elif cmd == "time":
            fn, u0 = get(req["case"])
            times, cpu = [], []
            for _ in range(req["reps"]):
                c0, t0 = time.process_time(), time.perf_counter()
                fn(u0).block_until_ready()
                times.append(time.perf_counter() - t0)
                cpu.append(time.process_time() - c0)
            out = {"times": times, "cpu": cpu}
        elif cmd == "result":
            fn, u0 = get(req["case"])
            np.save(req["path"], np.asarray(fn(u0)))
            out = {"path": req["path"]}
        else:
            out = {"error": f"unknown command {cmd!r}"}
        print(json.dumps(out), flush=True)


if __name__ == "__main__":
    main()
