"""The VINS-compatible feature tracker: persistent ids, GFTT top-up, flow-back and border checks, stereo.

:class:`FeatureTracker` reproduces VINS-Fusion's ``FeatureTracker::trackImage`` step by step, with the
optical-flow calls replaced by the NSFlow descriptor LM solver (:func:`nsflow_ros.core.solver.track`):

1. track the previous frame's points into the current frame (from the gyro prediction when there is one,
   falling back to a solve without it when fewer than 10 points survive; otherwise the method may start
   each point from its previous flow);
2. flow-back check: track the result back, starting at the previous position as VINS does; a point is
   kept only if it returns within 0.5 px;
3. border check: the rounded position must lie at least 1 px inside the image;
4. optional fundamental-matrix RANSAC on a virtual 460 px pinhole (VINS-Mono's ``rejectWithF``; VINS-Fusion
   leaves it commented out, so it is off by default);
5. every surviving track's count grows by 1; the mask (starting from VINS-Mono's fisheye mask when the
   config sets ``fisheye: 1``) keeps the longest tracks first, each blocking a disc of radius
   ``min_dist``; GFTT tops the set up to ``max_cnt`` on the raw gray image, new points get fresh ids
   and count 1;
6. undistorted normalised points from the camera model; velocity = change of the undistorted point over
   dt for ids seen in the previous frame, 0 for new ids;
7. stereo: left -> right tracking (the method may start each id from its previous disparity), the border
   check and a right -> left back-check (0.5 px); right points reuse the left ids, velocities come from
   the previous right points.

Each frame's representation (descriptor pyramid, gray image) is computed once: frame t's is frame 2 of
the pair (t-1, t) and frame 1 of (t, t+1); the right image's serves both stereo directions.

The optical-flow calls are made by a tracking method chosen once from the registry
:data:`nsflow_ros.core.methods.METHODS` (``nsflow``, ``classical``, ``klt``, ``nsflow_lk``): the method
decides, for each kind of solve, its start, levels and points; everything else (detection, the 0.5 px
check, border, mask, ids) is the same code for every method, so differences between methods come from
the flow alone. Method ``"klt"`` is the baseline VINS itself runs: OpenCV's ``cv2.calcOpticalFlowPyrLK``
with VINS-Fusion's exact arguments on the gray (or CLAHE'd) images.

Nothing here imports rclpy or torch: the ROS node and the offline replayer/demo share this class.
"""

from __future__ import annotations

import math
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, fields, replace
from typing import Any

import cv2
import numpy as np

from nsflow_ros.core.camera import CameraModel
from nsflow_ros.core.detector import detect_corners
from nsflow_ros.core.encoder import Encoder, to_gray
from nsflow_ros.core.errors import CoreError
from nsflow_ros.core.imu import body_to_camera_rotation, integrate_gyro, predict_pixels
from nsflow_ros.core.methods import METHODS as _REGISTRY
from nsflow_ros.core.methods import SolveKind, TrackingMethod, make_method
from nsflow_ros.core.solver import Jacobian, LMConfig

__all__ = [
    "METHODS",
    "CameraFeatures",
    "FeatureTracker",
    "FrameFeatures",
    "TrackerSettings",
    "reject_with_fundamental",
]

METHODS = tuple(_REGISTRY)
"""Tracking methods (:data:`nsflow_ros.core.methods.METHODS`): the NSFlow encoder (ONNX) or image
intensity through the paper's LM solver, OpenCV's pyramidal KLT called exactly as VINS-Fusion calls it
(the baseline), or the NSFlow descriptors through OpenCV's LK."""

# VINS-Mono's FOCAL_LENGTH: the virtual pinhole on which the F-matrix RANSAC threshold is measured.
_VIRTUAL_FOCAL = 460.0


