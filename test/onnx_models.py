"""Test helper: tiny ONNX encoders built with onnx.helper (no torch needed)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper


def graph_encoder(path: Path, nodes: list, initializers: list, c_in: int = 1, d: int = 3) -> Path:
    """Write any graph from ``image`` (1, c_in, H, W) to ``descriptors`` (1, d, H, W), dynamic H and W."""
    graph = helper.make_graph(
        nodes,
        "graph_encoder",
        [helper.make_tensor_value_info("image", TensorProto.FLOAT, [1, c_in, "H", "W"])],
        [helper.make_tensor_value_info("descriptors", TensorProto.FLOAT, [1, d, "H", "W"])],
        initializer=initializers,
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    onnx.save(model, path)
    return path


def conv_encoder(path: Path, c_in: int = 1, d: int = 3, seed: int = 0, opset: int = 17) -> Path:
    """Write a 3x3 conv + sigmoid encoder (1, c_in, H, W) -> (1, d, H, W) with dynamic H and W."""
    rng = np.random.default_rng(seed)
    w = rng.normal(0, 0.5, (d, c_in, 3, 3)).astype(np.float32)
    b = rng.normal(0, 0.1, (d,)).astype(np.float32)
    nodes = [
        helper.make_node("Conv", ["image", "w", "b"], ["pre"], pads=[1, 1, 1, 1]),
        helper.make_node("Sigmoid", ["pre"], ["descriptors"]),
    ]
    graph = helper.make_graph(
        nodes,
        "tiny_encoder",
        [helper.make_tensor_value_info("image", TensorProto.FLOAT, [1, c_in, "H", "W"])],
        [helper.make_tensor_value_info("descriptors", TensorProto.FLOAT, [1, d, "H", "W"])],
        initializer=[numpy_helper.from_array(w, "w"), numpy_helper.from_array(b, "b")],
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", opset)])
    model.ir_version = 8
    helper.set_model_props(model, {"name": f"tiny-d{d}"})
    onnx.checker.check_model(model)
    onnx.save(model, path)
    return path


def reference_conv(image01: np.ndarray, path: Path) -> np.ndarray:
    """Evaluate the model written by conv_encoder in NumPy: (c_in, H, W) -> (H, W, d)."""
    model = onnx.load(path)
    inits = {t.name: numpy_helper.to_array(t) for t in model.graph.initializer}
    w, b = inits["w"], inits["b"]
    c_in, h, wd = image01.shape
    pad = np.pad(image01, ((0, 0), (1, 1), (1, 1)))
    out = np.zeros((w.shape[0], h, wd), np.float64)
    for o in range(w.shape[0]):
        acc = np.full((h, wd), b[o], np.float64)
        for c in range(c_in):
            for dy in range(3):
                for dx in range(3):
                    acc += w[o, c, dy, dx] * pad[c, dy : dy + h, dx : dx + wd]
        out[o] = 1.0 / (1.0 + np.exp(-acc))
    return out.transpose(1, 2, 0)
