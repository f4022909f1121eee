"""Tests of phisim.io: Well layout, exact round trips, crash safety, corrupt files, training logs."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import h5py
import numpy as np
import pytest
import torch

from phisim import Boundary, CenteredGrid, Dirichlet, Grid, NoSlipWall, Open, Periodic, StaggeredGrid
from phisim.errors import FileFormatError, IncompleteFileWarning, ParameterError, PhisimError, ShapeError
from phisim.io import SimulationWriter, TrainingLog, read_simulation, read_training, well_bc_type

REPO = Path(__file__).resolve().parents[3]


def _grid2():
    return Grid((6, 4), bounds=[(0.0, 3.0), (-1.0, 1.0)])


def _write_demo(path, dtype=torch.float32, frames=3, batch=2, **kw):
    """A 2-D file with a scalar, a centred vector and a staggered vector; returns the written frames."""
    g = _grid2()
    bnd = Boundary.create({"x": "periodic", "y": (NoSlipWall(velocity=(1.0, 0.0)), Open())}, 2)
    gen = torch.Generator().manual_seed(0)
    written = []
    with SimulationWriter(path, g, bnd, dataset_name="demo", batch_size=batch,
                          fields={"rho": "scalar", "u": "vector", "v": "staggered"},
                          parameters={"viscosity": 0.01, "steps": frames}, config={"seed": 3, "name": "x"},
                          dtype=dtype, **kw) as w:
        for k in range(frames):
            rho = torch.rand((batch, *g.resolution), generator=gen, dtype=dtype)
            u = torch.rand((batch, 2, *g.resolution), generator=gen, dtype=dtype)
            v = StaggeredGrid(tuple(torch.rand((batch, *g.face_shape(i)), generator=gen, dtype=dtype)
                                    for i in range(2)), g, bnd)
            w.append(0.5 * k, rho=CenteredGrid(rho, g, bnd), u=u, v=v)
            written.append((rho, u, v))
    return g, bnd, written


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_round_trip_exact(tmp_path, dtype):
    path = tmp_path / "run.h5"
    g, bnd, written = _write_demo(path, dtype=dtype)
    d = read_simulation(path)
    assert d.grid == g and d.boundary == bnd
    assert d.dataset_name == "demo"
    np.testing.assert_array_equal(d.times, [0.0, 0.5, 1.0])
    assert d.kinds == {"rho": "scalar", "u": "vector", "v": "staggered"}
    assert d.parameters == {"viscosity": 0.01, "steps": 3, "dt": 0.5}  # the output interval, from the frames
    assert d.dt == 0.5
    assert d.config == {"seed": 3, "name": "x"}
    np_dtype = np.float32 if dtype == torch.float32 else np.float64
    for k, (rho, u, v) in enumerate(written):
        assert d.fields["rho"].dtype == np_dtype
        np.testing.assert_array_equal(d.fields["rho"][:, k], rho.numpy())
        np.testing.assert_array_equal(d.fields["u"][:, k], u.numpy())
        for i in range(2):
            np.testing.assert_array_equal(d.staggered["v"][i][:, k], v.values[i].numpy())
        # the staggered field's centred copy is the face average
        np.testing.assert_allclose(d.fields["v"][:, k], v.at_centers().values.numpy(), rtol=0, atol=1e-6)
    fr = d.frame("v", 1)
    assert isinstance(fr, StaggeredGrid) and fr.boundary == bnd
    assert torch.equal(fr.values[0], written[1][2].values[0])
    t = read_simulation(path, as_torch=True)
    assert isinstance(t.fields["rho"], torch.Tensor) and t.fields["u"].shape == (2, 3, 2, 6, 4)


def test_well_layout_attributes(tmp_path):
    path = tmp_path / "run.h5"
    g, _, written = _write_demo(path)
    with h5py.File(path, "r") as f:
        assert f.attrs["dataset_name"] == "demo"
        assert f.attrs["grid_type"] == "cartesian"
        assert f.attrs["n_spatial_dims"] == 2
        assert f.attrs["n_trajectories"] == 2
        assert list(f.attrs["simulation_parameters"]) == ["viscosity", "steps", "dt"]
        assert f.attrs["viscosity"] == 0.01 and f.attrs["steps"] == 3 and f.attrs["dt"] == 0.5
        dims = f["dimensions"]
        assert list(dims.attrs["spatial_dims"]) == ["x", "y"]
        assert dims["time"].shape == (3,)
        assert not dims["time"].attrs["sample_varying"] and dims["time"].attrs["time_varying"]
        np.testing.assert_allclose(dims["x"][:], [0.25, 0.75, 1.25, 1.75, 2.25, 2.75])
        np.testing.assert_allclose(dims["y"][:], [-0.75, -0.25, 0.25, 0.75])
        for ax in "xy":
            assert not dims[ax].attrs["sample_varying"] and not dims[ax].attrs["time_varying"]
        bcs = f["boundary_conditions"]
        assert sorted(bcs) == ["x_periodic", "y_open", "y_wall"]
        expect = {"x_periodic": ("PERIODIC", "x", [0, 5]), "y_wall": ("WALL", "y", [0]),
                  "y_open": ("OPEN", "y", [3])}
        for key, (bc_type, axis, true_idx) in expect.items():
            grp = bcs[key]
            assert grp.attrs["bc_type"] == bc_type
            assert list(grp.attrs["associated_dims"]) == [axis]
            assert list(grp.attrs["associated_fields"]) == []
            assert not grp.attrs["sample_varying"] and not grp.attrs["time_varying"]
            assert grp["mask"].dtype == bool
            assert list(np.flatnonzero(grp["mask"][:])) == true_idx
        sc = f["scalars"]
        assert list(sc.attrs["field_names"]) == ["viscosity", "steps", "dt"]
        assert sc["dt"][()] == 0.5 and not sc["dt"].attrs["time_varying"]
        assert sc["viscosity"][()] == 0.01 and sc["viscosity"].shape == ()
        assert not sc["viscosity"].attrs["sample_varying"] and not sc["viscosity"].attrs["time_varying"]
        assert list(f["t0_fields"].attrs["field_names"]) == ["rho"]
        assert list(f["t1_fields"].attrs["field_names"]) == ["u", "v"]
        assert list(f["t2_fields"].attrs["field_names"]) == []
        rho, u = f["t0_fields"]["rho"], f["t1_fields"]["u"]
        assert rho.shape == (2, 3, 6, 4) and u.shape == (2, 3, 6, 4, 2)  # channel last
        np.testing.assert_array_equal(u[:, 1, ..., 1], written[1][1][:, 1].numpy())
        for ds in (rho, u, f["t1_fields"]["v"]):
            assert ds.attrs["sample_varying"] and ds.attrs["time_varying"]
            assert list(ds.attrs["dim_varying"]) == [True, True]
            assert ds.chunks[:2] == (1, 1) and ds.compression == "gzip" and ds.shuffle
        assert f["staggered"]["v_x"].shape == (2, 3, 7, 4) and f["staggered"]["v_y"].shape == (2, 3, 6, 5)
        assert json.loads(f["extras"]["config"][()]) == {"seed": 3, "name": "x"}


def test_bc_type_mapping():
    assert well_bc_type(Periodic()) == "PERIODIC"
    assert well_bc_type(Open()) == "OPEN"
    for c in (NoSlipWall(), Dirichlet(1.0), Boundary.create("neumann", 1).sides[0][0],
              Boundary.create("free_slip", 1).sides[0][0]):
        assert well_bc_type(c) == "WALL"


def test_well_loader_reads_our_file(tmp_path):
    pytest.importorskip("the_well")
    from the_well.data import WellDataset

    folder = tmp_path / "well"
    folder.mkdir()
    g, _, written = _write_demo(folder / "demo.hdf5", frames=4)
    ds = WellDataset(path=str(folder), n_steps_input=2, n_steps_output=1, use_normalization=False)
    assert ds.metadata.spatial_resolution == (6, 4)
    assert ds.metadata.field_names[0] == ["rho"]
    assert ds.metadata.field_names[1] == ["u_x", "u_y", "v_x", "v_y"]
    assert sorted(ds.metadata.constant_scalar_names) == ["dt", "steps", "viscosity"]
    assert len(ds) == 2 * 2  # 2 trajectories x 2 windows of 3 frames out of 4
    s = ds[3]  # trajectory 1, window starting at frame 1
    assert tuple(s["input_fields"].shape) == (2, 6, 4, 5)
    rho, u, v = written[1]
    np.testing.assert_array_equal(s["input_fields"][0, ..., 0].numpy(), rho[1].numpy())
    np.testing.assert_array_equal(s["input_fields"][0, ..., 1].numpy(), u[1, 0].numpy())
    np.testing.assert_array_equal(s["input_fields"][0, ..., 2].numpy(), u[1, 1].numpy())
    np.testing.assert_array_equal(s["output_fields"][0, ..., 0].numpy(), written[3][0][1].numpy())
    # boundary codes of The Well: WALL=0, OPEN=1, PERIODIC=2; rows are axes, columns (lower, upper)
    assert s["boundary_conditions"].tolist() == [[2.0, 2.0], [0.0, 1.0]]
    np.testing.assert_allclose(s["space_grid"].numpy(), g.cell_centers(torch.float32).numpy())
    np.testing.assert_allclose(sorted(s["constant_scalars"].tolist()), [0.01, 0.5, 4.0])  # viscosity, dt, steps


_CHILD = textwrap.dedent("""
    import sys, torch
    sys.path.insert(0, {repo!r})
    from phisim import Grid
    from phisim.io import SimulationWriter
    g = Grid((48, 48))
    with SimulationWriter({path!r}, g, "periodic", dataset_name="killed", batch_size=4,
                          fields={{"rho": "scalar", "u": "vector"}}) as w:
        for k in range(100000):
            rho = torch.full((4, 48, 48), float(k)) + torch.rand(4, 48, 48) * 1e-3
            w.append(float(k), rho=rho, u=torch.full((4, 2, 48, 48), -float(k)))
            print(k, flush=True)
