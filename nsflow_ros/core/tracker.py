"""The VINS-compatible feature tracker: persistent ids, GFTT top-up, flow-back and border checks, stereo.

:class:`FeatureTracker` reproduces VINS-Fusion's ``FeatureTracker::trackImage`` step by step, the
optical-flow calls made by a method from :data:`nsflow_ros.core.methods.METHODS` and everything else the
same code for every method, so that differences between methods come from the flow alone:

1. track the previous frame's points into this one (from the gyro prediction when there is one, again
   without it when fewer than 10 points survive);
2. flow-back check: track the result back from the previous position; keep points returning within 0.5 px
   (a method with a :class:`~nsflow_ros.core.checks.CovarianceCheck` keeps the points its covariance pins
   down instead, unless ``reverse_checks``);
3. border check: the rounded position must lie at least 1 px inside the image;
4. optional fundamental-matrix RANSAC on a virtual 460 px pinhole (VINS-Mono's ``rejectWithF``);
5. track counts grow by 1; the mask (camera 0's static mask and this frame's mask, if any) keeps the
   longest tracks first, each blocking a disc of radius ``min_dist``; GFTT tops the set up to ``max_cnt``
   with fresh ids;
6. undistorted points from the camera model; velocities against the previous frame, 0 for new ids;
7. stereo: left -> right, the border check and a right -> left back-check (or the covariance check and
   the epipolar distance); right points reuse the left ids;
   a right point on a zero of camera 1's mask (static or this frame's) is dropped.

Masks (:mod:`nsflow_ros.core.masks`) are 0 / 255 images: no corner is detected and no track kept on a 0.

With ``downsample`` d > 1 (:mod:`nsflow_ros.core.downsample`) all of this runs on the images decimated by d,
with the cameras scaled inside and ``min_dist`` divided by d (the features keep their full-resolution
layout; the 0.5 px flow-back and 1 px border checks stay in tracking pixels, where the solver works), and
the output's pixels, undistorted points and velocities are in the full-resolution calibration.

Each image's representation (descriptor pyramid, gray image) is computed once for every solve it is in.
"""

from __future__ import annotations

import contextlib
import math
import time
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field, fields, replace
from typing import Any

import cv2
import numpy as np

from nsflow_ros.core.camera import CameraModel
from nsflow_ros.core.checks import StereoGeometry
from nsflow_ros.core.covariance import DETECTION_VARIANCE, max_sigma
from nsflow_ros.core.detector import detect_corners
from nsflow_ros.core.downsample import (
    check_downsample,
    downsample_camera,
    downsample_image,
    downsample_mask,
    to_full_resolution,
)
from nsflow_ros.core.encoder import Encoder, ExecutionProviders, to_gray
from nsflow_ros.core.errors import CoreError
from nsflow_ros.core.imu import body_to_camera_rotation, integrate_gyro, predict_pixels
from nsflow_ros.core.masks import check_mask, combine, usable_at
from nsflow_ros.core.methods import METHODS, SolveKind, TrackingMethod, make_method

__all__ = [
    "BORDER_PX",
    "FLOW_BACK_THRESHOLD_PX",
    "GFTT_QUALITY",
    "PREDICTION_MIN_TRACKED",
    "REBUILD_FIELDS",
    "CameraFeatures",
    "FeatureTracker",
    "FrameFeatures",
    "TrackerSettings",
    "reject_with_fundamental",
]

# VINS-Mono's FOCAL_LENGTH: the virtual pinhole on which the F-matrix RANSAC threshold is measured.
_VIRTUAL_FOCAL = 460.0
GFTT_QUALITY = 0.01
"""GFTT quality level relative to the best corner (VINS: 0.01)."""
FLOW_BACK_THRESHOLD_PX = 0.5
"""How far (px) a flow-back track may land from its start point (VINS: 0.5)."""
BORDER_PX = 1
"""Points whose rounded position is closer than this to the image edge are dropped (VINS: 1)."""
PREDICTION_MIN_TRACKED = 10
"""With an IMU prediction, the solve is repeated without it when fewer points survive (VINS: 10)."""

REBUILD_FIELDS = frozenset({
    "method", "model_path", "num_threads", "providers", "tensorrt_fp16", "tensorrt_cache",  # the encoder
    "equalize", "stereo", "downsample",  # the image preparation, the cameras
})
"""Settings the tracker's method or image preparation is built from: changing one needs a new tracker."""


