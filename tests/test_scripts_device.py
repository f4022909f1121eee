"""Every benchmark and reproduction script takes ``--device``.

* a device this machine lacks (``cuda`` without CUDA, ``cuda:99`` with it) or a malformed name stops the
  script with a :class:`~phisim.errors.ParameterError` before it writes anything;
* tiny ``--device cpu`` runs of the scripts that no other test runs record the device in their results;
* the same tiny runs on CUDA (skipped without a GPU) finish, record ``cuda`` and agree with the CPU run where
  the computation is deterministic up to round-off.
"""

from __future__ import annotations

import importlib.util
import json
import math
from pathlib import Path

import h5py
import numpy as np
import pytest
import torch

from phisim.errors import ParameterError

ROOT = Path(__file__).resolve().parents[1]
HAS_CUDA = torch.cuda.is_available()
#: A device name this machine does not have.
MISSING = "cuda:99" if HAS_CUDA else "cuda"
needs_cuda = pytest.mark.skipif(not HAS_CUDA, reason="needs CUDA")


def load(rel: str):
    """Import a script by its path relative to the repository root (under a name of its own)."""
    name = "devtest_" + rel.replace("/", "_").removesuffix(".py")
    spec = importlib.util.spec_from_file_location(name, ROOT / rel)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


# The smallest arguments (without --device) that make each script's main() do its work; "{out}" is a folder
# that must not exist before the run.
SCRIPTS = {
    "examples/hig_oscillators.py": ["--epochs", "1", "--n-train", "64", "--hig-batch-size", "32",
                                    "--adam-batch-size", "32", "--dtype", "float64", "--out", "{out}"],
    "examples/hig_toy.py": ["--iterations", "4", "--records", "2", "--batch-size", "8", "--lambdas", "0.01",
                            "--dtype", "float64", "--out", "{out}"],
    "examples/optimizer_toy.py": ["--iterations", "3", "--out", "{out}"],
    "examples/burgers_inverse.py": ["--iterations", "1", "--resolution", "8", "--batch-size", "2"],
    "examples/cylinder_benchmark.py": ["2D-1", "--ny", "8", "--t-end", "0.02", "--record-from", "0",
                                       "--out", "{out}/cylinder.json"],
    "examples/optimize_body.py": ["--iterations", "1", "--nx", "16", "--steps", "2", "--out", "{out}"],
    "examples/e5_diagnose.py": ["{out}:adam", "--samples", "2", "--window", "2"],
    "examples/reproduce.py": ["--experiment", "e2", "--iterations", "1", "--out", "{out}"],
    "examples/fluid_inverse.py": ["--resolution", "16", "--iterations", "1", "--out", "{out}"],
    "examples/karman.py": ["--ny", "8", "--t-end", "0.05", "--out", "{out}"],
    "examples/smoke_plume.py": ["--out", "{out}"],
    "examples/taylor_couette.py": ["--n", "16", "--max-steps", "2"],
    "examples/spherical_couette.py": ["--n", "12", "--max-steps", "2", "--out", "{out}/couette.json"],
    "examples/cylinder_array.py": ["--n", "8", "--max-steps", "2", "--out", "{out}/array.json"],
    "examples/sphere_drag.py": ["--n", "4", "--box", "1.5", "3", "3", "--t-end", "0.5", "--quiet", "--out",
                                "{out}/sphere.json"],
    "examples/oscillating_cylinder.py": ["--n", "8", "--steps", "24", "--out", "{out}/forces.csv"],
    "examples/dutsch_cylinder.py": ["--res", "2", "--periods", "0.1", "--half-width", "3", "--out", "{out}/dutsch"],
    "examples/pde_inverse.py": ["--iterations", "2", "--max-iterations", "hig=1", "--seeds", "0", "--heldout-size",
                                "4", "--eval-every", "1", "--reference-iterations", "1", "--width", "4", "--blocks",
                                "1", "--out", "{out}"],
    "benchmarks/bench_bodies.py": ["--sizes", "16", "--repeat", "1", "--json", "{out}/bodies.json"],
    "benchmarks/bench_layout.py": ["--static", "4", "--carried", "8", "--slip", "--resting", "4", "--steps", "1",
                                   "--rounds", "1", "--json", "{out}/layout.json"],
    "benchmarks/bench_spectral.py": ["--n", "16", "--repeat", "2"],
    "benchmarks/bench_reliability.py": ["--parts", "float32", "--float32-sizes", "16", "--out", "{out}/r.json"],
    "benchmarks/bench_flow_bodies.py": ["--sides", "phisim", "phisim_obstacle", "--scenes", "cylinder_wake",
                                        "--sizes", "24", "--rounds", "1", "--warm", "1", "--steps", "1",
                                        "--repeat", "1", "--out", "{out}/flow.json"],
    "benchmarks/bench_cg.py": ["--sizes", "16", "--repeats", "1"],
    "examples/bn_recalibrate.py": ["--experiment", "e4", "--resolution", "16", "--batch-size", "2", "--runs",
                                   "{out}/run", "--batches", "1"],
    "benchmarks/bench_training.py": ["--resolution", "16", "--batch-size", "2", "--out", "{out}/t.md"],
    "benchmarks/bench_hig.py": ["--batch-sizes", "2", "--widths", "4", "--out", "{out}/h.md"],
    "benchmarks/run.py": ["--suite", "operators", "--quick", "--out", "{out}"],
    "benchmarks/bench_viscosity.py": ["--sizes", "8", "--dtype", "float64"],
    "benchmarks/bench_jaxcfd.py": ["--sides", "phisim", "--sizes", "8"],
    "benchmarks/bench_etdrk.py": ["--quick", "--rounds", "1", "--out", "{out}/etdrk.json"],
    "benchmarks/bench_simulate.py": ["--step-cost", "--sizes", "8", "12", "--sizes3d", "--rounds", "1", "--calls",
                                     "2", "--out", "{out}/s.json"],
}


