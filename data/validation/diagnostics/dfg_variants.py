"""Diagnostic runs of the DFG benchmark with one part of the split step altered (docs/VALIDATION.md).

    python data/validation/diagnostics/dfg_variants.py CASE VARIANT NY T_END [CFL]
    INIT_FROM=STATE.npz RECORD_FROM=T python data/validation/diagnostics/dfg_variants.py ...

(``INIT_FROM``: start from a state saved by ``examples/cylinder_benchmark.py --save-state``, at its time, resampled
onto this grid; ``RECORD_FROM``: the first recorded time, default the last two time units for 2D-2, the last one for
2D-1.)

CASE is 2D-1 or 2D-2; prints one JSON line (the summary of examples/cylinder_benchmark.py; 2D-1: the state at T_END,
2D-2: the last two time units). VARIANT (each a change made here by replacing a function, not a setting; variants
combine with '+', e.g. noclamp+split2):

  base        the benchmark as it is
  noclamp     MacCormack without its min-max clamp
  midtrace    the midpoint back-trace instead of the Euler one
  probe15     the wall-profile probe of the extension, the cut-face flux and uncovered faces 1.5 cells out (not 2)
  probe3      the same probe 3 cells out
  noext       the transported velocity not extended into the body
  noant       no anticipated pressure gradient at the wall
  nofluxcorr  no flux correction on the cut faces
  sl          semi-Lagrangian instead of MacCormack advection
  implicit    implicit (backward Euler) viscosity;   cn: Crank-Nicolson viscosity
  mid         the advecting velocity extrapolated to the half step, 1.5 u^n - 0.5 u^{n-1}
  mid_p       mid, and u - G p^n / 2 transported instead of u (G p^n / 2 added back; faces between fluid cells)
  split2      the integrator 'split2' of phisim.fluid (a setting)
  sw          the explicit viscous step with the Shortley-Weller second difference on the faces whose stencil arms
              cross the surface (each axis' second difference times 2 / (s_- + s_+), the arms' fractions s; the
              linear ghost value of the code is that difference times (s_- + s_+) / 2, locally O(1) off)
  split2ext   split2 with u^n + dt/2 a extended into the body as a whole (a -> 0 at a resting wall) instead of
              u^n extended and dt/2 a added with a = 0 inside the body
  imex2, rk2  the integrators 'imex2' / 'rk2' of phisim.fluid (settings; central convection)
  quick       with imex2 or rk2: the QUICK convection (a setting: convection='quick')
  convext     with imex2 or rk2: the convection reads the velocity extended into the body (the band just inside
              a sharp no-slip body set to the extended wall profile, as the split steps' transport reads it)
  long        the channel 3.3 long instead of 2.2 (the outflow 31 diameters behind the cylinder instead of 20)
"""
import json
import os
import sys

ROOT = os.environ.get("REPO", os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "..", ".."))
sys.path.insert(0, ROOT)
sys.path.insert(0, os.path.join(ROOT, "examples"))
import torch  # noqa: E402

import phisim.fluid.stepper as S  # noqa: E402

ST = sys.modules["phisim.fluid.step"]
import cylinder_benchmark as cb  # noqa: E402

import phisim.fluid.projection as P  # noqa: E402

case, var, ny, t_end = sys.argv[1], sys.argv[2], int(sys.argv[3]), float(sys.argv[4])
cfl = float(sys.argv[5]) if len(sys.argv) > 5 else 0.5
orig_adv = S.advect_trusted
parts = set(var.split("+"))  # variants combine with '+', e.g. noclamp+split2
kw = {}
if "noclamp" in parts:
    kw["clamp"] = None
if "midtrace" in parts:
    kw["trace"] = "midpoint"
if kw:  # the split step advects in the stepper's module, 'split2' in the step's
    S.advect_trusted = ST.advect_trusted = (
        lambda f, v, dt, scheme="semi_lagrangian", **k: orig_adv(f, v, dt, scheme=scheme, **{**k, **kw}))