@dataclass(frozen=True)
class TrackerSettings:
    """Settings of :class:`FeatureTracker` (VINS names where VINS has the setting).

    Attributes:
        method: "nsflow" (learned encoder, the default), "classical" (intensity descriptors, same LM
            solver), "klt" (OpenCV ``calcOpticalFlowPyrLK`` on the gray / CLAHE'd image with VINS-Fusion's
            arguments: 21x21, maxLevel 3, criteria COUNT|EPS 30 / 0.01; ``lm`` is then unused, the rest of
            the pipeline is the same) or "nsflow_lk" (the learned descriptors as uint8 through the same
            OpenCV calls).
        model_path: ONNX encoder of the learned methods; None = the shipped ``models/nsflow_encoder.onnx``.
        num_threads: encoder threads; None = all usable cores.
        max_cnt: VINS ``max_cnt``, the number of features kept per frame.
        min_dist: VINS ``min_dist``, the minimum distance between features in pixels.
        quality: GFTT quality level (VINS: 0.01).
        F_threshold: VINS ``F_threshold``, RANSAC threshold in pixels of the virtual 460 px pinhole.
        reject_with_f: run the fundamental-matrix RANSAC (VINS-Mono does, VINS-Fusion does not).
        flow_back: VINS ``flow_back``, the reverse-tracking check.
        flow_back_threshold: how far (px) the reverse track may land from the start point (VINS: 0.5).
        border: points whose rounded position is closer than this to the image edge are dropped (VINS: 1).
        equalize: apply CLAHE (clip 3, 8x8 tiles, as VINS-Mono) before tracking and detection.
        stereo: track camera 0 into camera 1 (needs two cameras and an image pair per frame).
        lm: the solver's settings. Four levels by default: VINS calls OpenCV LK with maxLevel 3, i.e.
            four pyramid levels, and the capture range matters for stereo disparity and fast motion.
            ``min_eigen`` is the solver's 1e-5: on real textures at 320x240, 1e-4 rejected about 30 %
            of correctly tracked GFTT corners (survival per frame 0.59 -> 0.86 at 1e-5). ``margin`` 1:
            a point may be tracked until its window reaches past the edge, as OpenCV's LK allows (the
            VINS border check keeps 1 px); requiring the whole window inside lost 3 % of the tracks
            per frame on the 752x480 sample sequence, nearly all within 40 px of the border.
            ``jacobian`` ESM (the mean of frame 2's and the template's derivatives): on the evaluation
            suite it widened every basin figure (capture from zero flow, stereo under lighting change
            71.7 -> 83.6 %; trackable region one level fewer 48.4 -> 63.0 %; one-level convergence
            3.66 -> 3.07 px) for ~2 % more time per frame (interleaved with ``klt``, 752x480). Checks keep the
            forward Jacobian (``LMMethod.check_jacobian``). ``zero_mean``: windows are compared up to
            a constant per channel, so the offset a lighting change leaves between the two frames'
            descriptor windows costs nothing; on the evaluation suite NSFlow's illumination pairs within
            1 px rose 96.9 -> 98.6 %, stereo capture from zero flow under a lighting change 80.5 ->
            94.8 %, the trackable region under one 75.4 -> 84.8 %, while the basin without a lighting
            change narrowed a little (trackable region one level fewer 73.7 -> 67.4 %, one-level
            convergence 1.80 -> 2.18 px), which the model's coarser smoothing of the coarse levels, now
            affordable, more than won back (83.2 %; models/README.md). ``eps`` 0.05 (the library's
            0.01; checks keep 0.01, ``LMMethod.check_eps``): the looser stop test keeps every
            evaluation figure within about a point of eps 0.01-0.03 and pays back part of the
            zero-mean sums' cost: the two together cost ~4 % of the frame (zero mean alone +6 %;
            docs/benchmarks.md). Intensity (``classical``) loses more basin with the loose stop test;
            set ``eps=0.01`` there for its best accuracy. ``coarse_window`` 21 from level 2 (VINS's
            KLT window) widens every basin figure from zero flow (capture of photo shifts 94.1 ->
            98.2 %, the trackable region one level fewer 83.2 -> 95.6 %); the tracker's solves from a
            prior keep the fine window (``LMMethod.fill_levels``), so only solves without any start
            (the first frame) pay for it.
        use_imu_prediction: use gyro samples given to :meth:`FeatureTracker.process` to predict the flow.
        prediction_min_tracked: with a prediction, retry on the full pyramid when fewer points survive
            the single-level solve (VINS: 10).
    """

    method: str = "nsflow"
    model_path: str | None = None
    num_threads: int | None = None
    max_cnt: int = 150
    min_dist: float = 30.0
    quality: float = 0.01
    F_threshold: float = 1.0
    reject_with_f: bool = False
    flow_back: bool = True
    flow_back_threshold: float = 0.5
    border: int = 1
    equalize: bool = False
    stereo: bool = False
    lm: LMConfig = field(
        default_factory=lambda: LMConfig(
            levels=4, margin=1, tail_share=0.4, tail_passes=2, jacobian=Jacobian.ESM, eps=0.05,
            zero_mean=True, coarse_window=21, coarse_from=2,
        )
    )
    use_imu_prediction: bool = False
    prediction_min_tracked: int = 10

    def __post_init__(self) -> None:
        if self.method not in METHODS:
            raise CoreError(f"method must be one of {METHODS}, got {self.method!r}")
        if self.max_cnt < 1:
            raise CoreError(f"max_cnt must be >= 1, got {self.max_cnt}")
        if not (math.isfinite(self.min_dist) and self.min_dist >= 0):
            raise CoreError(f"min_dist must be finite and >= 0, got {self.min_dist}")
        if not 0 < self.quality < 1:
            raise CoreError(f"quality must be in (0, 1), got {self.quality}")
        if self.reject_with_f and not self.F_threshold > 0:
            raise CoreError(f"F_threshold must be > 0 when reject_with_f is on, got {self.F_threshold}")
        if not self.flow_back_threshold > 0:
            raise CoreError(f"flow_back_threshold must be > 0, got {self.flow_back_threshold}")
        if self.border < 0:
            raise CoreError(f"border must be >= 0, got {self.border}")
        if self.num_threads is not None and self.num_threads < 1:
            raise CoreError(f"num_threads must be >= 1 or None, got {self.num_threads}")
        if not isinstance(self.lm, LMConfig):
            raise CoreError(f"lm must be an LMConfig, got {type(self.lm).__name__}")

    def with_overrides(self, overrides: Mapping[str, Any]) -> TrackerSettings:
        """Return a copy with some fields replaced; unknown names raise a CoreError listing the valid ones.

        ``window`` and ``levels`` are accepted as shortcuts for the corresponding ``lm`` fields.
        """
        names = {f.name for f in fields(self)}
        values = dict(overrides)
        lm_changes = {k: values.pop(k) for k in ("window", "levels") if k in values}
        unknown = sorted(set(values) - names)
        if unknown:
            valid = sorted(names | {"window", "levels"})
            raise CoreError(f"unknown tracker setting(s) {unknown}; valid: {valid}")
        out = replace(self, **values)
        if lm_changes:
            out = replace(out, lm=replace(out.lm, **lm_changes))
        return out


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

    Shape:
        ids, track_counts: (N,) int64. pixels, undistorted, velocities, previous: (N, 2) float64.
    """

    camera_id: int
    ids: np.ndarray
    pixels: np.ndarray
    undistorted: np.ndarray
    velocities: np.ndarray
    track_counts: np.ndarray
    previous: np.ndarray

    def __len__(self) -> int:
        return int(self.ids.shape[0])


@dataclass(frozen=True)
class FrameFeatures:
    """Output of :meth:`FeatureTracker.process` for one frame.

    Attributes:
        stamp: the frame's time in seconds.
        cameras: camera 0, then camera 1 for stereo.
        image_size: (width, height) of the images.
        timings: wall time of the stages in milliseconds (encode, track, detect, stereo, total).
    """

    stamp: float
    cameras: tuple[CameraFeatures, ...]
    image_size: tuple[int, int]
    timings: dict[str, float] = field(default_factory=dict)

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

    The undistorted normalised points are mapped onto a pinhole of focal length ``focal`` centred in the
    image, so ``threshold`` means the same number of pixels for every lens model.

    Args:
        prev_undistorted: normalised points in the previous frame.
        cur_undistorted: the same points in the current frame.
        threshold: RANSAC threshold in virtual pixels (VINS ``F_threshold``).
        image_size: (width, height), for the virtual principal point.
        focal: virtual focal length (VINS: 460).

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


def _velocities(
    ids: np.ndarray, pts: np.ndarray, prev_ids: np.ndarray, prev_pts: np.ndarray, dt: float
) -> tuple[np.ndarray, np.ndarray]:
    """Velocity per id from the previous frame's points (0 for unseen ids) and the matched index (-1)."""
    vel = np.zeros_like(pts)
    match = np.full(ids.shape[0], -1, np.int64)
    if ids.size == 0 or prev_ids.size == 0 or not dt > 0:
        return vel, match
    order = np.argsort(prev_ids, kind="stable")
    sorted_ids = prev_ids[order]
    pos = np.clip(np.searchsorted(sorted_ids, ids), 0, sorted_ids.size - 1)
    found = sorted_ids[pos] == ids
    match[found] = order[pos[found]]
    vel[found] = (pts[found] - prev_pts[match[found]]) / dt
    return vel, match


