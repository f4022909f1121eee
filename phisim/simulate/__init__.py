"""Datasets of simulations from the command line (``phisim simulate``): scenarios and the parallel writer.

See :mod:`phisim.simulate.scenarios` for the scenarios and :mod:`phisim.simulate.dataset` for the folder
layout (The Well's ``data/<split>/*.h5`` plus ``stats.yaml``), seeding, workers and resuming.
"""

from phisim.simulate.dataset import (
    SPLITS,
    ChunkPlan,
    check_dataset_dir,
    get_scenario,
    load_config_file,
    plan_chunks,
    resolve_config,
    simulate_chunk,
    simulate_dataset,
)
from phisim.simulate.scenarios import COMMON_PARAMETERS, SCENARIOS, Param, Scenario, Simulation

__all__ = [
    "SCENARIOS", "COMMON_PARAMETERS", "Param", "Scenario", "Simulation", "SPLITS", "ChunkPlan",
    "get_scenario", "resolve_config", "load_config_file", "plan_chunks", "simulate_chunk", "simulate_dataset",
    "check_dataset_dir",
]
