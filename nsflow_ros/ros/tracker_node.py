"""The ``tracker`` node: NSFlow features for an unchanged VINS-Fusion / VINS-Mono estimator.

    ros2 run nsflow_ros tracker --ros-args -p config_file:=<VINS config.yaml>
    nsflow-tracker --help      (what it does, its topics, every parameter with its default)

The node is a thin shell around :class:`nsflow_ros.vins.session.FrontEndSession` (frame policy, tracker,
run-time parameter changes). Images are decoded and paired in the subscription callbacks and handed to one
worker thread through :class:`~nsflow_ros.ros.frame_queue.LatestFrames`, so the tracker works on the newest
frames and every superseded frame is counted. A bad frame is logged once per cause, then counted and
skipped; a bad config, model or parameter stops the node at start-up with one line and exit code 1;
SIGINT and SIGTERM stop it with exit code 0 after its summary line.
"""

from __future__ import annotations

import json
import re
import sys
import threading
import time
from array import array
from collections import deque
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import rclpy
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import Point32
from rcl_interfaces.msg import ParameterDescriptor, SetParametersResult
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import QoSHistoryPolicy, QoSProfile, QoSReliabilityPolicy, qos_profile_sensor_data
from rclpy.qos_overriding_options import QoSOverridingOptions
from sensor_msgs.msg import ChannelFloat32, CompressedImage, Image, Imu, PointCloud
from std_msgs.msg import Bool

from nsflow_ros.allocator import keep_large_buffers
from nsflow_ros.core.encoder import encoder_provider
from nsflow_ros.core.masks import MASK_CONVENTIONS, binarize
from nsflow_ros.core.tracker import FrameFeatures
from nsflow_ros.data.images import ImageDecodeError, compressed_for_tracker, decode_image, image_for_tracker
from nsflow_ros.data.messages import image_fields
from nsflow_ros.errors import NSFlowError
from nsflow_ros.files import atomic_write
from nsflow_ros.ros.counters import CAUSES, DROPPED, Kind, NodeCounters, cause, image_cause
from nsflow_ros.ros.errors import ParameterError
from nsflow_ros.ros.frame_masks import FrameMasks
from nsflow_ros.ros.frame_queue import LatestFrames
from nsflow_ros.ros.signals import StopRequested, StopSignals, init_without_signal_handlers
from nsflow_ros.ros.tracker_params import NODE_NAME, PARAMETERS, coerce, spec, usage
from nsflow_ros.ros.transport import use_large_image_transport
from nsflow_ros.stamps import stamp_to_ns, stamp_to_s
from nsflow_ros.threads import set_opencv_threads
from nsflow_ros.vins.config import load_vins_config
from nsflow_ros.vins.draw import draw_tracks
from nsflow_ros.vins.errors import ConfigError
from nsflow_ros.vins.health import (
    HealthMonitor,
    HealthReport,
    Thresholds,
    check_static_masks,
    usable_share,
)
from nsflow_ros.vins.messages import FeatureCloud, encode
from nsflow_ros.vins.pairing import StereoPairer
from nsflow_ros.vins.session import FrameOutcome, FrontEndSession, Skip
from nsflow_ros.vins.settings import SESSION_SETTINGS, Mode
from nsflow_ros.vins.tracker import load_static_masks

__all__ = [
    "FEATURE_QOS", "IMAGE_TRANSPORTS", "NODE_NAME", "PARAMETERS", "TrackerNode", "main", "rclpy_image",
    "resolve_config_path",
]

FEATURE_QOS = QoSProfile(
    depth=2000, reliability=QoSReliabilityPolicy.RELIABLE, history=QoSHistoryPolicy.KEEP_LAST
)
IMU_QOS = QoSProfile(
    depth=400, reliability=QoSReliabilityPolicy.BEST_EFFORT, history=QoSHistoryPolicy.KEEP_LAST
)
DIAGNOSTIC_NAME = f"{NODE_NAME}: front-end"
MASK_ENCODINGS = ("mono8", "8UC1")
"""Encodings of the per-frame mask topics (8-bit, one channel)."""
MASK_COUNTS = ("masks_received", "masks_used", "masks_missing", "masks_late", "masks_unused", "masks_refused",
               "masks_left_at_stop")
"""The per-frame mask counts (:meth:`TrackerNode.mask_counters`) as the summary and /diagnostics name them:
received = used + late + unused + refused + left at the stop (missing counts frames, not masks)."""

IMAGE_TRANSPORTS: dict[str, tuple[type, Any, str]] = {
    "raw": (Image, image_for_tracker, ""),
    "compressed": (CompressedImage, compressed_for_tracker, "/compressed"),
}
"""image_transport -> (message type, decoder to the tracker's array, suffix of the image topic)."""


def resolve_config_path(value: str) -> Path:
    """Find a config file: absolute as is; relative in the package share directory, then the cwd.

    Raises:
        ConfigError: naming every place looked at.
    """
    if not value:
        raise ConfigError("parameter config_file is empty: give the VINS config, e.g. -p config_file:=<path>")
    path = Path(value).expanduser()
    if path.is_absolute():
        candidates = [path]
    else:
        candidates = []
        try:
            from nsflow_ros.resources import share_dir

            candidates.append(share_dir() / path)
        except NSFlowError:
            pass
        candidates.append(Path.cwd() / path)
    for cand in candidates:
        if cand.is_file():
            return cand
    raise ConfigError(f"VINS config {value!r} not found (looked at {', '.join(str(c) for c in candidates)})")


def rclpy_image(image: np.ndarray, encoding: str | None = None) -> Image:
    """An rclpy sensor_msgs/Image (header unset) in :func:`~nsflow_ros.data.messages.image_fields`' layout.

    No rosbags typestore: building one inside the first frame would delay it (docs/benchmarks.md).

    Raises:
        DataError: the pixels do not match the encoding.
    """
    f = image_fields(image, encoding)
    msg = Image(height=f.height, width=f.width, encoding=f.encoding, is_bigendian=0, step=f.step)
    msg.data = f.data.tobytes()
    return msg


