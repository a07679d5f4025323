"""sensor_msgs/Image -> NumPy, with the checks a front-end that must never crash needs.

Accepted encodings: mono8 and 8UC1 (mono), mono16 (shifted to 8 bits, byte order from ``is_bigendian``),
bgr8, rgb8, bgra8, rgba8 (converted to BGR). Rows are read with the message's ``step``, so padded rows
work. Anything else raises :class:`ImageDecodeError` with a message naming the encoding or the sizes;
``cause`` is a short key ("encoding:<name>", "step", "truncated", ...) for counting failures by kind.

Works on any object with the Image fields (header is not used), so no ROS import is needed here.
"""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np

from nsflow_ros.errors import NSFlowError

__all__ = ["ENCODINGS", "ImageDecodeError", "image_to_numpy", "numpy_to_image_fields"]

# encoding -> (channels, bytes per channel)
ENCODINGS: dict[str, tuple[int, int]] = {
    "mono8": (1, 1),
    "8UC1": (1, 1),
    "mono16": (1, 2),
    "bgr8": (3, 1),
    "rgb8": (3, 1),
    "bgra8": (4, 1),
    "rgba8": (4, 1),
}
"""The encodings the tracker accepts, with (channels, bytes per channel)."""


class ImageDecodeError(NSFlowError):
    """An image message cannot be decoded.

    Attributes:
        cause: a short key of the failure kind, for once-per-cause logging.
    """

    def __init__(self, message: str, cause: str) -> None:
        super().__init__(message)
        self.cause = cause


def image_to_numpy(msg: Any) -> np.ndarray:
    """Decode a sensor_msgs/Image into a mono or BGR uint8 array.

    Args:
        msg: the message (fields encoding, height, width, step, is_bigendian, data).

    Returns:
        (H, W) uint8 for mono encodings, (H, W, 3) uint8 BGR for colour ones. The array owns its data.

    Raises:
        ImageDecodeError: on an unsupported encoding, zero size, a step shorter than a row, or data shorter
            or longer than step * height.
    """
    enc = str(msg.encoding)
    if enc not in ENCODINGS:
        raise ImageDecodeError(
            f"unsupported image encoding {enc!r}; accepted: {', '.join(ENCODINGS)}", f"encoding:{enc}"
        )
    ch, depth = ENCODINGS[enc]
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    if h <= 0 or w <= 0:
        raise ImageDecodeError(f"{enc} image has zero size: {w}x{h}", "size")
    row = w * ch * depth
    if step < row:
        raise ImageDecodeError(
            f"{enc} image {w}x{h}: step {step} is shorter than a row ({w} px x {ch * depth} bytes = {row})",
            "step",
        )
    buf = np.frombuffer(msg.data, dtype=np.uint8)
    expected = step * h
    if buf.size < expected:
        raise ImageDecodeError(
            f"{enc} image {w}x{h}, step {step}: data is truncated, {buf.size} bytes instead of {expected}",
            "truncated",
        )
    if buf.size > expected:
        raise ImageDecodeError(
            f"{enc} image {w}x{h}, step {step}: data has {buf.size} bytes, "
            f"more than step x height = {expected}",
            "oversized",
        )
    rows = buf.reshape(h, step)[:, :row]
    if depth == 2:
        big = bool(msg.is_bigendian)
        values = rows.copy().view(">u2" if big else "<u2").reshape(h, w)
        return (values >> 8).astype(np.uint8)  # the 8 most significant bits, as a mono16 -> mono8 shift
    img = rows.reshape(h, w, ch) if ch > 1 else rows.reshape(h, w)
    if enc in ("mono8", "8UC1", "bgr8"):
        return np.array(img, order="C")
    code = {"rgb8": cv2.COLOR_RGB2BGR, "bgra8": cv2.COLOR_BGRA2BGR, "rgba8": cv2.COLOR_RGBA2BGR}[enc]
    return cv2.cvtColor(np.ascontiguousarray(img), code)


def numpy_to_image_fields(image: np.ndarray, encoding: str | None = None) -> dict[str, Any]:
    """The Image fields (without header) for a uint8 mono or BGR array: for publishing and tests.

    Args:
        image: (H, W) or (H, W, 3) uint8.
        encoding: defaults to mono8 / bgr8.

    Returns:
        dict with height, width, encoding, is_bigendian, step, data (bytes).
    """
    if image.dtype != np.uint8 or image.ndim not in (2, 3):
        got = f"{image.dtype} {image.shape}"
        raise ImageDecodeError(f"expected a uint8 (H, W) or (H, W, 3) array, got {got}", "array")
    arr = np.ascontiguousarray(image)
    h, w = arr.shape[:2]
    ch = 1 if arr.ndim == 2 else arr.shape[2]
    enc = encoding or ("mono8" if ch == 1 else "bgr8")
    return {
        "height": h,
        "width": w,
        "encoding": enc,
        "is_bigendian": 0,
        "step": w * ch,
        "data": arr.tobytes(),
    }
