"""Data-parallel training over two processes (gloo, CPU) follows the single-process trajectory."""

import json
import os
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest
import torch
import torch.distributed as dist
import torch.multiprocessing as mp

from inverse.distributed import SyncBatchNorm, convert_sync_batchnorm
from inverse.problems import get_problem
from inverse.train import train
from tests.inverse.test_train import ToyProblem

ROOT = Path(__file__).resolve().parents[2]
UNET = dict(resolution=(16, 16), dtype=torch.float64, heldout_size=6)


def _worker(rank: int, world: int, init_file: str, out_dir: str) -> None:
    dist.init_process_group("gloo", init_method=f"file://{init_file}", rank=rank, world_size=world)
    try:
        torch.set_num_threads(1)
        r = train(ToyProblem(), "adam_pg", iterations=4, batch_size=7, seed=3, out=os.path.join(out_dir, "ddp.h5"))
        torch.save({k: v.detach() for k, v in r.model.state_dict().items()}, os.path.join(out_dir, f"rank{rank}.pt"))
        if rank == 0:
            np.save(os.path.join(out_dir, "metric.npy"), r.curves["metric"])
    finally:
        dist.destroy_process_group()


def test_two_processes_match_one(tmp_path):
    single = train(ToyProblem(), "adam_pg", iterations=4, batch_size=7, seed=3)
    mp.spawn(_worker, args=(2, str(tmp_path / "init"), str(tmp_path)), nprocs=2, join=True)
    p0 = torch.load(tmp_path / "rank0.pt")
    p1 = torch.load(tmp_path / "rank1.pt")
    for name, value in single.model.state_dict().items():
        torch.testing.assert_close(p0[name], value, rtol=1e-10, atol=1e-12)
        torch.testing.assert_close(p1[name], p0[name], rtol=0, atol=0)  # replicas stay identical
    # the log written by process 0 has the full-batch metric (7 samples split 4 + 3)
    np.testing.assert_allclose(np.load(tmp_path / "metric.npy"), single.curves["metric"], rtol=1e-10)


def _unet_worker(rank: int, world: int, init_file: str, out_dir: str, method: str) -> None:
    dist.init_process_group("gloo", init_method=f"file://{init_file}", rank=rank, world_size=world)
    try:
        torch.set_num_threads(1)
        r = train(get_problem("poisson", **UNET), method, iterations=3, batch_size=5, seed=1, eval_every=1,
                  out=os.path.join(out_dir, "ddp.h5"))
        torch.save({k: v.detach() for k, v in r.model.state_dict().items()}, os.path.join(out_dir, f"rank{rank}.pt"))
    finally:
        dist.destroy_process_group()


@pytest.mark.parametrize("method", ["adam", "pg"])
def test_two_processes_match_one_on_a_unet_with_batchnorm(tmp_path, method):
    """Whole-batch BatchNorm statistics: parameters, running statistics, training and held-out curves of 2
    processes (batch 5 split 3 + 2) equal one process to round-off (float64)."""
    torch.set_num_threads(1)
    single = train(get_problem("poisson", **UNET), method, iterations=3, batch_size=5, seed=1, eval_every=1)
    mp.spawn(_unet_worker, args=(2, str(tmp_path / "init"), str(tmp_path), method), nprocs=2, join=True)
    p0, p1 = torch.load(tmp_path / "rank0.pt"), torch.load(tmp_path / "rank1.pt")
    gauge = _biases_before_batchnorm(single.model)
    assert len(gauge) >= 8 and any(n.endswith("running_var") for n in single.model.state_dict())
    for name, value in single.model.state_dict().items():
        torch.testing.assert_close(p1[name], p0[name], rtol=0, atol=0)  # replicas stay identical
        if name in gauge:
            # a convolution bias followed by BatchNorm has zero gradient in exact arithmetic; Adam scales
            # its round-off gradient up (update ~ lr * g / (|g| + eps)), so it drifts apart at ~1e-6 in
            # either run. It has no effect on the training output (BatchNorm subtracts it again).
            torch.testing.assert_close(p0[name], value, rtol=0, atol=1e-4, msg=name)
        else:
            torch.testing.assert_close(p0[name], value, rtol=1e-9, atol=1e-11, msg=name)
    with h5py.File(tmp_path / "ddp.h5") as f:
        g = f[f"training/{method}"]
        for curve in ("loss", "metric"):
            np.testing.assert_allclose(g[curve][()], single.curves[curve], rtol=1e-10, err_msg=curve)
        for curve in ("eval_loss", "eval_metric"):  # eval mode sees those biases through running means
            np.testing.assert_allclose(g[curve][()], single.curves[curve], rtol=1e-5, err_msg=curve)


def _biases_before_batchnorm(model):
    """Names of convolution biases directly followed by BatchNorm, and of that BatchNorm's running mean."""
    names = set()
    for prefix, mod in model.named_modules():
        if isinstance(mod, torch.nn.Sequential):
            kids = list(mod.named_children())
            for (n1, m1), (n2, m2) in zip(kids, kids[1:]):
                if isinstance(m1, torch.nn.Conv2d) and isinstance(m2, torch.nn.modules.batchnorm._BatchNorm):
                    names |= {f"{prefix}.{n1}.bias".lstrip("."), f"{prefix}.{n2}.running_mean".lstrip(".")}
    return names


