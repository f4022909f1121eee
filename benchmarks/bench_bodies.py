"""Cost of one masked (cut-cell) PCG iteration against its floor, and of a step with bodies.

The floor of one iteration is one preconditioner transform round trip (the spectral inverse of the box, as
one fused FFTW pass where available) plus one application of the weighted stencil; an iteration also does a
few vector updates, two dot products, the null-space projection and the leaf elimination's gathers. Measured at
128^2 and 256^2 with a disc and two boxes (fractional faces), float64 and float32. On the CPU the direct solve
that a layout solved again and again switches to (:mod:`phisim.solvers.direct`) is timed as well: its one-time
build and one solve (two box solves, a small LU solve, CG's check of the answer).

On a GPU (``--device cuda``) the floor's transform is torch's FFT (pyfftw is CPU-only) and every timed call is
bracketed by CUDA synchronisations.

Run:  python benchmarks/bench_bodies.py [--sizes 128 256] [--repeat 5] [--threads 1] [--device cpu] [--wake]
      [--sharp] [--cylinder NY ...] [--json out.json]

``--cylinder NY [NY ...]`` counts the torch operations and host reads (numbers read back, ``nonzero``) of one step of
the DFG 2D-2 cylinder with PCG pressure, the path a GPU takes, and times it; on CUDA also the kernel launches, memory
copies and the GPU's busy time (profiler): where a step is bound by the host rather than the GPU.

``--sharp`` times whole steps of the wake (implicit and explicit viscosity) and the plume with sharp and with
blended no-slip bodies instead (direct pressure solve, interleaved, best of ``--repeat`` medians of the step's
thread time, CPU).
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from timing import synchronize  # noqa: E402

from phisim.boundary import Boundary  # noqa: E402
from phisim.checks import check_device  # noqa: E402
from phisim.fluid import Body, Box, FluidState, FluidStepper, Projection, Sphere, solid_layout  # noqa: E402  # noqa: E402
from phisim.grid import Grid  # noqa: E402
from phisim.solvers.box import TRANSFORMS, apply_multiplier, transform_layout, transform_scale  # noqa: E402
from phisim.solvers.linalg import Solve  # noqa: E402
from phisim.solvers.masked import MaskedPoisson  # noqa: E402
from phisim.solvers.poisson import field_kinds_and_values  # noqa: E402
from phisim.spectral.fft import r2r_multiply  # noqa: E402


def _best(fn, repeat: int, number: int, device="cpu") -> float:
    fn()
    best = float("inf")
    for _ in range(repeat):
        synchronize(device)
        t = time.perf_counter()
        for _ in range(number):
            fn()
        synchronize(device)
        best = min(best, (time.perf_counter() - t) / number)
    return best


def measure(n: int, dtype, repeat: int, device="cpu") -> dict:
    """Floor, per-iteration cost and whole solve of the masked pressure Poisson problem on ``n x n`` cells.

    Args:
        n: Cells per axis.
        dtype: Field dtype.
        repeat: Timed repeats (the best is kept).
        device: Torch device of the fields (the random right-hand side is drawn on the CPU and moved).

    Returns:
        The row: sizes, times in ms, the ratio iteration / floor, CG iterations to the tolerance, the device.
    """
    device = check_device(device)
    grid = Grid((n, n), bounds=[(0, 1), (0, 1)])
    boundary = Boundary.create({"x": ("wall", "open"), "y": "wall"}, 2)
    bodies = [Body(Sphere((0.3, 0.45), 0.1)), Body(Box((0.55, 0.2), (0.65, 0.35))),
              Body(Box((0.6, 0.6), (0.75, 0.7)))]
    layout = solid_layout(bodies, grid, boundary, 0.0, dtype, device)
    kinds = field_kinds_and_values(boundary.for_pressure())[0]
    op = MaskedPoisson(layout.theta, grid.dx, kinds, direct=False)  # the PCG figures
    g = torch.Generator().manual_seed(0)
    rhs = torch.randn(1, n, n, generator=g, dtype=torch.float64).to(device=device, dtype=dtype) * op.active.to(dtype)
    x = torch.randn(rhs.shape, generator=g, dtype=torch.float64).to(device=device, dtype=dtype)

    r2r, per = transform_layout(op.kinds)
    fwd = tuple(TRANSFORMS[op.kinds[a]][0] for a in r2r)
    inv = tuple(TRANSFORMS[op.kinds[a]][1] for a in r2r)
    mult = (op._inv * transform_scale(op.resolution, op.kinds)).to(dtype)

    def floor():  # the fastest transform round trip the library has (one FFTW pass), plus the stencil
        y = None if per else r2r_multiply(x, fwd, inv, tuple(1 + a for a in r2r), mult, engine=op.engine)
        if y is None:
            apply_multiplier(x, op.kinds, op._inv, op.engine)
        op.apply(x)

    tol = Solve(rtol=1e-6 if dtype == torch.float64 else 1e-5, raise_on_failure=False, refine=False)
    _, info = op.solve(rhs, solve=tol)
    iters = int(info.iterations[0])
    t_floor = _best(floor, repeat, 20, device)
    # per iteration: the difference of two solves stopped after k1 and k2 iterations (fixed costs cancel)
    tight = 1e-12 if dtype == torch.float64 else 2e-7
    k1, k2 = 4, 14

    def capped(k):
        s = Solve(rtol=tight, max_iter=k, raise_on_failure=False, refine=False, stagnation_window=10**6)
        return lambda: op.solve(rhs, solve=s)

    with torch.no_grad():
        per_iter = (_best(capped(k2), repeat, 3, device) - _best(capped(k1), repeat, 3, device)) / (k2 - k1)
        t_solve = _best(lambda: op.solve(rhs, solve=tol), repeat, 1, device)
    # the direct solve of the same operator (CPU): built once (k box solves), then two box solves per call
    direct = {}
    if device.type == "cpu":
        t = time.perf_counter()
        dop = MaskedPoisson(layout.theta, grid.dx, kinds, direct=True)  # the same layout, solved directly
        dop.solve(rhs, solve=tol)  # the first solve builds it
        t_build = time.perf_counter() - t
        with torch.no_grad():
            t_direct = _best(lambda: dop.solve(rhs, solve=tol), repeat, 3, device)
        _, dinfo = dop.solve(rhs, solve=tol)
        direct = {"direct_ms": 1e3 * t_direct, "direct_build_ms": 1e3 * t_build, "rank": dop._direct.rank,
                  "direct_iterations": int(dinfo.iterations[0])}
    return {"n": n, "dtype": str(dtype).replace("torch.", ""), "floor_ms": 1e3 * t_floor,
            "iteration_ms": 1e3 * per_iter, "ratio": per_iter / t_floor, "iterations_to_rtol": iters,
            "solve_ms": 1e3 * t_solve, "device": str(device), **direct}


def _median_step_ms(step, state, steps: int, clock=time.perf_counter) -> float:
    """Median ms of ``state = step(state, k)`` over the last half of ``steps`` steps, timed by ``clock``."""
    times = []
    for k in range(steps):
        t = clock()
        state = step(state, k)
        times.append(clock() - t)
    return 1e3 * statistics.median(times[steps // 2:])


def wake_step_ms(n: int, dtype, direct: bool, steps: int = 160, sharp: bool = True,
                 viscosity_scheme: str = "implicit", clock=time.perf_counter) -> float:
    """Median ms per split step (implicit viscosity) of a cylinder wake on ``n x n`` cells over the last half
    of ``steps`` steps: inflow 0.5 on the left, open right side, walls, a disc of radius 0.06 n, Re 100 (the
    wake scene of ``bench_flow_bodies.py``), with the pressure solved by PCG only or by the direct solve; ``sharp``:
    the sharp no-slip disc (default) or the blended one."""
    from phisim import Open, StaggeredGrid
    from phisim.boundary import Inflow

    u = 0.5
    grid = Grid((n, n), bounds=[(0.0, float(n)), (0.0, float(n))])
    v = StaggeredGrid.from_function(lambda x: torch.stack([torch.full_like(x[..., 0], u),
                                                           torch.zeros_like(x[..., 0])], -1),
                                    grid, {"x": (Inflow((u, 0.0)), Open()), "y": "wall"}, dtype=dtype)
    body = Body(Sphere((0.25 * n, 0.52 * n), 0.06 * n), sharp=sharp)
    nu = u * 0.12 * n / 100
    dt = 1.0 if viscosity_scheme != "explicit" else min(1.0, 0.45 / (4 * nu))
    stepper = FluidStepper(grid, v.boundary, obstacles=body, viscosity=nu,
                           advection="semi_lagrangian", viscosity_scheme=viscosity_scheme, dt=dt, dtype=dtype,
                           direct="auto" if direct else False)
    return _median_step_ms(lambda state, k: stepper(state), FluidState(v), steps, clock)


def plume_step_ms(n: int, dtype, direct: bool, steps: int = 160, sharp: bool = True,
                  clock=time.perf_counter) -> float:
    """Median ms per step of a smoke plume in a closed box with two box bodies (the ``plume_boxes`` scene of
    ``bench_flow_bodies.py``: MacCormack smoke, semi-Lagrangian velocity, buoyancy 0.1, ``make_incompressible``)
    over the last half of ``steps`` steps, with the pressure solved by PCG only or by the direct solve."""
    from phisim import CenteredGrid, StaggeredGrid
    from phisim.fluid import buoyancy
    from phisim.ops.advection import maccormack, semi_lagrangian

    grid = Grid((n, n), bounds=[(0.0, float(n)), (0.0, float(n))])
    x = grid.cell_centers(torch.float64)
    source = torch.exp(-((x[..., 0] - 0.45 * n) ** 2 + (x[..., 1] - 0.15 * n) ** 2) / (0.05 * n) ** 2)[None]
    source = source.to(dtype)
    smoke = CenteredGrid(torch.zeros(1, n, n, dtype=dtype), grid, "neumann")
    v = StaggeredGrid(tuple(torch.zeros(1, *grid.face_shape(i), dtype=dtype) for i in range(2)), grid, "wall")
    boxes = [((round(0.35 * n), round(0.45 * n)), (round(0.55 * n), round(0.52 * n))),
             ((round(0.55 * n), round(0.68 * n)), (round(0.80 * n), round(0.74 * n)))]
    bodies = [Body(Box(lo, hi), sharp=sharp) for lo, hi in boxes]
    project = Projection(grid, v.boundary, bodies, dtype=dtype, direct="auto" if direct else False)

    def step(state, k):
        m, vel, p = state
        m = maccormack(m, vel, 1.0) + source
        vel = buoyancy(semi_lagrangian(vel, vel, 1.0), m, 1.0, strength=0.1)
        out = project(vel, pressure_guess=p)
        return m, out.velocity, out.pressure

    return _median_step_ms(step, (smoke, v, None), steps, clock)


#: Operations that make the host wait for a GPU: a number read back (``item``, ``bool``, ``float``) and ``nonzero``
#: (whose output size the host must know), also behind boolean indexing.
_HOST_READS = ("_local_scalar_dense", "nonzero", "masked_select")


def cylinder_step_counts(ny: int, integrator: str, convection: str, device, steps: int = 20) -> dict:
    """Operations, host reads and ms per step of the DFG 2D-2 cylinder (``examples/cylinder_benchmark.py``,
    float64, CFL 0.5) with the pressure solved by PCG, the path a GPU takes (the direct solve is CPU-only): after
    ``steps`` steps to warm up, the mean over ``steps`` timed steps, then one step's torch operations and host reads
    counted (and on CUDA, from the profiler over that step, kernel launches and memory copies)."""
    from torch.utils._python_dispatch import TorchDispatchMode

    examples = str(Path(__file__).resolve().parents[1] / "examples")
    if examples not in sys.path:
        sys.path.insert(0, examples)
    from cylinder_benchmark import NU, setup

    class Count(TorchDispatchMode):
        ops = reads = 0

        def __torch_dispatch__(self, func, types, args=(), kwargs=None):
            name = func.__name__.split(".")[0]
            self.ops += 1
            self.reads += name in _HOST_READS or (name == "index" and any(
                isinstance(i, torch.Tensor) and i.dtype == torch.bool for i in (args[1] or ())))
            return func(*args, **(kwargs or {}))

    grid, body, state, um = setup("2D-2", ny, torch.float64, device)
    stepper = FluidStepper(grid, state.velocity.boundary, obstacles=body, viscosity=NU, integrator=integrator,
                           convection=convection, dtype=torch.float64, device=device,
                           dt=0.5 * grid.dx[0] / (1.5 * um), direct=False)
    for _ in range(steps):
        state = stepper(state)
    synchronize(device)
    t0 = time.perf_counter()
    for _ in range(steps):
        state = stepper(state)
    synchronize(device)
    out = {"cylinder": f"{grid.resolution[0]}x{ny}", "integrator": integrator, "convection": convection,
           "device": str(device), "step_ms": 1e3 * (time.perf_counter() - t0) / steps}
    with Count() as count:
        state = stepper(state)
    out.update(operations=count.ops, host_reads=count.reads)
    if device.type == "cuda":
        from torch.profiler import ProfilerActivity, profile

        with profile(activities=[ProfilerActivity.CPU, ProfilerActivity.CUDA]) as prof:
            state = stepper(state)
            synchronize(device)
        events = prof.key_averages()
        out["kernel_launches"] = sum(e.count for e in events if "LaunchKernel" in e.key)
        out["memory_copies"] = sum(e.count for e in events if e.key.startswith("cudaMemcpy"))
        out["gpu_busy_ms"] = sum(e.self_device_time_total for e in events if e.device_type.name == "CUDA") / 1e3
    return out


def main(argv=None) -> int:
    """Command-line entry point: prints one line per size and dtype, optionally writes the rows as JSON.

    Raises:
        ParameterError: For an unknown device or one this machine does not have.
    """
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", type=int, nargs="+", default=[128, 256])
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--json", default=None)
    ap.add_argument("--device", default="cpu", help="torch device: cpu, cuda or cuda:N (default cpu)")
    ap.add_argument("--wake", action="store_true",
                    help="also time wake and plume steps with PCG and with the direct solve")
    ap.add_argument("--sharp", action="store_true",
                    help="only time whole steps (direct pressure) with sharp and with blended no-slip bodies")
    ap.add_argument("--cylinder", type=int, nargs="+", default=None, metavar="NY",
                    help="only count the operations and host reads of a DFG 2D-2 cylinder step (PCG pressure) "
                         "with NY cells across the channel, 'imex2' + QUICK and 'split', and time it")
    args = ap.parse_args(argv)
    device = check_device(args.device)
    torch.set_num_threads(args.threads)
    rows = []
    if args.cylinder:
        for ny in args.cylinder:
            for integrator, convection in (("imex2", "quick"), ("split", "central")):
                r = cylinder_step_counts(ny, integrator, convection, device)
                rows.append(r)
                print(" ".join(f"{k} {v:.1f}" if isinstance(v, float) else f"{k} {v}" for k, v in r.items()),
                      flush=True)
        if args.json:
            Path(args.json).parent.mkdir(parents=True, exist_ok=True)
            Path(args.json).write_text(json.dumps(rows, indent=1))
        return 0
    if args.sharp:  # thread time: the CPU time of this thread, robust to other jobs on the machine
        for n in args.sizes:
            for dtype in (torch.float64, torch.float32):
                for scene, fn in (("wake implicit", lambda s, n=n, dtype=dtype: wake_step_ms(
                                      n, dtype, True, sharp=s, clock=time.thread_time)),
                                  ("wake explicit", lambda s, n=n, dtype=dtype: wake_step_ms(
                                      n, dtype, True, sharp=s, viscosity_scheme="explicit", clock=time.thread_time)),
                                  ("plume", lambda s, n=n, dtype=dtype: plume_step_ms(n, dtype, True, sharp=s,
                                                                                       clock=time.thread_time))):
                    times = {False: [], True: []}
                    for _ in range(args.repeat):  # interleaved
                        for s in (False, True):
                            times[s].append(fn(s))
                    a, b = min(times[False]), min(times[True])
                    rows.append({"scene": scene, "n": n, "dtype": str(dtype).replace("torch.", ""), "blended_ms": a,
                                 "sharp_ms": b})
                    print(f"{scene:14s} {n:4d}^2 {rows[-1]['dtype']:8s} blended {a:.2f} ms, sharp {b:.2f} ms "
                          f"({b / a:.2f}x)", flush=True)
        if args.json:
            Path(args.json).parent.mkdir(parents=True, exist_ok=True)
            Path(args.json).write_text(json.dumps(rows, indent=1))
        return 0
    for n in args.sizes:
        for dtype in (torch.float64, torch.float32):
            r = measure(n, dtype, args.repeat, device)
            rows.append(r)
            print(f"{n:4d}^2 {r['dtype']:8s} {r['device']} floor {r['floor_ms']:.3f} ms  "
                  f"iteration {r['iteration_ms']:.3f} ms  "
                  f"ratio {r['ratio']:.2f}  iterations to rtol {r['iterations_to_rtol']}  "
                  f"whole solve {r['solve_ms']:.1f} ms" + (
                      f"  direct solve {r['direct_ms']:.2f} ms (CG iterations after it {r['direct_iterations']}; "
                      f"built once in {r['direct_build_ms']:.0f} ms, rank {r['rank']})" if "direct_ms" in r else ""),
                  flush=True)
    if device.type == "cpu" and args.wake:
        for n in args.sizes:
            for dtype in (torch.float32, torch.float64):
                a, b = wake_step_ms(n, dtype, False), wake_step_ms(n, dtype, True)
                rows.append({"wake": n, "dtype": str(dtype).replace("torch.", ""), "pcg_ms": a, "direct_ms": b})
                print(f"wake {n:4d}^2 {rows[-1]['dtype']:8s} split step: PCG pressure {a:.2f} ms, direct {b:.2f} ms "
                      f"({a / b:.2f}x)", flush=True)
                a, b = plume_step_ms(n, dtype, False), plume_step_ms(n, dtype, True)
                rows.append({"plume": n, "dtype": str(dtype).replace("torch.", ""), "pcg_ms": a, "direct_ms": b})
                print(f"plume {n:4d}^2 {rows[-1]['dtype']:8s} step: PCG pressure {a:.2f} ms, direct {b:.2f} ms "
                      f"({a / b:.2f}x)", flush=True)
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
