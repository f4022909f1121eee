"""The carried free-slip sphere study (``tests/phisim/fluid/test_moving_bodies_order_3d.py --free-slip``) with ``m``
sub-faces per in-face axis in 3-D instead of ``FREE_SLIP_SUBFACES[3]``:
``python data/validation/diagnostics/free_slip_subcuts_carried.py M N... [--rtol R]`` prints one JSON row per grid
(solves to ``R``, default 1e-6, the study's default). Run at 1c8f227 (planar sub-cuts) with M = 8 for
``moving_spherical_couette_free_slip_subcuts_8x8.jsonl``; with the corrected sub-cuts, ``8 64 --rtol 1e-9`` and
``8 72 --rtol 1e-9`` for ``moving_spherical_couette_free_slip_8x8_64_72.jsonl``."""
import json
import sys
from pathlib import Path

import torch

root = Path(__file__).resolve().parents[3]
sys.path.insert(0, str(root))
sys.path.insert(0, str(root / "tests" / "phisim" / "fluid"))
from phisim.fluid.bodies import FREE_SLIP_SUBFACES  # noqa: E402

if __name__ == "__main__":
    import test_moving_bodies_order_3d as study_3d

    args = sys.argv[1:]
    rtol = 1e-6
    if "--rtol" in args:
        k = args.index("--rtol")
        rtol = float(args[k + 1])
        del args[k:k + 2]
    FREE_SLIP_SUBFACES[3] = int(args[0])
    torch.set_num_threads(1)
    study_3d.study([int(a) for a in args[1:]], free_slip=True, rtol=rtol, dt_cells=1.0,
                   on_row=lambda row: print(json.dumps({**row, "m": FREE_SLIP_SUBFACES[3], "rtol": rtol}), flush=True))