@dataclass(frozen=True)
class TrackerSettings:
    """Settings of :class:`FeatureTracker` (VINS names where VINS has the setting).

    The method's own configuration is its registry entry; these are the VINS pipeline's around it.

    Attributes:
        method: a key of :data:`~nsflow_ros.core.methods.METHODS`.
        model_path: ONNX encoder of the learned methods; None = the shipped model.
        num_threads: encoder threads (one: the least CPU per frame, docs/design.md); None = all usable
            cores.
        max_cnt: VINS ``max_cnt``, the number of features kept per frame.
        min_dist: VINS ``min_dist``, the minimum distance between features in pixels.
        F_threshold: VINS ``F_threshold``, RANSAC threshold in pixels of the virtual 460 px pinhole.
        reject_with_f: run the fundamental-matrix RANSAC (VINS-Mono does, VINS-Fusion does not).
        flow_back: VINS ``flow_back``: check every track (the method's check: its registry entry's
            covariance check, else the reverse solve).
        reverse_checks: check by VINS's reverse solves even a method whose registry entry checks by
            covariance (what each costs and catches: docs/benchmarks.md).
        equalize: apply the method's CLAHE before tracking and detection.
        stereo: track camera 0 into camera 1.
        use_imu_prediction: predict the flow from the gyro samples given to :meth:`FeatureTracker.process`.
        providers: the learned encoder's onnxruntime execution providers, best first, comma-separated.
        tensorrt_fp16: let TensorRT build half-precision engines.
        tensorrt_cache: folder of TensorRT's engine cache; None = no cache.
        downsample: track on images decimated by this factor (1, 2 or 4), publish at full resolution.
        publish_covariance: give every feature its calibrated covariance (:attr:`CameraFeatures.covariance`,
            :mod:`~nsflow_ros.core.covariance`, with its tail), for the feature message.
        max_sigma: drop a tracked point whose published standard deviation along its major axis exceeds this
            (px of the full-resolution image), as the reverse checks drop one (counted in
            :attr:`FrameFeatures.gated`); 0 = off.

    Raises:
        CoreError: an unknown method or an out-of-range value.
    """

    method: str = "nsflow"
    model_path: str | None = None
    num_threads: int | None = 1
    max_cnt: int = 150
    min_dist: float = 30.0
    F_threshold: float = 1.0
    reject_with_f: bool = False
    flow_back: bool = True
    reverse_checks: bool = False
    equalize: bool = False
    stereo: bool = False
    use_imu_prediction: bool = False
    providers: str = "cpu"
    tensorrt_fp16: bool = False
    tensorrt_cache: str | None = None
    downsample: int = 1
    publish_covariance: bool = False
    max_sigma: float = 0.0

    def __post_init__(self) -> None:
        check_downsample(self.downsample)
        if self.method not in METHODS:
            raise CoreError(f"method must be one of {tuple(METHODS)}, got {self.method!r}")
        if self.max_cnt < 1:
            raise CoreError(f"max_cnt must be >= 1, got {self.max_cnt}")
        if not (math.isfinite(self.min_dist) and self.min_dist >= 0):
            raise CoreError(f"min_dist must be finite and >= 0, got {self.min_dist}")
        if self.reject_with_f and not self.F_threshold > 0:
            raise CoreError(f"F_threshold must be > 0 when reject_with_f is on, got {self.F_threshold}")
        if not (math.isfinite(self.max_sigma) and self.max_sigma >= 0):
            raise CoreError(f"max_sigma must be finite and >= 0 (0 = off), got {self.max_sigma}")
        if self.num_threads is not None and self.num_threads < 1:
            raise CoreError(f"num_threads must be >= 1 or None, got {self.num_threads}")
        self.execution_providers()  # names checked here, availability when the encoder loads

    def with_overrides(self, overrides: Mapping[str, Any]) -> TrackerSettings:
        """Return a copy with some fields replaced; unknown names raise a CoreError listing the valid ones."""
        names = {f.name for f in fields(self)}
        unknown = sorted(set(overrides) - names)
        if unknown:
            raise CoreError(f"unknown tracker setting(s) {unknown}; valid: {sorted(names)}")
        return replace(self, **dict(overrides))

    @property
    def covariance(self) -> bool:
        """Whether the tracker computes covariances: to publish them or to gate by them."""
        return self.publish_covariance or self.max_sigma > 0

    def execution_providers(self) -> ExecutionProviders:
        """The encoder's execution providers with the TensorRT options (EncoderError: an unknown name)."""
        return ExecutionProviders.parse(
            self.providers, tensorrt_fp16=self.tensorrt_fp16, tensorrt_cache=self.tensorrt_cache
        )


@dataclass(frozen=True)
class CameraFeatures:
    """The features of one camera in one frame.

    Attributes:
        camera_id: 0 (left / mono) or 1 (right).
        ids: feature ids (shared by the two cameras of a stereo pair).
        pixels: distorted pixel positions (u, v).
        undistorted: undistorted normalised coordinates (x, y); the published point is (x, y, 1).
        velocities: (vx, vy) of the undistorted point per second; 0 for ids new to this camera.
        track_counts: frames each id has been tracked on camera 0 (1 = detected in this frame).
        previous: the id's pixel position on this camera in the previous frame; NaN where it had none.
        covariance: with ``publish_covariance``, each pixel position's calibrated covariance [sigma_uu,
            sigma_uv, sigma_vv] in px^2, from the solve that placed it (temporal on camera 0, stereo on
            camera 1; a corner detected in this frame: its whole-pixel rounding, 1/12 px^2); else None.

    Shape:
        ids, track_counts: (N,) int64. pixels, undistorted, velocities, previous: (N, 2) float64.
        covariance: (N, 3) float64.
    """

    camera_id: int
    ids: np.ndarray
    pixels: np.ndarray
    undistorted: np.ndarray
    velocities: np.ndarray
    track_counts: np.ndarray
    previous: np.ndarray
    covariance: np.ndarray | None = None

    def __len__(self) -> int:
        return int(self.ids.shape[0])


