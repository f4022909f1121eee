"""Normalisation statistics (stats.yaml) of a Well-layout dataset folder, and the constant output interval."""

from __future__ import annotations

import warnings

import h5py
import numpy as np
import pytest
import torch

from phisim import Grid
from phisim.errors import FileFormatError, ParameterError, ShapeError
from phisim.io import SimulationWriter, read_simulation
from phisim.io.stats import compute_statistics, format_statistics, write_statistics

yaml = pytest.importorskip("yaml")


def _write(path, seed, frames=5, batch=2, constant=None):
    g = Grid((6, 4), bounds=[(0, 3), (-1, 1)])
    gen = torch.Generator().manual_seed(seed)
    rho = torch.randn(frames, batch, 6, 4, generator=gen, dtype=torch.float64) * 3 + 1
    u = torch.randn(frames, batch, 2, 6, 4, generator=gen, dtype=torch.float64) * torch.tensor([1.0, 5.0]).view(
        1, 1, 2, 1, 1) - 2
    with SimulationWriter(path, g, "periodic", dataset_name="stats", fields={"rho": "scalar", "u": "vector"},
                          batch_size=batch, dtype=torch.float64, output_interval=0.25,
                          constant_fields=constant) as w:
        for k in range(frames):
            w.append(0.25 * k, rho=rho[k], u=u[k])
    return rho.numpy(), u.numpy()


