"""IMU-aided prediction: integrate the gyro between two frames and predict where each point moves.

The prediction is rotation only (points at infinity), projected with the camera model; the solver starts
from it and only has to cover the translational remainder. Gyro samples are (t, wx, wy, wz), t in seconds,
rad/s in the IMU (body) frame; ``body_R_cam`` rotates camera-frame vectors into the body frame.
"""

from __future__ import annotations

from collections import deque

import numpy as np

from nsflow_ros.core.camera import CameraModel
from nsflow_ros.core.errors import CoreError

__all__ = [
    "GyroBuffer",
    "body_to_camera_rotation",
    "integrate_gyro",
    "predict_pixels",
    "so3_exp",
]


def so3_exp(rotvec: np.ndarray) -> np.ndarray:
    """The (3, 3) rotation matrix of a rotation vector (3,), axis * angle in radians (Rodrigues)."""
    w = np.asarray(rotvec, dtype=np.float64).reshape(3)
    theta = float(np.linalg.norm(w))
    k = np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])
    if theta < 1e-12:
        return np.eye(3) + k  # first order is exact to machine precision here
    a = np.sin(theta) / theta
    b = (1.0 - np.cos(theta)) / (theta * theta)
    return np.eye(3) + a * k + b * (k @ k)


def _check_samples(samples: np.ndarray) -> np.ndarray:
    arr = np.asarray(samples, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != 4:
        raise CoreError(f"gyro samples must have shape (M, 4) as (t, wx, wy, wz), got {arr.shape}")
    if arr.shape[0] == 0:
        raise CoreError("gyro samples are empty: nothing to integrate")
    if not np.isfinite(arr).all():
        raise CoreError("gyro samples must be finite")
    if np.any(np.diff(arr[:, 0]) < 0):
        raise CoreError("gyro samples must be sorted by time")
    return arr


def integrate_gyro(samples: np.ndarray, t0: float, t1: float) -> np.ndarray:
    """Integrate gyro samples from t0 to t1 into the body rotation R_{b(t0) b(t1)} (v_b(t0) = R v_b(t1)).

    Midpoint integration, the rate interpolated linearly at t0 and t1 and held constant outside the
    samples' span, so that an IMU message arriving a little late does not disable the prediction.

    Raises:
        CoreError: on a wrong shape, unsorted or non-finite samples, or t1 < t0.

    Shape:
        samples: (M, 4). Returns (3, 3).
    """
    arr = _check_samples(samples)
    if not (np.isfinite(t0) and np.isfinite(t1)):
        raise CoreError(f"integration bounds must be finite, got t0={t0}, t1={t1}")
    if t1 < t0:
        raise CoreError(f"integration interval goes backwards: t0={t0} > t1={t1}")
    inner = arr[(arr[:, 0] > t0) & (arr[:, 0] < t1), 0]
    times = np.concatenate([[t0], inner, [t1]])
    # linear interpolation, holding the end values outside the covered interval
    rates = np.stack([np.interp(times, arr[:, 0], arr[:, k]) for k in (1, 2, 3)], axis=1)
    rot = np.eye(3)
    for k in range(times.size - 1):
        dt = times[k + 1] - times[k]
        if dt > 0:
            rot = rot @ so3_exp(0.5 * (rates[k] + rates[k + 1]) * dt)
    return rot


def body_to_camera_rotation(body_rot: np.ndarray, body_R_cam: np.ndarray | None) -> np.ndarray:
    """A (3, 3) body rotation R_{b0 b1} in the camera frame, R_bc^T R_{b0 b1} R_bc (R_bc None: identity)."""
    if body_R_cam is None:
        return np.asarray(body_rot, dtype=np.float64)
    r_bc = np.asarray(body_R_cam, dtype=np.float64)
    if r_bc.shape != (3, 3):
        raise CoreError(f"body_R_cam must have shape (3, 3), got {r_bc.shape}")
    return r_bc.T @ np.asarray(body_rot, dtype=np.float64) @ r_bc


def predict_pixels(camera: CameraModel, undistorted: np.ndarray, cam_rot: np.ndarray) -> np.ndarray:
    """Where points at infinity, undistorted (x, y) in the previous frame, appear after rotation R_{c0 c1}.

    Returns:
        distorted pixels in the current frame; NaN where the rotated ray points backwards.

    Shape:
        undistorted: (N, 2). cam_rot: (3, 3). Returns (N, 2).
    """
    pts = np.asarray(undistorted, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 2:
        raise CoreError(f"undistorted points must have shape (N, 2), got {pts.shape}")
    if pts.shape[0] == 0:
        return np.zeros((0, 2))
    rays = np.concatenate([pts, np.ones((pts.shape[0], 1))], axis=1)
    # p_c1 = R_{c1 c0} p_c0 = R_{c0 c1}^T p_c0; as row vectors that is rays @ R_{c0 c1}.
    rotated = rays @ np.asarray(cam_rot, dtype=np.float64)
    ahead = rotated[:, 2] > 1e-6
    out = np.full((pts.shape[0], 2), np.nan)
    if ahead.any():
        out[ahead] = camera.project(rotated[ahead])
    out[~np.isfinite(out).all(axis=1)] = np.nan
    return out


class GyroBuffer:
    """A bounded, time-ordered store of gyro samples for the node (IMU messages arrive between frames).

    Args:
        max_samples: how many samples to keep at most (oldest dropped first).
    """

    def __init__(self, max_samples: int = 4000) -> None:
        if max_samples < 2:
            raise CoreError(f"max_samples must be >= 2, got {max_samples}")
        self._data: deque[tuple[float, float, float, float]] = deque(maxlen=max_samples)

    def __len__(self) -> int:
        return len(self._data)

    def add(self, t: float, rate: tuple[float, float, float] | np.ndarray) -> None:
        """Append one sample; samples older than the newest are ignored (out-of-order delivery)."""
        wx, wy, wz = (float(v) for v in rate)
        if not all(np.isfinite([t, wx, wy, wz])):
            return
        if self._data and t <= self._data[-1][0]:
            return
        self._data.append((float(t), wx, wy, wz))

    def window(self, t0: float, t1: float) -> np.ndarray | None:
        """Samples covering [t0, t1] (one either side where available), or None when none overlap.

        Returns None when the newest sample is older than t0: a stale IMU must not drive the prediction.

        Shape:
            Returns (M, 4).
        """
        if not self._data or self._data[-1][0] < t0:
            return None
        arr = np.asarray(self._data, dtype=np.float64)
        lo = max(int(np.searchsorted(arr[:, 0], t0, side="right")) - 1, 0)
        hi = int(np.searchsorted(arr[:, 0], t1, side="left")) + 1
        return arr[lo:hi]

    def prune(self, before: float) -> None:
        """Drop samples older than ``before`` except the last one before it (kept for interpolation)."""
        while len(self._data) >= 2 and self._data[1][0] <= before:
            self._data.popleft()
