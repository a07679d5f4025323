"""nsflow_ros.train: training the NSFlow encoder through a differentiable LK layer, or by distillation.

This is the only part of the project that imports torch (``pip install 'nsflow_ros[train]'``); the core
and the ROS nodes never do. Modules, one concept each:

* :mod:`~nsflow_ros.train.ops` - Scharr derivative maps, exact bilinear window sampling and the
  descriptor pyramid (``cv2.pyrDown`` twin) in torch;
* :mod:`~nsflow_ros.train.lk_layer` - the LM Lucas-Kanade layer with implicit or unrolled backward, at one
  level or coarse to fine through the pyramid;
* :mod:`~nsflow_ros.train.model` - the encoder CNN;
* :mod:`~nsflow_ros.train.data` - homography pairs of real photos with exact flow and illumination changes;
* :mod:`~nsflow_ros.train.scenes` - stereo and temporal pairs rendered from the sample scenes, exact flow;
* :mod:`~nsflow_ros.train.sources` - every data source (photos, scenes, TartanAir, the user's footage)
  behind one interface, mixed by weight, as an indexed pair stream;
* :mod:`~nsflow_ros.train.device` - the device and the LK layer's map dtype;
* :mod:`~nsflow_ros.train.distributed` - data-parallel training under ``torchrun``;
* :mod:`~nsflow_ros.train.runlog` - step log (CSV, TensorBoard), progress and the run record;
* :mod:`~nsflow_ros.train.recipes` - presets (``--recipe paper``);
* :mod:`~nsflow_ros.train.footage_eval` - models side by side on held-out frames of the user's footage;
* :mod:`~nsflow_ros.train.loss` - the robust endpoint-error loss;
* :mod:`~nsflow_ros.train.distill` - distillation of a narrower encoder from a trained one's maps;
* :mod:`~nsflow_ros.train.trainer` - the training loop; :mod:`~nsflow_ros.train.cli` - ``nsflow-train``;
* :mod:`~nsflow_ros.train.export` - ONNX export; :mod:`~nsflow_ros.train.evaluate` - NSFlow vs classical;
* :mod:`~nsflow_ros.train.figures` - loss / validation PNGs; :mod:`~nsflow_ros.train.card` - the model card.

Without torch, importing this package raises :class:`TrainError` naming the install command.
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