def _check_mask(mask: np.ndarray, camera: CameraModel) -> np.ndarray:
    if not isinstance(mask, np.ndarray) or mask.ndim != 2:
        got = f"shape {mask.shape}" if isinstance(mask, np.ndarray) else type(mask).__name__
        raise CoreError(f"mask must be a 2-D uint8 array, got {got}")
    if mask.shape != (camera.height, camera.width):
        h, w = mask.shape
        raise CoreError(f"mask is {w}x{h} but camera 0 ({camera.name}) is {camera.width}x{camera.height}")
    if mask.dtype != np.uint8:
        raise CoreError(f"mask must be uint8 (0 / 255), got dtype {mask.dtype}")
    return np.where(mask > 127, 255, 0).astype(np.uint8)


@dataclass
class _CameraState:
    ids: np.ndarray
    pixels: np.ndarray
    undistorted: np.ndarray
    flow: np.ndarray  # pixel motion since the id's previous frame on this camera, NaN for new ids


def _empty_state() -> _CameraState:
    return _CameraState(np.zeros(0, np.int64), np.zeros((0, 2)), np.zeros((0, 2)), np.zeros((0, 2)))


def _lookup(ids: np.ndarray, table_ids: np.ndarray, values: np.ndarray) -> np.ndarray:
    """``values`` of ``table_ids`` for each of ``ids``; NaN where an id is not in the table."""
    out = np.full((ids.shape[0], values.shape[1]), np.nan)
    if ids.size == 0 or table_ids.size == 0:
        return out
    order = np.argsort(table_ids, kind="stable")
    pos = np.clip(np.searchsorted(table_ids[order], ids), 0, table_ids.size - 1)
    found = table_ids[order][pos] == ids
    out[found] = values[order[pos[found]]]
    return out


