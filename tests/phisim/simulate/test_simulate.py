"""phisim.simulate: scenario physics (analytic decay, invariants), dataset layout, seeds, workers, resume, errors."""

import json
import math
from pathlib import Path

import h5py
import numpy as np
import pytest
import torch

from phisim.errors import FileFormatError, ParameterError
from phisim.fluid import Body, Sphere
from phisim.fluid.bodies import solid_layout
from phisim.simulate import (
    SCENARIOS,
    check_dataset_dir,
    load_config_file,
    plan_chunks,
    resolve_config,
    simulate_dataset,
)
from phisim.simulate.dataset import _draw_parameters, _generator


def _build(name, **settings):
    cfg = resolve_config(name, **settings)
    sc = SCENARIOS[name]
    g = _generator(cfg["seed"], 0)
    params = _draw_parameters(sc, cfg, g)
    return cfg, params, sc.build(cfg, params, 2, g, torch.float64, torch.device("cpu"))


def _run(sim, steps):
    s = sim.state
    with torch.no_grad():
        for _ in range(steps):
            s = sim.step(s)
    return s


def test_taylor_green_energy_decays_at_the_analytic_rate():
    cfg, p, sim = _build("taylor_green", resolution=32, viscosity=0.05, dt=0.05)
    v0 = sim.state.velocity
    e0 = sum((c**2).sum(dim=tuple(range(1, c.ndim))) for c in v0.values)
    v = _run(sim, 20).velocity
    e = sum((c**2).sum(dim=tuple(range(1, c.ndim))) for c in v.values)
    expected = math.exp(-4 * 0.05 * 1.0 * 1.0)  # |u|^2 ~ exp(-2 nu |k|^2 t), |k|^2 = 2, t = 1
    # the scenario steps with imex2: what is left is the stencil's spatial error, 4 ν t dx²/12 = 6.4e-4
    # (measured +6e-4; the first-order split step with MacCormack was off by -1.2 %)
    assert torch.allclose(e / e0, torch.full_like(e, expected), rtol=1.5e-3), (e / e0, expected)


def test_burgers_is_dissipative_and_heat_keeps_the_mean():
    _, _, sim = _build("burgers", dim=1, resolution=64)
    u = sim.state
    energies = [float((u.values**2).sum())]
    with torch.no_grad():
        for _ in range(30):
            u = sim.step(u)
            energies.append(float((u.values**2).sum()))
    assert all(b <= a * (1 + 1e-9) for a, b in zip(energies, energies[1:]))
    assert energies[-1] < 0.99 * energies[0]
    _, _, heat = _build("heat", resolution=16)
    t = _run(heat, 5)
    assert torch.allclose(t.values.mean(dim=(1, 2)), heat.state.values.mean(dim=(1, 2)), atol=1e-12)
    assert float(t.values.std()) < float(heat.state.values.std())


def test_cavity_and_smoke_are_divergence_free_and_respect_the_obstacle():
    from phisim.fluid import relative_divergence

    _, p, cav = _build("cavity", resolution=16, lid_velocity=1.0)
    v = _run(cav, 20).velocity
    assert float(relative_divergence(v).max()) < 1e-4
    u_top = v.at_centers().values[:, 0, :, -1].mean()  # the lid drags the top row in +x
    assert float(u_top) > 0.05
    _, p, smoke = _build("smoke", resolution=16)
    s = _run(smoke, 10)
    solid = smoke.constant_fields["obstacle_mask"] > 0.5
    assert solid.any()
    assert float(s.marker.values[:, solid].abs().max()) == 0.0
    assert float(s.marker.values.sum()) > 0


def test_karman_channel_conserves_mass_and_stores_the_body():
    cfg, p, sim = _build("karman", resolution=10, dt=0.02)
    s = _run(sim, 2)
    assert s.time == pytest.approx(0.04)
    u = s.velocity.values[0]  # faces normal to x: (B, nx + 1, ny)
    inflow, outflow = u[:, 0].sum(dim=-1), u[:, -1].sum(dim=-1)
    assert torch.allclose(inflow, outflow, rtol=1e-6)  # no flux through the walls: what enters leaves
    assert float(inflow.min()) > 0
    mask = sim.constant_fields["obstacle_mask"] > 0.5
    assert 0 < int(mask.sum()) < mask.numel() // 10
    # the no-slip body holds the flow: the faces it covers entirely carry its velocity (at rest: zero); the faces it
    # cuts keep the fluid velocity (sharp bodies), so cell averages inside the body are not zero at this resolution
    body = Body(Sphere((0.2, float(p["cylinder_y"])), 0.05))
    layout = solid_layout(body, sim.grid, s.velocity.boundary, s.time, torch.float64, torch.device("cpu"))
    covered = 0
    for c, theta in zip(s.velocity.values, layout.theta):
        inside = (theta[0] == 0).expand_as(c[0])
        covered += int(inside.sum())
        if inside.any():
            assert float(c[:, inside].abs().max()) < 1e-12 * p["umax"]
    assert covered > 0


