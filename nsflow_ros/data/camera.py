"""Pinhole camera with radial-tangential (radtan) distortion, as calibrated for EuRoC MAV.

Pixels follow OpenCV (integer coordinates are pixel centres); normalised coordinates are the undistorted
``(X / Z, Y / Z)``. Projection is the tracker's own model (:class:`~nsflow_ros.core.camera.PinholeCamera`),
so the sample's images and the tracker agree on where a point lands; only the inverse differs, since the
ground truth needs the exact undistortion (Newton's method) where the tracker reproduces camodocal's
fixed-point iteration.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property
from typing import Any

import numpy as np

from nsflow_ros.core.camera import PinholeCamera, radtan_distort
from nsflow_ros.data.errors import DataError

__all__ = [
    "EUROC_CAM0",
    "EUROC_CAM1",
    "EUROC_T_BS_CAM0",
    "EUROC_T_BS_CAM1",
    "PinholeRadtan",
    "as_points",
]

# Sensor (camera) to body (IMU) extrinsics of EuRoC MAV's cam0 / cam1 (sensor.yaml, T_BS).
EUROC_T_BS_CAM0 = np.array(
    [
        [0.0148655429818, -0.999880929698, 0.00414029679422, -0.0216401454975],
        [0.999557249008, 0.0149672133247, 0.025715529948, -0.064676986768],
        [-0.0257744366974, 0.00375618835797, 0.999660727178, 0.00981073058949],
        [0.0, 0.0, 0.0, 1.0],
    ]
)
EUROC_T_BS_CAM1 = np.array(
    [
        [0.0125552670891, -0.999755099723, 0.0182237714554, -0.0198435579556],
        [0.999598781151, 0.0130119051815, 0.0251588363115, 0.0453689425024],
        [-0.0253898008918, 0.0179005838253, 0.999517347078, 0.00786212447038],
        [0.0, 0.0, 0.0, 1.0],
    ]
)


def as_points(points: Any, dim: int, name: str) -> np.ndarray:
    """``points`` as float64 (N, dim); a single point of shape (dim,) is accepted.

    Raises:
        DataError: naming ``name`` when the shape is neither.
    """
    arr = np.asarray(points, dtype=np.float64)
    if arr.ndim == 1 and arr.shape[0] == dim:
        arr = arr[None, :]
    if arr.ndim != 2 or arr.shape[1] != dim:
        raise DataError(f"{name}: expected shape (N, {dim}), got {arr.shape}")
    return arr


@dataclass(frozen=True, eq=False)
class PinholeRadtan:
    """A pinhole-radtan camera and its pose on the body (IMU) frame.

    Attributes:
        width, height: image size in pixels.
        fx, fy, cx, cy: projection parameters in pixels.
        k1, k2, p1, p2: radial and tangential distortion (OpenCV order).
        T_BS: 4x4 transform from this sensor's frame to the body frame (EuRoC's T_BS).
        name: frame id, e.g. ``cam0``.
    """

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    k1: float = 0.0
    k2: float = 0.0
    p1: float = 0.0
    p2: float = 0.0
    T_BS: np.ndarray = field(default_factory=lambda: np.eye(4))
    name: str = "cam0"

    def __post_init__(self) -> None:
        T = np.asarray(self.T_BS, dtype=np.float64)
        if T.shape != (4, 4):
            raise DataError(f"T_BS of {self.name}: expected shape (4, 4), got {T.shape}")
        object.__setattr__(self, "T_BS", T)
        if self.width <= 0 or self.height <= 0:
            raise DataError(f"camera {self.name}: image size must be positive, "
                            f"got {self.width}x{self.height}")

    # -- parameters -------------------------------------------------------------------------------------

    @property
    def dist(self) -> np.ndarray:
        """``[k1, k2, p1, p2]``."""
        return np.array([self.k1, self.k2, self.p1, self.p2])

    def to_dict(self) -> dict[str, Any]:
        """Plain-JSON description that :meth:`from_dict` reads back."""
        return {
            "name": self.name,
            "model": "pinhole-radtan",
            "width": self.width,
            "height": self.height,
            "intrinsics": [self.fx, self.fy, self.cx, self.cy],
            "distortion": [self.k1, self.k2, self.p1, self.p2],
            "T_BS": self.T_BS.tolist(),
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> PinholeRadtan:
        """Build a camera from :meth:`to_dict` output.

        Raises:
            DataError: when a key is missing or has the wrong length.
        """
        try:
            fx, fy, cx, cy = (float(v) for v in d["intrinsics"])
            k1, k2, p1, p2 = (float(v) for v in d["distortion"])
            return cls(int(d["width"]), int(d["height"]), fx, fy, cx, cy, k1, k2, p1, p2,
                       np.asarray(d["T_BS"], dtype=np.float64), str(d.get("name", "cam0")))
        except (KeyError, TypeError, ValueError) as err:
            raise DataError(f"invalid camera description {d!r}: {err}") from None

    def scaled(self, factor: float) -> PinholeRadtan:
        """The same camera at another resolution; pixel centres map as ``u' = (u + 0.5) * factor - 0.5``."""
        w, h = round(self.width * factor), round(self.height * factor)
        return PinholeRadtan(w, h, self.fx * factor, self.fy * factor, (self.cx + 0.5) * factor - 0.5,
                             (self.cy + 0.5) * factor - 0.5, self.k1, self.k2, self.p1, self.p2,
                             self.T_BS, self.name)

    def camera_model(self) -> PinholeCamera:
        """This camera as the tracker's camodocal ``PINHOLE`` model (same intrinsics and distortion)."""
        return self._model

    @cached_property
    def _model(self) -> PinholeCamera:
        return PinholeCamera(
            width=self.width, height=self.height, fx=self.fx, fy=self.fy, cx=self.cx, cy=self.cy,
            k1=self.k1, k2=self.k2, p1=self.p1, p2=self.p2, name=self.name,
        )

    # -- distortion -------------------------------------------------------------------------------------

    def distort(self, xn: np.ndarray) -> np.ndarray:
        """Distort normalised coordinates (the tracker's camodocal formula). Shape: (N, 2) -> (N, 2)."""
        return radtan_distort(xn, self.dist)

    def undistort_normalized(self, xd: np.ndarray, iterations: int = 20, tol: float = 1e-13) -> np.ndarray:
        """Invert :meth:`distort` by Newton's method (exact to ~1e-13). Shape: (N, 2) -> (N, 2)."""
        k1, k2, p1, p2 = self.k1, self.k2, self.p1, self.p2
        xd = np.asarray(xd, dtype=np.float64)
        x, y = xd[:, 0].copy(), xd[:, 1].copy()
        for _ in range(iterations):
            r2 = x * x + y * y
            radial = 1.0 + r2 * (k1 + k2 * r2)
            fx_ = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x) - xd[:, 0]
            fy_ = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y - xd[:, 1]
            drad = k1 + 2.0 * k2 * r2  # d radial / d r2
            j11 = radial + 2.0 * x * x * drad + 2.0 * p1 * y + 6.0 * p2 * x
            j12 = 2.0 * x * y * drad + 2.0 * p1 * x + 2.0 * p2 * y
            j21 = 2.0 * x * y * drad + 2.0 * p1 * x + 2.0 * p2 * y
            j22 = radial + 2.0 * y * y * drad + 6.0 * p1 * y + 2.0 * p2 * x
            det = j11 * j22 - j12 * j21
            dx = (j22 * fx_ - j12 * fy_) / det
            dy = (-j21 * fx_ + j11 * fy_) / det
            x -= dx
            y -= dy
            if max(np.abs(dx).max(initial=0.0), np.abs(dy).max(initial=0.0)) < tol:
                break
        return np.stack([x, y], axis=1)

    @cached_property
    def max_radius(self) -> float:
        """Largest normalised radius where the distortion is monotonic; points beyond it are not visible."""
        corners = np.array([[0, 0], [self.width - 1, 0], [0, self.height - 1],
                            [self.width - 1, self.height - 1]], dtype=np.float64)
        r_img = np.linalg.norm(self.pixels_to_normalized(corners), axis=1).max()
        # Radial-only monotonicity limit: d/dr [r (1 + k1 r^2 + k2 r^4)] > 0.
        r = np.linspace(0.0, 4.0 * max(r_img, 1.0), 4001)[1:]
        slope = 1.0 + 3.0 * self.k1 * r**2 + 5.0 * self.k2 * r**4
        bad = np.nonzero(slope <= 0.05)[0]
        r_mono = r[bad[0]] if bad.size else np.inf
        return float(min(1.1 * r_img, r_mono))

    # -- projection -------------------------------------------------------------------------------------

    def normalized_to_pixels(self, xn: np.ndarray) -> np.ndarray:
        """Pixels of normalised coordinates, as the tracker's model projects (x, y, 1). Shape: (N, 2)."""
        p = as_points(xn, 2, "normalized points")
        return self._model.project(np.column_stack([p, np.ones(len(p))]))

    def pixels_to_normalized(self, pixels: Any) -> np.ndarray:
        """Undistorted normalised coordinates of pixels. Shape: (N, 2) -> (N, 2), float64.

        Raises:
            DataError: when ``pixels`` is not (N, 2).
        """
        uv = as_points(pixels, 2, "pixels")
        xd = np.stack([(uv[:, 0] - self.cx) / self.fx, (uv[:, 1] - self.cy) / self.fy], axis=1)
        return self.undistort_normalized(xd)

    def project(self, points_cam: Any) -> tuple[np.ndarray, np.ndarray]:
        """Project (N, 3) points of the camera frame.

        Returns:
            ``(pixels, valid)``: (N, 2) pixels, NaN where ``valid`` (N,) is false: behind the camera or
            beyond :attr:`max_radius`.
        """
        P = as_points(points_cam, 3, "points_cam")
        z = P[:, 2]
        valid = z > 1e-9
        with np.errstate(divide="ignore", invalid="ignore"):
            xn = P[:, :2] / z[:, None]
        valid &= np.linalg.norm(np.where(valid[:, None], xn, 0.0), axis=1) <= self.max_radius
        xn[~valid] = 0.0
        uv = self.normalized_to_pixels(xn)
        uv[~valid] = np.nan
        return uv, valid

    def in_image(self, pixels: np.ndarray, margin: float = 0.0) -> np.ndarray:
        """(N,) bool: pixel lies inside ``[margin, size - 1 - margin]`` on both axes (NaN -> False)."""
        u, v = pixels[:, 0], pixels[:, 1]
        with np.errstate(invalid="ignore"):
            inside_u = (u >= margin) & (u <= self.width - 1 - margin)
            return inside_u & (v >= margin) & (v <= self.height - 1 - margin)

    @cached_property
    def ray_grid(self) -> np.ndarray:
        """Undistorted normalised coordinates of every pixel centre. Shape: (height, width, 2)."""
        u, v = np.meshgrid(np.arange(self.width, dtype=np.float64), np.arange(self.height, dtype=np.float64))
        xn = self.pixels_to_normalized(np.stack([u.ravel(), v.ravel()], axis=1))
        return xn.reshape(self.height, self.width, 2)


def _euroc(name: str, size: tuple[int, int], intr: tuple[float, ...], dist: tuple[float, ...],
           T_BS: np.ndarray) -> PinholeRadtan:
    return PinholeRadtan(size[0], size[1], *intr, *dist, T_BS=T_BS, name=name)


EUROC_CAM0 = _euroc("cam0", (752, 480), (458.654, 457.296, 367.215, 248.375),
                    (-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05), EUROC_T_BS_CAM0)
EUROC_CAM1 = _euroc("cam1", (752, 480), (457.587, 456.134, 379.999, 255.238),
                    (-0.28368365, 0.07451284, -0.00010473, -3.55590700e-05), EUROC_T_BS_CAM1)