""")


def test_killed_writer_leaves_readable_file(tmp_path):
    path = tmp_path / "killed.h5"
    env = dict(os.environ, OMP_NUM_THREADS="1")
    proc = subprocess.Popen([sys.executable, "-c", _CHILD.format(repo=str(REPO), path=str(path))],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    try:
        done = -1
        deadline = time.monotonic() + 60
        while done < 4 and time.monotonic() < deadline:
            line = proc.stdout.readline()
            if not line:
                break
            done = int(line)
        assert done >= 4, proc.stderr.read()
        proc.send_signal(signal.SIGKILL)  # most likely in the middle of a later frame
    finally:
        proc.kill()
        proc.wait()
    with pytest.warns(IncompleteFileWarning, match="not closed cleanly"):  # read from the journal
        d = read_simulation(path)
    assert d.dataset_name == "killed"
    assert d.n_frames >= done + 1
    for k in range(d.n_frames):
        assert d.times[k] == k
        np.testing.assert_allclose(d.fields["rho"][:, k], k, atol=1e-3)
        assert np.all(d.fields["u"][:, k] == -k)


def test_append_errors(tmp_path):
    g = _grid2()
    with SimulationWriter(tmp_path / "a.h5", g, "periodic", dataset_name="e", batch_size=2,
                          fields={"rho": "scalar", "u": "vector"}) as w:
        u = torch.zeros(2, 2, 6, 4)
        with pytest.raises(ShapeError, match="rho"):
            w.append(0.0, rho=torch.zeros(2, 4, 6), u=u)  # transposed
        with pytest.raises(ShapeError):
            w.append(0.0, rho=torch.zeros(3, 6, 4), u=u)  # wrong batch
        with pytest.raises(ShapeError):
            w.append(0.0, rho=torch.zeros(2, 6, 4), u=torch.zeros(2, 6, 4, 2))  # channel last given
        with pytest.raises(ShapeError):
            w.append(0.0, rho=CenteredGrid(torch.zeros(2, 6, 4), Grid((6, 4)), "periodic"), u=u)  # other grid
        with pytest.raises(ShapeError):
            w.append(0.0, rho=u, u=u)  # vector for a scalar
        with pytest.raises(ParameterError, match="missing"):
            w.append(0.0, rho=torch.zeros(2, 6, 4))
        with pytest.raises(ParameterError, match="unknown"):
            w.append(0.0, rho=torch.zeros(2, 6, 4), u=u, p=u)
        assert w.n_frames == 0
        w.append(0.0, rho=torch.zeros(2, 6, 4), u=u)
        with pytest.raises(ParameterError, match="increasing"):
            w.append(0.0, rho=torch.zeros(2, 6, 4), u=u)
        with pytest.raises(ShapeError, match="staggered"):
            w.append(1.0, rho=torch.zeros(2, 6, 4), u=StaggeredGrid.zeros(g, "periodic", 2))
    assert read_simulation(tmp_path / "a.h5").n_frames == 1
    with pytest.raises(ParameterError):
        SimulationWriter(tmp_path / "b.h5", g, "periodic", dataset_name="e", batch_size=1,
                         fields={"a": "tensor"})
    with pytest.raises(ParameterError):
        SimulationWriter(tmp_path / "b.h5", g, "periodic", dataset_name="e", batch_size=0,
                         fields={"a": "scalar"})
    with pytest.raises(ParameterError, match="config"):
        SimulationWriter(tmp_path / "b.h5", g, "periodic", dataset_name="e", batch_size=1,
                         fields={"a": "scalar"}, config={"f": object()})


def test_staggered_from_component_tuples(tmp_path):
    g = Grid((3, 2, 2))
    comps = tuple(
        torch.arange(np.prod(g.face_shape(i)), dtype=torch.float64).reshape(1, *g.face_shape(i))
        for i in range(3)
    )
    with SimulationWriter(tmp_path / "s.h5", g, "wall", dataset_name="s", batch_size=1,
                          fields={"v": "staggered"}, dtype=torch.float64) as w:
        w.append(0.0, v=comps)
        with pytest.raises(ShapeError, match="component 1"):
            w.append(1.0, v=(comps[0], comps[0], comps[2]))
    d = read_simulation(tmp_path / "s.h5")
    for i in range(3):
        np.testing.assert_array_equal(d.staggered["v"][i][:, 0], comps[i].numpy())
    assert d.fields["v"].shape == (1, 1, 3, 3, 2, 2)


def test_corrupt_and_foreign_files(tmp_path):
    good = tmp_path / "good.h5"
    _write_demo(good)
    with pytest.raises(FileFormatError, match="does not exist"):
        read_simulation(tmp_path / "missing.h5")
    text = tmp_path / "notes.h5"
    text.write_text("this is not HDF5\n" * 10)
    with pytest.raises(FileFormatError, match="not a readable HDF5"):
        read_simulation(text)
    truncated = tmp_path / "truncated.h5"
    truncated.write_bytes(good.read_bytes()[: good.stat().st_size // 3])
    with pytest.raises(FileFormatError):
        read_simulation(truncated)
    foreign = tmp_path / "foreign.h5"
    with h5py.File(foreign, "w") as f:
        f.create_dataset("data", data=np.zeros(3))
    with pytest.raises(FileFormatError, match="dataset_name"):
        read_simulation(foreign)
    # missing group
    nogroup = tmp_path / "nogroup.h5"
    nogroup.write_bytes(good.read_bytes())
    with h5py.File(nogroup, "a") as f:
        del f["t0_fields"]
    with pytest.raises(FileFormatError, match="t0_fields"):
        read_simulation(nogroup)
    # wrong shape
    badshape = tmp_path / "badshape.h5"
    badshape.write_bytes(good.read_bytes())
    with h5py.File(badshape, "a") as f:
        del f["t0_fields/rho"]
        f["t0_fields"].create_dataset("rho", data=np.zeros((2, 3, 4, 6), np.float32))
    with pytest.raises(FileFormatError, match="shape"):
        read_simulation(badshape)
    # fewer frames than time lists
    short = tmp_path / "short.h5"
    short.write_bytes(good.read_bytes())
    with h5py.File(short, "a") as f:
        f["t1_fields/u"].resize(2, axis=1)
    with pytest.warns(IncompleteFileWarning, match="hold only 2"):  # torn write: the complete frames
        d = read_simulation(short)
    assert d.n_frames == 2 and d.fields["u"].shape[1] == 2 and d.fields["rho"].shape[1] == 2
    assert issubclass(FileFormatError, PhisimError)


def test_reads_plain_well_file(tmp_path):
    """A Well file without phisim extras: grid from coordinates, boundary from bc types."""
    path = tmp_path / "plain.hdf5"
    x = (np.arange(4) + 0.5) / 4
    with h5py.File(path, "w") as f:
        f.attrs.update(dataset_name="plain", grid_type="cartesian", n_spatial_dims=2, n_trajectories=1,
                       simulation_parameters=["a"], a=2.0)
        dims = f.create_group("dimensions")
        dims.attrs["spatial_dims"] = ["x", "y"]
        dims["time"], dims["x"], dims["y"] = np.arange(2.0), x, x
        for name, bc in (("x_periodic", "PERIODIC"), ("y_wall", "WALL")):
            grp = f.create_group(f"boundary_conditions/{name}")
            grp.attrs.update(bc_type=bc, associated_dims=[name[0]], associated_fields=[])
            grp["mask"] = np.array([True, False, False, True])
        f.create_group("scalars").attrs["field_names"] = []
        t0 = f.create_group("t0_fields")
        t0.attrs["field_names"] = ["p", "const"]
        t0["p"] = np.arange(32, dtype=np.float32).reshape(1, 2, 4, 4)
        t0["p"].attrs.update(sample_varying=True, time_varying=True, dim_varying=[True, True])
        t0["const"] = np.zeros((1, 4, 4), np.float32)
        t0["const"].attrs.update(sample_varying=True, time_varying=False, dim_varying=[True, True])
        f.create_group("t1_fields").attrs["field_names"] = []
        f.create_group("t2_fields").attrs["field_names"] = []
    d = read_simulation(path)
    assert d.grid == Grid((4, 4), [(0.0, 1.0), (0.0, 1.0)])
    assert d.boundary == Boundary.create({"x": "periodic", "y": "wall"}, 2)
    assert list(d.fields) == ["p"] and d.parameters == {"a": 2.0}
    np.testing.assert_array_equal(d.fields["p"][0, 1], np.arange(16, 32).reshape(4, 4))


def test_training_log(tmp_path):
    path = tmp_path / "train.h5"
    with TrainingLog(path, "adam", attrs={"lr": 1e-3, "betas": [0.9, 0.99]}) as log:
        for it in range(3):
            log.append(it, loss=1.0 / (it + 1), metric=torch.tensor(2.0 * it))
        log.append(3, loss=0.1)
    # the file is complete after each record: reopen and continue (resume=True: an explicit request)
    with TrainingLog(path, "adam", resume=True) as log:
        assert log.n_records == 4
        log.append(4, loss=0.05, val=7.0)
    with TrainingLog(path, "hig") as log:
        log.append(0, loss=2.0)
        with pytest.raises(ParameterError):
            log.append(1)
        with pytest.raises(ParameterError):
            log.append(1, loss="high")
        with pytest.raises(ParameterError):
            log.append(1, loss=torch.ones(3))
    res = read_training(path)
    assert sorted(res) == ["adam", "hig"]
    a = res["adam"]
    np.testing.assert_array_equal(a["iteration"], [0, 1, 2, 3, 4])
    np.testing.assert_allclose(a["loss"], [1.0, 0.5, 1 / 3, 0.1, 0.05])
    np.testing.assert_array_equal(a["metric"], [0.0, 2.0, 4.0, np.nan, np.nan])
    np.testing.assert_array_equal(a["val"], [np.nan] * 4 + [7.0])
    with h5py.File(path, "r") as f:
        assert f["training/adam"].attrs["lr"] == 1e-3
        assert json.loads(f["training/adam"].attrs["betas"]) == [0.9, 0.99]


def test_training_log_inside_simulation_file(tmp_path):
    path = tmp_path / "sim.h5"
    g = Grid((4,))
    with SimulationWriter(path, g, "open", dataset_name="one_d", batch_size=1, fields={"c": "scalar"}) as w:
        log = w.training_log("physgrad")
        w.append(0.0, c=torch.ones(1, 4))
        log.append(0, loss=3.0)
        log.append(1, loss=2.0)
    d = read_simulation(path)
    np.testing.assert_array_equal(d.training["physgrad"]["loss"], [3.0, 2.0])
    assert d.boundary == Boundary.create("open", 1)
