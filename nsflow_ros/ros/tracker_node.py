"""The ``tracker`` node: NSFlow features for an unchanged VINS-Fusion / VINS-Mono estimator.

    ros2 run nsflow_ros tracker --ros-args -p config_file:=<VINS config.yaml>
    nsflow-tracker --help      (what it does, its topics, every parameter with its default)

The node is a thin shell around :class:`nsflow_ros.vins.session.FrontEndSession` (frame policy, tracker,
run-time parameter changes). Images are decoded and paired in the subscription callbacks and handed to one
worker thread through :class:`~nsflow_ros.ros.frame_queue.LatestFrames`, so the tracker works on the newest
frames and every superseded frame is counted. A bad frame is logged once per cause, then counted and
skipped; a bad config, model or parameter stops the node at start-up with one line and exit code 1;
SIGINT and SIGTERM stop it with exit code 0 after its summary line.

This module wires the parts: the process (:mod:`.node_process`), messages and QoS (:mod:`.node_messages`),
mask topics (:mod:`.node_masks`), status, /diagnostics and summary (:mod:`.node_status`), the counts by
cause (:mod:`.counters`) and the tracking state (:mod:`nsflow_ros.vins.health`).
"""

from __future__ import annotations

import re
import sys
import threading
import time
from collections import deque
from pathlib import Path
from typing import Any

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from rcl_interfaces.msg import SetParametersResult
from rclpy.node import Node
from rclpy.qos import qos_profile_sensor_data
from rclpy.qos_overriding_options import QoSOverridingOptions
from sensor_msgs.msg import CompressedImage, Image, Imu, PointCloud
from std_msgs.msg import Bool

from nsflow_ros.core.encoder import encoder_provider
from nsflow_ros.core.tracker import FrameFeatures
from nsflow_ros.data.images import ImageDecodeError
from nsflow_ros.errors import NSFlowError
from nsflow_ros.ros.counters import CauseLog, NodeCounters, image_cause
from nsflow_ros.ros.errors import ParameterError
from nsflow_ros.ros.frame_queue import LatestFrames, QueuedFrame
from nsflow_ros.ros.node_masks import MaskTopics, static_masks
from nsflow_ros.ros.node_messages import (
    FEATURE_QOS,
    IMAGE_TRANSPORTS,
    IMU_QOS,
    feature_cloud,
    image_transport,
    rclpy_image,
    resolve_config_path,
)
from nsflow_ros.ros.node_process import main  # the entry point, re-exported
from nsflow_ros.ros.node_status import (
    ArrivalStamps,
    StatusWindow,
    covariance_line,
    declare_parameters,
    diagnostic_status,
    period_line,
    period_values,
    run_counters,
    startup_line,
    status_level,
    summary_line,
    write_summary,
)
from nsflow_ros.ros.tracker_params import NODE_NAME, PARAMETERS, coerce, spec
from nsflow_ros.stamps import stamp_to_ns, stamp_to_s
from nsflow_ros.threads import set_opencv_threads
from nsflow_ros.vins.config import load_vins_config
from nsflow_ros.vins.draw import draw_tracks
from nsflow_ros.vins.health import (
    HealthMonitor,
    HealthReport,
    Thresholds,
    usable_share,
)
from nsflow_ros.vins.pairing import StereoPairer
from nsflow_ros.vins.session import FrameOutcome, FrontEndSession, Skip
from nsflow_ros.vins.settings import SESSION_SETTINGS

