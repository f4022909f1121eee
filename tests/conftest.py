"""Fixtures shared by the whole test suite.

* ``repo_root``: the repository's root folder;
* ``load_example``: ``load_example("karman")`` imports ``examples/karman.py`` as a fresh module (a script with
  a ``main``), ``load_example("benchmarks/bench_cg.py")`` any script by its path;
* ``random_velocity``: ``random_velocity(grid, boundary, batch=2, seed=0, dtype=torch.float64)`` a MAC velocity
  of standard-normal face values (boundary faces as drawn; call ``.with_boundary_faces()`` to impose them).
"""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import pytest
import torch

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


@pytest.fixture(scope="session")
def random_velocity():
    from phisim import StaggeredGrid
    from phisim.boundary import Boundary

    def make(grid, boundary, batch: int = 2, seed: int = 0, dtype=torch.float64):
        g = torch.Generator().manual_seed(seed)
        values = tuple(torch.randn(batch, *grid.face_shape(i), generator=g, dtype=dtype) for i in range(grid.rank))
        return StaggeredGrid(values, grid, Boundary.create(boundary, grid.rank))

    return make
