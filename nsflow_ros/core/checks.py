"""The track check that replaces VINS's reverse solves: each point's own covariance, and for a stereo match
its distance from the epipolar line.

VINS tracks every point back and keeps it when it returns within 0.5 px: a second solve per point (its
cost: docs/benchmarks.md). An LM solve already gives each point a calibrated covariance (its final
J^T J and residual, :mod:`~nsflow_ros.core.covariance`), which ranks the bad tracks better than the return
distance does, and a right point of a calibrated stereo pair must lie on the epipolar line of its left
point. :class:`CovarianceCheck` keeps a point when both say it is pinned down where it is. What neither
sees is a confident match on the wrong thing (a window sliding onto an occluder's edge): such a point lands
far from where its track's motion predicted, and those few points are still solved in reverse.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from nsflow_ros.core.camera import CameraModel
from nsflow_ros.core.covariance import max_sigma
from nsflow_ros.core.errors import CoreError

__all__ = ["CovarianceCheck", "StereoGeometry"]


@dataclass(frozen=True)
class CovarianceCheck:
    """A method's check of its tracks by their covariance, in place of the reverse solves.

    Attributes:
        max_sigma: a point is dropped when the standard deviation along its covariance's major axis
            exceeds this (px of the tracking resolution, where the reverse check's 0.5 px is measured)
            and ``relative`` times the solve's median: the window does not pin it down, or its residual
            says it matched something else. About a clean solve's 95th percentile: the bound at which
            fewer features over 1 px pass than the reverse solves let through (docs/design.md).
        stereo_max_sigma: ``max_sigma`` of a stereo match, looser since it also has the epipolar test and
            a dropped match leaves its feature without depth in its first frame (docs/design.md).
        relative: how far above the solve's median sigma a point may stand: image noise (a dark frame)
            raises every sigma alike, and a fixed bound would then cut the tracks short.
        max_epipolar: a stereo match is dropped when it lies farther than this (px of camera 1) from the
            epipolar line of its left point; large enough for a real calibration's error, small enough
            to catch a match on another row. Only with the pair's extrinsics known.
        max_departure: a point that lands farther than this (px) from its prior (its track's previous
            motion or disparity) is also tracked back as VINS does: few points do, while solving back
            every new point (which has no prior) would cost nearly what checking all does.

    Raises:
        CoreError: a bound that is not finite and > 0.
    """

    max_sigma: float = 0.15
    stereo_max_sigma: float = 0.2
    relative: float = 2.0
    max_epipolar: float = 2.0
    max_departure: float = 3.0

    def __post_init__(self) -> None:
        for name in ("max_sigma", "stereo_max_sigma", "relative", "max_epipolar", "max_departure"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise CoreError(f"CovarianceCheck.{name} must be finite and > 0, got {value}")

    def keep(self, cov: np.ndarray, live: np.ndarray, stereo: bool = False) -> np.ndarray:
        """Where the covariance pins the point down against ``max_sigma`` (``stereo_max_sigma`` for
        ``stereo`` matches) and the ``live`` points' median (NaN or a singular J^T J: not).

        Shape:
            cov: (N, 3) [uu, uv, vv] px^2. live: (N,) bool. Returns (N,) bool.
        """
        sigma = max_sigma(cov)
        floor = self.stereo_max_sigma if stereo else self.max_sigma
        typical = sigma[live & np.isfinite(sigma)]
        if typical.size:
            return sigma <= max(floor, self.relative * float(np.median(typical)))
        return sigma <= floor

    def unsure(self, positions: np.ndarray, prior: np.ndarray | None) -> np.ndarray:
        """Where a solution needs the reverse solve: farther than ``max_departure`` from its prior.

        Shape:
            positions: (N, 2). prior: (N, 2), NaN where none, or None (no point has one). Returns (N,).
        """
        if prior is None:
            return np.zeros(len(positions), bool)
        with np.errstate(invalid="ignore"):
            return np.hypot(*(positions - prior).T) > self.max_departure  # NaN: no prior, not unsure


class StereoGeometry:
    """A calibrated stereo pair's epipolar constraint, in pixels of camera 1.

    Args:
        cam0, cam1: the two cameras (the tracking resolution's).
        cam1_T_cam0: (4, 4) the pose of camera 0 in camera 1's frame (a point X0 of camera 0 is
            ``R X0 + t`` in camera 1).

    Raises:
        CoreError: a transform that is not a finite (4, 4) rigid motion with a baseline.
    """

    def __init__(self, cam0: CameraModel, cam1: CameraModel, cam1_T_cam0: np.ndarray) -> None:
        tf = np.asarray(cam1_T_cam0, dtype=np.float64)
        if tf.shape != (4, 4) or not np.isfinite(tf).all():
            raise CoreError(f"cam1_T_cam0 must be a finite (4, 4) matrix, got shape {tf.shape}")
        rot, t = tf[:3, :3], tf[:3, 3]
        if not np.allclose(rot @ rot.T, np.eye(3), atol=1e-6) or np.linalg.norm(t) < 1e-9:
            raise CoreError("cam1_T_cam0 must be a rigid motion (orthonormal rotation) with a baseline")
        skew = np.array([[0.0, -t[2], t[1]], [t[2], 0.0, -t[0]], [-t[1], t[0], 0.0]])
        self.essential = skew @ rot
        self.cam0, self.cam1 = cam0, cam1
        # pixels per radian at camera 1's centre: any model (pinhole, fisheye) alike
        centre = cam1.project(np.array([[0.0, 0.0, 1.0], [1e-3, 0.0, 1.0]]))
        self.focal = float(np.hypot(*(centre[1] - centre[0]))) / 1e-3

    def distance(self, left: np.ndarray, right: np.ndarray) -> np.ndarray:
        """Each right pixel's distance from the epipolar plane of its left pixel: the angle between its
        ray and the plane, in pixels of camera 1's centre (the distance to the epipolar line there; a
        little less towards a pinhole's corners, where a pixel spans a smaller angle).

        Shape:
            left, right: (N, 2) distorted pixels of camera 0 and camera 1. Returns (N,); NaN where a
            pixel has no ray.
        """
        if len(left) == 0:
            return np.zeros(0)
        return self.distance_rays(self.cam0.lift_rays(left), self.cam1.lift_rays(right))

    def distance_rays(self, left: np.ndarray, right: np.ndarray) -> np.ndarray:
        """:meth:`distance` from the pixels' rays (``CameraModel.lift_rays``), for a caller that lifts them
        anyway (the tracker publishes every feature's undistorted point).

        Shape:
            left, right: (N, 3) rays in camera 0 and camera 1. Returns (N,).
        """
        if len(left) == 0:
            return np.zeros(0)
        normal = left @ self.essential.T  # the epipolar plane's normal in camera 1
        with np.errstate(divide="ignore", invalid="ignore"):
            sine = np.abs(np.einsum("ij,ij->i", right, normal)) / (
                np.linalg.norm(right, axis=1) * np.linalg.norm(normal, axis=1))
        return np.arcsin(np.minimum(sine, 1.0)) * self.focal
