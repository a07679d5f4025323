"""ONNX export of the encoder, in the contract ``nsflow_ros.load_encoder`` checks.

Input "image" (1, c_in, H, W) float32 in [0, 1], output "descriptors" (1, d, H, W) float32, H and W
dynamic, opset 17, metadata_props name="nsflow-d{d}" plus the encoder spec. A network of a one-channel input
up to :data:`~nsflow_ros.train.bands.MAX_WIDTH` wide also gets its band layout
(:mod:`nsflow_ros.train.bands`) beside it.
"""

from __future__ import annotations

import json
import os
import warnings
from pathlib import Path

import torch

from nsflow_ros.optional import require
from nsflow_ros.train.errors import TrainError
from nsflow_ros.train.model import Encoder

__all__ = ["OPSET", "export_onnx"]

OPSET = 17


def export_onnx(model: Encoder, path: str | os.PathLike[str], metadata: dict[str, str] | None = None) -> Path:
    """Export an encoder to ONNX (parent folders are created); returns the path written.

    Args:
        model: the encoder.
        path: the .onnx file to write.
        metadata: extra metadata_props (string values), e.g. the training command.

    Raises:
        TrainError: a metadata value that is not a string.
    """
    onnx = require("onnx", "the ONNX export")
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    spec = model.spec
    was_training = model.training
    model = model.eval()
    dummy = torch.rand(1, spec.in_channels, 48, 64)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        torch.onnx.export(
            model,
            (dummy,),
            str(out),
            input_names=["image"],
            output_names=["descriptors"],
            dynamic_axes={"image": {2: "height", 3: "width"}, "descriptors": {2: "height", 3: "width"}},
            opset_version=OPSET,
            dynamo=False,
        )
    model.train(was_training)
    proto = onnx.load(str(out))
    props = {"name": f"nsflow-d{spec.d}", "spec": json.dumps(spec.as_dict()), **(metadata or {})}
    for key, value in props.items():
        if not isinstance(value, str):
            raise TrainError(f"metadata value for {key!r} must be a string, got {type(value).__name__}")
        entry = proto.metadata_props.add()
        entry.key, entry.value = key, value
    onnx.checker.check_model(proto)
    onnx.save(proto, str(out))
    # imported here: ``python -m nsflow_ros.train.bands`` runs that module after the package's imports
    from nsflow_ros.train.bands import MAX_WIDTH, export_bands

    if spec.in_channels == 1 and spec.width <= MAX_WIDTH:
        # A narrow network runs faster in the band layout on the CPU (nsflow_ros.core.bands).
        export_bands(out)
    return out
