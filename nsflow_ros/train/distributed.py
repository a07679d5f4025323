"""Data-parallel training over processes with ``torch.distributed`` (started by ``torchrun``).

Step ``s`` with global batch ``B N`` takes pairs ``s B N .. (s + 1) B N - 1`` of the indexed stream, rank
``r`` its own ``B`` of them (:func:`shard`), so N processes with batch B see the pairs (and, with
DistributedDataParallel's averaged gradients, take the step) of one process with batch ``B N``.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field

import torch
import torch.distributed as dist

from nsflow_ros.train.errors import TrainError

__all__ = ["World", "all_mean", "broadcast_flag", "init_distributed", "leave_distributed", "shard"]


@dataclass(frozen=True)
class World:
    """This process's place in the run: ``size`` processes, this one ``rank`` (0 writes); ``device`` holds
    the small tensors the ranks exchange (nccl exchanges GPU tensors only)."""

    size: int = 1
    rank: int = 0
    device: torch.device = field(default_factory=lambda: torch.device("cpu"))

    @property
    def main(self) -> bool:
        return self.rank == 0


def init_distributed(device: torch.device, backend: str | None = None) -> World:
    """Join the process group ``torchrun`` describes (or the one already joined); one process otherwise.

    Args:
        device: this process's device (nccl for CUDA, gloo for the CPU unless ``backend`` says).
        backend: ``gloo`` or ``nccl``.

    Raises:
        TrainError: the environment names a world but torch.distributed is unavailable.
    """
    if dist.is_available() and dist.is_initialized():
        backend = dist.get_backend()
    else:
        size = int(os.environ.get("WORLD_SIZE", "1"))
        if size <= 1:
            return World()
        if not dist.is_available():
            raise TrainError(f"WORLD_SIZE={size} but this torch build has no torch.distributed")
        backend = backend or ("nccl" if device.type == "cuda" else "gloo")
        dist.init_process_group(backend)
    comm = device if backend == "nccl" else torch.device("cpu")
    return World(dist.get_world_size(), dist.get_rank(), comm)


def leave_distributed(clean: bool = True) -> None:
    """Leave the process group (if one was joined).

    Args:
        clean: this rank got through its run; it waits for the others first, because a peer that tears
            its gloo pairs down while another still writes or talks can abort that process natively
            (SIGABRT, no Python traceback). After an error this rank does not wait, since the others may
            never come; ranks that finished then wait for it until ``torchrun`` stops them on its exit.
    """
    if not (dist.is_available() and dist.is_initialized()):
        return
    if clean:
        dist.barrier()
    dist.destroy_process_group()


def shard(step: int, batch: int, world: World) -> list[int]:
    """The stream indices rank ``world.rank`` trains on at ``step`` (``batch`` pairs per rank)."""
    base = (step * world.size + world.rank) * batch
    return list(range(base, base + batch))


def all_mean(value: float, world: World) -> float:
    """The mean of ``value`` over all ranks (itself in a single process)."""
    if world.size == 1:
        return value
    t = torch.tensor([value], dtype=torch.float64, device=world.device)
    dist.all_reduce(t)
    return float(t[0]) / world.size


def broadcast_flag(flag: bool, world: World) -> bool:
    """Rank 0's ``flag`` on every rank (e.g. "the time is up": ranks must stop at the same step)."""
    if world.size == 1:
        return flag
    t = torch.tensor([int(flag)], dtype=torch.int64, device=world.device)
    dist.broadcast(t, 0)
    return bool(t[0])
