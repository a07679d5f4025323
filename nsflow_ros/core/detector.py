"""Corner detection: OpenCV's GFTT (Shi-Tomasi), as the VINS front-end uses it."""

from __future__ import annotations

import cv2
import numpy as np

from nsflow_ros.core.errors import CoreError

__all__ = ["detect_corners"]


def detect_corners(
    gray: np.ndarray,
    max_corners: int,
    *,
    quality: float = 0.01,
    min_distance: float = 30.0,
    mask: np.ndarray | None = None,
) -> np.ndarray:
    """Detect up to ``max_corners`` GFTT corners (x, y) on a gray image, strongest first.

    Args:
        quality: GFTT quality level relative to the best corner.
        min_distance: minimum distance between corners in pixels.
        mask: uint8; corners only where it is non-zero.

    Raises:
        CoreError: on a wrong image or mask shape/dtype.

    Shape:
        gray: (H, W) uint8. mask: (H, W) uint8. Returns (N, 2) float64.
    """
    if not isinstance(gray, np.ndarray) or gray.ndim != 2 or gray.dtype != np.uint8:
        desc = f"{gray.shape} {gray.dtype}" if isinstance(gray, np.ndarray) else type(gray).__name__
        raise CoreError(f"detect_corners expects an (H, W) uint8 image, got {desc}")
    if mask is not None and (mask.shape != gray.shape or mask.dtype != np.uint8):
        raise CoreError(f"mask must be {gray.shape} uint8 like the image, got {mask.shape} {mask.dtype}")
    if max_corners <= 0:
        return np.zeros((0, 2))
    found = cv2.goodFeaturesToTrack(gray, int(max_corners), quality, min_distance, mask=mask)
    if found is None:
        return np.zeros((0, 2))
    return found.reshape(-1, 2).astype(np.float64)
