"""Test helper: image sequences with exactly known motion, rendered from a real photo of scikit-image.

Every frame k is the base texture warped by a 3x3 homography M_k (base pixel -> frame-k pixel), so the
true position in frame k of a point seen at x in frame j is M_k M_j^-1 x. Frames are rendered at 2x and
area-downsampled, which makes sub-pixel motion realistic (no bilinear blur that depends on the shift).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from skimage import data as skdata

from nsflow_ros.core.camera import PinholeCamera
from nsflow_ros.core.imu import so3_exp

W, H = 320, 240
FX = FY = 250.0
UP = 2


def base_texture(name: str = "coffee") -> np.ndarray:
    """A gray photo twice the frame size: frames look at its central part."""
    img = getattr(skdata, name)()
    if img.ndim == 3:
        img = cv2.cvtColor(img[..., :3], cv2.COLOR_RGB2GRAY)
    return cv2.resize(img, (2 * W, 2 * H), interpolation=cv2.INTER_AREA)


def camera(width: int = W, height: int = H) -> PinholeCamera:
    return PinholeCamera(width=width, height=height, fx=FX, fy=FY, cx=width / 2.0, cy=height / 2.0)


def k_matrix() -> np.ndarray:
    return np.array([[FX, 0, W / 2.0], [0, FY, H / 2.0], [0, 0, 1]])


def render(base: np.ndarray, m: np.ndarray, size: tuple[int, int] = (W, H)) -> np.ndarray:
    """Frame with frame(M b) = base(b), rendered at UP x resolution and area-downsampled."""
    s = np.array([[UP, 0, (UP - 1) / 2], [0, UP, (UP - 1) / 2], [0, 0, 1]], np.float64)
    big = cv2.resize(base, (base.shape[1] * UP, base.shape[0] * UP), interpolation=cv2.INTER_CUBIC)
    out = cv2.warpPerspective(
        big, s @ m @ np.linalg.inv(s), (size[0] * UP, size[1] * UP), flags=cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_REFLECT,
    )
    return cv2.resize(out, size, interpolation=cv2.INTER_AREA)


def apply_h(m: np.ndarray, pts: np.ndarray) -> np.ndarray:
    ph = np.c_[pts, np.ones(len(pts))] @ m.T
    return ph[:, :2] / ph[:, 2:]


def translation(tx: float, ty: float) -> np.ndarray:
    return np.array([[1, 0, tx], [0, 1, ty], [0, 0, 1]], np.float64)


@dataclass
class Sequence:
    """Frames, their stamps and homographies (base -> frame), optional right frames and gyro samples."""

    stamps: np.ndarray
    frames: list[np.ndarray]
    homographies: list[np.ndarray]
    right: list[np.ndarray] | None = None
    disparity: float = 0.0
    gyro: np.ndarray | None = None

    def truth(self, j: int, k: int, pts: np.ndarray) -> np.ndarray:
        """True positions in frame k of points at ``pts`` in frame j."""
        return apply_h(self.homographies[k] @ np.linalg.inv(self.homographies[j]), pts)


def translating(n: int = 12, step: tuple[float, float] = (2.7, 1.3), dt: float = 0.05, *,
                stereo_disparity: float | None = None, name: str = "coffee") -> Sequence:
    """The camera pans: the image content moves by -step px per frame; stereo right = left + disparity."""
    base = base_texture(name)
    hs = [translation(-W / 2 - k * step[0], -H / 2 - k * step[1]) for k in range(n)]
    frames = [render(base, m) for m in hs]
    right = None
    if stereo_disparity is not None:
        right = [render(base, translation(stereo_disparity, 0) @ m) for m in hs]
    return Sequence(np.arange(n) * dt, frames, hs, right, stereo_disparity or 0.0)


def rotating(n: int, rate: np.ndarray, dt: float = 0.05, imu_hz: float = 400.0, name: str = "coffee",
             translation_px: float = 0.0) -> Sequence:
    """The camera rotates at a constant rate (rad/s, camera frame); gyro samples in the camera frame.

    A point at infinity with ray p in camera 0 is seen along R_k^T p in frame k, R_k = exp(rate t_k), so
    M_k = K R_k^T K^-1 T^-1 with T mapping frame-0 pixels to base pixels. ``translation_px`` adds an image
    shift per frame that the gyro does not see (parallax stand-in).
    """
    base = base_texture(name)
    kk = k_matrix()
    t_inv = translation(-W / 2, -H / 2)
    stamps = np.arange(n) * dt
    hs = []
    for k, t in enumerate(stamps):
        r = so3_exp(np.asarray(rate) * t)
        hs.append(translation(translation_px * k, 0) @ kk @ r.T @ np.linalg.inv(kk) @ t_inv)
    frames = [render(base, m) for m in hs]
    ts = np.arange(0.0, stamps[-1] + 1e-9, 1.0 / imu_hz)
    gyro = np.c_[ts, np.tile(np.asarray(rate, float), (ts.size, 1))]
    return Sequence(stamps, frames, hs, gyro=gyro)