class FeatureTracker:
    """VINS-Fusion's feature tracker on NSFlow descriptors (see the module docstring for the steps).

    Args:
        cameras: camera 0, and camera 1 when ``settings.stereo``.
        settings: tracker settings.
        encoder: descriptor encoder to use instead of the one ``settings.method`` selects (tests, benchmarks);
            not allowed with method "klt", which tracks the gray image.
        body_R_cam0: rotation camera 0 -> IMU body (VINS ``body_T_cam0[:3, :3]``) for the gyro prediction;
            None = identity.
        mask: camera 0's static mask, VINS-Mono's fisheye mask: uint8 (H, W) of the camera's size,
            255 where features may be, 0 elsewhere. Tracked points on 0 are dropped and no corner is
            detected there (VINS-Mono ``setMask``, on the frames that detect). None = the whole image.

    Raises:
        CoreError: on inconsistent settings (stereo without a second camera, a mask of the wrong size, ...).
        EncoderError: when the "nsflow" model cannot be loaded.
    """

    def __init__(
        self,
        cameras: Sequence[CameraModel],
        settings: TrackerSettings | None = None,
        *,
        encoder: Encoder | None = None,
        body_R_cam0: np.ndarray | None = None,
        mask: np.ndarray | None = None,
    ) -> None:
        self.settings = settings or TrackerSettings()
        self.cameras = tuple(cameras)
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
        # The method is chosen here, once; every solve below is method-blind.
        self.method: TrackingMethod = make_method(
            s.method, lm=s.lm, encoder=encoder, model_path=s.model_path, threads=s.num_threads
        )
        self.body_R_cam0 = None if body_R_cam0 is None else np.asarray(body_R_cam0, dtype=np.float64)
        if self.body_R_cam0 is not None and self.body_R_cam0.shape != (3, 3):
            raise CoreError(f"body_R_cam0 must have shape (3, 3), got {self.body_R_cam0.shape}")
        self._clahe = cv2.createCLAHE(clipLimit=3.0, tileGridSize=(8, 8)) if self.settings.equalize else None
        self.mask = None if mask is None else _check_mask(mask, self.cameras[0])
        self._next_id = 0
        self.reset()

    # -- state -----------------------------------------------------------------------------------------

    @property
    def encoder(self) -> Encoder | None:
        """The method's descriptor encoder (None for ``klt``, which tracks the gray image)."""
        return self.method.encoder

    def reset(self) -> None:
        """Forget all tracks (ids keep counting up, so an id is never reused)."""
        self._stamp: float | None = None
        self._frame: Any = None  # the previous camera-0 frame's representation
        self._left = _empty_state()
        self._counts = np.zeros(0, np.int64)
        self._right = _empty_state()

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
        """Return (gray for detection, the method's representation of the image)."""
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
        check: SolveKind,
        frame1: Any,
        frame2: Any,
        pts: np.ndarray,
        size: tuple[int, int],
        start: np.ndarray | None = None,
        prior: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """A solve, the border check and its reverse check, the same for every method.

        Returns (positions in frame 2, status). A trusted ``start`` (the IMU prediction) that leaves fewer
        than ``prediction_min_tracked`` points is dropped and the solve repeated without it (VINS).
        """
        s = self.settings
        m = self.method
        new, status = m.solve(kind, frame1, frame2, pts, start, prior)
        if start is not None and int(status.sum()) < s.prediction_min_tracked:
            new, status = m.solve(kind, frame1, frame2, pts, None, prior)
        status &= _in_border(new, size, s.border)
        if s.flow_back and status.any():
            # Only live points are checked: the others are dropped anyway.
            idx = np.flatnonzero(status)
            back, ok = m.solve(check, frame2, frame1, new[idx], pts[idx])
            status[idx] = ok & (np.hypot(*(back - pts[idx]).T) <= s.flow_back_threshold)
        return new, status

    def _predict(self, gyro: np.ndarray | None, stamp: float) -> np.ndarray | None:
        if not self.settings.use_imu_prediction or gyro is None:
            return None
        if self._stamp is None or self._left.ids.size == 0:
            return None
        body_rot = integrate_gyro(gyro, self._stamp, stamp)
        cam_rot = body_to_camera_rotation(body_rot, self.body_R_cam0)
        return predict_pixels(self.cameras[0], self._left.undistorted, cam_rot)

    def _set_mask(
        self, pts: np.ndarray, counts: np.ndarray, size: tuple[int, int]
    ) -> tuple[np.ndarray, np.ndarray]:
        """Keep the longest tracks first, each blocking a disc of radius min_dist; returns (keep, mask).

        Starts from the static (fisheye) mask, so tracks on its zeros are dropped as well.
        """
        w, h = size
        mask = np.full((h, w), 255, np.uint8) if self.mask is None else self.mask.copy()
        order = np.argsort(-counts, kind="stable")
        radius = round(self.settings.min_dist)
        keep: list[int] = []
        for i in order:
            x, y = int(np.rint(pts[i, 0])), int(np.rint(pts[i, 1]))
            if 0 <= x < w and 0 <= y < h and mask[y, x] == 255:
                keep.append(int(i))
                cv2.circle(mask, (x, y), radius, 0, -1)
        return np.asarray(keep, np.int64), mask

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
        cam = self.cameras[0]
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

    # -- main entry ------------------------------------------------------------------------------------

    def process(
        self,
        stamp: float,
        image0: np.ndarray,
        image1: np.ndarray | None = None,
        gyro: np.ndarray | None = None,
        *,
        detect: bool = True,
    ) -> FrameFeatures:
        """Track one frame (VINS-Fusion ``trackImage``).

        Args:
            stamp: the frame's time in seconds; must increase from frame to frame.
            image0: camera-0 image, uint8 (H, W) mono or (H, W, 3) BGR.
            image1: camera-1 image of the same stamp (stereo only).
            gyro: gyro samples (t, wx, wy, wz) covering the interval since the previous frame, in the IMU
                frame; used when ``settings.use_imu_prediction`` is on.
            detect: top the features up with new corners (VINS-Mono skips this on throttled frames).

        Returns:
            the frame's features.

        Raises:
            CoreError: on a stamp that does not increase, a wrong image size or type, or a missing
                stereo image. The tracker's state is unchanged when it raises.

        Shape:
            gyro: (M, 4).
        """
        t_start = time.perf_counter()
        if not math.isfinite(stamp):
            raise CoreError(f"stamp must be finite, got {stamp}")
        if self._stamp is not None and stamp <= self._stamp:
            raise CoreError(
                f"timestamps must increase: got {stamp:.9f} after {self._stamp:.9f} "
                "(call reset() to start over, e.g. when a bag loops)"
            )
        size = self._check_images(image0, image1)
        s = self.settings
        timings: dict[str, float] = {}

        predicted = self._predict(gyro, stamp)  # before any state changes: may raise on bad samples
        t0 = time.perf_counter()
        gray0, frame0 = self._prepare(image0, "image0")
        timings["encode"] = (time.perf_counter() - t0) * 1e3

        t0 = time.perf_counter()
        prev = self._left
        if self._frame is not None and prev.ids.size:
            # Constant-velocity prior: each id moves as it did into the previous frame.
            prior = prev.pixels + prev.flow
            pts, status = self._track(
                SolveKind.FORWARD, SolveKind.FLOW_BACK, self._frame, frame0, prev.pixels, size,
                predicted, prior,
            )
            ids, counts, prev_px = prev.ids[status], self._counts[status], prev.pixels[status]
            pts = pts[status]
            prev_un = prev.undistorted[status]
        else:
            ids, counts = np.zeros(0, np.int64), np.zeros(0, np.int64)
            pts, prev_px, prev_un = np.zeros((0, 2)), np.zeros((0, 2)), np.zeros((0, 2))
        counts = counts + 1
        timings["track"] = (time.perf_counter() - t0) * 1e3

        t0 = time.perf_counter()
        if detect:
            if s.reject_with_f and ids.size >= 8:
                inl = reject_with_fundamental(prev_un, self.cameras[0].lift(pts), s.F_threshold, size)
                ids, counts, pts, prev_px = ids[inl], counts[inl], pts[inl], prev_px[inl]
            keep, mask = self._set_mask(pts, counts, size)
            ids, counts, pts, prev_px = ids[keep], counts[keep], pts[keep], prev_px[keep]
            wanted = s.max_cnt - ids.size
            if wanted > 0:
                new = detect_corners(gray0, wanted, quality=s.quality, min_distance=s.min_dist, mask=mask)
                k = new.shape[0]
                ids = np.concatenate([ids, np.arange(self._next_id, self._next_id + k, dtype=np.int64)])
                self._next_id += k
                counts = np.concatenate([counts, np.ones(k, np.int64)])
                pts = np.concatenate([pts, new])
                prev_px = np.concatenate([prev_px, np.full((k, 2), np.nan)])
        timings["detect"] = (time.perf_counter() - t0) * 1e3

        dt = stamp - self._stamp if self._stamp is not None else 0.0
        un0 = self.cameras[0].lift(pts) if pts.size else np.zeros((0, 2))
        vel0, _ = _velocities(ids, un0, prev.ids, prev.undistorted, dt)
        left = CameraFeatures(0, ids, pts, un0, vel0, counts, prev_px)
        cams = [left]

        right_state = _empty_state()
        if s.stereo:
            t0 = time.perf_counter()
            _, frame1 = self._prepare(image1, "image1")  # type: ignore[arg-type]
            r_ids, r_pts, r_cnt = np.zeros(0, np.int64), np.zeros((0, 2)), np.zeros(0, np.int64)
            if ids.size:
                # Prior: each id's disparity in the previous frame.
                r = self._right
                disparity = r.pixels - _lookup(r.ids, prev.ids, prev.pixels)
                prior = pts + _lookup(ids, r.ids, disparity)
                rpts, st = self._track(
                    SolveKind.STEREO, SolveKind.STEREO_BACK, frame0, frame1, pts, size, None, prior
                )
                r_ids, r_pts, r_cnt = ids[st], rpts[st], counts[st]
            r_un = self.cameras[1].lift(r_pts) if r_pts.size else np.zeros((0, 2))
            r_vel, r_match = _velocities(r_ids, r_un, self._right.ids, self._right.undistorted, dt)
            r_prev = np.full_like(r_pts, np.nan)
            r_prev[r_match >= 0] = self._right.pixels[r_match[r_match >= 0]]
            cams.append(CameraFeatures(1, r_ids, r_pts, r_un, r_vel, r_cnt, r_prev))
            right_state = _CameraState(r_ids, r_pts, r_un, r_pts - r_prev)
            timings["stereo"] = (time.perf_counter() - t0) * 1e3

        # Commit the new state only now, so an exception above leaves the tracker as it was.
        self._stamp = float(stamp)
        self._frame = frame0
        self._left = _CameraState(ids, pts, un0, pts - prev_px)
        self._counts = counts
        self._right = right_state
        timings["total"] = (time.perf_counter() - t_start) * 1e3
        return FrameFeatures(float(stamp), tuple(cams), size, timings)
