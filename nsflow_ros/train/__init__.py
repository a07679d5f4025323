"""nsflow_ros.train: training the NSFlow encoder through a differentiable LK layer, or by distillation.

The only part of the project that imports torch (``pip install 'nsflow_ros[train]'``); without torch,
importing it raises :class:`TrainError` naming the install command. ``nsflow-train`` is
:mod:`~nsflow_ros.train.cli`, the loop :mod:`~nsflow_ros.train.trainer`, the layer
:mod:`~nsflow_ros.train.lk_layer` and the data :mod:`~nsflow_ros.train.sources`.
"""

from __future__ import annotations

from nsflow_ros.train.errors import TrainError

try:
    import torch  # noqa: F401
except ImportError as err:  # pragma: no cover - depends on the environment
    raise TrainError(
        "nsflow_ros.train needs PyTorch, which is not installed: pip install 'nsflow_ros[train]' "
        "(from a git clone: pip install -e '.[train]')"
    ) from err

from nsflow_ros.train.distill import Teacher, distill_loss
from nsflow_ros.train.evaluate import compare, heldout_pairs
from nsflow_ros.train.export import export_onnx
from nsflow_ros.train.lk_layer import BackwardMode, LKOutput, LKPyramidOutput, lk_track, lk_track_pyramid
from nsflow_ros.train.model import Encoder, EncoderSpec
from nsflow_ros.train.trainer import TrainConfig, train

__all__ = [
    "BackwardMode",
    "Encoder",
    "EncoderSpec",
    "LKOutput",
    "LKPyramidOutput",
    "Teacher",
    "TrainConfig",
    "TrainError",
    "compare",
    "distill_loss",
    "export_onnx",
    "heldout_pairs",
    "lk_track",
    "lk_track_pyramid",
    "train",
]
