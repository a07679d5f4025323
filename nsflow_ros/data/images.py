"""sensor_msgs/Image -> NumPy: the one decoder of the node, the replayer, the offline run and the feature bag.

:func:`decode_image` returns the pixels as the encoding stores them (what a record keeps, so it can be
re-serialised); :func:`tracker_image` turns them into what the tracker is given: mono8 (H, W) for mono
encodings, BGR (H, W, 3) for colour ones, 16-bit shifted to its 8 most significant bits. The tracker gets
the image as received rather than a gray copy so that a colour encoder sees colour and the debug image
stays in colour; for a gray encoder (the shipped models) both give the same features.

Works on any object with the Image fields (the header is not used), so no ROS import is needed.
"""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np

from nsflow_ros.data.errors import DataError

__all__ = ["ENCODINGS", "ImageDecodeError", "decode_image", "image_for_tracker", "to_gray", "tracker_image"]

ENCODINGS: dict[str, tuple[np.dtype, int]] = {
    "mono8": (np.dtype(np.uint8), 1),
    "8UC1": (np.dtype(np.uint8), 1),
    "mono16": (np.dtype(np.uint16), 1),
    "16UC1": (np.dtype(np.uint16), 1),
    "bgr8": (np.dtype(np.uint8), 3),
    "rgb8": (np.dtype(np.uint8), 3),
    "bgra8": (np.dtype(np.uint8), 4),
    "rgba8": (np.dtype(np.uint8), 4),
}
"""The accepted encodings, with (dtype, channels)."""

_TO_BGR = {"rgb8": cv2.COLOR_RGB2BGR, "bgra8": cv2.COLOR_BGRA2BGR, "rgba8": cv2.COLOR_RGBA2BGR}
_TO_GRAY = {"bgr8": cv2.COLOR_BGR2GRAY, "rgb8": cv2.COLOR_RGB2GRAY, "bgra8": cv2.COLOR_BGRA2GRAY,
            "rgba8": cv2.COLOR_RGBA2GRAY}


class ImageDecodeError(DataError):
    """An image message cannot be decoded.

    Attributes:
        cause: a short key of the failure kind ("encoding:<name>", "size", "step", "truncated",
            "oversized"), for counting failures by kind.
    """

    def __init__(self, message: str, cause: str) -> None:
        super().__init__(message)
        self.cause = cause


def decode_image(msg: Any, topic: str = "") -> tuple[np.ndarray, str]:
    """Pixels of a sensor_msgs/Image, honouring ``step`` (padded rows) and ``is_bigendian``.

    Args:
        msg: the message (fields encoding, height, width, step, is_bigendian, data).
        topic: named in error messages ("" = none).

    Returns:
        ``(image, encoding)``: a writable C-contiguous copy in native byte order.

    Raises:
        ImageDecodeError: an unsupported encoding, zero size, a step shorter than a row, or data shorter or
            longer than step x height.

    Shape:
        image: (H, W) for mono encodings, (H, W, C) for colour ones; uint8, or uint16 for 16-bit ones.
    """
    enc = str(msg.encoding)
    where = f"{topic}: " if topic else ""
    if enc not in ENCODINGS:
        raise ImageDecodeError(
            f"{where}unsupported image encoding {enc!r}; accepted: {', '.join(ENCODINGS)}", f"encoding:{enc}"
        )
    dtype, ch = ENCODINGS[enc]
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    if h <= 0 or w <= 0:
        raise ImageDecodeError(f"{where}{enc} image has zero size: {w}x{h}", "size")
    row = w * ch * dtype.itemsize
    if step < row:
        raise ImageDecodeError(
            f"{where}{enc} image {w}x{h}: step {step} is shorter than a row ({w} px x {ch * dtype.itemsize} "
            f"bytes = {row})",
            "step",
        )
    data = msg.data if isinstance(msg.data, np.ndarray) else np.frombuffer(msg.data, dtype=np.uint8)
    data = data.reshape(-1).view(np.uint8)
    expected = step * h
    if data.size < expected:
        raise ImageDecodeError(
            f"{where}{enc} image {w}x{h}, step {step}: data is truncated, {data.size} bytes instead of "
            f"{expected}",
            "truncated",
        )
    if data.size > expected:
        raise ImageDecodeError(
            f"{where}{enc} image {w}x{h}, step {step}: data has {data.size} bytes, more than step x height = "
            f"{expected}",
            "oversized",
        )
    rows = data.reshape(h, step)[:, :row]
    wire = dtype.newbyteorder(">" if msg.is_bigendian else "<")
    pixels = np.ascontiguousarray(rows).view(wire).astype(dtype)  # a copy in native order
    return pixels.reshape((h, w) if ch == 1 else (h, w, ch)), enc


def _check_encoding(encoding: str) -> None:
    if encoding not in ENCODINGS:
        raise DataError(f"unknown image encoding {encoding!r}; supported: {', '.join(ENCODINGS)}")


def to_gray(image: np.ndarray, encoding: str) -> np.ndarray:
    """8-bit gray version of decoded pixels. Shape: (H, W[, C]) -> (H, W) uint8.

    Raises:
        DataError: for an unknown encoding.
    """
    _check_encoding(encoding)
    if ENCODINGS[encoding][0].itemsize == 2:
        return (image >> 8).astype(np.uint8)
    if encoding in _TO_GRAY:
        return cv2.cvtColor(image, _TO_GRAY[encoding])
    return image


def tracker_image(image: np.ndarray, encoding: str) -> np.ndarray:
    """What the tracker is given for decoded pixels: mono8 as it is, 16-bit shifted to 8 bits, colour as BGR.

    Raises:
        DataError: for an unknown encoding.

    Shape:
        (H, W[, C]) -> (H, W) uint8 for mono encodings, (H, W, 3) uint8 BGR for colour ones.
    """
    _check_encoding(encoding)
    if ENCODINGS[encoding][1] == 1:
        return to_gray(image, encoding)
    if encoding in _TO_BGR:
        return cv2.cvtColor(np.ascontiguousarray(image), _TO_BGR[encoding])
    return image


def image_for_tracker(msg: Any, topic: str = "") -> np.ndarray:
    """Decode a sensor_msgs/Image into the array the tracker is given (:func:`tracker_image`).

    Raises:
        ImageDecodeError: as :func:`decode_image`.
    """
    return tracker_image(*decode_image(msg, topic))
