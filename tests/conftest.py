"""Fixtures shared by the whole test suite.

* ``repo_root``: the repository's root folder;
* ``load_example``: ``load_example("karman")`` imports ``examples/karman.py`` as a fresh module (a script with
  a ``main``), ``load_example("benchmarks/bench_cg.py")`` any script by its path.

Every test process runs torch with one thread.
"""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import pytest
import torch

# One torch thread per test process: `bash run.sh test` runs two worker processes on two cores, and a pool of two
# threads per worker would oversubscribe them (tests that compare thread counts set their own).
torch.set_num_threads(1)

ROOT = Path(__file__).resolve().parents[1]


def _load_script(name: str):
    rel = name if name.endswith(".py") else f"examples/{name}.py"
    path = ROOT / rel
    folder = str(path.parent)
    if folder not in sys.path:  # scripts import their siblings (timing, inputs, ...)
        sys.path.insert(0, folder)
    spec = importlib.util.spec_from_file_location("script_" + rel.replace("/", "_").removesuffix(".py"), path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.fixture(scope="session")
def repo_root() -> Path:
    return ROOT


@pytest.fixture(scope="session")
def load_example():
    return _load_script