@dataclass
class _Frame:
    """A decoded frame waiting for the tracker."""

    header: Any
    image0: np.ndarray
    image1: np.ndarray | None
    t_recv: float  # perf_counter when its (first) image arrived
    t_queued: float = 0.0  # perf_counter when it joined the queue (decoded and paired)
    masks: tuple[np.ndarray | None, ...] = ()  # this frame's masks per camera, once the worker took them


def _percentile(values: list[float], q: float) -> float | None:
    return float(np.percentile(values, q)) if values else None


def _cpu_per_frame(cpu_s: float, frames: int) -> float | None:
    """The process's CPU time (all threads) per processed frame, in ms."""
    return cpu_s * 1e3 / frames if frames else None


class TrackerNode(Node):
    """The nsflow_tracker node.

    Args:
        context: rclpy context (None = the default one).
        parameter_overrides: parameters to set at construction (tests, composition).

    Raises:
        NSFlowError: a bad parameter, config, model or setting.
    """

    def __init__(self, *, context: Any = None, parameter_overrides: list[Any] | None = None) -> None:
        super().__init__(NODE_NAME, context=context, parameter_overrides=parameter_overrides)
        p: dict[str, Any] = {}
        for ps in PARAMETERS:
            # dynamic typing so that a slip (-p F_threshold:=1) reaches spec.coerce and gets a clear answer
            desc = ParameterDescriptor(
                description=ps.full_description,
                additional_constraints=f"{ps.kind} (checked by the node)",
                read_only=ps.mode is Mode.READ_ONLY,
                dynamic_typing=True,
            )
            p[ps.name] = coerce(ps, self.declare_parameter(ps.name, ps.default, desc).value)
        self._params = p
        set_opencv_threads(int(p["opencv_threads"]))  # process-wide, before the tracker's first call

        cfg = load_vins_config(resolve_config_path(str(p["config_file"])))
        use_imu = bool(p["use_imu_prediction"])
        if use_imu and not cfg.imu_topic:
            self.get_logger().warning("use_imu_prediction is on but the config names no imu_topic: disabled")
            use_imu = False
        settings = {k: p[k] for k in SESSION_SETTINGS if k != "use_imu_prediction"}
        convention = str(p["mask_convention"])
        if convention not in MASK_CONVENTIONS:
            raise ParameterError(
                f"parameter mask_convention: got {convention!r}, expected {' or '.join(MASK_CONVENTIONS)}"
            )
        self._mask_convention = convention
        static = load_static_masks(cfg, str(p["mask0"]) or None, str(p["mask1"]) or None, convention)
        # before the tracker is built: a mask with no usable pixel stops the node in one line
        names = [f"mask{i} {str(p[f'mask{i}']) or getattr(cfg, f'mask{i}')}" for i in range(2)]
        mask_warnings = check_static_masks(dict(zip(names, static, strict=True)), float(p["mask_min_usable"]))
        self._health = HealthMonitor(Thresholds.from_values(p))
        self._gated_last = 0  # the session's gated count at the last status report
        self.session = FrontEndSession(
            cfg,
            {**settings, "use_imu_prediction": use_imu},
            layout=str(p["output_layout"]) or None,
            fisheye_mask=str(p["fisheye_mask"]) or None,
            masks=static,
        )
        self.layout = self.session.layout

        self.stats = NodeCounters()
        self.latencies_ms: deque[float] = deque(maxlen=2000)
        self._lat_lock = threading.Lock()
        self._logged_causes: set[str] = set()
        cameras = 2 if self.session.tracker.settings.stereo else 1
        self._pairer: StereoPairer[tuple[Any, np.ndarray, float]] = StereoPairer(
            cameras, float(p["stereo_sync_tolerance"])
        )
        self._tolerance_checked = cameras == 1  # checked once a frame period is measured (stereo only)
        self._last_stamp: float | None = None  # of the last frame handed to the session (worker thread)
        transport = str(p["image_transport"])
        if transport not in IMAGE_TRANSPORTS:
            raise ParameterError(
                f"parameter image_transport: got {transport!r}, expected one of {', '.join(IMAGE_TRANSPORTS)}"
            )
        image_type, self._decode, suffix = IMAGE_TRANSPORTS[transport]
        self._track_last = -np.inf  # monotonic time of the last debug image
        self.track_images_published = 0
        self._lock = threading.Lock()  # the session and the publishers: worker vs. parameter updates
        self._queue: LatestFrames[_Frame] = LatestFrames(int(p["queue_size"]))
        self._stop_lock = threading.Lock()
        self._stopping = False
        self._cpu_start = time.process_time()
        self._status = _StatusWindow()
        self._gaps = [_StampGaps() for _ in range(cameras)]  # per camera, every image that arrived
        self._missing = [0] * cameras

        self._feature_pub = self.create_publisher(PointCloud, str(p["feature_topic"]), FEATURE_QOS)
        self._restart_pub = self.create_publisher(Bool, str(p["restart_topic"]), FEATURE_QOS)
        self._track_pub: Any = None
        self._set_track_publisher(self.session.show_track)
        self._diag_pub = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        # image_transport's naming: the image topic (remapped) plus the transport's suffix
        topics = [self.resolve_topic_name(t) + suffix if suffix else t for t in cfg.image_topics]
        self._subs = [
            self.create_subscription(
                image_type,
                topic,
                lambda m, i=i: self._on_image(i, m),
                qos_profile_sensor_data,
                qos_overriding_options=QoSOverridingOptions.with_default_policies(),
            )
            for i, topic in enumerate(topics)
        ]
        if use_imu:
            self._subs.append(self.create_subscription(Imu, cfg.imu_topic, self._on_imu, IMU_QOS))
        self._masks, self._mask_subs = self._subscribe_masks(cfg, float(p["stereo_sync_tolerance"]))
        self.masks_received = 0
        self.masks_refused = 0
        self._mask_waiting = False  # the worker waits for a frame's mask (see _enqueue)
        self._mask_last: dict[str, int] = {}  # the mask counts at the last status report
        self._timer: Any = None
        self._set_status_timer(float(p["status_period"]))
        self.add_on_set_parameters_callback(self._on_set_parameters)

        self._worker = threading.Thread(target=self._work, name="nsflow_tracker_frames", daemon=True)
        self._worker.start()
        s = self.session.tracker.settings
        self._image_topics = [sub.topic_name for sub in self._subs[: len(cfg.image_topics)]]
        images = ", ".join(self._image_topics)
        self.get_logger().info(
            f"{cfg.dialect} config {cfg.path} ({'stereo' if s.stereo else 'mono'}, {cfg.image_width}x"
            f"{cfg.image_height}); method {s.method} (encoder on {encoder_provider(self.tracker.encoder)}), "
            f"layout {self.layout}, max_cnt {s.max_cnt}, min_dist "
            f"{s.min_dist:g}, flow_back {s.flow_back}, F-RANSAC {s.reject_with_f}, IMU prediction {use_imu}"
            + (f", downsample {s.downsample}" if s.downsample != 1 else "")
            + (f", publish_rate {self.session.publish_rate:g} Hz" if self.session.publish_rate else "")
            + "; "
            f"{transport} images on {images}"
            + (f", IMU on {self._subs[-1].topic_name}" if use_imu else "")
            + f"; features on {self._feature_pub.topic_name}"
            + self._mask_note(static)
        )
        for warning in mask_warnings:
            self.get_logger().warning(warning)
        if s.covariance:  # what the covariance channels are scaled by, and whether it was fitted
            scale = self.tracker.method.covariance_scale
            self.get_logger().info(f"covariance scale {scale.scale:.4g}, floor {scale.floor:.3g} px^2 "
                                   f"({scale.source}), max_sigma {s.max_sigma:g} px (0 = off)")

    # -- accessors -------------------------------------------------------------------------------------

    @property
    def tracker(self) -> Any:
        """The session's :class:`~nsflow_ros.core.tracker.FeatureTracker`."""
        return self.session.tracker

    @property
    def config(self) -> Any:
        """The effective VINS config (file values with the parameter overrides)."""
        return self.session.config

    # -- masks -----------------------------------------------------------------------------------------

    def _subscribe_masks(self, cfg: Any, tolerance: float) -> tuple[list[FrameMasks | None], list[Any]]:
        """The per-frame mask buffers per camera (None = no mask topic) and their subscriptions."""
        topics = [str(self._params["mask_topic"]), str(self._params["mask1_topic"])]
        cams = 2 if self.session.tracker.settings.stereo else 1
        if topics[1] and cams < 2:
            raise ParameterError(f"parameter mask1_topic: {topics[1]!r} given, but {cfg.path} is mono")
        if topics[1] and not topics[0]:
            raise ParameterError("parameter mask1_topic needs mask_topic (camera 0's masks) too")
        buffers: list[FrameMasks | None] = []
        subs = []
        for cam, topic in enumerate(topics[:cams]):
            if not topic:
                buffers.append(None)
                continue
            buffers.append(FrameMasks(tolerance))
            subs.append(self.create_subscription(
                Image, topic, lambda m, c=cam: self._on_mask(c, m), qos_profile_sensor_data,
                qos_overriding_options=QoSOverridingOptions.with_default_policies(),
            ))
        return buffers, subs

    def _mask_note(self, static: tuple[np.ndarray | None, np.ndarray | None]) -> str:
        """The masks in use, for the start-up line ("" = none)."""
        parts = [f"static mask{i}" for i, m in enumerate(static) if m is not None]
        if self._mask_subs:
            topics = ", ".join(sub.topic_name for sub in self._mask_subs)
            wait = float(self._params["mask_wait_ms"])
            parts.append(f"per-frame masks on {topics} (waiting up to {wait:g} ms)")
        if not parts:
            return ""
        meaning = "usable" if MASK_CONVENTIONS[self._mask_convention] else "masked out"
        return f"; {', '.join(parts)}, read as {self._mask_convention} (255 = {meaning})"

    def _bad_mask(self, cause: str, message: str) -> None:
        """Log a refused mask once per cause; count every one."""
        self.masks_refused += 1
        self.stats.note(cause)  # masks are not images or frames: only their precise cause is kept
        if cause not in self._logged_causes:
            self._logged_causes.add(cause)
            self.get_logger().error(
                f"ignoring mask: {message}; frames go on with the static masks (further masks like it are "
                "only counted)"
            )

    def _on_mask(self, cam: int, msg: Image) -> None:
        """A per-frame mask: checked (encoding, size), read in mask_convention and kept for its frame."""
        self.masks_received += 1
        topic = self._mask_topic(cam)
        buffer = self._masks[cam]
        if buffer is not None and buffer.silent and buffer.silences == 1:
            self.get_logger().info(f"masks on {topic} again: frames wait for theirs again (mask_wait_ms)")
        if msg.encoding not in MASK_ENCODINGS:
            self._bad_mask(f"mask_encoding:{msg.encoding}",
                           f"{topic}: encoding {msg.encoding!r}, expected {' or '.join(MASK_ENCODINGS)}")
            return
        try:
            raw, _ = decode_image(msg, topic)
        except ImageDecodeError as err:
            self._bad_mask(f"mask_{err.cause}", str(err))
            return
        cfg = self.config
        h, w = raw.shape
        if (w, h) != (cfg.image_width, cfg.image_height):
            self._bad_mask(
                "mask_size",
                f"{topic}: mask is {w}x{h} but the images are {cfg.image_width}x{cfg.image_height}",
            )
            return
        if buffer is not None:
            buffer.add(stamp_to_ns(msg.header.stamp), binarize(raw, self._mask_convention))

    def _take_masks(self, frame: _Frame) -> tuple[np.ndarray | None, ...]:
        """The frame's masks per camera, each waited for until mask_wait_ms after its image arrived, or
        until the next frame arrives (a longer wait would cost that frame), but not on a silent topic."""
        if all(b is None for b in self._masks):  # (an empty buffer is falsy: test for None)
            return ()
        deadline = frame.t_recv + float(self._params["mask_wait_ms"]) * 1e-3
        stamp = stamp_to_ns(frame.header.stamp)
        masks = []
        for cam, b in enumerate(self._masks):
            if b is None:
                masks.append(None)
                continue
            silences = b.silences
            self._mask_waiting = True  # a frame superseded meanwhile is the wait's, not the CPU's
            try:
                masks.append(b.take(stamp, deadline - time.perf_counter(), until=self._newer_frame))
            finally:
                self._mask_waiting = False
            if b.silences > silences:
                self._once(f"mask_silent:{cam}",
                           f"no mask on {self._mask_topic(cam)} within mask_wait_ms "
                           f"{float(self._params['mask_wait_ms']):g} ms: frames are tracked without waiting "
                           "for it until a mask comes again (counted as missing)")
        return tuple(masks)

    def _newer_frame(self) -> bool:
        """Whether a newer frame waits for the tracker (ends a wait for a mask)."""
        return len(self._queue) > 0

    def _mask_topic(self, cam: int) -> str:
        return self._mask_subs[cam].topic_name if cam < len(self._mask_subs) else f"camera {cam}"

    def mask_counters(self) -> dict[str, int]:
        """Per-frame masks received, used, missing (frames tracked without theirs), late, unused, refused
        and left at the stop."""
        buffers = [b for b in self._masks if b is not None]
        return {
            "masks_received": self.masks_received,
            "masks_used": sum(b.used for b in buffers),
            "masks_missing": sum(b.missing for b in buffers),
            "masks_late": sum(b.late for b in buffers),
            "masks_unused": sum(b.unused for b in buffers),
            "masks_refused": self.masks_refused,
            "masks_left_at_stop": sum(b.left_at_stop for b in buffers),
        }

    # -- parameters ------------------------------------------------------------------------------------

    def _set_track_publisher(self, on: bool) -> None:
        if on and self._track_pub is None:
            self._track_pub = self.create_publisher(Image, str(self._params["image_track_topic"]), 10)
        elif not on and self._track_pub is not None:
            self.destroy_publisher(self._track_pub)
            self._track_pub = None

    def _set_status_timer(self, period: float) -> None:
        if self._timer is not None:
            self.destroy_timer(self._timer)
            self._timer = None
        if period > 0:
            self._timer = self.create_timer(period, self._report_status)

    def _on_set_parameters(self, params: list[Any]) -> SetParametersResult:
        """Apply a parameter change to the running node, or refuse it with the reason."""
        ours = [q for q in params if q.name in self._params]
        if not ours:
            return SetParametersResult(successful=True)
        try:
            values = {q.name: coerce(spec(q.name), q.value) for q in ours}
            period = values.get("status_period")
            session = {k: v for k, v in values.items() if k in SESSION_SETTINGS}
            tolerance = values.get("stereo_sync_tolerance")
            if tolerance is not None and (problem := self._tolerance_problem(float(tolerance))):
                raise ParameterError(f"parameter {problem}")
            thresholds = Thresholds.from_values({**self._params, **values})  # lost <= degraded
            with self._lock:
                notes = self.session.update(**session) if session else []
                self._set_track_publisher(self.session.show_track)
            if tolerance is not None:  # the pairer runs in this (the executor's) thread
                self._pairer.tolerance = float(tolerance)
                # not measured yet: checked once it is
                self._tolerance_checked = self._pairer.cameras == 1 or self._frame_period() is not None
                for buffer in self._masks:
                    if buffer is not None:
                        buffer.tolerance = float(tolerance)
        except NSFlowError as err:
            return SetParametersResult(successful=False, reason=str(err))
        if period is not None:
            self._set_status_timer(period)
        self._health.thresholds = thresholds
        # the node's own settings: the session's notes name its changes
        notes += [f"{k} is now {v}" for k, v in values.items()
                  if k not in SESSION_SETTINGS and v != self._params.get(k)]
        self._params.update(values)
        for note in notes:
            self.get_logger().info(f"parameter change: {note}")
        return SetParametersResult(successful=True)

    # -- inputs ----------------------------------------------------------------------------------------

    def _frame_period(self) -> float | None:
        """The frame period measured from the stamps of the first camera that has enough of them (s)."""
        return next((g.period for g in self._gaps if g.period is not None), None)

    def _tolerance_problem(self, tolerance: float) -> str | None:
        """Why ``tolerance`` cannot pair stereo images safely; None when it can or no period is measured.

        At half the frame period or more, an image can pair with the other camera's image of the next frame.
        """
        period = self._frame_period()
        if self._pairer.cameras == 1 or period is None or tolerance < period / 2:
            return None
        return (
            f"stereo_sync_tolerance: got {tolerance:g} s, expected less than half the frame period measured "
            f"from the image stamps ({period * 1e3:.1f} ms, {1 / period:.1f} Hz), i.e. < {period / 2:.4g} s: "
            "images of different frames would pair"
        )

    def _bad(self, key: str, detail: str, message: str, n: int = 1) -> None:
        """Count ``n`` images or frames under cause ``key``; log once per precise ``detail``."""
        self.stats.count(key, n, detail)
        if detail not in self._logged_causes:
            self._logged_causes.add(detail)
            c = cause(key)
            what = "image" if c.unit == "image" else "frame"
            self.get_logger().error(
                f"skipping {what} ({c.label}): {message} (further {what}s like it are only counted)"
            )

    def _once(self, key: str, message: str) -> None:
        """Log a warning the first time ``key`` happens; after that it is only counted."""
        if key not in self._logged_causes:
            self._logged_causes.add(key)
            self.get_logger().warning(f"{message} (further ones are only counted)")

    def _on_imu(self, msg: Imu) -> None:
        w = msg.angular_velocity
        with self._lock:
            self.session.add_gyro(stamp_to_s(msg.header.stamp), (w.x, w.y, w.z))

    def _note_arrival(self, cam: int, stamp: float) -> None:
        """Stamp gaps per camera, from every image that arrived (usable or not)."""
        self._missing[cam] += self._gaps[cam].add(stamp)
        # a frame is missing when no camera delivered it: the smallest count of the cameras heard from
        heard = [m for m, g in zip(self._missing, self._gaps, strict=True) if g.seen]
        self.stats.frames_missing_upstream = min(heard)
        if not self._tolerance_checked and self._frame_period() is not None:
            self._tolerance_checked = True
            problem = self._tolerance_problem(self._pairer.tolerance)
            if problem:
                self.get_logger().warning(f"parameter {problem}; set it lower with ros2 param set")

    def _on_image(self, cam: int, msg: Image | CompressedImage) -> None:
        t_recv = time.perf_counter()
        self.stats.add("images_received")
        self._note_arrival(cam, stamp_to_s(msg.header.stamp))
        try:
            img = self._decode(msg)
        except ImageDecodeError as err:
            self._bad(image_cause(err.cause), err.cause, f"camera {cam}: {err}")
            return
        cfg = self.session.config
        h, w = img.shape[:2]
        if (w, h) != (cfg.image_width, cfg.image_height):
            self._bad("wrong_size", f"size:{w}x{h}",
                      f"camera {cam}: image is {w}x{h}, the config's image_width x image_height is "
                      f"{cfg.image_width}x{cfg.image_height}")
            return
        unpaired = self._pairer.unpaired
        pair = self._pairer.add(cam, stamp_to_ns(msg.header.stamp), (msg.header, img, t_recv))
        if self._pairer.unpaired > unpaired:
            self._count_unpaired(self._pairer.unpaired - unpaired)
        if pair is None:
            return
        left, right = pair
        if right is None:
            self._enqueue(_Frame(left[0], left[1], None, left[2]))
        else:
            self._enqueue(_Frame(left[0], left[1], right[1], min(left[2], right[2])))

    def _count_unpaired(self, n: int) -> None:
        self._bad("unpaired", "unpaired",
                  f"{n} stereo image(s) without a partner within stereo_sync_tolerance "
                  f"{self._pairer.tolerance:g} s", n)

    def _enqueue(self, frame: _Frame) -> None:
        self.stats.add("frames_received")
        frame.t_queued = time.perf_counter()
        waiting = self._mask_waiting  # before the put: the worker may take the frame at once
        superseded = self._queue.put(frame)
        if superseded:  # the worker waiting for a mask is not the CPU falling behind
            self.stats.count("mask_wait" if waiting else "superseded", superseded)
        for buffer in self._masks:
            if buffer is not None:
                buffer.wake()  # a frame waiting for its mask is tracked now (see _take_masks)

    # -- the worker --------------------------------------------------------------------------------------

    def _work(self) -> None:
        while True:
            frame = self._queue.take()
            if frame is None:  # stopped
                return
            # a frame that waited in the queue for the one before is late: skip its checks to catch up
            limit = float(self._params["late_frame_ms"])
            checks = not (limit > 0 and (time.perf_counter() - frame.t_queued) * 1e3 > limit)
            frame.masks = self._take_masks(frame)  # outside the lock: a parameter change need not wait
            try:
                with self._lock:
                    self._frame(frame, checks)
            except Exception as err:
                self._bad("tracker_error", f"internal:{type(err).__name__}", f"{type(err).__name__}: {err}")

    def _frame(self, item: _Frame, checks: bool = True) -> None:
        stamp = stamp_to_s(item.header.stamp)
        last, self._last_stamp = self._last_stamp, stamp
        backwards = last is not None and stamp < last
        out: FrameOutcome = self.session.process(
            stamp, item.image0, item.image1, checks=checks, frame_masks=item.masks
        )
        if out.skipped is Skip.DUPLICATE_STAMP:
            self._bad("repeated_stamp", "repeated_stamp", out.note)
            return
        if out.skipped is Skip.TRACKER:  # digits vary from frame to frame, the kind of error does not
            self._bad("tracker_error", "tracker:" + re.sub(r"[0-9.]+", "#", out.note), out.note)
            return
        if out.skipped is Skip.FIRST_FRAME:
            self.stats.count("first_frame")
            return
        if out.restart:
            if backwards:  # refused: VINS-Mono drops it and restarts
                self._bad("stamp_backwards", "stamp_backwards", out.note)
            else:  # a jump forward of more than 1 s: VINS-Mono's policy
                self.stats.count("restart")
                self._once("restart", out.note)
            self._restart_pub.publish(Bool(data=True))
            return
        if not out.tracked:
            return
        if out.note:
            if backwards:
                self.stats.count("reset_backwards")
            self._once("reset_backwards" if backwards else out.note, out.note)
        self.stats.add("frames_processed")
        if not checks:
            self.stats.add("frames_unchecked")
        if out.features is None:  # tracked, held back by publish_rate / freq or VINS-Mono's first
            self.stats.count(out.held or "throttled")
            return
        msg = self._cloud(item.header, out.features)
        latency = (time.perf_counter() - item.t_recv) * 1e3
        with self._lat_lock:
            self.latencies_ms.append(latency)
        self._status.add(latency, len(out.features.cameras[0]))
        # what reaches the estimator: its ids, the image and the masks, for the tracking state
        frame_mask = item.masks[0] if item.masks else None
        self._health.add_frame(out.features.cameras[0].ids, image=item.image0,
                               usable=usable_share(self.tracker.mask, frame_mask))
        self._feature_pub.publish(msg)
        self.stats.add("frames_published")
        if self._track_pub is not None and self._track_due():
            self._publish_track(item.header, out.features, item.image0, item.image1)

    # -- outputs ---------------------------------------------------------------------------------------

    def _cloud(self, header: Any, frame: FrameFeatures) -> PointCloud:
        cloud: FeatureCloud = encode(frame, self.layout, self.config.num_of_cam)  # type: ignore[arg-type]
        msg = PointCloud()
        msg.header = header
        msg.points = [Point32(x=float(x), y=float(y), z=1.0) for x, y in cloud.points[:, :2].tolist()]
        chans = []
        for name, values in zip(cloud.names, cloud.channels, strict=True):
            ch = ChannelFloat32(name=name)
            ch.values = array("f", values.tobytes())
            chans.append(ch)
        msg.channels = chans
        return msg

    def _track_due(self) -> bool:
        """Whether to draw the debug image now: someone subscribes, and track_image_rate allows one."""
        if self._track_pub.get_subscription_count() == 0:
            return False
        rate = float(self._params["track_image_rate"])
        now = time.monotonic()
        if rate > 0 and now - self._track_last < 1.0 / rate:
            return False
        self._track_last = now
        return True

    def _publish_track(
        self, header: Any, frame: FrameFeatures, img0: np.ndarray, img1: np.ndarray | None
    ) -> None:
        msg = rclpy_image(draw_tracks(frame, img0, img1), "bgr8")
        msg.header = header
        self._track_pub.publish(msg)
        self.track_images_published += 1

    # -- status ----------------------------------------------------------------------------------------

    def counters(self) -> dict[str, Any]:
        """The run's counters: images and frames received / processed / dropped by cause, latency."""
        s = self.stats
        with self._lat_lock:
            lat = list(self.latencies_ms)
        settings = self.session.tracker.settings
        return {
            "node": self.get_fully_qualified_name(),
            "method": settings.method,
            "stereo": bool(settings.stereo),
            **s.totals(),
            "frames_skipped_by_policy": s.of(Kind.POLICY),
            "dropped": {c.key: s.lost[c.key] for c in CAUSES if c.unit == "frame" and c.kind in DROPPED},
            "cpu_ms_per_frame": _cpu_per_frame(time.process_time() - self._cpu_start, s.frames_processed),
            "track_images_published": self.track_images_published,
            "restarts": self.session.counters.restarts,
            "features_gated": self.session.counters.gated,
            "latency_ms_p50": _percentile(lat, 50),
            "latency_ms_p90": _percentile(lat, 90),
            **self.mask_counters(),
            **self._health_counters(),
        }

    def _health_counters(self) -> dict[str, Any]:
        """The run's tracking state (the whole run judged as one period) and the status periods by state."""
        gated = self.session.counters.gated
        run = self._health.run_report(max_cnt=self.tracker.settings.max_cnt, gated=gated)
        return {
            "tracking_state": run.state.value,
            "tracking_cause": run.cause,
            "tracking_state_last": self._health.state.value,
            "tracking_periods": dict(self._health.periods),
            "features_per_frame": run.features,
            "ids_carried": run.carried,
        }

    def summary(self) -> str:
        """One line: images and frames received / processed / published, every cause, latency."""
        c = self.counters()
        if not c["images_received"]:
            return "no images received"
        lat = (
            f"; latency p50 {c['latency_ms_p50']:.1f} ms, p90 {c['latency_ms_p90']:.1f} ms"
            if c["latency_ms_p50"] is not None
            else ""
        )
        causes = ", ".join(f"{x.unit}s {x.label} {c[x.name]}" for x in CAUSES if c[x.name]) or "none"
        return (
            f"images received {c['images_received']}, frames received {c['frames_received']}, processed "
            f"{c['frames_processed']} (late, without the reverse checks: {c['frames_unchecked']}), published "
            f"{c['frames_published']}, dropped {c['frames_dropped']}; by cause: {causes}; frames missing "
            f"before the node (stamp gaps) {c['frames_missing_upstream']}{lat}"
            f"{self._mask_summary(c)}{self._health_summary(c)}"
        )

    @staticmethod
    def _health_summary(c: dict[str, Any]) -> str:
        """The run's tracking state for the summary line."""
        periods = ", ".join(f"{k} {n}" for k, n in c["tracking_periods"].items() if n)
        cause = f": {c['tracking_cause']}" if c["tracking_cause"] else ""
        carried = "" if c["ids_carried"] is None else f", {100 * c['ids_carried']:.0f} % of ids carried"
        return (f"; tracking state {c['tracking_state']}{cause} ({c['features_per_frame']:.0f} features/frame"
                f"{carried}{'; status periods ' + periods if periods else ''})")

    def _mask_summary(self, c: dict[str, Any]) -> str:
        """The per-frame mask counts for the summary line ("" without mask topics)."""
        if not self._mask_subs:
            return ""
        return (f"; masks received {c['masks_received']}, missing (frames tracked without theirs) "
                f"{c['masks_missing']}, used {c['masks_used']}, late {c['masks_late']}, unused "
                f"{c['masks_unused']}, refused {c['masks_refused']}, left at the stop "
                f"{c['masks_left_at_stop']}")

    def _report_status(self) -> None:
        """Log one status line and publish it on /diagnostics (see :func:`_status_level`)."""
        c = self.counters()
        window = self._status.take(self.stats)
        level, message = _status_level(window, self._image_topics)
        masks = self._mask_window(c)
        if masks:  # per-frame masks missing, late or refused in this period
            level = max(level, DiagnosticStatus.WARN)
            message = masks if message == "tracking" else f"{message}; {masks}"
        health = self._assess(window)
        if health.state.rank:  # DEGRADED or LOST: at least WARN, whatever the counts say
            level = max(level, DiagnosticStatus.WARN)
        message = f"{message} [{health.text}]"
        values = {
            **{_label(k): c[k] for k in _TOTALS},
            **{f"{_label(k)} (period)": window[k] for k in _TOTALS},
            **{f"{x.unit}s {x.label}": c[x.name] for x in CAUSES},
            **{f"{x.unit}s {x.label} (period)": window[x.name] for x in CAUSES},
            "frames missing upstream (period)": window["frames_missing_upstream"],
            "features per frame (period)": window["features"],
            "latency p50 ms (period)": window["latency_p50"],
            "latency p90 ms (period)": window["latency_p90"],
            "tracking state": health.state.value,
            "tracking state cause": health.cause,
            "ids carried (period)": health.carried,
            "features gated (period)": health.gated,
            "method": c["method"],
            "encoder provider": encoder_provider(self.session.tracker.encoder),
            "CPU ms per frame": c["cpu_ms_per_frame"],
            **({_label(k): c[k] for k in MASK_COUNTS} if self._mask_subs else {}),
        }
        array_msg = DiagnosticArray()
        array_msg.header.stamp = self.get_clock().now().to_msg()
        array_msg.status = [
            DiagnosticStatus(
                level=level,
                name=DIAGNOSTIC_NAME,
                message=message,
                hardware_id=self.get_fully_qualified_name(),
                values=[KeyValue(key=k, value="" if v is None else f"{v:.1f}" if isinstance(v, float)
                                 else str(v)) for k, v in values.items()],
            )
        ]
        self._diag_pub.publish(array_msg)
        if window["images_received"] == 0:
            if not window["quiet"]:  # say it once, then stay quiet until images come
                self.get_logger().info(f"{message} in the last {window['seconds']:.1f} s")
            return
        line = (
            f"{message} (last {window['seconds']:.1f} s: {window['images_received']} images, "
            f"{window['frames_received']} frames received, {window['frames_processed']} processed, "
            f"{window['frames_dropped']} dropped"
        )
        if window["latency_p50"] is not None:
            line += (
                f"; {window['features']:.0f} features/frame, latency p50 {window['latency_p50']:.1f} ms, "
                f"p90 {window['latency_p90']:.1f} ms"
            )
        line += ")"
        if level == DiagnosticStatus.OK:
            self.get_logger().info(line)
        else:  # ERROR on /diagnostics (nothing tracked) is a WARN line: the node itself is fine
            self.get_logger().warning(line)

    def _assess(self, window: dict[str, Any]) -> HealthReport:
        """The period's tracking state from what reached the estimator (:class:`HealthMonitor`)."""
        gated = self.session.counters.gated
        report = self._health.assess(max_cnt=self.tracker.settings.max_cnt, gated=gated - self._gated_last,
                                     images=window["images_received"], tracked=window["frames_processed"])
        self._gated_last = gated
        return report

    def _mask_window(self, c: dict[str, Any]) -> str:
        """The period's mask problems in words ("" = none); starts the next period."""
        now = {k: c[k] for k in MASK_COUNTS}
        d = {k: now[k] - self._mask_last.get(k, 0) for k in MASK_COUNTS}
        self._mask_last = now
        problems = []
        if d["masks_missing"]:
            problems.append(f"{d['masks_missing']} frames tracked without their mask")
        if d["masks_late"]:
            problems.append(f"{d['masks_late']} masks came after their frame was tracked (see mask_wait_ms)")
        if d["masks_refused"]:
            problems.append(f"{d['masks_refused']} masks refused")
        return "; ".join(problems)

    # -- shutdown --------------------------------------------------------------------------------------

    def stop_worker(self, timeout: float = 5.0) -> None:
        """Stop the frame worker (frames still waiting are counted as left at the stop)."""
        with self._stop_lock:
            if not self._stopping:  # frames and images still waiting were not processed
                for buffer in self._masks:
                    if buffer is not None:
                        buffer.close()  # a worker waiting for a mask returns at once
                left = self._queue.close()
                if left:
                    self.stats.count("left_at_stop", left)
                unpaired = self._pairer.flush()
                if unpaired:  # images still waiting for a partner: it can no longer come
                    self.stats.count("unpaired", unpaired, "unpaired")
            self._stopping = True
        if self._worker.is_alive() and self._worker is not threading.current_thread():
            self._worker.join(timeout)

    def write_summary_file(self) -> Path | None:
        """Write :meth:`counters` as JSON to the summary_file parameter's path, if one is set."""
        target = str(self._params["summary_file"])
        if not target:
            return None
        path = Path(target)
        text = json.dumps(self.counters(), indent=2)
        atomic_write(path, lambda tmp: tmp.write_text(text))
        return path

    def destroy_node(self) -> None:
        self.stop_worker()
        super().destroy_node()


