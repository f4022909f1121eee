"""Old module paths of phisim, kept importable.

phisim's modules live in one folder per layer (``phisim.ops``, ``phisim.spectral``, ``phisim.solvers``,
``phisim.fluid``, ``phisim.io``, ``phisim.viz``, ``phisim.simulate``). Scripts written against the earlier flat
layout (``import phisim.poisson``, ``from phisim.advection import advect``) keep working: importing an old path
returns the module at its new home (the same module object, so settings and monkeypatches agree) and issues a
:class:`DeprecationWarning` naming the new path. :data:`MOVED` lists every old path.
"""

from __future__ import annotations

import importlib
import importlib.abc
import importlib.util
import sys
import warnings

__all__ = ["MOVED", "install"]

#: Old module path -> new module path.
MOVED: dict[str, str] = {
    "phisim.fft": "phisim.spectral.fft",
    "phisim.differential": "phisim.ops.differential",
    "phisim.advection": "phisim.ops.advection",
    "phisim.linalg": "phisim.solvers.linalg",
    "phisim.poisson": "phisim.solvers.poisson",
    "phisim.poisson_masked": "phisim.solvers.masked",
    "phisim.diffusion": "phisim.solvers.diffusion",
    "phisim.traininglog": "phisim.io.traininglog",
    "phisim.wellstats": "phisim.io.stats",
    "phisim.plot": "phisim.viz.plot",
    "phisim.plotfile": "phisim.viz.plotfile",
    "phisim.noise": "phisim.simulate.noise",
}


class _AliasLoader(importlib.abc.Loader):
    def __init__(self, new: str):
        self.new = new

    def create_module(self, spec):
        warnings.warn(f"{spec.name} moved to {self.new}; import it from there", DeprecationWarning, stacklevel=3)
        return importlib.import_module(self.new)

    def exec_module(self, module):
        """The module at its new home is already executed."""


class _AliasFinder(importlib.abc.MetaPathFinder):
    def find_spec(self, fullname, path=None, target=None):
        new = MOVED.get(fullname)
        if new is None:
            return None
        return importlib.util.spec_from_loader(fullname, _AliasLoader(new))


def install() -> None:
    """Make the old module paths of :data:`MOVED` importable (idempotent)."""
    if not any(isinstance(f, _AliasFinder) for f in sys.meta_path):
        sys.meta_path.append(_AliasFinder())
