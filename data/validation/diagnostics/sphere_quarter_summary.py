"""Grid convergence of the sphere at Re = 100 in the wide box, quarter runs D/8-D/24 (``examples/sphere_drag.py --box 4
10 8 --quarter``): per grid the drag with both pressure readings, its parts and the recirculation length, and for each
quantity the observed order and the Richardson limit of every three consecutive grids (``sphere_drag.convergence``).

``python data/validation/diagnostics/sphere_quarter_summary.py [JSON ...]`` (default: the split step's quarter runs'
files in data/validation) prints a Markdown table and one JSON line per quantity; ``... imex2`` the same for the runs
with ``--integrator imex2 --convection quick``; ``... compare`` a table of the two integrators side by side per grid.
"""
import json
import sys
from math import nan
from pathlib import Path

ROOT = Path(__file__).resolve().parents[3]
sys.path.insert(0, str(ROOT / "examples"))
import sphere_drag as sd  # noqa: E402

DEFAULT = ["sphere_re100_box8_quarter.json", "sphere_re100_box8_quarter_n20.json",
           "sphere_re100_box8_quarter_n24.json"]
IMEX2 = [f"sphere_re100_box8_quarter_imex2_quick_n{n}.json" for n in (8, 12, 16, 20, 24)]
QUANTITIES = ("cd", "cd_surface", "cd_momentum", "cd_pressure", "cd_pressure_surface", "cd_pressure_momentum",
              "cd_viscous", "cd_viscous_momentum", "recirculation")


def load(paths):
    runs = {}
    for p in paths:
        for r in json.loads(Path(p).read_text())["runs"]:
            runs[r["n"]] = r
    return [runs[n] for n in sorted(runs)]


def _files(names):
    return [str(ROOT / "data" / "validation" / f) for f in names]


def compare() -> int:
    """The split step's and ``'imex2'`` + QUICK's readings per grid, and the gap of the momentum readings."""
    split = {r["n"]: r for r in load([f for f in _files(DEFAULT) if Path(f).exists()])}
    imex = {r["n"]: r for r in load([f for f in _files(IMEX2) if Path(f).exists()])}
    print("| grid | C_D cells / momentum: split | `imex2` + QUICK | gap of the momentum readings | "
          "pressure part (momentum): split / `imex2` | viscous part (momentum): split / `imex2` | L / D: split / "
          "`imex2` |")
    print("|---|---|---|---|---|---|---|")
    for n in sorted(set(split) & set(imex)):
        a, b = split[n], imex[n]
        print(f"| D/{n} | {a['cd']:.4f} / {a['cd_momentum']:.4f} | {b['cd']:.4f} / {b['cd_momentum']:.4f} | "
              f"{a['cd_momentum'] - b['cd_momentum']:.4f} | {a['cd_pressure_momentum']:.4f} / "
              f"{b['cd_pressure_momentum']:.4f} | {a['cd_viscous_momentum']:.4f} / {b['cd_viscous_momentum']:.4f} | "
              f"{a['recirculation']:.3f} / {b['recirculation']:.3f} |")
    return 0


def main(argv=None) -> int:
    args = argv if argv is not None else sys.argv[1:]
    if args == ["compare"]:
        return compare()
    args = _files(IMEX2) if args == ["imex2"] else (args or _files(DEFAULT))
    runs = load([a for a in args if Path(a).exists()])
    print("| grid | cells | C_D: cells / surface / momentum | pressure part: cells / surface / momentum | "
          "viscous part: probes / momentum | L / D | steps | t | CPU |")
    print("|---|---|---|---|---|---|---|---|---|")
    for r in runs:
        cells = " x ".join(str(c) for c in r["cells"])
        print(f"| D/{r['n']} | {cells} | {r['cd']:.4f} / {r['cd_surface']:.4f} / {r.get('cd_momentum', nan):.4f} | "
              f"{r['cd_pressure']:.4f} / {r['cd_pressure_surface']:.4f} / {r.get('cd_pressure_momentum', nan):.4f} | "
              f"{r['cd_viscous']:.4f} / {r.get('cd_viscous_momentum', nan):.4f} | {r['recirculation']:.3f} | "
              f"{r['steps']} | {r['t']:.0f} | {r['cpu_s']:.0f} s |")
    ns = [r["n"] for r in runs]
    for q in QUANTITIES:
        vals = [r.get(q, nan) for r in runs]
        triples = []
        for k in range(len(runs) - 2):
            c = sd.convergence(ns[k:k + 3], vals[k:k + 3])
            triples.append({"grids": ns[k:k + 3], "order": c.get("order"), "limit": c.get("richardson")})
        print(json.dumps({"quantity": q, "values": dict(zip(ns, vals)), "triples": triples}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
