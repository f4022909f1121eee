"""The simulation-file API in one place, as imported before :mod:`phisim.io` was split into modules.

:class:`SimulationWriter` lives in :mod:`phisim.io.writer` (with the description of the file layout),
:func:`read_simulation` and :class:`SimulationData` in :mod:`phisim.io.reader`, :func:`recover_file` in
:mod:`phisim.io.recovery`, :class:`TrainingLog` and :func:`read_training` in :mod:`phisim.io.traininglog` and
:func:`well_bc_type` in :mod:`phisim.io.well`. Prefer importing them from :mod:`phisim.io`.
"""

from __future__ import annotations

from phisim.io.reader import SimulationData, read_simulation
from phisim.io.recovery import recover_file
from phisim.io.traininglog import TrainingLog, read_training
from phisim.io.well import well_bc_type
from phisim.io.writer import FIELD_KINDS, SimulationWriter

__all__ = [
    "SimulationWriter",
    "SimulationData",
    "read_simulation",
    "recover_file",
    "TrainingLog",
    "read_training",
    "well_bc_type",
    "FIELD_KINDS",
]
