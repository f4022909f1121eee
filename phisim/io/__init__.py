"""Files layer: simulations in The Well's HDF5 layout written frame by frame (:class:`SimulationWriter`,
:func:`read_simulation`), training logs, the write-ahead journal and recovery of killed runs, Well attributes
and normalisation statistics.

Modules, each importing only those before it: :mod:`~phisim.io.journal` (the crash-safety journal),
:mod:`~phisim.io.interrupts` (prompt, clean SIGINT/SIGTERM), :mod:`~phisim.io.h5util`, :mod:`~phisim.io.extras`,
:mod:`~phisim.io.well`, :mod:`~phisim.io.traininglog`, :mod:`~phisim.io.reader`, :mod:`~phisim.io.writer`,
:mod:`~phisim.io.recovery`; :mod:`~phisim.io.stats` needs only :mod:`~phisim.io.h5util`.
"""

from phisim.io.reader import SimulationData, read_simulation
from phisim.io.recovery import recover_file
from phisim.io.stats import STATISTICS_KEYS, compute_statistics, format_statistics, write_statistics
from phisim.io.traininglog import TrainingCurves, TrainingLog, read_training
from phisim.io.well import well_bc_type
from phisim.io.writer import FIELD_KINDS, SimulationWriter

__all__ = [
    "SimulationWriter", "SimulationData", "read_simulation", "recover_file", "TrainingLog", "read_training",
    "TrainingCurves", "well_bc_type", "FIELD_KINDS",
    "compute_statistics", "write_statistics", "format_statistics", "STATISTICS_KEYS",
]