class _StampGaps:
    """Frames lost before the node: an interval of k median periods (k >= 2) means k - 1 were lost."""

    def __init__(self, history: int = 50) -> None:
        self._intervals: deque[float] = deque(maxlen=history)
        self._last: float | None = None

    @property
    def seen(self) -> bool:
        """Whether a stamp has been recorded."""
        return self._last is not None

    @property
    def period(self) -> float | None:
        """The median interval of the recent stamps (s); None before 5 intervals were seen."""
        return float(np.median(self._intervals)) if len(self._intervals) >= 5 else None

    def add(self, stamp: float) -> int:
        """Record a frame's stamp; return how many frames are missing just before it."""
        last, self._last = self._last, stamp
        if last is None or stamp <= last:
            return 0
        dt = stamp - last
        period = self.period
        missing = max(0, round(dt / period) - 1) if period else 0
        if not missing:
            self._intervals.append(dt)
        return missing


class _StatusWindow:
    """Counters and latencies since the last status report."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._latencies: list[float] = []
        self._features: list[int] = []
        self._last: dict[str, int] = {}
        self._t = time.monotonic()
        self._idle = 0

    def add(self, latency_ms: float, features: int) -> None:
        with self._lock:
            self._latencies.append(latency_ms)
            self._features.append(features)

    def take(self, counters: NodeCounters) -> dict[str, Any]:
        """The period's figures (every count of ``counters``, features, latency); starts the next period."""
        with self._lock:
            lat, feats = self._latencies, self._features
            self._latencies, self._features = [], []
        now = time.monotonic()
        totals = counters.totals()
        out: dict[str, Any] = {
            "seconds": now - self._t,
            **{k: v - self._last.get(k, 0) for k, v in totals.items()},
            "features": float(np.mean(feats)) if feats else 0.0,
            "latency_p50": _percentile(lat, 50),
            "latency_p90": _percentile(lat, 90),
        }
        self._idle = self._idle + 1 if out["images_received"] == 0 else 0
        out["quiet"] = self._idle > 1
        self._t = now
        self._last = totals
        return out


