"""Custom problems (inverse.custom), the Burgers tutorial at tiny size, model files and predict, offline data."""

import importlib.util
from pathlib import Path

import h5py
import numpy as np
import pytest
import torch

from inverse import load_model, make_problem, model_path, train
from inverse.custom import load_problem
from inverse.nets import MLP
from phisim.errors import FileFormatError, ParameterError

ROOT = Path(__file__).resolve().parents[2]
BURGERS = ROOT / "examples" / "burgers_inverse.py"


def _burgers_module():
    spec = importlib.util.spec_from_file_location("burgers_inverse_test", BURGERS)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


A = torch.tensor([[2.0, 1.0], [0.0, 0.5]], dtype=torch.float64)


def _linear_problem(**kw):
    return make_problem(
        "linear",
        data=lambda b, g: torch.randn(b, 2, generator=g, dtype=torch.float64),
        physics=lambda x: x @ A.T,
        local_inverse=lambda y, x0: torch.linalg.solve(A, y.T).T,
        network=lambda: MLP([2, 16, 2]),
        dtype=torch.float64, **kw)


def test_custom_problem_methods_and_exact_physical_update():
    from inverse.physgrad import physical_update

    p = _linear_problem()
    assert {"adam", "sgd", "pg", "pg_inverse_gradient", "pg_newton", "pg_lbfgsb", "supervised", "hig"} <= set(
        p.methods)
    g = torch.Generator().manual_seed(0)
    b = p.sample(5, g)
    assert torch.allclose(b.y_target, b.x_true @ A.T)
    x = torch.randn(5, 2, dtype=torch.float64)
    for op in (b.operator, p.methods["pg_inverse_gradient"].local_solver):
        if op is b.operator:
            x_t, _ = physical_update(x, b.y_target, op)
        else:
            from inverse.local_solvers import SolverOperator

            x_t, _ = physical_update(x, b.y_target, SolverOperator(b.operator, op))
        assert torch.allclose(x_t, b.x_true, atol=1e-8)  # exact inverse, eta = 1: P(x~) = y*
    for m in p.methods:
        r = train(p, m, iterations=3, batch_size=4)
        assert np.isfinite(r.curves["metric"]).all()


def test_custom_problem_bad_input():
    with pytest.raises(ParameterError, match="physics"):
        make_problem("x", data=lambda b, g: None, physics=None, network=lambda: MLP([1, 1]))
    p = make_problem("x", data=lambda b, g: "nope", physics=lambda x: x, network=lambda: MLP([1, 1]))
    with pytest.raises(ParameterError, match="must return"):
        p.sample(2, torch.Generator())
    p = make_problem("x", data=lambda b, g: torch.zeros(b, 3), physics=lambda x: x, network=lambda: "net")
    with pytest.raises(ParameterError, match="torch.nn.Module"):
        p.make_network()