def test_statistics_match_numpy_over_the_training_split(tmp_path):
    train = tmp_path / "ds" / "data" / "train"
    train.mkdir(parents=True)
    mask = np.zeros((6, 4))
    mask[2:4, 1:3] = 1.0
    r1, u1 = _write(train / "a.h5", 1, constant={"obstacle": mask})
    r2, u2 = _write(train / "b.h5", 2, frames=7, batch=3, constant={"obstacle": mask})
    (tmp_path / "ds" / "data" / "valid").mkdir()
    _write(tmp_path / "ds" / "data" / "valid" / "c.h5", 3)  # must not enter the statistics
    path = write_statistics(tmp_path / "ds")
    assert path == tmp_path / "ds" / "stats.yaml"
    stats = yaml.safe_load(path.read_text())
    assert set(stats) == {"mean", "std", "rms", "mean_delta", "std_delta", "rms_delta"}
    rho = np.concatenate([r1.reshape(-1), r2.reshape(-1)])
    u = np.concatenate([np.moveaxis(u1, 2, -1).reshape(-1, 2), np.moveaxis(u2, 2, -1).reshape(-1, 2)])
    np.testing.assert_allclose(stats["mean"]["rho"], rho.mean(), rtol=1e-13)
    np.testing.assert_allclose(stats["std"]["rho"], rho.std(), rtol=1e-13)
    np.testing.assert_allclose(stats["rms"]["rho"], np.sqrt((rho**2).mean()), rtol=1e-13)
    np.testing.assert_allclose(stats["mean"]["u"], u.mean(0), rtol=1e-13)
    np.testing.assert_allclose(stats["std"]["u"], u.std(0), rtol=1e-13)
    assert stats["std"]["u"][1] > 3 * stats["std"]["u"][0]  # components are kept apart
    drho = np.concatenate([np.diff(r1, axis=0).reshape(-1), np.diff(r2, axis=0).reshape(-1)])
    du = np.concatenate([np.moveaxis(np.diff(u1, axis=0), 2, -1).reshape(-1, 2),
                         np.moveaxis(np.diff(u2, axis=0), 2, -1).reshape(-1, 2)])
    np.testing.assert_allclose(stats["mean_delta"]["rho"], drho.mean(), rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(stats["std_delta"]["rho"], drho.std(), rtol=1e-13)
    np.testing.assert_allclose(stats["rms_delta"]["u"], np.sqrt((du**2).mean(0)), rtol=1e-13)
    np.testing.assert_allclose(stats["mean"]["obstacle"], mask.mean(), rtol=1e-13)
    np.testing.assert_allclose(stats["std"]["obstacle"], mask.std(), rtol=1e-13)
    assert "obstacle" not in stats["mean_delta"]  # constant in time


def test_well_loader_normalises_with_our_statistics(tmp_path):
    from the_well.data import WellDataset
    from the_well.data.normalization import ZScoreNormalization

    train = tmp_path / "ds" / "data" / "train"
    train.mkdir(parents=True)
    rho, u = _write(train / "a.h5", 4)
    write_statistics(tmp_path / "ds")
    stats = compute_statistics(train)
    ds = WellDataset(path=str(tmp_path / "ds"), well_split_name="train", n_steps_input=1, n_steps_output=1,
                     use_normalization=True, normalization_type=ZScoreNormalization)
    s = ds[0]  # trajectory 0, window at frame 0
    expect_rho = (rho[0, 0] - stats["mean"]["rho"]) / stats["std"]["rho"]
    np.testing.assert_allclose(s["input_fields"][0, ..., 0].numpy(), expect_rho, rtol=1e-5, atol=1e-5)
    expect_uy = (u[0, 0, 1] - stats["mean"]["u"][1]) / stats["std"]["u"][1]
    np.testing.assert_allclose(s["input_fields"][0, ..., 2].numpy(), expect_uy, rtol=1e-5, atol=1e-5)
    all_rho = np.stack([ds[i]["input_fields"][0, ..., 0].numpy() for i in range(len(ds))])
    assert abs(all_rho.mean()) < 0.5 and 0.5 < all_rho.std() < 1.5


def test_statistics_errors(tmp_path):
    with pytest.raises(FileFormatError, match="data/train"):
        write_statistics(tmp_path)
    (tmp_path / "data" / "train").mkdir(parents=True)
    with pytest.raises(FileFormatError, match="no .h5"):
        write_statistics(tmp_path)
    (tmp_path / "data" / "train" / "x.h5").write_text("not hdf5")
    with pytest.raises(FileFormatError):
        write_statistics(tmp_path)
    with pytest.raises(ParameterError):
        compute_statistics([])
    assert not list(tmp_path.glob("*.tmp")) and not (tmp_path / "stats.yaml").exists()


def test_yaml_text_is_read_back_exactly():
    stats = {"mean": {"a": 1e-5, "b": [0.1, -2.5e30]}, "std": {}, "rms": {"a": 0.0},
             "mean_delta": {"t": [[1.0, 2.0], [3.0, 4.0]]}, "std_delta": {}, "rms_delta": {"x y": 7.0}}
    assert yaml.safe_load(format_statistics(stats)) == stats


# ---- constant output interval -------------------------------------------------------------------------


def _writer(path, **kw):
    return SimulationWriter(path, Grid((4, 4)), "periodic", dataset_name="t", fields={"c": "scalar"},
                            batch_size=1, **kw)


def test_uneven_intervals_are_refused_or_warned(tmp_path):
    c = torch.zeros(1, 4, 4)
    with _writer(tmp_path / "a.h5") as w:
        w.append(0.0, c=c)
        w.append(0.5, c=c)
        w.append(1.0 + 1e-9, c=c)  # round-off is accepted (relative 1e-6)
        with pytest.raises(ParameterError, match="interval is 0.5"):
            w.append(1.2, c=c)
        w.append(1.5, c=c)  # the refused frame left nothing behind
    d = read_simulation(tmp_path / "a.h5")
    assert d.n_frames == 4 and d.dt == 0.5
    with h5py.File(tmp_path / "a.h5") as f:
        assert f["scalars/dt"][()] == 0.5 and f.attrs["dt"] == 0.5 and "dt" in list(f["scalars"].attrs["field_names"])
    with _writer(tmp_path / "b.h5", output_interval=0.3, uneven_intervals="warn") as w:
        w.append(0.0, c=c)
        with pytest.warns(UserWarning, match="interval is 0.3"):
            w.append(0.5, c=c)
    with _writer(tmp_path / "c.h5", output_interval=0.3) as w:
        w.append(1.0, c=c)
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            w.append(1.3, c=c)
        with pytest.raises(ParameterError):
            w.append(1.9, c=c)
    assert read_simulation(tmp_path / "c.h5").parameters["dt"] == 0.3
    for bad in (0.0, -1.0, float("nan"), "x"):
        with pytest.raises(ParameterError):
            _writer(tmp_path / "d.h5", output_interval=bad)
    with pytest.raises(ParameterError, match="uneven_intervals"):
        _writer(tmp_path / "d.h5", uneven_intervals="ignore")
    with pytest.raises(ParameterError, match="contradicts"):
        _writer(tmp_path / "d.h5", output_interval=0.1, parameters={"dt": 0.2})


def test_constant_fields_round_trip_and_errors(tmp_path):
    shared = np.zeros((4, 4), dtype=bool)
    shared[1, 2] = True
    per_sample = np.arange(16.0).reshape(1, 4, 4)
    with _writer(tmp_path / "a.h5", constant_fields={"solid": shared, "k": per_sample}) as w:
        w.append(0.0, c=torch.zeros(1, 4, 4))
    d = read_simulation(tmp_path / "a.h5")
    np.testing.assert_array_equal(d.constant_fields["solid"], shared.astype(np.float32))
    np.testing.assert_array_equal(d.constant_fields["k"], per_sample)
    assert set(d.fields) == {"c"}
    with h5py.File(tmp_path / "a.h5") as f:
        assert not f["t0_fields/solid"].attrs["time_varying"] and not f["t0_fields/solid"].attrs["sample_varying"]
        assert f["t0_fields/k"].attrs["sample_varying"]
    with pytest.raises(ShapeError):
        _writer(tmp_path / "b.h5", constant_fields={"solid": np.zeros((3, 4))})
    with pytest.raises(ParameterError):
        _writer(tmp_path / "b.h5", constant_fields={"c": shared})
    with pytest.raises(ParameterError):
        _writer(tmp_path / "b.h5", constant_fields={"s": np.full((4, 4), np.nan)})
