"""Long validations of the method (marked slow): physical gradients beat backpropagation on E3 and E4."""

import pytest

from inverse.problems import get_problem
from inverse.train import train


@pytest.mark.slow
def test_e3_poisson_physical_gradients_beat_adam():
    # docs/RESULTS.md: at 32^2, batch 16, Adam / PG = 1.49 at iteration 60 and 4.6 at 1500
    problem = get_problem("poisson", resolution=(32, 32))
    adam = train(problem, "adam", iterations=300, batch_size=16, seed=0)
    pg = train(problem, "pg", iterations=300, batch_size=16, seed=0)
    assert adam.final("metric", 30) > 2.0 * pg.final("metric", 30)


@pytest.mark.slow
def test_e4_heat_physical_gradients_beat_adam():
    # docs/RESULTS.md: at 64^2, batch 16, Adam / PG = 1.32 at iteration 100 (published 1.34)
    problem = get_problem("heat")
    adam = train(problem, "adam", iterations=150, batch_size=16, seed=0)
    pg = train(problem, "pg", iterations=150, batch_size=16, seed=0)
    assert adam.final("metric", 30) > 1.15 * pg.final("metric", 30)