def test_sync_batchnorm_outside_a_group_is_batchnorm():
    torch.manual_seed(0)
    bn = torch.nn.Sequential(torch.nn.Conv2d(2, 3, 3), torch.nn.BatchNorm2d(3)).double()
    bn[1].running_mean.uniform_()
    ref = {k: v.clone() for k, v in bn.state_dict().items()}
    x = torch.randn(4, 2, 6, 6, dtype=torch.float64)
    y_ref = bn(x)
    bn.load_state_dict(ref)
    conv = convert_sync_batchnorm(bn)
    assert isinstance(conv[1], SyncBatchNorm) and conv[1].running_mean.dtype == torch.float64
    torch.testing.assert_close(conv(x), y_ref, rtol=0, atol=0)
    assert set(conv.state_dict()) == set(ref)


def _cli(args, env_extra=None, torchrun=0):
    env = {**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1", **(env_extra or {})}
    for k in ("RANK", "WORLD_SIZE", "LOCAL_RANK", "MASTER_ADDR", "MASTER_PORT"):
        env.pop(k, None)
    head = [sys.executable, "-m", "torch.distributed.run", "--standalone", f"--nproc_per_node={torchrun}",
            "-m", "inverse.cli"] if torchrun else [sys.executable, "-m", "inverse.cli"]
    return subprocess.run(head + args, cwd=ROOT, env=env, capture_output=True, text=True, timeout=300)


def test_torchrun_cli_two_processes_reproduce_one(tmp_path):
    """``torchrun --nproc_per_node 2 -m inverse.cli train ...``: the group comes from torchrun's environment,
    only rank 0 prints and writes, and the curves equal a one-process run of the same command."""
    common = ["train", "poisson", "adam", "--iterations", "3", "--batch-size", "4", "--resolution", "16", "16",
              "--heldout-size", "4", "--eval-every", "1", "--quiet", "--dtype", "float64"]
    one = _cli(common + ["--out", str(tmp_path / "one.h5")])
    assert one.returncode == 0, one.stderr
    two = _cli(common + ["--out", str(tmp_path / "two.h5")], torchrun=2)
    assert two.returncode == 0, two.stderr[-3000:]
    lines = [ln for ln in two.stdout.splitlines() if ln.startswith("{")]
    assert len(lines) == 1  # rank 0 prints, rank 1 does not
    rep2, rep1 = json.loads(lines[0]), json.loads(one.stdout.strip().splitlines()[-1])
    assert rep2["metric_name"] == rep1["metric_name"] and "sum over cells" in rep1["metric_name"]
    # only rank 0 writes: one log and one model file per run
    assert sorted(p.name for p in tmp_path.iterdir()) == ["one.h5", "one.h5.adam.model.pt", "two.h5",
                                                          "two.h5.adam.model.pt"]
    with h5py.File(tmp_path / "one.h5") as f1, h5py.File(tmp_path / "two.h5") as f2:
        for curve, rtol in (("loss", 1e-10), ("metric", 1e-10), ("eval_metric", 1e-5)):
            # eval mode sees the drift of the gauge biases (see the test above)
            np.testing.assert_allclose(f2[f"training/adam/{curve}"][()], f1[f"training/adam/{curve}"][()],
                                       rtol=rtol, err_msg=curve)


_SCRIPT = """
import sys, torch
sys.path.insert(0, {root!r})
from inverse.train import train
from tests.inverse.test_train import ToyProblem
torch.set_num_threads(1)
r = train(ToyProblem(), "adam_pg", iterations=4, batch_size=7, seed=3, out={out!r}, progress=True)
sys.stdout.write("RESULT " + repr(r.curves["metric"].tolist()) + "\\n")  # one write: ranks share the pipe
sys.stdout.flush()
"""


def test_torchrun_script_calling_train_initialises_the_group(tmp_path):
    """A plain script calling ``train(...)`` under ``torchrun --nproc_per_node 2`` trains data-parallel (no
    ``init_process_group`` in the script), and only rank 0 writes the file."""
    script = tmp_path / "job.py"
    script.write_text(_SCRIPT.format(root=str(ROOT), out=str(tmp_path / "toy.h5")))
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    proc = subprocess.run([sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node=2",
                           str(script)], cwd=ROOT, env=env, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    results = [json.loads(ln.split(" ", 1)[1]) for ln in proc.stdout.splitlines() if ln.startswith("RESULT")]
    assert len(results) == 2 and results[0] == results[1], proc.stdout + proc.stderr[-2000:]
    single = train(ToyProblem(), "adam_pg", iterations=4, batch_size=7, seed=3)
    np.testing.assert_allclose(results[0], single.curves["metric"], rtol=1e-10)
    assert proc.stderr.count("toy/adam_pg") >= 1  # rank 0's progress bar
    assert sorted(p.name for p in tmp_path.iterdir()) == ["job.py", "toy.h5", "toy.h5.adam_pg.model.pt"]


def test_rank_devices_and_environment(monkeypatch):
    from inverse.distributed import init_from_env, is_main_process, launched_by_torchrun, rank_device
    from phisim.errors import ParameterError

    for k in ("RANK", "WORLD_SIZE", "LOCAL_RANK", "MASTER_ADDR", "MASTER_PORT"):
        monkeypatch.delenv(k, raising=False)
    assert not launched_by_torchrun() and not init_from_env("cpu") and is_main_process()
    monkeypatch.setenv("LOCAL_RANK", "3")
    assert rank_device("cuda") == torch.device("cuda", 3)  # one GPU per local process
    assert rank_device("cuda:1") == torch.device("cuda", 1)  # an explicit index is kept
    assert rank_device("cpu") == torch.device("cpu")
    with pytest.raises(ParameterError, match="process group"):
        train(ToyProblem(), "adam_pg", iterations=1, distributed=True)
