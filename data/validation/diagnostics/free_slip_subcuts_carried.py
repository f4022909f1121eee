"""The carried free-slip sphere study (``tests/phisim/fluid/test_moving_bodies_order_3d.py --free-slip``) with ``m``
sub-faces per in-face axis in 3-D instead of ``FREE_SLIP_SUBFACES[3]``:
``python data/validation/diagnostics/free_slip_subcuts_carried.py M N...`` prints one JSON row per grid (solves to
1e-6, the study's default). Run at 1c8f227 (planar sub-cuts) with M = 8 for
``moving_spherical_couette_free_slip_subcuts_8x8.jsonl``."""
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

    FREE_SLIP_SUBFACES[3] = int(sys.argv[1])
    torch.set_num_threads(1)
    study_3d.study([int(a) for a in sys.argv[2:]], free_slip=True, rtol=1e-6, dt_cells=1.0,
                   on_row=lambda row: print(json.dumps({**row, "m": FREE_SLIP_SUBFACES[3]}), flush=True))