_TOTALS = ("images_received", "frames_received", "frames_processed", "frames_unchecked", "frames_dropped",
           "frames_published", "frames_missing_upstream")
"""The plain counts on /diagnostics (the causes follow them)."""


def _by_cause(window: dict[str, Any], kind: Kind) -> str:
    """ "300 undecodable images, 2 repeated stamp frames" for the causes of ``kind`` counted in ``window``."""
    return ", ".join(
        f"{window[c.name]} {c.unit}s {c.label}" if window[c.name] != 1 else f"1 {c.unit} {c.label}"
        for c in CAUSES if c.kind is kind and window[c.name]
    )


def _status_level(window: dict[str, Any], topics: list[str]) -> tuple[int, str]:
    """A status period's /diagnostics level and message.

    OK while everything is tracked; WARN when something was refused, superseded or lost upstream, or when
    nothing was tracked without a refusal; ERROR when images came, nothing was tracked and something was
    refused. Every count named by cause.
    """
    if window["images_received"] == 0:
        return DiagnosticStatus.OK, f"no images on {', '.join(topics)}"
    parts = []
    if refused := _by_cause(window, Kind.REFUSED):
        parts.append(f"refused {refused}")
    if window["frames_superseded"]:
        parts.append(f"falling behind: {window['frames_superseded']} of {window['frames_received']} frames "
                     "superseded by newer ones")
    if waited := _by_cause(window, Kind.WAIT):  # the mask's wait, not the CPU
        parts.append(f"{waited} (mask_wait_ms)")
    if window["frames_missing_upstream"]:
        parts.append(f"{window['frames_missing_upstream']} frames missing before the node (stamp gaps)")
    if events := _by_cause(window, Kind.EVENT):
        parts.append(events)
    level = DiagnosticStatus.WARN if parts else DiagnosticStatus.OK
    if policy := _by_cause(window, Kind.POLICY):
        parts.append(f"skipped by the VINS-Mono policy: {policy}")
    if window["frames_processed"] == 0:
        level = DiagnosticStatus.ERROR if refused else DiagnosticStatus.WARN
        waiting = f"{window['images_received']} images received, none tracked yet"
        return level, "nothing tracked: " + ("; ".join(parts) if parts else waiting)
    return level, "tracking" + (": " + "; ".join(parts) if parts else "")


