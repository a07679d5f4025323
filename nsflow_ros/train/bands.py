"""The band layout of an exported encoder of a one-channel input (:mod:`nsflow_ros.core.bands`): the same
weights in a graph that takes the image cut into bands of rows as channels, every convolution per band.

Written beside the model as ``<stem>.bands.onnx``; the tracker uses it on the CPU where it reproduces the
model (checked at load time). ``python -m nsflow_ros.train.bands MODEL`` writes it for an exported model;
a network up to :data:`MAX_WIDTH` channels wide gains, a wider one is slower in bands (docs/design.md).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from nsflow_ros.core.bands import HALO, bands_file
from nsflow_ros.optional import require
from nsflow_ros.train.errors import TrainError

__all__ = ["BANDS", "MAX_WIDTH", "export_bands", "main"]

BANDS = 16
"""Bands of the written layout: two blocks of onnxruntime's 8-channel AVX2 kernels, one of AVX-512's."""

MAX_WIDTH = 3
"""The widest network that :func:`~nsflow_ros.train.export.export_onnx` writes a layout for: the hidden 3x3
convolution costs width^2 per-band passes, and at width 8 the layout is slower than the model's own graph
(docs/design.md)."""

# The encoder's layers (nsflow_ros.train.model.Encoder): kernel sizes of its four convolutions.
_KERNELS = (3, 3, 1, 1)
_HEADS = ("Sigmoid", "Relu")


def export_bands(path: str | os.PathLike[str], bands: int = BANDS) -> Path:
    """Write the band layout of the exported encoder ``path`` beside it; returns the path written.

    Input: ``bands`` (1, bands, B + 2 HALO, W + 2 HALO), each band B rows of the image with HALO rows of
    context each side and HALO replicated columns each side. Output: ``descriptors``, in memory the
    original's (1, d, bands * B, W) of the bands' rows one after the other; only its first and last row
    and column differ from the original's (the original pads the hidden layer, not the image), and
    :class:`~nsflow_ros.core.bands.BandLayout` mends them.

    Every 3x3 convolution becomes per-band (depthwise) convolutions, one per pair of input and output
    channel, summed: onnxruntime runs those in its blocked-channel kernels, where a grouped convolution of
    several channels per band it does not. The 1x1 head then runs on the hidden channels as two matrix
    products (which the blocked-channel rewrite leaves alone: on a few channels it is slower). A network
    one channel wide with one output channel gets its head folded into per-band 1x1 convolutions instead:
    a hidden unit whose ReLU is the identity on the non-negative map before it joins one linear term, the
    others stay a ReLU (or a clip at 0 for a negative output weight) each.

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
    layers = [(weights[c.input[1]], weights[c.input[2]]) for c in convs]
    graph = _Graph(bands)
    hidden = ["bands"]  # one tensor per channel, band k in its channel k
    for w, b in layers[:2]:  # the 3x3 convs: context rows and columns, no padding
        hidden = [graph.channel(hidden, w[c], b[c]) for c in range(w.shape[0])]
    if len(hidden) == 1 and channels == 1:
        current = _folded_head(graph, hidden[0], *layers[2], *layers[3])
        out_shape: list[int | str] = [1, bands, "rows", "width"]
    else:
        # (channels, bands * rows * width): each hidden channel's bands one after the other
        stacked = graph.node("Concat", hidden, axis=1) if len(hidden) > 1 else hidden[0]
        current = graph.node("Reshape", [stacked, graph.const(np.array([len(hidden), -1]), np.int64)])
        current = graph.node("Relu", [graph.matmul(current, *layers[2])])
        current = graph.matmul(current, *layers[3])
        out_shape = [channels, "pixels"]
    if heads:
        current = graph.node(heads[0], [current])
    graph.nodes.append(helper.make_node("Identity", [current], ["descriptors"]))
    onnx_graph = helper.make_graph(
        graph.nodes, "nsflow_bands",
        [helper.make_tensor_value_info("bands", TensorProto.FLOAT, [1, bands, "rows", "width"])],
        [helper.make_tensor_value_info("descriptors", TensorProto.FLOAT, out_shape)],
        [numpy_helper.from_array(v, k) for k, v in graph.inits.items()],
    )
    layout = helper.make_model(onnx_graph, opset_imports=[helper.make_opsetid("", 17)])
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


