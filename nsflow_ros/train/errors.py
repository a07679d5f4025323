"""Errors of the training package."""

from __future__ import annotations

from nsflow_ros.errors import NSFlowError

__all__ = ["TrainError"]


class TrainError(NSFlowError):
    """Bad input to a training component (shapes, settings), or a missing training dependency."""
