"""The band layout of an exported one-channel encoder (:mod:`nsflow_ros.core.bands`): the same weights in
a graph that takes the image cut into bands of rows as channels, every convolution grouped by band, and
runs the original network on the image's edge rows beside it.

Written beside the model as ``<stem>.bands.onnx``; the tracker uses it on the CPU where it reproduces the
model (checked at load time). ``python -m nsflow_ros.train.bands MODEL`` writes it for an exported model;
only a one-channel network (width 1) gains: a wider one is slower in bands (docs/design.md).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from nsflow_ros.core.bands import HALO, bands_file
from nsflow_ros.optional import require
from nsflow_ros.train.errors import TrainError

__all__ = ["BANDS", "export_bands", "main"]

BANDS = 16
"""Bands of the written layout: two blocks of onnxruntime's 8-channel AVX2 kernels, one of AVX-512's."""

# The encoder's layers (nsflow_ros.train.model.Encoder): kernel sizes of its four convolutions.
_KERNELS = (3, 3, 1, 1)
_HEADS = ("Sigmoid", "Relu")


def export_bands(path: str | os.PathLike[str], bands: int = BANDS) -> Path:
    """Write the band layout of the exported encoder ``path`` beside it; returns the path written.

    Inputs: ``bands`` (1, bands, B + 2 HALO, W + 2), each band B rows of the image with HALO rows of context
    each side and one replicated column each side; ``edges`` (1, 1, R, W), rows of the image. Outputs:
    ``descriptors`` (1, bands * d, B, W) and ``edge_descriptors`` (1, d, R, W), the original network's
    output for ``edges``, padded as the original pads.

    Raises:
        TrainError: an unreadable file, a graph that is not the encoder's (four convolutions, 3x3, 3x3,
            1x1, 1x1, of a one-channel input), or ``bands < 2``.
    """
    onnx = require("onnx", "writing the band layout")
    from onnx import TensorProto, helper, numpy_helper

    source = Path(path)
    if bands < 2:
        raise TrainError(f"bands must be >= 2, got {bands}")
    try:
        proto = onnx.load(str(source))
    except (OSError, ValueError) as err:
        raise TrainError(f"cannot read the ONNX model {source}: {err}") from err
    weights = {i.name: numpy_helper.to_array(i) for i in proto.graph.initializer}
    for node in proto.graph.node:  # the exporter shares equal initializers through Identity nodes
        if node.op_type == "Identity" and node.input[0] in weights:
            weights[node.output[0]] = weights[node.input[0]]
    convs = [n for n in proto.graph.node if n.op_type == "Conv"]
    found = [weights[n.input[1]].shape for n in convs if n.input[1] in weights]
    if len(found) != len(_KERNELS) or [s[2] for s in found] != list(_KERNELS) or found[0][1] != 1:
        raise TrainError(
            f"{source}: expected the encoder's four convolutions (3x3, 3x3, 1x1, 1x1) of a one-channel"
            f" input, found weights {found}"
        )
    heads = [n.op_type for n in proto.graph.node if n.op_type in _HEADS and n.input[0] == convs[-1].output[0]]
    channels = found[-1][0]
    inits: dict[str, np.ndarray] = {
        "pad_columns": np.array([0, 0, 0, 1, 0, 0, 0, 1], np.int64),
        "pad_both": np.array([0, 0, 1, 1, 0, 0, 1, 1], np.int64),
    }
    nodes = []

    def network(x: str, prefix: str, groups: int, pads: str, first_pads: str | None) -> str:
        """The encoder's layers on ``x``, each conv in ``groups`` copies; returns the output's name."""
        current = x
        for k, conv in enumerate(convs):
            w, b = f"{prefix}w{k}", f"{prefix}b{k}"
            inits[w] = np.concatenate([weights[conv.input[1]]] * groups)
            inits[b] = np.concatenate([weights[conv.input[2]]] * groups)
            if _KERNELS[k] == 3 and (k > 0 or first_pads is not None):
                # Padded as the original pads: replicated borders (a band's rows need none: context).
                nodes.append(helper.make_node("Pad", [current, pads if k else first_pads], [f"{prefix}p{k}"],
                                              mode="edge"))
                current = f"{prefix}p{k}"
            nodes.append(helper.make_node("Conv", [current, w, b], [f"{prefix}c{k}"], group=groups,
                                          kernel_shape=[_KERNELS[k]] * 2))
            current = f"{prefix}c{k}"
            if k < len(convs) - 1:
                nodes.append(helper.make_node("Relu", [current], [f"{prefix}r{k}"]))
                current = f"{prefix}r{k}"
        if heads:
            nodes.append(helper.make_node(heads[0], [current], [f"{prefix}head"]))
            current = f"{prefix}head"
        return current

    # The bands come with their context rows and padded columns; the edges are the original's input.
    out = network("bands", "band_", bands, "pad_columns", None)
    nodes.append(helper.make_node("Identity", [out], ["descriptors"]))
    out = network("edges", "edge_", 1, "pad_both", "pad_both")
    nodes.append(helper.make_node("Identity", [out], ["edge_descriptors"]))

    def tensor(name: str, ch: int) -> object:
        return helper.make_tensor_value_info(name, TensorProto.FLOAT, [1, ch, f"{name}_h", f"{name}_w"])

    graph = helper.make_graph(
        nodes, "nsflow_bands", [tensor("bands", bands), tensor("edges", 1)],
        [tensor("descriptors", bands * channels), tensor("edge_descriptors", channels)],
        [numpy_helper.from_array(v, k) for k, v in inits.items()],
    )
    layout = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    layout.ir_version = proto.ir_version
    props = {p.key: p.value for p in proto.metadata_props}
    meta = {"name": f"{props.get('name', source.stem)} (bands)", "layout": "bands", "bands": str(bands),
            "halo": str(HALO), "source": source.name}
    for key, value in meta.items():
        entry = layout.metadata_props.add()
        entry.key, entry.value = key, value
    onnx.checker.check_model(layout)
    target = bands_file(source)
    onnx.save(layout, str(target))
    return target


def main(args: list[str] | None = None) -> int:
    """``python -m nsflow_ros.train.bands MODEL [--bands N]``: :func:`export_bands` from the shell."""
    import argparse

    parser = argparse.ArgumentParser(prog="python -m nsflow_ros.train.bands", description=main.__doc__)
    parser.add_argument("model", help="the exported encoder (.onnx); the layout is written beside it")
    parser.add_argument("--bands", type=int, default=BANDS, help=f"bands (default {BANDS})")
    opts = parser.parse_args(args)
    try:
        print(export_bands(opts.model, opts.bands))
    except TrainError as err:
        print(f"nsflow_ros.train.bands: {err}")
        return 1
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
