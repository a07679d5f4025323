"""Entry points whose real module needs an optional extra: importable without it, with an install hint."""

from __future__ import annotations

import sys

from nsflow_ros.errors import NSFlowError

__all__ = ["train"]


def train(args: list[str] | None = None) -> int:
    """``nsflow-train`` / ``ros2 run nsflow_ros train``: needs the ``train`` extra (PyTorch)."""
    try:
        from nsflow_ros.train.cli import main
    except NSFlowError as err:  # TrainError naming the missing extra
        print(f"nsflow-train: {err}", file=sys.stderr)
        return 1
    return main(args)
