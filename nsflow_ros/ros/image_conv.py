"""NumPy -> sensor_msgs/Image fields, for the images the node publishes (the debug image).

Decoding is :func:`nsflow_ros.data.images.image_for_tracker`, shared with the offline tools. Works on any
object with the Image fields, so no ROS import is needed here.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from nsflow_ros.data.images import ImageDecodeError

__all__ = ["numpy_to_image_fields"]


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
