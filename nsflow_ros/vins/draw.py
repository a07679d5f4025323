"""The VINS debug image (``image_track``): features coloured by track length, arrows to previous positions.

Colours follow VINS-Fusion's ``drawTrack``: a camera-0 feature's circle goes from blue (new) to red (tracked
20 frames or more), BGR = (255 (1 - s), 0, 255 s) with s = min(1, track_count / 20); camera-1 features are
green; a green arrow points from each camera-0 feature to its position in the previous frame. Stereo
frames are drawn left | right.
"""

from __future__ import annotations

import cv2
import numpy as np

from nsflow_ros.core.errors import CoreError
from nsflow_ros.core.tracker import FrameFeatures

__all__ = ["FULL_TRACK", "draw_tracks", "track_colour"]

FULL_TRACK = 20
"""Track length drawn fully red (VINS: 20 frames)."""


def track_colour(track_count: int) -> tuple[int, int, int]:
    """BGR colour of a camera-0 feature tracked ``track_count`` frames."""
    s = min(1.0, track_count / FULL_TRACK)
    return (round(255 * (1 - s)), 0, round(255 * s))


def _bgr(image: np.ndarray) -> np.ndarray:
    if image.ndim == 2:
        return cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
    if image.ndim == 3 and image.shape[2] == 3:
        return image.copy()
    raise CoreError(f"debug image input must be (H, W) or (H, W, 3) uint8, got {image.shape}")


def _pt(p: np.ndarray) -> tuple[int, int]:
    return round(float(p[0])), round(float(p[1]))


def draw_tracks(frame: FrameFeatures, image0: np.ndarray, image1: np.ndarray | None = None) -> np.ndarray:
    """Draw a frame's features VINS-style.

    Args:
        frame: the tracker's output for these images.
        image0: camera-0 image (mono or BGR, uint8).
        image1: camera-1 image for stereo; drawn to the right of image0.

    Returns:
        the BGR debug image.

    Shape:
        image0, image1: (H, W) or (H, W, 3). Returns (H, W, 3), or (H, 2W, 3) with image1.
    """
    canvas = _bgr(image0)
    width = canvas.shape[1]
    if image1 is not None:
        canvas = np.hstack([canvas, _bgr(image1)])
    left = frame.cameras[0]
    for p, cnt in zip(left.pixels, left.track_counts, strict=True):
        cv2.circle(canvas, _pt(p), 2, track_colour(int(cnt)), 2)
    if image1 is not None and frame.num_cameras > 1:
        for p in frame.cameras[1].pixels:
            x, y = _pt(p)
            cv2.circle(canvas, (x + width, y), 2, (0, 255, 0), 2)
    for p, q in zip(left.pixels, left.previous, strict=True):
        if np.isfinite(q).all():
            cv2.arrowedLine(canvas, _pt(p), _pt(q), (0, 255, 0), 1, cv2.LINE_8, 0, 0.2)
    return canvas