if parts & {"probe15", "probe3"}:  # the distance of the wall-profile probe (extension, cut-face flux, uncovered faces)
    import phisim.fluid.bodies as B
    import phisim.fluid.extension as E
    B.PROBE_CELLS = E.PROBE_CELLS = 1.5 if "probe15" in parts else 3.0
if "noext" in parts:
    S.extend_into_bodies = lambda v, o, t=0.0: v
if "noant" in parts:
    ST.anticipate_pressure = lambda layout, *a, **k: layout
if "nofluxcorr" in parts:
    P._correction_values = lambda values, layout: None
if parts & {"mid_p", "p"}:
    from phisim.field import CenteredGrid
    from phisim.fluid.bodies import solid_layout
    from phisim.ops.differential import gradient
    _adv = S.advance
    cur = {}
    def _advance(state, dt, **k):
        cur["p"] = state.pressure
        cur["obs"] = k.get("obstacles")
        cur["t"] = state.time
        return _adv(state, dt, **k)
    S.advance = _advance
    prev = {}
    def _midp(field, velocity, dt, scheme="semi_lagrangian", **k):
        if not (field is velocity and field.__class__.__name__ == "StaggeredGrid"):
            return orig_adv(field, velocity, dt, scheme=scheme, **k)
        if "mid_p" in parts:
            p = prev.get("v")
            prev["v"] = field
            if p is not None:
                velocity = field._with_components([1.5 * a - 0.5 * b for a, b in zip(field.values, p.values)])
        q = cur.get("p")
        if q is None:
            return orig_adv(field, velocity, dt, scheme=scheme, **k)
        grid = field.grid
        lay = solid_layout(cur["obs"], grid, field.boundary, cur["t"], field.dtype, field.device)
        act = (lay.cell_fraction > 0).to(field.dtype)
        qq = CenteredGrid(q.values * act, grid, field.boundary.for_pressure())
        g = gradient(qq, at="face").values
        masks = []
        for i in range(grid.rank):
            a = act
            d = i + 1
            first = a.narrow(d, 0, 1)
            last = a.narrow(d, a.shape[d] - 1, 1)
            pa = torch.cat([first, a, last], d)
            masks.append(torch.minimum(pa.narrow(d, 0, a.shape[d] + 1), pa.narrow(d, 1, a.shape[d] + 1)))
        half = [0.5 * gi * mi for gi, mi in zip(g, masks)]
        w = field._with_components([a - h for a, h in zip(field.values, half)])
        out = orig_adv(w, velocity, dt, scheme=scheme, **k)
        return out._with_components([a + h for a, h in zip(out.values, half)])
    S.advect_trusted = _midp
if "mid" in parts:
    prev = {}
    def _mid(field, velocity, dt, scheme="semi_lagrangian", **k):
        if field is velocity and field.__class__.__name__ == "StaggeredGrid":
            p = prev.get("v")
            prev["v"] = field
            if p is not None:
                velocity = field._with_components([1.5 * a - 0.5 * b for a, b in zip(field.values, p.values)])
        return orig_adv(field, velocity, dt, scheme=scheme, **k)
    S.advect_trusted = _mid
if "split2ext" in parts:
    ctx = {}
    _ext = S.extend_into_bodies
    def _ext_capture(v, o, t=0.0):
        ctx["o"], ctx["t"] = o, t
        return _ext(v, o, t)
    S.extend_into_bodies = _ext_capture
    def _s2(src, state, dt, scheme):
        carrier = ST.half_step_velocity(src, state.velocity_rate, dt)
        if state.acceleration is None:
            return S.advect_trusted(src, carrier, dt, scheme=scheme)
        half = [(0.5 * dt) * a for a in state.acceleration.values]
        v0 = state.velocity
        moved = _ext(v0._with_components([u + h for u, h in zip(v0.values, half)]), ctx["o"], ctx["t"])
        v = S.advect_trusted(moved, carrier, dt, scheme=scheme)
        return v._with_components([u - h for u, h in zip(v.values, half)])
    S.split2_advection = _s2