def _label(name: str) -> str:
    """A counter's name as /diagnostics shows it: frames_received -> "frames received"."""
    return name.replace("_", " ")


# -- the process ---------------------------------------------------------------------------------------


def _program(argv0: str | None) -> str:
    name = Path(argv0 or "nsflow-tracker").name
    if name == "tracker":
        return "ros2 run nsflow_ros tracker"
    return name if name.startswith("nsflow") else "nsflow-tracker"


def _check_ros_args(ros_args: list[str]) -> None:
    """Reject, in one line where rcl would write many, a malformed -p or a params file that cannot be read.

    Raises:
        ParameterError: naming the argument or the file.
    """
    for k, arg in enumerate(ros_args):
        if arg in ("-p", "--param"):
            value = ros_args[k + 1] if k + 1 < len(ros_args) else ""
            if ":=" not in value or value.startswith(":="):
                raise ParameterError(f"{arg} {value}: expected NAME:=VALUE, e.g. -p max_cnt:=150")
        if arg == "--params-file":
            if k + 1 >= len(ros_args):
                raise ParameterError("--params-file needs a file name")
            path = Path(ros_args[k + 1])
            if not path.is_file():
                what = "is not a file" if path.exists() else "does not exist"
                raise ParameterError(f"--params-file {path}: {what} (expected a ROS 2 parameters YAML file)")
            try:
                text = path.read_text(errors="replace")
            except OSError as err:
                raise ParameterError(f"--params-file {path}: cannot read it ({err.strerror})") from err
            _check_yaml(path, text)


