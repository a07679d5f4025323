"""Where training runs: the torch device and the dtype of the descriptor maps in the LK layer.

The LK layer keeps only its per-point LM state in float64, so ``float32`` maps put all the heavy work in
float32 (what a GPU should use); ``float64`` maps are the CPU reference of the gradient tests.
"""

from __future__ import annotations

import os

import torch

from nsflow_ros.train.errors import TrainError

__all__ = ["DTYPES", "resolve_device", "resolve_dtype"]

DTYPES = {"float32": torch.float32, "float64": torch.float64}


def resolve_device(text: str, local_rank: int | None = None) -> torch.device:
    """``auto`` (the GPU when torch sees one), ``cpu``, ``cuda`` or ``cuda:K`` -> a device that exists here.

    Args:
        text: the ``--device`` value.
        local_rank: this process's rank on its machine (default ``LOCAL_RANK``): ``auto`` and ``cuda``
            then take GPU ``local_rank``.

    Raises:
        TrainError: an unknown value, or a GPU asked for that torch does not see.
    """
    if local_rank is None and "LOCAL_RANK" in os.environ:
        local_rank = int(os.environ["LOCAL_RANK"])
    if text == "cpu":
        return torch.device("cpu")
    if text == "auto" and not torch.cuda.is_available():
        return torch.device("cpu")
    if text in ("auto", "cuda"):
        text = f"cuda:{local_rank or 0}"
    kind, _, index = text.partition(":")
    if kind != "cuda" or not index.isdigit():
        raise TrainError(f"device must be auto, cpu, cuda or cuda:K, got {text!r}")
    if not torch.cuda.is_available():
        raise TrainError(
            f"device {text} asked for, but this torch build sees no GPU (torch {torch.__version__}; "
            "install a CUDA build of torch, see docs/training.md)"
        )
    if int(index) >= torch.cuda.device_count():
        raise TrainError(f"device {text} asked for, but torch sees {torch.cuda.device_count()} GPU(s)")
    return torch.device(text)


def resolve_dtype(text: str) -> torch.dtype:
    """``float32`` or ``float64`` -> the torch dtype; TrainError for another value."""
    if text not in DTYPES:
        raise TrainError(f"dtype must be one of {tuple(DTYPES)}, got {text!r}")
    return DTYPES[text]
