"""The evaluation suite: the paper's analyses for NSFlow beside the classical baselines.

Only NumPy/OpenCV/onnxruntime (and matplotlib for figures, imported inside functions); no ROS, no torch.
Every analysis is ``run(ctx: EvalContext) -> Section``; :mod:`~nsflow_ros.evaluation.registry` lists them
in report order and ``nsflow-evaluate`` (:mod:`~nsflow_ros.evaluation.cli`) runs them into one report.
"""

from __future__ import annotations

from nsflow_ros.evaluation.context import EvalContext
from nsflow_ros.evaluation.errors import EvaluationError
from nsflow_ros.evaluation.methods import (
    CLASSICAL,
    KLT,
    KLT_CLAHE,
    NSFLOW,
    NSFLOW_LK,
    VARIANTS,
    EvalMethod,
    KLTPairMethod,
    LMPairMethod,
    PairResult,
    default_methods,
    eval_method,
)
from nsflow_ros.evaluation.section import HeadlineRow, Section

__all__ = [
    "CLASSICAL",
    "KLT",
    "KLT_CLAHE",
    "NSFLOW",
    "NSFLOW_LK",
    "VARIANTS",
    "EvalContext",
    "EvalMethod",
    "EvaluationError",
    "HeadlineRow",
    "KLTPairMethod",
    "LMPairMethod",
    "PairResult",
    "Section",
    "default_methods",
    "eval_method",
]