def _check_yaml(path: Path, text: str) -> None:
    """A params file must be YAML mapping node names to ``ros__parameters``."""
    try:
        import yaml
    except ImportError:  # rcl checks it then
        return
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as err:
        where = getattr(err, "problem_mark", None)
        line = f" at line {where.line + 1}" if where is not None else ""
        raise ParameterError(f"--params-file {path}: not valid YAML{line}") from err
    if not isinstance(data, dict) or not all(
        isinstance(v, dict) and "ros__parameters" in v for v in data.values()
    ):
        raise ParameterError(
            f"--params-file {path}: expected 'node_name: {{ros__parameters: {{...}}}}' entries "
            "(see config/tracker_params.yaml)"
        )


def _rcl_message(err: Exception) -> str:
    """The first sentence of an rcl error, without the C source locations."""
    text = str(err).split(", at /")[0]
    return text.removeprefix("failed to initialize rcl: ")


def main(args: list[str] | None = None) -> int:
    """Entry point of ``ros2 run nsflow_ros tracker`` / ``nsflow-tracker``; ``args`` include the program.

    Returns:
        0 after a normal stop or ``--help``; 1 on a start-up error; 2 on an unknown argument.
    """
    argv = list(sys.argv if args is None else args)
    prog = _program(argv[0] if argv else None)
    user = argv[1:]
    ros_args: list[str] = []
    if "--ros-args" in user:
        ros_args = user[user.index("--ros-args") + 1 :]
        user = user[: user.index("--ros-args")]
    if "-h" in user or "--help" in user:
        print(usage(prog), end="")
        return 0
    if user:
        print(f"usage: {prog} [-h] [--ros-args ...]\n{prog}: error: unrecognized arguments: {' '.join(user)}",
              file=sys.stderr)
        return 2
    try:
        _check_ros_args(ros_args)
    except ParameterError as err:
        print(f"{NODE_NAME}: error: {err}", file=sys.stderr)
        return 1
    keep_large_buffers()  # per-frame buffers stay on the heap (nsflow_ros.allocator)
    profile = use_large_image_transport()
    with StopSignals() as stop:
        try:
            init_without_signal_handlers(argv)
        except Exception as err:
            print(f"{NODE_NAME}: error: bad ROS arguments: {_rcl_message(err)}", file=sys.stderr)
            return 1
        return _run(stop, profile)