def test_config_errors_suggest_the_closest_name():
    with pytest.raises(ParameterError, match="did you mean 'smoke'"):
        resolve_config("smok")
    with pytest.raises(ParameterError, match="did you mean 'viscosity'"):
        resolve_config("burgers", {"viscositty": 0.1})
    with pytest.raises(ParameterError, match="1-D"):
        resolve_config("burgers", dim=3)
    with pytest.raises(ParameterError, match="resolution"):
        resolve_config("heat", resolution=[8, 2])


def test_config_file_json_and_yaml(tmp_path):
    (tmp_path / "c.json").write_text(json.dumps({"viscosity": 0.02, "trajectories": 3}))
    cfg = resolve_config("burgers", load_config_file(tmp_path / "c.json"))
    assert cfg["viscosity"] == 0.02 and cfg["trajectories"] == 3
    pytest.importorskip("yaml")
    (tmp_path / "c.yaml").write_text("viscosity: 0.03\ndim: 2\n")
    cfg = resolve_config("burgers", load_config_file(tmp_path / "c.yaml"))
    assert cfg["viscosity"] == 0.03 and cfg["dim"] == 2
    (tmp_path / "bad.json").write_text("[1, 2]")
    with pytest.raises(FileFormatError):
        load_config_file(tmp_path / "bad.json")


def test_plan_splits_files():
    cfg = resolve_config("heat", trajectories=20, trajectories_per_file=2)
    chunks = plan_chunks(cfg)
    assert [c.split for c in chunks].count("valid") == 1 and [c.split for c in chunks].count("test") == 1
    assert sum(c.trajectories for c in chunks) == 20
    cfg = resolve_config("heat", trajectories=5, trajectories_per_file=2)
    assert [c.trajectories for c in plan_chunks(cfg)] == [2, 2, 1]


def _small(**kw):
    return resolve_config("heat", **{"trajectories": 6, "trajectories_per_file": 2, "steps": 3, "resolution": 8,
                                     **kw})


def _contents(root):
    out = {}
    for p in check_dataset_dir(root):
        with h5py.File(p, "r") as f:
            out[p.relative_to(root).as_posix()] = (np.asarray(f["t0_fields/temperature"]),
                                                   dict(f.attrs)["diffusivity"])
    return out


def test_dataset_layout_stats_and_the_well_loader(tmp_path):
    cfg = _small()
    r = simulate_dataset(tmp_path / "ds", cfg, progress=False)
    root = tmp_path / "ds"
    assert r["files"] == 3 and r["written"] == 3
    assert json.loads((root / "config.json").read_text()) == cfg
    assert [len(check_dataset_dir(root, s)) for s in ("train", "valid", "test")] == [1, 1, 1]
    files = _contents(root)
    diffusivities = {v[1] for v in files.values()}
    assert len(diffusivities) == 3  # one parameter draw per file
    assert all(0.1 <= d <= 1.0 for d in diffusivities)
    assert (root / "stats.yaml").is_file()
    train = next(v for k, v in files.items() if "train" in k)[0]
    yaml = pytest.importorskip("yaml")
    stats = yaml.safe_load((root / "stats.yaml").read_text())
    assert stats["mean"]["temperature"] == pytest.approx(float(train.astype(np.float64).mean()), rel=1e-6)
    pytest.importorskip("the_well")
    from the_well.data import WellDataset
    from the_well.data.normalization import ZScoreNormalization

    ds = WellDataset(path=str(root), well_split_name="train", n_steps_input=1, n_steps_output=1,
                     use_normalization=True, normalization_type=ZScoreNormalization)
    assert len(ds) == 2 * 3  # 2 trajectories x 3 input/output windows of 4 frames
    assert ds.norm is not None  # the statistics file was read
    x = ds[0]["input_fields"][..., 0].double().numpy()
    raw = train[0, 0].astype(np.float64)
    assert np.allclose(x[0], (raw - stats["mean"]["temperature"]) / stats["std"]["temperature"], atol=1e-4)


