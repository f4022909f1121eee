"""The resting free-slip sphere study (``examples/spherical_couette.py --free-slip --start-exact``, solves to 1e-10,
steady below 1e-9) with ``m`` sub-faces per in-face axis in 3-D instead of ``FREE_SLIP_SUBFACES[3]``:
``python data/validation/diagnostics/free_slip_subcuts_resting.py M N...`` prints one JSON row per grid.
``8 64`` for ``spherical_couette_free_slip_8x8_64.jsonl``."""
import json
import sys
from pathlib import Path

import torch

root = Path(__file__).resolve().parents[3]
sys.path.insert(0, str(root))
sys.path.insert(0, str(root / "examples"))
from phisim.fluid.bodies import FREE_SLIP_SUBFACES  # noqa: E402

if __name__ == "__main__":
    import spherical_couette

    FREE_SLIP_SUBFACES[3] = int(sys.argv[1])
    torch.set_num_threads(1)
    for n in (int(a) for a in sys.argv[2:]):
        row = spherical_couette.study([n], free_slip=True, start_exact=True, rtol=1e-10, tol=1e-9)[0]
        print(json.dumps({**row, "m": FREE_SLIP_SUBFACES[3]}), flush=True)
