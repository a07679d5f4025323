"""Errors of the evaluation suite."""

from __future__ import annotations

from nsflow_ros.errors import NSFlowError

__all__ = ["EvaluationError", "MethodLeftOutError"]


class EvaluationError(NSFlowError):
    """An evaluation cannot run: missing model or data, bad settings, an unwritable output folder."""


class MethodLeftOutError(EvaluationError):
    """A compared method cannot track the evaluated model's descriptors; the run goes on without it."""
