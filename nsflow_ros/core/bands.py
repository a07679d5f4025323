"""The band layout of a one-channel encoder on the CPU: the image cut into bands of rows, run as channels.

onnxruntime's CPU convolution of a one-channel map expands every 3x3 window into a column before a
matrix product, which costs far more than the nine multiply-adds it needs. The same network with the
image cut into ``bands`` horizontal bands, stacked as that many channels and every convolution grouped
by band, runs on onnxruntime's blocked-channel (NCHWc) depthwise kernels instead, in well under the time
(docs/design.md). ``python -m nsflow_ros.train.bands MODEL`` writes that graph from a model's ONNX file as
its sibling ``<stem>.bands.onnx``.

The bands overlap by the receptive field of the two 3x3 convolutions (:data:`HALO` rows each side), so
every output row is computed from its true neighbours except the image's first and last: there the
original pads its hidden layer, not the image. The same graph therefore also runs the original network on
the image's :data:`EDGE_ROWS` top and bottom rows, stacked, for those two rows. The result equals the
original's to float32 rounding; :class:`~nsflow_ros.core.encoder.OnnxEncoder` checks that on a probe image
before it uses a layout, and otherwise runs the original.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import cv2
import numpy as np

from nsflow_ros.core.errors import EncoderError

__all__ = ["BANDS_SUFFIX", "EDGE_ROWS", "HALO", "BandLayout", "bands_file"]

BANDS_SUFFIX = ".bands.onnx"
"""The suffix of a model's band-layout sibling: ``nsflow_encoder_fast.onnx`` ->
``nsflow_encoder_fast.bands.onnx``."""

HALO = 2
"""Rows of context each band carries on each side: the receptive-field radius of two 3x3 convs."""

EDGE_ROWS = HALO + 2
"""The image's top and bottom rows the original network runs on for the first and last output row: each
edge's receptive field stays within its own rows when the two are stacked."""

_SCALE = np.float32(1.0 / 255.0)  # the encoders' input scaling, pixel / 255 in float32


def bands_file(model: Path) -> Path:
    """Where the band layout of the model file ``model`` is (it may not exist)."""
    return model.with_name(model.stem + BANDS_SUFFIX)


class BandLayout:
    """Encode with a band-layout session: cut the image into bands, run, stack the bands, mend two rows.

    Args:
        session: the onnxruntime session of the ``.bands.onnx`` graph. Inputs: ``bands`` (1, S, B + 2
            :data:`HALO`, W + 2), each band B rows of the image with its context and one replicated column
            each side; ``edges`` (1, 1, 2 :data:`EDGE_ROWS`, W), the image's top and bottom rows. Outputs:
            (1, S * d, B, W) and the original's (1, d, 2 :data:`EDGE_ROWS`, W) of the edges.
        channels: d, the descriptor channels.

    Raises:
        EncoderError: a session whose inputs and outputs are not those.
    """

    def __init__(self, session: Any, channels: int) -> None:
        inputs, outputs = session.get_inputs(), session.get_outputs()
        shapes = [i.shape for i in inputs] + [o.shape for o in outputs]
        bands = shapes[0][1] if len(shapes) == 4 and all(len(s) == 4 for s in shapes) else None
        if (not isinstance(bands, int) or bands < 2 or shapes[1][1] != 1 or shapes[2][1] != bands * channels
                or shapes[3][1] != channels):
            raise EncoderError(
                f"band layout: expected inputs (1, S, H, W), (1, 1, H, W) with S >= 2 and outputs (1, S *"
                f" {channels}, H, W), (1, {channels}, H, W); found {shapes}"
            )
        self.session = session
        self.bands: int = bands
        self.channels = channels
        self._inputs = [i.name for i in inputs]

    def fits(self, height: int) -> bool:
        """Whether an image this tall is encoded in bands (a short one is not worth the halos)."""
        return height >= 4 * self.bands

    def __call__(self, gray: np.ndarray) -> np.ndarray:
        """Encode a uint8 (H, W) gray image (``fits(H)``) into the original's (1, d, H, W) output.

        Shape:
            gray: (H, W) uint8. Returns (1, d, H, W) float32.
        """
        h, w = gray.shape
        s, d = self.bands, self.channels
        b = -(-h // s)  # band height; the last band reaches past the image into its replicated border
        padded = cv2.copyMakeBorder(gray, HALO, s * b - h + HALO, 1, 1, cv2.BORDER_REPLICATE)
        row = padded.strides[0]
        # Band k is padded rows [k b, k b + b + 2 HALO): overlapping windows of one contiguous buffer.
        bands = np.ndarray((1, s, b + 2 * HALO, w + 2), np.uint8, padded, 0, (0, b * row, row, 1))
        edges = np.concatenate((gray[:EDGE_ROWS], gray[-EDGE_ROWS:]))[None, None]
        # Scaled as the original's input is: pixel / 255 in float32.
        x = [np.multiply(a, _SCALE, dtype=np.float32) for a in (bands, edges)]
        y, mended = self.session.run(None, dict(zip(self._inputs, x, strict=True)))
        # Band k's channels are k d ... k d + d - 1 (groups are consecutive): stack the bands per channel.
        y = y.reshape(s, d, b, w)
        out = (y[:, 0] if d == 1 else y.transpose(1, 0, 2, 3)).reshape(1, d, s * b, w)[:, :, :h]
        out[:, :, 0], out[:, :, -1] = mended[:, :, 0], mended[:, :, -1]
        return out