def _run(stop: StopSignals, profile: Path | None) -> int:
    node: TrackerNode | None = None
    executor: SingleThreadedExecutor | None = None
    code = 0
    try:
        node = TrackerNode()
        if profile is not None:
            node.get_logger().info(f"Fast DDS transports from {profile} (FASTRTPS_DEFAULT_PROFILES_FILE)")
        executor = SingleThreadedExecutor()
        executor.add_node(node)
        # Short waits: a signal only sets a flag, seen here within 0.2 s.
        while not stop.requested.is_set() and rclpy.ok():
            executor.spin_once(timeout_sec=0.2)
    except NSFlowError as err:
        print(f"{NODE_NAME}: error: {err}", file=sys.stderr)
        code = 1
    except (KeyboardInterrupt, ExternalShutdownException, StopRequested):
        pass  # a stop while starting up, or a second signal
    finally:
        if node is not None:
            node.stop_worker()
            if rclpy.ok():
                node.get_logger().info(f"shutting down: {node.summary()}")
            try:
                node.write_summary_file()
            except OSError as err:
                print(f"{NODE_NAME}: error: cannot write the summary file: {err}", file=sys.stderr)
                code = code or 1
            if executor is not None:
                executor.shutdown(timeout_sec=1.0)
            node.destroy_node()
        if rclpy.ok():
            rclpy.shutdown()
    return code


if __name__ == "__main__":
    sys.exit(main())
