"""Errors of the evaluation suite."""

from __future__ import annotations

from nsflow_ros.errors import NSFlowError

__all__ = ["EstimatorError", "EvaluationError", "MethodLeftOutError"]


class EvaluationError(NSFlowError):
    """An evaluation cannot run: missing model or data, bad settings, an unwritable output folder."""


class MethodLeftOutError(EvaluationError):
    """A compared method cannot track the evaluated model's descriptors; the run goes on without it."""


class EstimatorError(EvaluationError):
    """The VINS-Fusion estimator cannot be run or gave no trajectory: a build folder missing a file, a
    config missing a key, a process that died or did not finish in time, no ``vio.csv``."""