@dataclass(frozen=True)
class FrameFeatures:
    """Output of :meth:`FeatureTracker.process` for one frame.

    Attributes:
        stamp: the frame's time in seconds.
        cameras: camera 0, then camera 1 for stereo.
        image_size: (width, height) of the images (full resolution, as given).
        timings: wall time of the stages in milliseconds (encode, track, detect, stereo, total).
        cpu_timings: the process's CPU time over all its threads in the same stages, in milliseconds.
        gated: tracked points dropped because their predicted sigma exceeded ``max_sigma`` (both cameras).
    """

    stamp: float
    cameras: tuple[CameraFeatures, ...]
    image_size: tuple[int, int]
    timings: dict[str, float] = field(default_factory=dict)
    cpu_timings: dict[str, float] = field(default_factory=dict)
    gated: int = 0

    @property
    def num_cameras(self) -> int:
        return len(self.cameras)


def reject_with_fundamental(
    prev_undistorted: np.ndarray,
    cur_undistorted: np.ndarray,
    threshold: float,
    image_size: tuple[int, int],
    focal: float = _VIRTUAL_FOCAL,
) -> np.ndarray:
    """Fundamental-matrix RANSAC inlier mask, measured on a virtual pinhole (VINS-Mono ``rejectWithF``).

    The undistorted points of the previous and current frame are mapped onto a pinhole of focal length
    ``focal`` centred in the ``image_size`` (width, height) image, so that ``threshold`` means the same
    number of pixels for every lens model.

    Returns:
        True for inliers; all True when fewer than 8 points (no F can be estimated).

    Shape:
        prev_undistorted, cur_undistorted: (N, 2). Returns (N,) bool.
    """
    a = np.asarray(prev_undistorted, dtype=np.float64)
    b = np.asarray(cur_undistorted, dtype=np.float64)
    if a.shape != b.shape or a.ndim != 2 or a.shape[1] != 2:
        raise CoreError(f"point sets must both be (N, 2), got {a.shape} and {b.shape}")
    n = a.shape[0]
    good = np.isfinite(a).all(axis=1) & np.isfinite(b).all(axis=1)
    if good.sum() < 8:
        return good if n else np.zeros(0, bool)
    centre = np.array([image_size[0] / 2.0, image_size[1] / 2.0])
    pa = (focal * a[good] + centre).astype(np.float32)
    pb = (focal * b[good] + centre).astype(np.float32)
    _, mask = cv2.findFundamentalMat(pa, pb, cv2.FM_RANSAC, float(threshold), 0.99)
    out = np.zeros(n, bool)
    if mask is None:  # degenerate configuration: keep everything rather than drop the frame
        out[good] = True
    else:
        out[np.flatnonzero(good)] = mask.reshape(-1).astype(bool)
    return out


def _in_border(pts: np.ndarray, size: tuple[int, int], border: int) -> np.ndarray:
    # VINS rounds to the nearest pixel (cvRound) before comparing.
    w, h = size
    r = np.rint(pts)
    with np.errstate(invalid="ignore"):
        return (r[:, 0] >= border) & (r[:, 0] < w - border) & (r[:, 1] >= border) & (r[:, 1] < h - border)


def _match(ids: np.ndarray, table_ids: np.ndarray) -> np.ndarray:
    """The index of each of ``ids`` in ``table_ids``; -1 where it is not there."""
    match = np.full(ids.shape[0], -1, np.int64)
    if ids.size == 0 or table_ids.size == 0:
        return match
    order = np.argsort(table_ids, kind="stable")
    sorted_ids = table_ids[order]
    pos = np.clip(np.searchsorted(sorted_ids, ids), 0, sorted_ids.size - 1)
    found = sorted_ids[pos] == ids
    match[found] = order[pos[found]]
    return match


def _velocities(
    ids: np.ndarray, pts: np.ndarray, prev_ids: np.ndarray, prev_pts: np.ndarray, dt: float
) -> np.ndarray:
    """Velocity per id from the previous frame's points; 0 for unseen ids."""
    vel = np.zeros_like(pts)
    if not dt > 0:
        return vel
    match = _match(ids, prev_ids)
    found = match >= 0
    vel[found] = (pts[found] - prev_pts[match[found]]) / dt
    return vel


def _check_mask(mask: np.ndarray, camera: CameraModel, index: int, what: str) -> np.ndarray:
    return check_mask(mask, (camera.width, camera.height), what, f"camera {index} ({camera.name})")


def _no_features(camera_id: int) -> CameraFeatures:
    ids, points = np.zeros(0, np.int64), np.zeros((0, 2))
    return CameraFeatures(camera_id, ids, points, points, points, ids, points)


