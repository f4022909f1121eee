"""Files layer: simulations in The Well's HDF5 layout written frame by frame (:class:`SimulationWriter`,
:func:`read_simulation`), training logs, the write-ahead journal and recovery of killed runs, Well attributes
and normalisation statistics."""

from phisim.io.simulation import (
    FIELD_KINDS,
    SimulationData,
    SimulationWriter,
    read_simulation,
    recover_file,
    well_bc_type,
)
from phisim.io.stats import STATISTICS_KEYS, compute_statistics, format_statistics, write_statistics
from phisim.io.traininglog import TrainingLog, read_training

__all__ = [
    "SimulationWriter", "SimulationData", "read_simulation", "recover_file", "TrainingLog", "read_training",
    "well_bc_type", "FIELD_KINDS",
    "compute_statistics", "write_statistics", "format_statistics", "STATISTICS_KEYS",
]