def argv(script: str, out: Path, device: str) -> list[str]:
    return [a.replace("{out}", str(out)) for a in SCRIPTS[script]] + ["--device", device]


def test_every_script_is_listed():
    """A new benchmark or reproduction script must join the table above (and so take --device)."""
    found = {f"examples/{p.name}" for p in (ROOT / "examples").glob("*.py")}
    found |= {f"benchmarks/{p.name}" for p in (ROOT / "benchmarks").glob("*.py")}
    helpers = {"examples/demo.py", "examples/seed_table.py", "benchmarks/cases_phisim.py", "benchmarks/inputs.py",
               "benchmarks/peer_phiflow.py", "benchmarks/timing.py", "benchmarks/peer_jaxcfd.py",
               "benchmarks/peer_exponax.py"}
    assert found - helpers == set(SCRIPTS)
    for script in SCRIPTS:
        assert "--device" in (ROOT / script).read_text(), script


@pytest.mark.parametrize("bad", [MISSING, "gpu-please"])
@pytest.mark.parametrize("script", sorted(SCRIPTS))
def test_a_device_this_machine_lacks_is_a_clear_error(script, bad, tmp_path):
    out = tmp_path / "out"
    mod = load(script)
    with pytest.raises(ParameterError, match="CUDA is not available|CUDA device|unknown device"):
        mod.main(argv(script, out, bad))
    assert not out.exists()  # checked before anything is written


# ---------------------------------------------------------------------------------------------------------
# tiny runs of the scripts no other test runs (the others: tests/inverse/test_examples_*.py,
# tests/inverse/test_custom.py, tests/phisim/fluid/test_examples_bodies.py)
# ---------------------------------------------------------------------------------------------------------


def _cylinder(out: Path, device: str) -> dict:
    cb = load("examples/cylinder_benchmark.py")
    assert cb.main(argv("examples/cylinder_benchmark.py", out, device)) == 0
    res = json.loads((out / "cylinder.json").read_text())
    (run,) = res["runs"]
    assert run["device"] == str(torch.device(device)) and run["ny"] == 8
    assert math.isfinite(run["cd"]) and run["cd"] > 0  # a drag that pushes the cylinder downstream
    return run


def test_cylinder_benchmark_tiny_cpu(tmp_path):
    _cylinder(tmp_path / "new", "cpu")  # a folder that does not exist yet: the script makes it