class _Graph:
    """The nodes and weights of a band graph."""

    def __init__(self, bands: int) -> None:
        self.bands = bands
        self.nodes: list[object] = []
        self.inits: dict[str, np.ndarray] = {}

    def node(self, op: str, inputs: list[str], **attrs: object) -> str:
        from onnx import helper

        out = f"n{len(self.nodes)}"
        self.nodes.append(helper.make_node(op, inputs, [out], **attrs))
        return out

    def const(self, value: object, dtype: type = np.float32) -> str:
        name = f"c{len(self.inits)}"
        self.inits[name] = np.asarray(value, dtype)
        return name

    def conv(self, x: str, w: np.ndarray, b: float, activation: str | None = None) -> str:
        """The 2-d kernel ``w`` and bias ``b`` on every band of ``x`` (a depthwise convolution), then
        ``activation`` (None, "Relu" or "Clip", the latter to at most 0)."""
        s, k = self.bands, np.shape(w)
        weight = np.broadcast_to(np.asarray(w, np.float32), (s, 1, *k))
        out = self.node("Conv", [x, self.const(weight), self.const(np.full(s, b))], group=s,
                        kernel_shape=list(k))
        if activation == "Relu":
            return self.node("Relu", [out])
        if activation == "Clip":
            return self.node("Clip", [out, "", self.const(0.0)])
        return out

    def channel(self, inputs: list[str], w: np.ndarray, b: float) -> str:
        """One output channel of a convolution and its ReLU: the sum over i of ``w[i]`` on ``inputs[i]``,
        plus ``b``, on every band."""
        if len(inputs) == 1:
            return self.conv(inputs[0], w[0], b, "Relu")
        pairs = enumerate(zip(inputs, w, strict=True))
        terms = [self.conv(x, k, b if i == 0 else 0.0) for i, (x, k) in pairs]
        return self.node("Relu", [self.node("Sum", terms)])

    def matmul(self, x: str, w: np.ndarray, b: np.ndarray) -> str:
        """A 1x1 convolution of (channels, pixels) ``x``: w @ x + b."""
        return self.node("Gemm", [self.const(w[:, :, 0, 0]), x, self.const(b[:, None])])


def _folded_head(
    graph: _Graph, h: str, w3: np.ndarray, b3: np.ndarray, w4: np.ndarray, b4: np.ndarray
) -> str:
    """The 1x1 head of a one-channel hidden map ``h`` (>= 0, after a ReLU) into one output channel, as
    per-band 1x1 convolutions: y = b4 + sum_j w4_j relu(w3_j h + b3_j)."""
    w3, b3, w4 = w3.ravel().astype(np.float64), b3.astype(np.float64), w4.ravel().astype(np.float64)
    linear = (w3 >= 0) & (b3 >= 0)  # relu(a) = a for every h >= 0
    zero = (w3 <= 0) & (b3 <= 0)  # relu(a) = 0 for every h >= 0
    terms = []
    for j in np.flatnonzero(~linear & ~zero & (w4 != 0)):
        # w4 relu(a) = relu(w4 a) for w4 > 0, min(w4 a, 0) for w4 < 0
        terms.append(graph.conv(h, [[w4[j] * w3[j]]], w4[j] * b3[j], "Relu" if w4[j] > 0 else "Clip"))
    out = graph.conv(h, [[w4[linear] @ w3[linear]]], b4[0] + w4[linear] @ b3[linear])
    for term in terms:  # onnxruntime adds each into the convolution before it
        out = graph.node("Add", [out, term])
    return out


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