def test_load_problem_errors(tmp_path, capsys):
    f = tmp_path / "myprob.py"
    f.write_text("def not_a_problem():\n    return 42\n\ndef burgers_problem():\n    return 1\n")
    with pytest.raises(ParameterError, match="returned int"):
        load_problem(f"{f}:not_a_problem")
    with pytest.raises(ParameterError, match="did you mean 'burgers_problem'"):
        load_problem(f"{f}:burger_problem")
    with pytest.raises(ParameterError, match="cannot import"):
        load_problem("no_such_module_xyz:f")
    from inverse.cli import main

    assert main(["train", f"{f}:not_a_problem", "adam", "--iterations", "1"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "expected an inverse.Problem" in err


def test_burgers_tutorial_physics_is_differentiable_and_the_generic_inverse_improves():
    mod = _burgers_module()
    phys = mod.burgers_physics(resolution=8, steps=2, dt=0.1, viscosity=0.1)
    x = 0.5 * torch.randn(2, 8, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    assert torch.autograd.gradcheck(phys, (x.requires_grad_(),), eps=1e-6, atol=1e-6)
    p = mod.burgers_problem(resolution=16, steps=4, batch_size=4, solver_iterations=3)
    b = p.sample(4, torch.Generator().manual_seed(0))
    x0 = torch.zeros_like(b.x_true)
    solver = p.methods["pg_inverse_gradient"].local_solver
    x1 = solver(p.physics, b.y_target, x0)
    before = (p.physics(x0) - b.y_target).norm(dim=1)
    after = (p.physics(x1) - b.y_target).norm(dim=1)
    assert (after < 0.05 * before).all()  # inverse-gradient iterations solve P(x) = y*
    out = mod.main(["--iterations", "1", "--resolution", "8", "--batch-size", "2", "--device", "cpu"])
    assert set(out) == {"adam", "pg_inverse_gradient", "identity", "device"} and out["device"] == "cpu"
    # the network starts as the identity map (zero last layer): one small step stays close to it
    assert out["adam"]["heldout_metric"] == pytest.approx(out["identity"]["heldout_metric"], rel=0.2)


def test_burgers_tutorial_trains_through_the_cli(tmp_path):
    from inverse.cli import main

    out = tmp_path / "b.h5"
    args = ["compare", f"{BURGERS}:burgers_problem", "adam", "pg_inverse_gradient", "--iterations", "2",
            "--setting", "resolution=8", "--setting", "steps=2", "--batch-size", "2", "--out", str(out), "--quiet"]
    assert main(args) == 0
    net = load_model(model_path(out, "pg_inverse_gradient"))
    with h5py.File(out, "r") as f:
        assert f["training/adam"].attrs["model_file"] == model_path(out, "adam").name
    y = torch.randn(3, 8, dtype=torch.float64)
    assert net(y).shape == (3, 8)


def test_model_of_a_python_built_problem_needs_the_network(tmp_path):
    p = _linear_problem()
    out = tmp_path / "l.h5"
    r = train(p, "adam", iterations=2, batch_size=2, out=out)
    with pytest.raises(ParameterError, match="network="):
        load_model(model_path(out, "adam"))
    net = load_model(model_path(out, "adam"), network=MLP([2, 16, 2]))
    x = torch.randn(4, 2, dtype=torch.float64)
    with torch.no_grad():
        assert torch.equal(net(x), r.model.eval()(x))


def test_model_file_round_trip_predict_and_mismatch(tmp_path, capsys):
    from inverse import get_problem
    from inverse.nets import UNet

    p = get_problem("poisson", resolution=(16, 16))
    out = tmp_path / "p.h5"
    r = train(p, "adam", iterations=2, batch_size=2, out=out)
    path = model_path(out, "adam")
    net = load_model(path)
    assert not net.training
    b = p.sample(3, torch.Generator().manual_seed(3))
    r.model.eval()
    with torch.no_grad():
        assert torch.equal(net(b.inputs), r.model(b.inputs))
    with pytest.raises(FileFormatError, match="different network"):
        load_model(path, network=UNet(1, 1, levels=3))
    (tmp_path / "junk.pt").write_bytes(b"not a model")
    with pytest.raises(FileFormatError):
        load_model(tmp_path / "junk.pt")
    with h5py.File(tmp_path / "in.h5", "w") as f:
        f["inputs"] = b.inputs[:, 0].numpy()  # (N, 16, 16): the channel axis is added
    from inverse.cli import main

    assert main(["predict", str(path), str(tmp_path / "in.h5"), "--out", str(tmp_path / "pred.h5")]) == 0
    with h5py.File(tmp_path / "pred.h5", "r") as f:
        pred = np.asarray(f["predictions"])
    with torch.no_grad():
        assert np.allclose(pred, net(b.inputs).numpy(), atol=1e-6)
    with h5py.File(tmp_path / "bad.h5", "w") as f:
        f["inputs"] = np.zeros((2, 5, 5), dtype=np.float32)
    capsys.readouterr()
    assert main(["predict", str(path), str(tmp_path / "bad.h5"), "--out", str(tmp_path / "x.h5")]) == 2
    assert len(capsys.readouterr().err.strip().splitlines()) == 1


def test_offline_training_from_a_dataset_and_csv(tmp_path):
    from inverse.export import TensorBoardLogger, export_csv, tensorboard_available
    from inverse.offline import DatasetSampler
    from phisim.simulate import resolve_config, simulate_dataset

    root = tmp_path / "heat"
    simulate_dataset(root, resolve_config("heat", trajectories=4, trajectories_per_file=2, steps=3, resolution=8),
                     progress=False)
    s = DatasetSampler(root, "temperature", "train", x_frame=0, y_frame=-1)
    x, y = s(3, torch.Generator().manual_seed(0))
    x2, y2 = s(3, torch.Generator().manual_seed(0))
    assert torch.equal(x, x2) and x.shape == (3, 8, 8)
    rows = set()
    for path in s.files:
        with h5py.File(path, "r") as f:
            rows |= {tuple(np.round(a.ravel(), 6)) for a in np.asarray(f["t0_fields/temperature"])[:, 0]}
    assert all(tuple(np.round(a.numpy().ravel(), 6)) in rows for a in x)
    with pytest.raises(FileFormatError, match="no field"):
        DatasetSampler(root, "density")
    with pytest.raises(FileFormatError, match="Well's layout"):
        DatasetSampler(tmp_path, "temperature")
    out = tmp_path / "w.h5"
    TensorBoardLogger._warned = False
    if tensorboard_available():
        r = train(load_problem_well(root), "supervised", iterations=3, batch_size=2, out=out,
                  tensorboard=tmp_path / "tb")
        assert any((tmp_path / "tb" / "supervised").iterdir())
    else:
        with pytest.warns(UserWarning, match="TensorBoard logging skipped"):
            r = train(load_problem_well(root), "supervised", iterations=3, batch_size=2, out=out,
                      tensorboard=tmp_path / "tb")
    assert np.isfinite(r.curves["metric"]).all()
    p = load_problem_well(root)
    assert p.heldout_split is None  # two files: both train
    root2 = tmp_path / "heat3"
    simulate_dataset(root2, resolve_config("heat", trajectories=6, trajectories_per_file=2, steps=3, resolution=8),
                     progress=False)
    p = load_problem_well(root2)
    valid = DatasetSampler(root2, "temperature", "valid")
    assert p.heldout_split == "valid" and p.heldout_size == valid.trajectories == 2
    assert torch.equal(p.heldout().x_true, valid.all()[0].float())
    files = export_csv(out, tmp_path / "csv")
    text = files[0].read_text().splitlines()
    assert text[0].startswith("iteration,") and len(text) == 4
    col = text[0].split(",").index("metric")
    assert float(text[-1].split(",")[col]) == pytest.approx(float(r.curves["metric"][-1]))


def load_problem_well(root):
    from inverse import get_problem

    return get_problem("well", data_dir=str(root), field="temperature", levels=2, filters=4)


def test_plot_file_vorticity_mask_and_curves(tmp_path):
    from phisim.io import read_simulation
    from phisim.simulate import resolve_config, simulate_dataset
    from phisim.viz.plotfile import field_frames, obstacle_of, plot_file

    cfg = resolve_config("taylor_green", trajectories=1, trajectories_per_file=1, steps=2, resolution=32,
                         valid_fraction=0, test_fraction=0, dtype="float64")
    root = simulate_dataset(tmp_path / "tg", cfg, progress=False)["root"]
    f = next((root / "data" / "train").glob("*.h5"))
    d = read_simulation(f)
    w = field_frames(d, "vorticity")[0]
    u = d.fields["velocity"][0, 0]
    # Taylor-Green: u = A sin(kx') cos(ky'), v = -A cos(kx') sin(ky') -> vorticity = -2 k A sin(kx') sin(ky')
    amp = float(np.abs(u).max())
    assert np.abs(w).max() == pytest.approx(2 * amp, rel=0.02)
    assert obstacle_of(d) is None
    paths = plot_file(f, tmp_path / "pics", field="vorticity")
    assert [p.suffix for p in paths] == [".png", ".gif"] and all(p.stat().st_size > 0 for p in paths)
    with pytest.raises(ParameterError, match="choose from"):
        plot_file(f, tmp_path / "pics", field="pressure")
    cfg = resolve_config("smoke", trajectories=1, trajectories_per_file=1, steps=2, resolution=16,
                         valid_fraction=0, test_fraction=0)
    root = simulate_dataset(tmp_path / "sm", cfg, progress=False)["root"]
    d = read_simulation(next((root / "data" / "train").glob("*.h5")))
    assert obstacle_of(d).sum() > 0
    out = tmp_path / "t.h5"
    train(_linear_problem(), "adam", iterations=3, batch_size=2, out=out)
    assert plot_file(out, tmp_path / "pics")[0].name == "t_training.png"


def test_factory_file_errors_use_the_command_lines_wording(tmp_path):
    with pytest.raises(ParameterError, match=r"problem factory file .*nope\.py does not exist"):
        load_problem(f"{tmp_path}/nope.py:make")
    folder = tmp_path / "pkg.py"
    folder.mkdir()
    with pytest.raises(ParameterError, match=r"problem factory file .*pkg\.py is a folder, not a file"):
        load_problem(f"{folder}:make")
