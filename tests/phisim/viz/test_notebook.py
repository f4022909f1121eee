"""The quickstart notebook (examples/notebooks/quickstart.ipynb) runs in a Jupyter kernel and shows its pictures
inline: every code cell after the imports displays a picture (HTML and PNG), the trajectory as a JavaScript
player with one image per recorded state, and the GIF it saves has the same frames.

Needs ``nbclient``, ``nbformat`` and ``ipykernel`` (the ``test`` extra); skipped, saying why, where they are
missing or a kernel cannot start.
"""

from __future__ import annotations

import base64
import io
import re
from pathlib import Path

import pytest

NOTEBOOK = Path(__file__).resolve().parents[3] / "examples" / "notebooks" / "quickstart.ipynb"


def test_quickstart_notebook_runs_and_shows_pictures(tmp_path):
    nbformat = pytest.importorskip("nbformat", reason="nbformat is not installed (pip install -e .[test])")
    nbclient = pytest.importorskip("nbclient", reason="nbclient is not installed (pip install -e .[test])")
    pytest.importorskip("ipykernel", reason="ipykernel is not installed (pip install -e .[test])")
    from jupyter_client.manager import start_new_kernel
    from PIL import Image

    nb = nbformat.read(NOTEBOOK, as_version=4)
    assert all(not c.get("outputs") for c in nb.cells if c.cell_type == "code"), "store the notebook without outputs"
    try:
        km, kc = start_new_kernel(kernel_name="python3", startup_timeout=120, cwd=str(tmp_path))
    except Exception as exc:  # no kernel spec, no ZMQ sockets, a sandbox that forbids subprocesses, ...
        pytest.skip(f"a Jupyter kernel cannot start here ({type(exc).__name__}: {exc}); notebook not executed")
    try:
        kc.stop_channels()
        client = nbclient.NotebookClient(nb, km=km, timeout=600, resources={"metadata": {"path": str(tmp_path)}})
        client.execute()
    finally:
        if km.has_kernel:
            km.shutdown_kernel(now=True)

    code = [c for c in nb.cells if c.cell_type == "code"]
    errors = [o for c in code for o in c.outputs if o.output_type == "error"]
    assert not errors, errors
    shown = []
    for cell in code[1:]:  # every cell after the imports ends with a picture
        results = [o for o in cell.outputs if o.output_type == "execute_result"]
        assert results, f"no picture from:\n{cell.source}"
        data = results[-1]["data"]
        assert {"text/html", "image/png"} <= set(data), sorted(data)
        assert data["text/plain"].startswith("Picture(")
        png = Image.open(io.BytesIO(base64.b64decode(data["image/png"])))
        assert png.format == "PNG" and min(png.size) > 100
        shown.append((cell.source, data))
    player = [d for src, d in shown if "rollout(" in src]
    assert len(player) == 1
    html = player[0]["text/html"]
    n_states = 12 // 2 + 1  # rollout of 12 steps, every 2nd state and the initial one
    assert "<script" in html and len(re.findall(r'frames\[\d+\] = "data:image/png;base64,', html)) == n_states
    assert player[0]["text/plain"] == f"Picture(animation of {n_states} frames, 1 panel)"
    with Image.open(tmp_path / "smoke.gif") as gif:
        assert gif.n_frames == n_states
    stills = [d["text/html"] for src, d in shown if "rollout(" not in src]
    assert all(h.startswith('<img src="data:image/png;base64,') for h in stills)
