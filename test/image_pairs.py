"""Test helper: image pairs with exactly known motion, made from real photos that ship with scikit-image.

Frame 2 is rendered at 4x resolution with the known warp and area-downsampled, which approximates an
ideal sub-pixel warp far better than interpolating the low-resolution image (uint8 rounding remains).
"""

from __future__ import annotations

import cv2
import numpy as np
from skimage import data as skdata

UP = 4


def texture(name: str, size: tuple[int, int] = (752, 480)) -> np.ndarray:
    img = getattr(skdata, name)()
    if img.ndim == 3:
        img = cv2.cvtColor(img[..., :3], cv2.COLOR_RGB2GRAY)
    return cv2.resize(img, size, interpolation=cv2.INTER_AREA)


def warp_pair(gray: np.ndarray, homography: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Return (frame1, frame2) with frame2(H x) = frame1(x) for the 3x3 pixel homography H."""
    h, w = gray.shape
    big = cv2.resize(gray, (w * UP, h * UP), interpolation=cv2.INTER_CUBIC).astype(np.float32)
    # low-res pixel centre x maps to high-res coordinate UP * x + (UP - 1) / 2
    s = np.array([[UP, 0, (UP - 1) / 2], [0, UP, (UP - 1) / 2], [0, 0, 1]], np.float64)
    hb = s @ homography @ np.linalg.inv(s)
    size = (w * UP, h * UP)
    big2 = cv2.warpPerspective(big, hb, size, flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
    a = cv2.resize(big, (w, h), interpolation=cv2.INTER_AREA)
    b = cv2.resize(big2, (w, h), interpolation=cv2.INTER_AREA)
    return np.clip(a + 0.5, 0, 255).astype(np.uint8), np.clip(b + 0.5, 0, 255).astype(np.uint8)


def apply_h(homography: np.ndarray, pts: np.ndarray) -> np.ndarray:
    ph = np.c_[pts, np.ones(len(pts))] @ homography.T
    return ph[:, :2] / ph[:, 2:]


def translation(tx: float, ty: float) -> np.ndarray:
    return np.array([[1, 0, tx], [0, 1, ty], [0, 0, 1]], np.float64)


def rotation(deg: float, center: tuple[float, float]) -> np.ndarray:
    m = cv2.getRotationMatrix2D(center, deg, 1.0)
    return np.vstack([m, [0, 0, 1]])