def _lookup(ids: np.ndarray, table_ids: np.ndarray, values: np.ndarray) -> np.ndarray:
    """``values`` of ``table_ids`` for each of ``ids``; NaN where an id is not in the table."""
    out = np.full((ids.shape[0], values.shape[1]), np.nan)
    match = _match(ids, table_ids)
    found = match >= 0
    out[found] = values[match[found]]
    return out


@dataclass(frozen=True)
class _Tracks:
    """One camera's features in the making: ids, track counts, pixels, previous pixels (NaN: new) and the
    pixels' covariances (NaN when not computed)."""

    ids: np.ndarray
    counts: np.ndarray
    pixels: np.ndarray
    previous: np.ndarray
    cov: np.ndarray

    @staticmethod
    def empty() -> _Tracks:
        return _Tracks(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 2)), np.zeros((0, 2)),
                       np.zeros((0, 3)))

    def __getitem__(self, sel: np.ndarray) -> _Tracks:
        return _Tracks(self.ids[sel], self.counts[sel], self.pixels[sel], self.previous[sel], self.cov[sel])

    def append(self, other: _Tracks) -> _Tracks:
        pairs = zip(vars(self).values(), vars(other).values(), strict=True)
        return _Tracks(*(np.concatenate(pair) for pair in pairs))


@contextlib.contextmanager
def _timed(timings: dict[str, float], cpu: dict[str, float], stage: str) -> Iterator[None]:
    """Record the block's wall time in ``timings[stage]`` and its process CPU time in ``cpu[stage]`` (ms)."""
    t0, c0 = time.perf_counter(), time.process_time()
    yield
    timings[stage] = (time.perf_counter() - t0) * 1e3
    cpu[stage] = (time.process_time() - c0) * 1e3


