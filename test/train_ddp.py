"""The training run the distributed test starts in each process (importable by spawned children)."""

from __future__ import annotations

from datetime import timedelta

import torch

from nsflow_ros.train.data import PairConfig
from nsflow_ros.train.distributed import leave_distributed
from nsflow_ros.train.model import EncoderSpec
from nsflow_ros.train.sources import MixedSource, PhotoSource
from nsflow_ros.train.trainer import TrainConfig, TrainData, train

STEPS = 3


def config(out, batch: int) -> TrainConfig:
    return TrainConfig(
        spec=EncoderSpec(d=2, width=4),
        out=out,
        steps=STEPS,
        batch=batch,
        seed=3,
        val_every=0,
        threads=1,
        pair=PairConfig(96, 72, max_points=30, min_distance=5.0),
        tensorboard=False,
    )


def run(out, batch: int):
    """Train; return the loss curve and the flattened parameters after every step."""
    record: list[tuple[float, torch.Tensor]] = []

    def on_step(step, loss, model):
        record.append((loss, torch.cat([p.detach().flatten().clone() for p in model.parameters()])))

    data = TrainData(MixedSource([(PhotoSource(("astronaut", "camera")), 1.0)]))
    train(config(out, batch), progress=False, data=data, on_step=on_step)
    return [r[0] for r in record], torch.stack([r[1] for r in record])


def agent_store():
    """The rendezvous store ``torchrun``'s agent hosts: a TCPStore server bound to a free port by the OS,
    held open for the whole run (``.port`` names it)."""
    import torch.distributed as dist

    timeout = timedelta(seconds=120)
    return dist.TCPStore("127.0.0.1", 0, is_master=True, wait_for_workers=False, timeout=timeout)


def worker(rank: int, port: int, out: str, result: str) -> None:
    """One process of a two-process run, joined through the environment ``torchrun`` sets.

    As under ``torchrun``, the store is the launcher's (the test's :func:`agent_store`), already listening
    on ``port``: no worker binds a port, so none can lose it to another process between pick and bind.
    """
    import os

    import torch.distributed as dist

    os.environ.update(
        MASTER_ADDR="127.0.0.1", MASTER_PORT=str(port), RANK=str(rank), LOCAL_RANK=str(rank), WORLD_SIZE="2",
        TORCHELASTIC_USE_AGENT_STORE="True",
    )
    clean = False
    try:
        losses, params = run(out, batch=1)
        assert dist.is_initialized() and dist.get_backend() == "gloo"
        torch.save({"losses": losses, "params": params}, f"{result}{rank}.pt")
        clean = True
    finally:
        leave_distributed(clean)
