"""Data-parallel training over two processes (gloo, CPU) follows the single-process trajectory."""

import os

import numpy as np
import torch
import torch.distributed as dist
import torch.multiprocessing as mp

from inverse.train import train
from tests.inverse.test_train import ToyProblem


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