class FeatureTracker:
    """VINS-Fusion's feature tracker on NSFlow descriptors (the steps of the module docstring).

    Args:
        cameras: camera 0, and camera 1 when ``settings.stereo``.
        settings: tracker settings.
        encoder: descriptor encoder to use instead of the one ``settings.method`` selects; not with "klt".
        method: the tracking method, already built (:func:`~nsflow_ros.core.methods.make_method`); its
            name must be ``settings.method``. None = built here from ``settings`` (and ``encoder``).
        body_R_cam0: rotation camera 0 -> IMU body (VINS ``body_T_cam0[:3, :3]``); None = identity.
        mask: camera 0's static mask (VINS-Mono's fisheye mask, a mask0 or both intersected), uint8
            (H, W) at full resolution, 255 where features may be: tracked points on 0 are dropped and no
            corner is detected there (VINS-Mono ``setMask``). None = everywhere.
        mask1: camera 1's static mask at full resolution (stereo only): right points on its zeros are
            dropped. None = everywhere.
        cam1_T_cam0: (4, 4) camera 0's pose in camera 1's frame (VINS ``body_T_cam1^-1 body_T_cam0``), for
            the covariance check's epipolar test of stereo matches; None = no epipolar test.

    Masks (static and per frame) are given at full resolution and decimated here with ``downsample``
    (:func:`~nsflow_ros.core.downsample.downsample_mask`, the one place a mask follows the images).

    Attributes:
        full_cameras: the cameras as given (full resolution), in which the output is.
        cameras: the cameras at the tracking resolution (``full_cameras`` when ``downsample`` is 1).

    Raises:
        CoreError: on inconsistent settings, cameras, mask or method.
        EncoderError: when the model cannot be loaded.
    """

    def __init__(
        self,
        cameras: Sequence[CameraModel],
        settings: TrackerSettings | None = None,
        *,
        encoder: Encoder | None = None,
        body_R_cam0: np.ndarray | None = None,
        mask: np.ndarray | None = None,
        mask1: np.ndarray | None = None,
        method: TrackingMethod | None = None,
        cam1_T_cam0: np.ndarray | None = None,
    ) -> None:
        self.settings = settings or TrackerSettings()
        self.full_cameras = tuple(cameras)
        self.cameras = self.full_cameras
        need = 2 if self.settings.stereo else 1
        if len(self.cameras) < need:
            mode = "stereo" if need == 2 else "mono"
            raise CoreError(f"{mode} tracking needs {need} camera(s), got {len(self.cameras)}")
        for i, cam in enumerate(self.cameras):
            if not isinstance(cam, CameraModel):
                raise CoreError(f"cameras[{i}] must be a CameraModel, got {type(cam).__name__}")
        if self.settings.stereo:
            c0, c1 = self.cameras[0], self.cameras[1]
            if (c0.width, c0.height) != (c1.width, c1.height):
                raise CoreError(
                    f"stereo cameras differ in size: cam0 {c0.width}x{c0.height}, cam1 {c1.width}x{c1.height}"
                )
        s = self.settings
        self._down = s.downsample
        self.cameras = tuple(downsample_camera(c, self._down) for c in self.full_cameras)
        # The method is chosen here, once; every solve below is method-blind.
        if method is None:
            method = make_method(
                s.method, encoder=encoder, model_path=s.model_path, threads=s.num_threads,
                providers=s.execution_providers(),
            )
        elif encoder is not None or method.name != s.method:
            raise CoreError(
                f"a given method ({method.name!r}) must be settings.method ({s.method!r}) and comes with "
                "its own encoder"
            )
        self.method: TrackingMethod = method
        if s.covariance:
            method.covariance_scale  # noqa: B018 - a malformed stored scale fails here, not on a frame
        self.body_R_cam0 = None if body_R_cam0 is None else np.asarray(body_R_cam0, dtype=np.float64)
        if self.body_R_cam0 is not None and self.body_R_cam0.shape != (3, 3):
            raise CoreError(f"body_R_cam0 must have shape (3, 3), got {self.body_R_cam0.shape}")
        self._clahe = method.spec.clahe.create() if s.equalize else None
        self.mask = None if mask is None else self._tracking_mask(mask, 0, "mask")
        if mask1 is not None and not s.stereo:
            raise CoreError("mask1 given but the tracker is mono (settings.stereo is False)")
        self.mask1 = None if mask1 is None else self._tracking_mask(mask1, 1, "mask1")
        self.stereo_geometry = (StereoGeometry(self.cameras[0], self.cameras[1], cam1_T_cam0)
                                if cam1_T_cam0 is not None and s.stereo else None)
        self._next_id = 0
        self._gated = 0  # points the max_sigma gate dropped in the current frame
        self.reset()

    # -- state -----------------------------------------------------------------------------------------

    @property
    def encoder(self) -> Encoder | None:
        """The method's descriptor encoder (None for ``klt``, which tracks the gray image)."""
        return self.method.encoder

    def warm_up(self) -> None:
        """Prepare a black frame of camera 0's size and discard it, so the method's first-run costs
        (onnxruntime's buffers) do not land on the first real frame, which a live node's queue of one would
        pay with a superseded frame (docs/design.md, "The node")."""
        cam = self.cameras[0]
        black = np.zeros((cam.height, cam.width), np.uint8)
        self.method.prepare(black, black)

    def update_settings(self, changes: Mapping[str, Any]) -> None:
        """Change settings of the running tracker (not :data:`REBUILD_FIELDS`); its tracks go on.

        Raises:
            CoreError: an unknown or invalid setting, or one of :data:`REBUILD_FIELDS`; nothing changes.
        """
        new = self.settings.with_overrides(changes)
        fixed = sorted(f for f in REBUILD_FIELDS if getattr(new, f) != getattr(self.settings, f))
        if fixed:
            raise CoreError(f"{', '.join(fixed)} cannot change on a running tracker; build a new one")
        self.settings = new

    def reset(self) -> None:
        """Forget all tracks (ids keep counting up, so an id is never reused)."""
        self._stamp: float | None = None
        self._frame: Any = None  # the previous camera-0 frame's representation
        self._left = _no_features(0)  # the previous frame's features
        self._right = _no_features(1)

    @property
    def last_stamp(self) -> float | None:
        """Stamp of the last processed frame (None before the first or after :meth:`reset`)."""
        return self._stamp

    @property
    def next_id(self) -> int:
        """The id the next new feature will get."""
        return self._next_id

    # -- helpers ---------------------------------------------------------------------------------------

    def _prepare(self, image: np.ndarray, name: str) -> tuple[np.ndarray, Any]:
        """Return (gray for detection, the method's representation of the image), at the tracking
        resolution."""
        image = downsample_image(image, self._down)
        try:
            gray = to_gray(image)
        except CoreError as err:
            raise CoreError(f"{name}: {err}") from err
        if self._clahe is not None:
            gray = self._clahe.apply(gray)
            return gray, self.method.prepare(gray, gray)
        return gray, self.method.prepare(image, gray)

    def _track(
        self,
        kind: SolveKind,
        check: SolveKind | None,
        frame1: Any,
        frame2: Any,
        pts: np.ndarray,
        size: tuple[int, int],
        start: np.ndarray | None = None,
        prior: np.ndarray | None = None,
        rays: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray | None]:
        """A solve, the border check, the track check and the ``max_sigma`` gate: (positions in frame 2,
        status, covariances: NaN unless ``settings.covariance`` or the covariance check computed them,
        camera 1's rays of the positions where the epipolar test lifted them: None without one).

        ``rays``: camera 0's rays of ``pts`` (None: lifted here if the epipolar test needs them), so that
        each point is lifted once a frame for the test and the published features alike.

        The track check (``flow_back``) is the reverse solve ``check`` of every point, or with the method's
        :class:`~nsflow_ros.core.checks.CovarianceCheck` the covariance (and for stereo the epipolar) test
        and the reverse solve of its unsure points only (``check`` None: a late frame, no reverse solve).
        A ``start`` (the IMU prediction) that leaves fewer than :data:`PREDICTION_MIN_TRACKED` points is
        dropped and the solve repeated without it, as VINS does.
        """
        m, s = self.method, self.settings
        gate = m.spec.check if s.flow_back and not s.reverse_checks else None
        solve = m.solve_with_covariance if s.covariance or gate is not None else m.solve
        new, status, *cov = solve(kind, frame1, frame2, pts, start, prior)
        if start is not None and int(status.sum()) < PREDICTION_MIN_TRACKED:
            new, status, *cov = solve(kind, frame1, frame2, pts, None, prior)
        status &= _in_border(new, size, BORDER_PX)
        new_rays = None
        if gate is None:  # VINS's check: every live point back, or none without flow_back
            reverse = status.copy() if s.flow_back else np.zeros_like(status)
        else:
            status &= gate.keep(cov[0], status, stereo=kind is SolveKind.STEREO)
            if kind is SolveKind.STEREO and self.stereo_geometry is not None and status.any():
                idx = np.flatnonzero(status)
                left = self.cameras[0].lift_rays(pts[idx]) if rays is None else rays[idx]
                new_rays = np.full((len(pts), 3), np.nan)
                new_rays[idx] = self.cameras[1].lift_rays(new[idx])
                status[idx] = self.stereo_geometry.distance_rays(left, new_rays[idx]) <= gate.max_epipolar
            reverse = status & gate.unsure(new, prior)
        if check is not None and reverse.any():
            # Only live points are checked: the others are dropped anyway.
            idx = np.flatnonzero(reverse)
            back, ok = m.solve(check, frame2, frame1, new[idx], pts[idx])
            status[idx] = ok & (np.hypot(*(back - pts[idx]).T) <= FLOW_BACK_THRESHOLD_PX)
        if not cov:
            return new, status, np.full((len(pts), 3), np.nan), new_rays
        if not s.covariance:  # computed for the check only: not published
            return new, status, cov[0], new_rays
        published = m.covariance_scale.expected(cov[0])  # the check above read it without the tail
        if s.max_sigma > 0:
            # sigma in tracking pixels against a limit in full-resolution pixels; NaN / inf count as wide
            wide = status & ~(max_sigma(published) * self._down <= s.max_sigma)
            self._gated += int(wide.sum())
            status &= ~wide
        return new, status, published, new_rays

    def _predict(self, gyro: np.ndarray | None, stamp: float) -> np.ndarray | None:
        if not self.settings.use_imu_prediction or gyro is None:
            return None
        if self._stamp is None or self._left.ids.size == 0:
            return None
        body_rot = integrate_gyro(gyro, self._stamp, stamp)
        cam_rot = body_to_camera_rotation(body_rot, self.body_R_cam0)
        return predict_pixels(self.cameras[0], self._left.undistorted, cam_rot)

    def _set_mask(
        self, pts: np.ndarray, counts: np.ndarray, size: tuple[int, int], usable: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """Keep the longest tracks first, each blocking a disc of radius min_dist, from the ``usable``
        mask (tracks on its zeros are dropped; None = the static mask); returns (keep, mask)."""
        w, h = size
        usable = self.mask if usable is None else usable
        mask = np.full((h, w), 255, np.uint8) if usable is None else usable.copy()
        order = np.argsort(-counts, kind="stable")
        radius = round(self._min_dist)
        keep: list[int] = []
        for i in order:
            x, y = int(np.rint(pts[i, 0])), int(np.rint(pts[i, 1]))
            if 0 <= x < w and 0 <= y < h and mask[y, x] == 255:
                keep.append(int(i))
                cv2.circle(mask, (x, y), radius, 0, -1)
        return np.asarray(keep, np.int64), mask

    def _tracking_mask(self, mask: np.ndarray, camera: int, what: str) -> np.ndarray:
        """A full-resolution mask of ``camera``, checked, at the tracking resolution."""
        return downsample_mask(_check_mask(mask, self.full_cameras[camera], camera, what), self._down)

    def _frame_masks(
        self, frame_masks: Sequence[np.ndarray | None]
    ) -> tuple[np.ndarray | None, np.ndarray | None]:
        """Each camera's mask for this frame: its static mask and its frame mask intersected (None = none)."""
        n = len(self.cameras) if self.settings.stereo else 1
        if len(frame_masks) > n:
            raise CoreError(f"{len(frame_masks)} frame masks for a tracker of {n} camera(s)")
        given = [
            None if m is None else self._tracking_mask(m, i, f"frame mask {i}")
            for i, m in enumerate(frame_masks)
        ]
        given += [None] * (2 - len(given))
        return combine(self.mask, given[0]), combine(self.mask1, given[1])

    def _check_images(self, image0: np.ndarray, image1: np.ndarray | None) -> tuple[int, int]:
        for name, img in (("image0", image0), ("image1", image1)):
            if img is None:
                continue
            if (
                not isinstance(img, np.ndarray)
                or img.dtype != np.uint8
                or img.ndim not in (2, 3)
                or (img.ndim == 3 and img.shape[2] not in (1, 3))
            ):
                got = f"{img.dtype} {img.shape}" if isinstance(img, np.ndarray) else type(img).__name__
                raise CoreError(f"{name} must be a uint8 (H, W) or (H, W, 3) array, got {got}")
        h, w = image0.shape[:2]
        cam = self.full_cameras[0]
        if (w, h) != (cam.width, cam.height):
            raise CoreError(
                f"image0 is {w}x{h} but camera 0 ({cam.name}) is calibrated for {cam.width}x{cam.height}"
            )
        if self.settings.stereo:
            if image1 is None:
                raise CoreError("stereo tracking needs image1 for every frame, got None")
            if image1.shape[:2] != image0.shape[:2]:
                h1, w1 = image1.shape[:2]
                raise CoreError(f"stereo images differ in size: image0 {w}x{h}, image1 {w1}x{h1}")
        elif image1 is not None:
            raise CoreError("image1 given but the tracker is mono (settings.stereo is False)")
        return w, h

    def _track_previous(
        self, frame0: Any, size: tuple[int, int], predicted: np.ndarray | None, checks: bool
    ) -> tuple[_Tracks, np.ndarray]:
        """Step 1-3: the previous frame's points into this one; returns the survivors and their previous
        undistorted points, counts already grown by 1."""
        prev = self._left
        if self._frame is None or not prev.ids.size:
            return _Tracks.empty(), np.zeros((0, 2))
        # constant velocity: each id moves as it did into the previous frame
        prior = prev.pixels + (prev.pixels - prev.previous)
        back = SolveKind.FLOW_BACK if checks else None
        pts, status, cov, _ = self._track(
            SolveKind.FORWARD, back, self._frame, frame0, prev.pixels, size, predicted, prior
        )
        tracks = _Tracks(prev.ids[status], prev.track_counts[status] + 1, pts[status], prev.pixels[status],
                         cov[status])
        return tracks, prev.undistorted[status]

    def _reject_mask_detect(
        self,
        gray0: np.ndarray,
        tracks: _Tracks,
        prev_un: np.ndarray,
        size: tuple[int, int],
        usable: np.ndarray | None,
    ) -> _Tracks:
        """Steps 4-5: the optional F-matrix RANSAC, the mask (longest tracks first), GFTT top-up."""
        s = self.settings
        if s.reject_with_f and tracks.ids.size >= 8:
            tracks = tracks[reject_with_fundamental(prev_un, self.cameras[0].lift(tracks.pixels),
                                                    s.F_threshold, size)]
        keep, mask = self._set_mask(tracks.pixels, tracks.counts, size, usable)
        tracks = tracks[keep]
        wanted = s.max_cnt - tracks.ids.size
        if wanted <= 0:
            return tracks
        new = detect_corners(gray0, wanted, quality=GFTT_QUALITY, min_distance=self._min_dist, mask=mask)
        k = new.shape[0]
        ids = np.arange(self._next_id, self._next_id + k, dtype=np.int64)
        self._next_id += k
        cov = np.zeros((k, 3))
        cov[:, 0::2] = DETECTION_VARIANCE if s.covariance else np.nan
        return tracks.append(_Tracks(ids, np.ones(k, np.int64), new, np.full((k, 2), np.nan), cov))

    def _lift(
        self, camera: int, tracks: _Tracks, before: CameraFeatures, dt: float, rays: np.ndarray | None = None
    ) -> CameraFeatures:
        """Step 6: undistorted points and velocities against ``before`` (``rays``: the pixels' rays in
        this camera, lifted already; used at full resolution only)."""
        pts = tracks.pixels
        if self._down == 1 and rays is not None:
            with np.errstate(divide="ignore", invalid="ignore"):  # as CameraModel.lift
                un = rays[:, :2] / rays[:, 2:3]
        elif self._down == 1:
            un = self.cameras[camera].lift(pts) if pts.size else np.zeros((0, 2))
        else:  # the full-resolution calibration, so the estimator's config applies as it is
            full = to_full_resolution(pts, self._down)
            un = self.full_cameras[camera].lift(full) if pts.size else np.zeros((0, 2))
        vel = _velocities(tracks.ids, un, before.ids, before.undistorted, dt)
        cov = tracks.cov if self.settings.publish_covariance else None
        return CameraFeatures(camera, tracks.ids, pts, un, vel, tracks.counts, tracks.previous, cov)

    def _stereo(
        self,
        image1: np.ndarray,
        frame0: Any,
        left: _Tracks,
        size: tuple[int, int],
        dt: float,
        checks: bool,
        usable: np.ndarray | None,
        rays: np.ndarray | None = None,
    ) -> CameraFeatures:
        """Step 7: left -> right with its back-check, each id starting from its previous disparity; right
        points on a zero of ``usable`` (camera 1's mask; None = none) are dropped. ``rays``: the left
        points' rays, if lifted already."""
        _, frame1 = self._prepare(image1, "image1")
        right = _Tracks.empty()
        if left.ids.size:
            r, prev = self._right, self._left
            disparity = r.pixels - _lookup(r.ids, prev.ids, prev.pixels)
            prior = left.pixels + _lookup(left.ids, r.ids, disparity)
            back = SolveKind.STEREO_BACK if checks else None
            rpts, st, cov, rays1 = self._track(SolveKind.STEREO, back, frame0, frame1, left.pixels, size,
                                               None, prior, rays)
            if usable is not None:
                st &= usable_at(usable, rpts)
            ids = left.ids[st]
            right = _Tracks(ids, left.counts[st], rpts[st], _lookup(ids, r.ids, r.pixels), cov[st])
            return self._lift(1, right, self._right, dt, None if rays1 is None else rays1[st])
        return self._lift(1, right, self._right, dt)

    def _commit(self, stamp: float, frame0: Any, left: CameraFeatures, right: CameraFeatures | None) -> None:
        """Keep this frame as the next one's previous (only after every step succeeded)."""
        self._stamp = float(stamp)
        self._frame = frame0
        self._left = left
        self._right = _no_features(1) if right is None else right

    def _check_stamp(self, stamp: float) -> None:
        if not math.isfinite(stamp):
            raise CoreError(f"stamp must be finite, got {stamp}")
        if self._stamp is not None and stamp <= self._stamp:
            raise CoreError(
                f"timestamps must increase: got {stamp:.9f} after {self._stamp:.9f} "
                "(call reset() to start over, e.g. when a bag loops)"
            )

    @property
    def _min_dist(self) -> float:
        """``min_dist`` in tracking pixels: the same feature layout as at full resolution."""
        return self.settings.min_dist / self._down

    def _full_resolution(self, cam: CameraFeatures) -> CameraFeatures:
        """A camera's features with pixels (and covariances, px^2) in full-resolution pixels (points and
        velocities already are)."""
        if self._down == 1:
            return cam
        d = self._down
        cov = None if cam.covariance is None else cam.covariance * float(d * d)
        return replace(cam, pixels=to_full_resolution(cam.pixels, d),
                       previous=to_full_resolution(cam.previous, d), covariance=cov)

    # -- main entry ------------------------------------------------------------------------------------

    def process(
        self,
        stamp: float,
        image0: np.ndarray,
        image1: np.ndarray | None = None,
        gyro: np.ndarray | None = None,
        *,
        detect: bool = True,
        checks: bool = True,
        frame_masks: Sequence[np.ndarray | None] = (),
    ) -> FrameFeatures:
        """Track one frame (VINS-Fusion ``trackImage``; the steps of the module docstring).

        Args:
            stamp: the frame's time in seconds; must increase from frame to frame.
            image0: camera-0 image, uint8 (H, W) mono or (H, W, 3) BGR.
            image1: camera-1 image of the same stamp (stereo only).
            gyro: (M, 4) gyro samples (t, wx, wy, wz) in the IMU frame since the previous frame.
            detect: top the features up with new corners (VINS-Mono skips this on throttled frames).
            checks: run the reverse checks that ``settings.flow_back`` asks for; False skips them on this
                frame only (a live node catching up on a frame that waited). A covariance check costs
                nothing and always runs.
            frame_masks: this frame's masks (moving objects), camera 0 first, each uint8 (H, W) 255 where
                features may be or None; they apply with the static masks. Camera 0's applies where new
                corners are detected (``detect``), camera 1's to the right points.

        Raises:
            CoreError: on a stamp that does not increase, a wrong image or mask size or type, or a missing
                stereo image; the tracker's state is then unchanged.
        """
        t_start, c_start = time.perf_counter(), time.process_time()
        self._check_stamp(stamp)
        full_size = self._check_images(image0, image1)
        size = (self.cameras[0].width, self.cameras[0].height)  # where the tracking happens
        usable0, usable1 = self._frame_masks(frame_masks)
        timings: dict[str, float] = {}
        cpu: dict[str, float] = {}
        predicted = self._predict(gyro, stamp)  # before any state changes: may raise on bad samples
        self._gated = 0
        with _timed(timings, cpu, "encode"):
            gray0, frame0 = self._prepare(image0, "image0")
        with _timed(timings, cpu, "track"):
            tracks, prev_un = self._track_previous(frame0, size, predicted, checks)
        with _timed(timings, cpu, "detect"):
            if detect:
                tracks = self._reject_mask_detect(gray0, tracks, prev_un, size, usable0)
        dt = stamp - self._stamp if self._stamp is not None else 0.0
        # At the tracking resolution the published points are the rays' (as CameraModel.lift): lifted once
        # here, they serve the stereo epipolar test too.
        rays0 = self.cameras[0].lift_rays(tracks.pixels) if self._down == 1 and len(tracks.pixels) else None
        left = self._lift(0, tracks, self._left, dt, rays0)
        right = None
        if self.settings.stereo:
            with _timed(timings, cpu, "stereo"):
                right = self._stereo(image1, frame0, tracks, size, dt, checks, usable1,  # type: ignore[arg-type]
                                     rays0)
        self._commit(stamp, frame0, left, right)
        timings["total"] = (time.perf_counter() - t_start) * 1e3
        cpu["total"] = (time.process_time() - c_start) * 1e3
        cams = tuple(self._full_resolution(c) for c in ((left,) if right is None else (left, right)))
        return FrameFeatures(float(stamp), cams, full_size, timings, cpu, self._gated)