def test_bench_layout_tiny_cpu(tmp_path):
    """The layout benchmark's tiny run: one resting-sphere layout, one carried step and one ``imex2`` step of the
    resting sphere, timed in fresh processes."""
    out = tmp_path / "out"
    mod = load("benchmarks/bench_layout.py")
    assert mod.main(argv("benchmarks/bench_layout.py", out, "cpu")) == 0
    rows = json.loads((out / "layout.json").read_text())
    assert [(r["case"], r["n"]) for r in rows] == [("static", 4), ("carried", 8), ("resting", 4)]
    for r in rows:
        assert r["device"] == "cpu" and r["this"] > 0
    assert rows[0]["cells"] == [56, 32, 32] and 0 < rows[1]["this_max_u"] < 10
    assert rows[2]["cells"] == [56, 16, 16] and 0.5 < rows[2]["this_max_u"] < 10  # the stream past the sphere


def _bench_bodies(out: Path, device: str) -> list[dict]:
    bb = load("benchmarks/bench_bodies.py")
    assert bb.main(argv("benchmarks/bench_bodies.py", out, device)) == 0
    rows = json.loads((out / "bodies.json").read_text())
    assert [(r["n"], r["dtype"]) for r in rows] == [(16, "float64"), (16, "float32")]
    for r in rows:
        assert r["device"] == str(torch.device(device))
        assert r["floor_ms"] > 0 and r["solve_ms"] > 0 and r["iterations_to_rtol"] >= 1
    return rows


def test_bench_bodies_tiny_cpu(tmp_path):
    _bench_bodies(tmp_path / "new", "cpu")


def test_bench_bodies_counts_a_cylinder_step(tmp_path):
    bb = load("benchmarks/bench_bodies.py")
    out = tmp_path / "new" / "cyl.json"
    assert bb.main(["--cylinder", "8", "--json", str(out)]) == 0
    rows = json.loads(out.read_text())
    assert [(r["cylinder"], r["integrator"]) for r in rows] == [("43x8", "imex2"), ("43x8", "split")]
    for r in rows:
        assert r["step_ms"] > 0 and r["operations"] > 100 and 0 <= r["host_reads"] < r["operations"]


def _bench_spectral(device: str, capsys) -> list:
    bs = load("benchmarks/bench_spectral.py")
    rows = bs.main(argv("benchmarks/bench_spectral.py", Path("unused"), device))
    printed = capsys.readouterr().out
    assert f"device {torch.device(device)}" in printed
    names = [r[0] for r in rows]
    assert any("scipy" in n for n in names) and any("numpy.fft" in n for n in names)
    phisim_rows = [r for r in rows if "phisim" in r[0]]
    assert phisim_rows and all(ms > 0 for _, ms, _ in rows)
    for name, _, err in phisim_rows:  # every engine on the device solves the same problem as scipy/numpy
        assert err < 1e-12, name
    return rows


def test_bench_spectral_tiny_cpu(capsys):
    rows = _bench_spectral("cpu", capsys)
    assert any("torch" in r[0] for r in rows)


def _bench_reliability(out: Path, device: str) -> list[dict]:
    br = load("benchmarks/bench_reliability.py")
    res = br.main(argv("benchmarks/bench_reliability.py", out, device))
    rows = json.loads((out / "r.json").read_text())["float32"]
    assert rows == res["float32"] and [r["dtype"] for r in rows] == ["float32", "float64"]
    for r in rows:
        assert r["device"] == str(torch.device(device)) and r["n"] == 16
        assert r["residual"] <= r["tolerance"] and r["status"] == "converged"
    return rows


def test_bench_reliability_float32_part_tiny_cpu(tmp_path):
    _bench_reliability(tmp_path, "cpu")


def _bench_flow_bodies(out: Path, device: str) -> dict:
    bf = load("benchmarks/bench_flow_bodies.py")
    assert bf.main(argv("benchmarks/bench_flow_bodies.py", out, device)) == 0
    data = json.loads((out / "flow.json").read_text())
    assert data["device"] == device
    assert len(data["results"]) == 2
    for r in data["results"]:
        assert "error" not in r, r
        assert r["device"] == str(torch.device(device))  # the child ran the side on the device
        assert r["median_s"] > 0 and r["stats"]["rms_div"] < 1e-3
    return data