def test_same_seed_same_files_and_workers_do_not_matter(tmp_path):
    simulate_dataset(tmp_path / "a", _small(), progress=False)
    simulate_dataset(tmp_path / "b", _small(), workers=2, progress=False)
    a, b = _contents(tmp_path / "a"), _contents(tmp_path / "b")
    assert a.keys() == b.keys()
    for k in a:
        assert np.array_equal(a[k][0], b[k][0]) and a[k][1] == b[k][1]
    c = _contents(simulate_dataset(tmp_path / "c", _small(seed=1), progress=False)["root"])
    assert not np.array_equal(a[next(iter(a))][0], c[next(iter(c))][0])


def test_a_killed_run_continues_where_it_stopped(tmp_path):
    root = tmp_path / "ds"
    simulate_dataset(root, _small(), progress=False)
    before = _contents(root)
    victim = check_dataset_dir(root, "valid")[0]
    victim.unlink()
    (victim.parent / (victim.name + ".part")).write_bytes(b"half a file")
    (root / "stats.yaml").unlink()
    r = simulate_dataset(root, _small(), progress=False)
    assert r["written"] == 1 and r["skipped"] == 2
    after = _contents(root)
    for k in before:
        assert np.array_equal(before[k][0], after[k][0])
    assert (root / "stats.yaml").is_file()
    with pytest.raises(ParameterError, match="other settings"):
        simulate_dataset(root, _small(seed=3), progress=False)
    simulate_dataset(root, _small(seed=3), progress=False, overwrite=True)
    assert not np.array_equal(before[k][0], _contents(root)[k][0])


def test_bad_dataset_dir(tmp_path):
    with pytest.raises(FileFormatError, match="does not exist"):
        check_dataset_dir(tmp_path / "nope")
    (tmp_path / "data" / "train").mkdir(parents=True)
    with pytest.raises(FileFormatError, match="Well's layout"):
        check_dataset_dir(tmp_path, "train")


def test_cli_simulate_and_one_line_errors(tmp_path, capsys):
    from inverse.cli import main

    assert main(["simulate", "burgers", "--set", "dim=1", "--trajectories", "2", "--trajectories-per-file", "1",
                 "--steps", "2", "--resolution", "16", "--out", str(tmp_path / "b"), "--quiet"]) == 0
    assert len(check_dataset_dir(tmp_path / "b")) == 2
    capsys.readouterr()
    assert main(["simulate", "burgers", "--set", "dim=1", "--trajectories", "2", "--trajectories-per-file", "1",
                 "--steps", "2", "--resolution", "16", "--out", str(tmp_path / "b"), "--quiet"]) == 0
    assert json.loads(capsys.readouterr().out)["skipped"] == 2  # the same command continues: nothing left
    assert main(["simulate", "burgers", "--set", "viscocity=1", "--out", str(tmp_path / "x")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "did you mean 'viscosity'" in err
    assert main(["simulate", "--list"]) == 0
    assert "taylor_green" in capsys.readouterr().out


def _rank_worker(rank: int, world: int, init_file: str, out_dir: str) -> None:
    import torch.distributed as dist

    dist.init_process_group("gloo", init_method=f"file://{init_file}", rank=rank, world_size=world)
    try:
        torch.set_num_threads(1)
        r = simulate_dataset(out_dir, _small(), progress=False)
        (Path(out_dir) / f"rank{rank}.json").write_text(json.dumps({"written": r["written"]}))
    finally:
        dist.destroy_process_group()


def test_two_ranks_share_the_files_and_match_one_process(tmp_path):
    import torch.multiprocessing as mp

    one = _contents(simulate_dataset(tmp_path / "one", _small(), progress=False)["root"])
    mp.spawn(_rank_worker, args=(2, str(tmp_path / "init"), str(tmp_path / "two")), nprocs=2, join=True)
    written = [json.loads((tmp_path / "two" / f"rank{r}.json").read_text())["written"] for r in (0, 1)]
    assert written == [2, 1]  # files 0, 2 on rank 0 and file 1 on rank 1
    two = _contents(tmp_path / "two")
    assert one.keys() == two.keys()
    assert all(np.array_equal(one[k][0], two[k][0]) for k in one)
    assert (tmp_path / "two" / "stats.yaml").is_file()
