"""Data-parallel training (nsflow_ros.train.distributed): two gloo processes on the CPU."""

from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from train_ddp import STEPS, agent_store, run, worker  # noqa: E402

from nsflow_ros.train.distributed import World, shard  # noqa: E402


def test_shards_cover_the_global_batch_once():
    got = [shard(s, 2, World(3, r)) for s in range(2) for r in range(3)]
    assert sorted(i for idx in got for i in idx) == list(range(12))
    assert shard(1, 2, World(3, 1)) == [8, 9]


def test_two_processes_follow_one_process_with_the_double_batch(tmp_path):
    import torch.multiprocessing as mp

    store = agent_store()  # bound before the workers start, held until they are done
    mp.spawn(worker, args=(store.port, str(tmp_path / "ddp"), str(tmp_path / "rank")), nprocs=2, join=True)
    del store
    r0, r1 = (torch.load(tmp_path / f"rank{r}.pt", weights_only=True) for r in (0, 1))
    # both ranks hold the same weights after every step, and log the same (averaged) loss
    assert torch.equal(r0["params"], r1["params"]) and r0["losses"] == r1["losses"]
    assert len(r0["losses"]) == STEPS
    # one process with batch 2 trains on the same pairs, so it follows the same curve
    losses, params = run(tmp_path / "single", batch=2)
    np.testing.assert_allclose(r0["losses"], losses, rtol=1e-5)
    torch.testing.assert_close(r0["params"], params, rtol=1e-5, atol=1e-6)
    assert not torch.equal(params[0], params[-1])  # the weights did move
    assert (tmp_path / "ddp" / "encoder.pt").is_file() and (tmp_path / "ddp" / "train.csv").is_file()


def test_leaving_without_a_process_group_does_nothing():
    import torch.distributed as dist

    from nsflow_ros.train.distributed import leave_distributed

    leave_distributed(True)
    leave_distributed(False)
    assert not dist.is_initialized()