def test_bench_flow_bodies_phisim_sides_tiny_cpu(tmp_path):
    _bench_flow_bodies(tmp_path, "cpu")


def _fake_e5_run(folder: Path) -> None:
    """A checkpoint of an untrained 16x16 E5 network and a short training log, as fluid_inverse.py writes."""
    from inverse.fluid_inverse import FluidProblem
    from phisim.io import TrainingLog

    folder.mkdir(parents=True)
    problem = FluidProblem(resolution=(16, 16))
    torch.manual_seed(0)
    net = problem.make_network().to(problem.dtype)
    torch.save({"model": net.state_dict(), "iteration": 3, "settings": {"resolution": [16, 16]}},
               folder / "fluid_inverse.h5.adam.ckpt")
    with TrainingLog(folder / "fluid_inverse.h5", "adam") as log:
        for i in range(3):
            log.append(i, loss=1.0, metric=float(i + 1))


def _e5(tmp_path: Path, device: str) -> dict:
    run = tmp_path / "run"
    if not run.exists():
        _fake_e5_run(run)
    e5 = load("examples/e5_diagnose.py")
    res = e5.main(argv("examples/e5_diagnose.py", run, device))
    entry = res[f"{run}:adam"]
    assert entry["iteration"] == 3 and math.isfinite(entry["metric"]) and entry["metric"] > 0
    assert -1 <= entry["strength_corr"] <= 1
    assert entry["train_running_mean"] == {}  # fewer than 50 iterations logged
    return entry


def test_bench_simulate_step_cost_tiny_cpu(tmp_path):
    out = tmp_path / "out"
    load("benchmarks/bench_simulate.py").main(argv("benchmarks/bench_simulate.py", out, "cpu"))
    rows = json.loads((out / "s.json").read_text())
    assert [r["resolution"] for r in rows] == ["8x8", "12x12"]
    for r in rows:
        assert r["device"] == "cpu"
        for phase in ("step", "marker", "velocity", "buoyancy", "projection"):
            assert r[f"{phase}_cpu_ms"] > 0 and r[f"{phase}_wall_ms"] > 0


def test_e5_diagnose_tiny_cpu(tmp_path):
    _e5(tmp_path, "cpu")


# ---------------------------------------------------------------------------------------------------------
# CUDA: the same tiny runs on the GPU, compared with the CPU where the numbers are deterministic
# ---------------------------------------------------------------------------------------------------------


@needs_cuda
def test_hig_toy_on_cuda_matches_cpu(tmp_path):
    toy = load("examples/hig_toy.py")
    cpu = toy.main(argv("examples/hig_toy.py", tmp_path / "cpu", "cpu"))
    gpu = toy.main(argv("examples/hig_toy.py", tmp_path / "gpu", "cuda"))
    with h5py.File(tmp_path / "gpu" / "hig_toy_lambda0.01.h5", "r") as f:
        assert f.attrs["device"] == "cuda"
    for m in ("adam", "gn", "hig"):  # float64, same weights and batches: round-off apart
        assert gpu[0.01][m] == pytest.approx(cpu[0.01][m], rel=1e-5)


@needs_cuda
def test_hig_oscillators_on_cuda_matches_cpu(tmp_path):
    osc = load("examples/hig_oscillators.py")
    cpu = osc.main(argv("examples/hig_oscillators.py", tmp_path / "cpu", "cpu"))
    gpu = osc.main(argv("examples/hig_oscillators.py", tmp_path / "gpu", "cuda"))
    with h5py.File(tmp_path / "gpu" / "hig_oscillators.h5", "r") as f:
        assert f.attrs["device"] == "cuda"
    for m in ("hig", "adam", "gn"):  # float64 (see SCRIPTS)
        assert gpu[m] == pytest.approx(cpu[m], rel=1e-5)


