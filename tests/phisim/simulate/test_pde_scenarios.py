"""`phisim simulate` scenarios of the spectral (phisim.pde) equations: every one runs, writes Well files whose
frames are the stepper's states, and keeps the equation's invariants."""

from __future__ import annotations

import h5py
import numpy as np
import pytest
import torch

from phisim.io import read_simulation
from phisim.pde import make_stepper
from phisim.simulate import SCENARIOS, resolve_config, simulate_dataset
from phisim.simulate.dataset import _draw_parameters, _generator

PDE_SCENARIOS = sorted(name for name, sc in SCENARIOS.items() if sc.description.endswith("(phisim.pde)"))


def test_every_spectral_equation_has_a_scenario():
    assert len(PDE_SCENARIOS) == 15


@pytest.mark.parametrize("name", PDE_SCENARIOS)
def test_scenario_steps_stay_finite_and_fit_the_grid(name):
    sc = SCENARIOS[name]
    cfg = resolve_config(name, resolution=16, steps=2, dim=sc.dims[0])
    g = _generator(cfg["seed"], 0)
    params = _draw_parameters(sc, cfg, g)
    sim = sc.build(cfg, params, 2, g, torch.float64, torch.device("cpu"))
    state = sim.state
    for _ in range(3):
        state = sim.step(state)
    frame = sim.frame(state)
    assert set(frame) == set(sim.fields)
    for value in frame.values():
        v = value if isinstance(value, torch.Tensor) else value.values
        assert v.shape[0] == 2 and tuple(v.shape[-sim.grid.rank:]) == sim.grid.resolution
        assert bool(torch.isfinite(v).all())


def test_cahn_hilliard_dataset_conserves_mass_and_matches_its_stepper(tmp_path):
    cfg = resolve_config("cahn_hilliard", resolution=16, steps=4, trajectories=2, trajectories_per_file=2,
                         valid_fraction=0.0, test_fraction=0.0, dtype="float64")
    simulate_dataset(tmp_path / "ch", cfg, progress=False)
    (path,) = sorted((tmp_path / "ch" / "data" / "train").glob("*.h5"))
    data = read_simulation(path)
    u = data.fields["u"]  # (B, T, 16)
    assert u.shape == (2, 5, 16)
    mass = u.mean(axis=-1)
    assert np.abs(mass - mass[:, :1]).max() < 1e-13  # conserved to round-off
    with h5py.File(path, "r") as f:
        assert float(f.attrs["gamma"]) == pytest.approx(2.5e-3)
    # the stored frames are the stepper's states: one step from frame 0 gives frame 1
    stepper = make_stepper("cahn_hilliard", ndim=1, resolution=16, dt=SCENARIOS["cahn_hilliard"].dt,
                           dtype=torch.float64)
    nxt = stepper(torch.as_tensor(u[:, 0])[:, None])[:, 0].numpy()
    np.testing.assert_allclose(nxt, u[:, 1], rtol=0, atol=1e-12)
    # cell centres of the file's grid are the spectral sample points j L / N
    x = data.grid.cell_centers(torch.float64)[..., 0].numpy()
    np.testing.assert_allclose(x, np.arange(16) / 16, atol=1e-14)