__all__ = [
    "FEATURE_QOS", "IMAGE_TRANSPORTS", "NODE_NAME", "PARAMETERS", "TrackerNode", "main", "rclpy_image",
    "resolve_config_path",
]


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
        p = declare_parameters(self)
        self._params = p
        set_opencv_threads(int(p["opencv_threads"]))  # process-wide, before the tracker's first call

        cfg = load_vins_config(resolve_config_path(str(p["config_file"])))
        use_imu = bool(p["use_imu_prediction"])
        if use_imu and not cfg.imu_topic:
            self.get_logger().warning("use_imu_prediction is on but the config names no imu_topic: disabled")
            use_imu = False
        settings = {k: p[k] for k in SESSION_SETTINGS if k != "use_imu_prediction"}
        convention = str(p["mask_convention"])
        # before the tracker is built: a mask with no usable pixel stops the node in one line
        static, mask_warnings = static_masks(cfg, str(p["mask0"]), str(p["mask1"]), convention,
                                             float(p["mask_min_usable"]))
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
        self._log = CauseLog(self.stats, self.get_logger())  # each precise cause logged once, then counted
        cameras = 2 if self.session.tracker.settings.stereo else 1
        self._pairer: StereoPairer[tuple[Any, np.ndarray, float]] = StereoPairer(
            cameras, float(p["stereo_sync_tolerance"])
        )
        self._tolerance_checked = cameras == 1  # checked once a frame period is measured (stereo only)
        self._last_stamp: float | None = None  # of the last frame handed to the session (worker thread)
        transport = str(p["image_transport"])
        image_type, self._decode, suffix = image_transport(transport)
        self._track_last = -np.inf  # monotonic time of the last debug image
        self.track_images_published = 0
        self._lock = threading.Lock()  # the session and the publishers: worker vs. parameter updates
        self._queue: LatestFrames[QueuedFrame] = LatestFrames(int(p["queue_size"]))
        self._stop_lock = threading.Lock()
        self._stopping = False
        self._cpu_start = time.process_time()
        self._status = StatusWindow()
        self._arrivals = ArrivalStamps(cameras)  # stamp gaps and the frame period, every image that arrived

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
        self._masks = MaskTopics(
            self, [str(p["mask_topic"]), str(p["mask1_topic"])], cameras, cfg.path,
            float(p["stereo_sync_tolerance"]), convention, self.stats,
            lambda: (self.config.image_width, self.config.image_height), self._newer_frame,
        )
        self._timer: Any = None
        self._set_status_timer(float(p["status_period"]))
        self.add_on_set_parameters_callback(self._on_set_parameters)

        self._worker = threading.Thread(target=self._work, name="nsflow_tracker_frames", daemon=True)
        self._worker.start()
        self._image_topics = [sub.topic_name for sub in self._subs[: len(cfg.image_topics)]]
        self.get_logger().info(startup_line(
            cfg, self.session, encoder_provider(self.tracker.encoder), transport, self._image_topics,
            self._subs[-1].topic_name if use_imu else None, self._feature_pub.topic_name,
        ) + self._masks.note(static, float(p["mask_wait_ms"])))
        for warning in mask_warnings:
            self.get_logger().warning(warning)
        if self.tracker.settings.covariance:  # what the channels are scaled by, and whether it was fitted
            self.get_logger().info(covariance_line(self.tracker))

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

    @property
    def masks_received(self) -> int:
        """Per-frame masks that arrived (:class:`~nsflow_ros.ros.node_masks.MaskTopics`)."""
        return self._masks.received

    def mask_counters(self) -> dict[str, int]:
        """Per-frame masks received, used, missing (frames tracked without theirs), late, unused, refused
        and left at the stop."""
        return self._masks.counters()

    def _newer_frame(self) -> bool:
        """Whether a newer frame waits for the tracker (ends a wait for a mask)."""
        return len(self._queue) > 0

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
            if tolerance is not None and (problem := self._arrivals.tolerance_problem(float(tolerance))):
                raise ParameterError(f"parameter {problem}")
            thresholds = Thresholds.from_values({**self._params, **values})  # lost <= degraded
            with self._lock:
                notes = self.session.update(**session) if session else []
                self._set_track_publisher(self.session.show_track)
            if tolerance is not None:  # the pairer runs in this (the executor's) thread
                self._pairer.tolerance = float(tolerance)
                # not measured yet: checked once it is
                self._tolerance_checked = self._pairer.cameras == 1 or self._arrivals.period() is not None
                self._masks.set_tolerance(float(tolerance))
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

    def _on_imu(self, msg: Imu) -> None:
        w = msg.angular_velocity
        with self._lock:
            self.session.add_gyro(stamp_to_s(msg.header.stamp), (w.x, w.y, w.z))

    def _note_arrival(self, cam: int, stamp: float) -> None:
        """Stamp gaps per camera, from every image that arrived (usable or not)."""
        self.stats.frames_missing_upstream = self._arrivals.add(cam, stamp)
        if not self._tolerance_checked and self._arrivals.period() is not None:
            self._tolerance_checked = True
            problem = self._arrivals.tolerance_problem(self._pairer.tolerance)
            if problem:
                self.get_logger().warning(f"parameter {problem}; set it lower with ros2 param set")

    def _on_image(self, cam: int, msg: Image | CompressedImage) -> None:
        t_recv = time.perf_counter()
        self.stats.add("images_received")
        self._note_arrival(cam, stamp_to_s(msg.header.stamp))
        try:
            img = self._decode(msg)
        except ImageDecodeError as err:
            self._log.bad(image_cause(err.cause), err.cause, f"camera {cam}: {err}")
            return
        cfg = self.session.config
        h, w = img.shape[:2]
        if (w, h) != (cfg.image_width, cfg.image_height):
            self._log.bad("wrong_size", f"size:{w}x{h}",
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
            self._enqueue(QueuedFrame(left[0], left[1], None, left[2]))
        else:
            self._enqueue(QueuedFrame(left[0], left[1], right[1], min(left[2], right[2])))

    def _count_unpaired(self, n: int) -> None:
        self._log.bad("unpaired", "unpaired",
                  f"{n} stereo image(s) without a partner within stereo_sync_tolerance "
                  f"{self._pairer.tolerance:g} s", n)

    def _enqueue(self, frame: QueuedFrame) -> None:
        self.stats.add("frames_received")
        frame.t_queued = time.perf_counter()
        waiting = self._masks.waiting  # before the put: the worker may take the frame at once
        superseded = self._queue.put(frame)
        if superseded:  # the worker waiting for a mask is not the CPU falling behind
            self.stats.count("mask_wait" if waiting else "superseded", superseded)
        self._masks.wake()  # a frame waiting for its mask is tracked now (see MaskTopics.take)

    # -- the worker --------------------------------------------------------------------------------------

    def _work(self) -> None:
        while True:
            frame = self._queue.take()
            if frame is None:  # stopped
                return
            # a frame that waited in the queue for the one before is late: skip its checks to catch up
            limit = float(self._params["late_frame_ms"])
            checks = not (limit > 0 and (time.perf_counter() - frame.t_queued) * 1e3 > limit)
            # outside the lock: a parameter change need not wait
            frame.masks = self._masks.take(stamp_to_ns(frame.header.stamp), frame.t_recv,
                                           float(self._params["mask_wait_ms"]))
            try:
                with self._lock:
                    self._frame(frame, checks)
            except Exception as err:
                name = type(err).__name__
                self._log.bad("tracker_error", f"internal:{name}", f"{name}: {err}")

    def _frame(self, item: QueuedFrame, checks: bool = True) -> None:
        stamp = stamp_to_s(item.header.stamp)
        last, self._last_stamp = self._last_stamp, stamp
        backwards = last is not None and stamp < last
        out: FrameOutcome = self.session.process(
            stamp, item.image0, item.image1, checks=checks, frame_masks=item.masks
        )
        if out.skipped is Skip.DUPLICATE_STAMP:
            self._log.bad("repeated_stamp", "repeated_stamp", out.note)
            return
        if out.skipped is Skip.TRACKER:  # digits vary from frame to frame, the kind of error does not
            self._log.bad("tracker_error", "tracker:" + re.sub(r"[0-9.]+", "#", out.note), out.note)
            return
        if out.skipped is Skip.FIRST_FRAME:
            self.stats.count("first_frame")
            return
        if out.restart:
            if backwards:  # refused: VINS-Mono drops it and restarts
                self._log.bad("stamp_backwards", "stamp_backwards", out.note)
            else:  # a jump forward of more than 1 s: VINS-Mono's policy
                self.stats.count("restart")
                self._log.once("restart", out.note)
            self._restart_pub.publish(Bool(data=True))
            return
        if not out.tracked:
            return
        if out.note:
            if backwards:
                self.stats.count("reset_backwards")
            self._log.once("reset_backwards" if backwards else out.note, out.note)
        self.stats.add("frames_processed")
        if not checks:
            self.stats.add("frames_unchecked")
        if out.features is None:  # tracked, held back by publish_rate / freq or VINS-Mono's first
            self.stats.count(out.held or "throttled")
            return
        msg = feature_cloud(item.header, out.features, self.layout, self.config.num_of_cam)
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
        with self._lat_lock:
            lat = list(self.latencies_ms)
        return run_counters(
            self.get_fully_qualified_name(), self.session, self.stats, time.process_time() - self._cpu_start,
            lat, self.track_images_published, self.mask_counters(), self._health,
        )

    def summary(self) -> str:
        """One line: images and frames received / processed / published, every cause, latency."""
        return summary_line(self.counters(), self._masks.active)

    def _report_status(self) -> None:
        """Log one status line and publish it on /diagnostics (see :func:`status_level`)."""
        c = self.counters()
        window = self._status.take(self.stats)
        level, message = status_level(window, self._image_topics)
        masks = self._masks.window(c)
        if masks:  # per-frame masks missing, late or refused in this period
            level = max(level, DiagnosticStatus.WARN)
            message = masks if message == "tracking" else f"{message}; {masks}"
        health = self._assess(window)
        if health.state.rank:  # DEGRADED or LOST: at least WARN, whatever the counts say
            level = max(level, DiagnosticStatus.WARN)
        message = f"{message} [{health.text}]"
        provider = encoder_provider(self.session.tracker.encoder)
        values = period_values(c, window, health, provider, self._masks.active)
        array_msg = DiagnosticArray()
        array_msg.header.stamp = self.get_clock().now().to_msg()
        array_msg.status = [diagnostic_status(level, message, self.get_fully_qualified_name(), values)]
        self._diag_pub.publish(array_msg)
        if window["images_received"] == 0:
            if not window["quiet"]:  # say it once, then stay quiet until images come
                self.get_logger().info(f"{message} in the last {window['seconds']:.1f} s")
            return
        line = period_line(message, window)
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

    # -- shutdown --------------------------------------------------------------------------------------

    def stop_worker(self, timeout: float = 5.0) -> None:
        """Stop the frame worker (frames still waiting are counted as left at the stop)."""
        with self._stop_lock:
            if not self._stopping:  # frames and images still waiting were not processed
                self._masks.close()  # a worker waiting for a mask returns at once
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
        """Write :meth:`counters` as JSON to the summary_file parameter's path, if one is set, with the last
        frames' latencies (``latencies_ms``, at most 2000), which a benchmark pools over several runs."""
        target = str(self._params["summary_file"])
        if not target:
            return None
        with self._lat_lock:
            lat = [round(x, 3) for x in self.latencies_ms]
        return write_summary(Path(target), {**self.counters(), "latencies_ms": lat})

    def destroy_node(self) -> None:
        self.stop_worker()
        super().destroy_node()


if __name__ == "__main__":
    sys.exit(main())