@needs_cuda
def test_optimizer_toy_on_cuda_matches_cpu(tmp_path):
    toy = load("examples/optimizer_toy.py")
    cpu = toy.main(argv("examples/optimizer_toy.py", tmp_path / "cpu", "cpu"))
    gpu = toy.main(argv("examples/optimizer_toy.py", tmp_path / "gpu", "cuda"))
    for m in cpu:  # closed-form updates to round-off; L-BFGS-B to its own tolerance (as against the analytic PG)
        tol = 1e-5 if m == "pg_lbfgsb" else 1e-10
        np.testing.assert_allclose(gpu[m]["trajectory"], cpu[m]["trajectory"], rtol=tol, atol=tol)


@needs_cuda
def test_burgers_on_cuda_matches_cpu():
    b = load("examples/burgers_inverse.py")
    cpu = b.main(argv("examples/burgers_inverse.py", Path("unused"), "cpu"))
    gpu = b.main(argv("examples/burgers_inverse.py", Path("unused"), "cuda"))
    assert gpu["device"] == "cuda"
    for m in ("adam", "pg_inverse_gradient", "identity"):
        assert gpu[m]["heldout_metric"] == pytest.approx(cpu[m]["heldout_metric"], rel=1e-4)


@needs_cuda
def test_optimize_body_on_cuda_matches_cpu(tmp_path):
    ob = load("examples/optimize_body.py")
    cpu = ob.main(argv("examples/optimize_body.py", tmp_path / "cpu", "cpu"))
    gpu = ob.main(argv("examples/optimize_body.py", tmp_path / "gpu", "cuda"))
    assert gpu["device"] == "cuda"
    for hc, hg in zip(cpu["history"], gpu["history"]):  # iterative pressure solves: agreement to their tolerance
        assert hg["drag"] == pytest.approx(hc["drag"], rel=1e-3)


@needs_cuda
def test_cylinder_benchmark_on_cuda_matches_cpu(tmp_path):
    cpu = _cylinder(tmp_path / "cpu", "cpu")
    gpu = _cylinder(tmp_path / "gpu", "cuda")
    assert gpu["cd"] == pytest.approx(cpu["cd"], rel=1e-3)


@needs_cuda
def test_bench_bodies_on_cuda(tmp_path):
    cpu = _bench_bodies(tmp_path / "cpu", "cpu")
    gpu = _bench_bodies(tmp_path / "gpu", "cuda")
    for rc, rg in zip(cpu, gpu):  # the same preconditioned solve: iteration counts within one or two
        assert abs(rc["iterations_to_rtol"] - rg["iterations_to_rtol"]) <= 2


@needs_cuda
def test_bench_spectral_on_cuda(capsys):
    rows = _bench_spectral("cuda", capsys)
    assert not any("pyfftw" in r[0] for r in rows)  # CPU-only engine left out on the GPU


@needs_cuda
def test_bench_reliability_on_cuda(tmp_path):
    _bench_reliability(tmp_path, "cuda")


@needs_cuda
def test_bench_flow_bodies_on_cuda(tmp_path):
    _bench_flow_bodies(tmp_path, "cuda")


@needs_cuda
def test_e5_diagnose_on_cuda_matches_cpu(tmp_path):
    cpu = _e5(tmp_path, "cpu")
    gpu = _e5(tmp_path, "cuda")
    # float32 network; cuDNN may run its convolutions in TF32 (about 1e-3 relative)
    assert gpu["metric"] == pytest.approx(cpu["metric"], rel=1e-2)


def test_bench_viscosity_tiny_cpu(tmp_path):
    text = load("benchmarks/bench_viscosity.py").main(argv("benchmarks/bench_viscosity.py", tmp_path / "out", "cpu"))
    assert "| 8² |" in text and "float64" in text and "Device:" not in text  # the CPU table carries no device line


def test_bench_jaxcfd_phisim_side_tiny_cpu(tmp_path, capsys):
    mod = load("benchmarks/bench_jaxcfd.py")
    assert mod.main(argv("benchmarks/bench_jaxcfd.py", tmp_path, "cpu")) == []
    out = capsys.readouterr().out
    assert "one step, 8², float32: phisim" in out and " ms" in out