if parts & {"sw", "split2sw"}:
    import phisim.solvers.mac_diffusion as MD
    from phisim.fluid.bodies import WALL_FRACTION_MIN
    _sharp = MD._sharp_component
    geo = {}

    def _factors(shape, dtype):
        key = (tuple(shape), dtype)
        if key in geo:
            return geo[key]
        grid = cb.setup(case, ny)[0]
        i = 0 if tuple(shape) == tuple(grid.face_shape(0)) else 1
        x = grid.face_centers(i, torch.float64, "cpu")
        phi = ((x - torch.tensor(cb.CENTER, dtype=torch.float64)) ** 2).sum(-1).sqrt() - cb.D / 2
        h2 = [d * d for d in grid.dx]
        out = []
        for a in range(2):
            ss = []
            for side in (-1, 1):
                pn = torch.roll(phi, -side, a)  # the neighbour at index + side
                link = (phi > 0) & (pn <= 0)
                gap = torch.where(link, phi - pn, torch.ones_like(phi))
                ss.append(torch.where(link, (phi / gap).clamp(WALL_FRACTION_MIN, 1.0), torch.ones_like(phi)))
            sm, sp = ss
            f = 2.0 / (sm + sp)
            ca = ((1 / sm - 1) + (1 / sp - 1)) / h2[a]
            out.append((f.to(dtype), ca.to(dtype), h2[a]))
        geo[key] = out
        return out

    def _sw(comp, u, mask, wall, method, alpha, theta, solve, engine, capacitance):
        if method != "explicit":
            return _sharp(comp, u, mask, wall, method, alpha, theta, solve, engine, capacitance)
        cut, coef, source = wall
        facs = _factors(u.shape[1:], u.dtype)
        z = u.masked_fill(cut, 0)
        num = u + alpha * comp.laplace(z)
        den_coef = torch.zeros_like(u)
        for a, (f, ca, h2) in enumerate(facs):
            d = a + 1
            d2 = (torch.roll(z, -1, d) - 2 * z + torch.roll(z, 1, d)) / h2
            num = num + alpha * (f - 1) * d2
            den_coef = den_coef + f * ca
        if source is not None:
            c0 = coef.to(u.dtype)
            num = num + alpha * source.to(u.dtype) * torch.where(c0 > 0, den_coef / c0.clamp_min(1e-300), 1.0)
        return torch.where(mask, u, num / (1 + alpha * den_coef))
    MD._sharp_component = _sw
if "convext" in parts:
    import phisim.fluid.integrators as I
    from phisim.fluid.extension import extend_into_bodies
    _conv, _body = I.convection, cb.setup(case, ny)[1]
    I.convection = lambda v, scheme="central": _conv(extend_into_bodies(v, _body), scheme)
if "long" in parts:
    cb.L = 3.3
adv = "semi_lagrangian" if "sl" in parts else "maccormack"
vs = "implicit" if "implicit" in parts else "crank_nicolson" if "cn" in parts else "explicit"
torch.set_num_threads(1)
rec = float(os.environ.get("RECORD_FROM", t_end - (1 if case == "2D-1" else 2)))
init = cb.load_state(os.environ["INIT_FROM"]) if os.environ.get("INIT_FROM") else None
integ = "split2" if any(q.startswith("split2") for q in parts) else "split"
integ = next((q for q in ("imex2", "rk2") if q in parts), integ)
hist, state, meta = cb.run(case, ny, t_end, cfl=cfl, record_from=rec, advection=adv, viscosity_scheme=vs,
                          integrator=integ, convection="quick" if "quick" in parts else "central", init=init)
tail = hist[hist[:, 0] >= t_end - (1 if case == "2D-1" else 2)]
extra = {"init_from": os.environ["INIT_FROM"], "record_from": rec} if init is not None else {}
print(json.dumps({"case": case, "variant": var, "cfl": cfl, **meta, **extra, **cb.summarize(case, tail)}), flush=True)
