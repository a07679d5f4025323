"""The band layout of a narrow encoder on the CPU: the image cut into bands of rows, run as channels.

onnxruntime's CPU convolution of a map of few channels expands every 3x3 window into a column before a
matrix product, which costs far more than the multiply-adds it needs. The same network with the image
cut into ``bands`` horizontal bands, stacked as that many channels and every convolution taken per band,
runs on onnxruntime's blocked-channel (NCHWc) depthwise kernels instead, in well under the time
(docs/design.md). ``python -m nsflow_ros.train.bands MODEL`` writes that graph from a model's ONNX file as
its sibling ``<stem>.bands.onnx``.

The bands overlap by the receptive field of the two 3x3 convolutions (:data:`HALO` rows each side) and
carry as many replicated columns each side, so every output pixel is computed from its true neighbours
except on the image's first and last row and column: there the original pads its hidden layer, not the
image. Those four lines come from the original network run on the image's :data:`EDGE` outer rows
(top and bottom stacked) and columns (left and right side by side). The result equals the original's to
float32 rounding; :class:`~nsflow_ros.core.encoder.OnnxEncoder` checks that on a probe image before it
uses a layout, and otherwise runs the original.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from nsflow_ros.core.errors import EncoderError

__all__ = ["BANDS_SUFFIX", "EDGE", "HALO", "BandLayout", "bands_file"]

BANDS_SUFFIX = ".bands.onnx"
"""The suffix of a model's band-layout sibling: ``nsflow_encoder_fast.onnx`` ->
``nsflow_encoder_fast.bands.onnx``."""

HALO = 2
"""Rows (and replicated columns) of context each band carries on each side: the receptive-field radius of
two 3x3 convs."""

EDGE = HALO + 2
"""The image's outer rows (columns) on each side the original network runs on for the first and last output
row (column): each edge's receptive field stays within its own lines when the two sides are stacked."""

_SCALE = np.float32(1.0 / 255.0)  # the encoders' input scaling, pixel / 255 in float32


def bands_file(model: Path) -> Path:
    """Where the band layout of the model file ``model`` is (it may not exist)."""
    return model.with_name(model.stem + BANDS_SUFFIX)


class BandLayout:
    """Encode with a band-layout session: cut the image into bands, run, stack the bands, mend the edges.

    Args:
        session: the onnxruntime session of the ``.bands.onnx`` graph. Input ``bands`` (1, S, B + 2
            :data:`HALO`, W + 2 :data:`HALO`), each band B rows of the image with its context rows and
            replicated columns; one output, in memory the (1, d, S B, W) of the bands' rows one after the
            other.
        channels: d, the descriptor channels.
        original: the model's own network, (1, 1, h, w) float32 image / 255 -> (1, d, h, w): the edges.

    Raises:
        EncoderError: a session whose inputs and outputs are not those.
    """

    def __init__(self, session: Any, channels: int, original: Callable[[np.ndarray], np.ndarray]) -> None:
        inputs, outputs = session.get_inputs(), session.get_outputs()
        shape = inputs[0].shape if len(inputs) == 1 and len(outputs) == 1 else []
        bands = shape[1] if len(shape) == 4 else None
        out = outputs[0].shape if outputs else []
        # (1, S, rows, W) of one channel, or (d, pixels)
        out_ok = (out[:2] == [1, bands] and channels == 1) or (len(out) == 2 and out[0] == channels)
        if not isinstance(bands, int) or bands < 2 or not out_ok:
            found = f"inputs {[i.shape for i in inputs]}, outputs {[o.shape for o in outputs]}"
            raise EncoderError(
                f"band layout: expected one input (1, S, H, W) with S >= 2 and one output of {channels}"
                f" channel(s), found {found} (one written by an earlier version? write it again with"
                " python -m nsflow_ros.train.bands MODEL)"
            )
        self.session = session
        self.bands: int = bands
        self.channels = channels
        self._original = original
        self._input = inputs[0].name

    def fits(self, height: int, width: int) -> bool:
        """Whether an image of this size is encoded in bands (a short one is not worth the halos, a narrow
        one has no two separate column edges)."""
        return height >= 4 * self.bands and width >= 2 * EDGE

    def __call__(self, gray: np.ndarray) -> np.ndarray:
        """Encode a uint8 (H, W) gray image (``fits(H, W)``) into the original's (1, d, H, W) output.

        Shape:
            gray: (H, W) uint8. Returns (1, d, H, W) float32.
        """
        h, w = gray.shape
        s = self.bands
        b = -(-h // s)  # band height; the last band reaches past the image into its replicated border
        padded = cv2.copyMakeBorder(gray, HALO, s * b - h + HALO, HALO, HALO, cv2.BORDER_REPLICATE)
        row = padded.strides[0]
        # Band k is padded rows [k b, k b + b + 2 HALO): overlapping windows of one contiguous buffer.
        bands = np.ndarray((1, s, b + 2 * HALO, w + 2 * HALO), np.uint8, padded, 0, (0, b * row, row, 1))
        # Scaled as the original's input is: pixel / 255 in float32.
        (y,) = self.session.run(None, {self._input: np.multiply(bands, _SCALE, dtype=np.float32)})
        out = y.reshape(1, self.channels, s * b, w)[:, :, :h]
        # The outer lines from the original on the image's edge strips, both sides stacked.
        top_bottom = np.concatenate((gray[:EDGE], gray[-EDGE:]))
        left_right = np.concatenate((gray[:, :EDGE], gray[:, -EDGE:]), axis=1)
        rows, cols = (self._original(np.multiply(e[None, None], _SCALE, dtype=np.float32))
                      for e in (top_bottom, left_right))
        out[:, :, 0], out[:, :, -1] = rows[:, :, 0], rows[:, :, -1]
        out[:, :, :, 0], out[:, :, :, -1] = cols[:, :, :, 0], cols[:, :, :, -1]
        return out
