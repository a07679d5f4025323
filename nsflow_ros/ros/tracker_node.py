"""The ``tracker`` node: NSFlow features for an unchanged VINS-Fusion / VINS-Mono estimator.

    ros2 run nsflow_ros tracker --ros-args -p config_file:=<VINS config.yaml>

Subscribes to the config's image0_topic (and image1_topic for stereo, paired by exact stamp) with
sensor-data QoS, optionally to its imu_topic (gyro prediction), and publishes

* ``/feature_tracker/feature`` (sensor_msgs/PointCloud, reliable, depth 2000 like the estimator's queue),
  header = the image header, in the VINS-Fusion layout (default for VINS-Fusion configs) or the VINS-Mono
  layout (first frame dropped, ``freq`` throttling, only points tracked more than once);
* ``/feature_tracker/restart`` (std_msgs/Bool, VINS-Mono layout) on a stamp gap > 1 s or time going back;
* ``image_track`` (sensor_msgs/Image, bgr8) when show_track is on.

A bad frame (unsupported encoding, wrong step, truncated data, wrong size, duplicate stamp) is logged once
per cause, then counted, and skipped. A missing or malformed config or model file stops the node at
start-up with a clear message and exit code 1.
"""

from __future__ import annotations

import sys
import time
from array import array
from collections import Counter, deque
from pathlib import Path
from typing import Any

import numpy as np
import rclpy
from geometry_msgs.msg import Point32
from rcl_interfaces.msg import ParameterDescriptor
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.qos import QoSHistoryPolicy, QoSProfile, QoSReliabilityPolicy, qos_profile_sensor_data
from sensor_msgs.msg import ChannelFloat32, Image, Imu, PointCloud
from std_msgs.msg import Bool

from nsflow_ros.allocator import keep_large_buffers
from nsflow_ros.core.errors import CoreError
from nsflow_ros.core.imu import GyroBuffer
from nsflow_ros.core.tracker import FeatureTracker, FrameFeatures
from nsflow_ros.errors import NSFlowError
from nsflow_ros.ros.image_conv import ImageDecodeError, image_to_numpy, numpy_to_image_fields
from nsflow_ros.stamps import stamp_to_ns, stamp_to_s
from nsflow_ros.vins.config import OVERRIDABLE_KEYS, VinsConfig, apply_overrides, load_vins_config
from nsflow_ros.vins.draw import draw_tracks
from nsflow_ros.vins.errors import ConfigError
from nsflow_ros.vins.messages import LAYOUTS, FeatureCloud, encode

__all__ = ["NODE_NAME", "PARAMETERS", "TrackerNode", "main", "resolve_config_path"]

NODE_NAME = "nsflow_tracker"
FEATURE_QOS = QoSProfile(
    depth=2000, reliability=QoSReliabilityPolicy.RELIABLE, history=QoSHistoryPolicy.KEEP_LAST
)
IMU_QOS = QoSProfile(
    depth=400, reliability=QoSReliabilityPolicy.BEST_EFFORT, history=QoSHistoryPolicy.KEEP_LAST
)
MAX_PENDING = 10  # unpaired stereo images kept per side
RESTART_GAP_S = 1.0  # VINS-Mono: a larger stamp gap restarts the estimator

# name -> (default, description). -1 means "take the value from the VINS config file".
PARAMETERS: dict[str, tuple[Any, str]] = {
    "config_file": ("config/euroc/euroc_mono_imu_config.yaml",
                    "VINS-Fusion or VINS-Mono config file (OpenCV YAML); a relative path is looked up in the "
                    "package share directory, then in the working directory"),
    "method": (
        "nsflow",
        "'nsflow' (learned encoder + LM solver), 'classical' (intensity, same solver) or 'klt' (OpenCV "
        "calcOpticalFlowPyrLK as VINS-Fusion calls it: 21x21, maxLevel 3, 30 iterations / eps 0.01)",
    ),
    "model_path": ("", "ONNX encoder for method 'nsflow'; '' = the model shipped in models/"),
    "max_cnt": (-1, "most features per image (VINS max_cnt, >= 1); -1 = from the VINS config"),
    "min_dist": (-1, "minimum distance between features in px (VINS min_dist); -1 = from the VINS config"),
    "F_threshold": (-1.0, "fundamental-matrix RANSAC threshold in pixels (VINS F_threshold, > 0); "
                          "-1.0 = from the VINS config"),
    "flow_back": (-1, "reverse-tracking check, 0/1 (VINS flow_back); -1 = from the VINS config"),
    "show_track": (-1, "publish the image_track debug image, 0/1 (VINS show_track); -1 = from the config"),
    "freq": (-1, "feature publishing rate in Hz for the VINS-Mono layout (VINS freq, 0 = 100); "
                 "-1 = from the VINS config"),
    "equalize": (-1, "CLAHE before tracking, 0/1 (VINS-Mono equalize); -1 = from the VINS config"),
    "reject_with_f": (-1, "fundamental-matrix RANSAC on tracked points, 0/1; -1 = on for the VINS-Mono "
                          "layout (VINS-Mono does it), off for VINS-Fusion (it does not)"),
    "output_layout": ("", "feature message layout 'fusion' or 'mono'; '' = the dialect of the config file"),
    "feature_topic": ("/feature_tracker/feature", "topic of the sensor_msgs/PointCloud features"),
    "restart_topic": ("/feature_tracker/restart", "topic of the std_msgs/Bool restart (VINS-Mono layout)"),
    "image_track_topic": ("image_track", "topic of the debug image"),
    "use_imu_prediction": (False, "predict feature positions from the gyro (needs imu_topic in the config)"),
    "num_threads": (0, "CPU threads for the encoder; 0 = all usable cores"),
    "fisheye_mask": ("", "mask image for a config with fisheye: 1 (255 = usable); '' = fisheye_mask.jpg in "
                         "the config's folder or its parent, where VINS-Mono keeps it"),
}


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


class TrackerNode(Node):
    """The nsflow_tracker node.

    Args:
        context: rclpy context (None = the default one).
        parameter_overrides: parameters to set at construction (tests, composition).

    Raises:
        NSFlowError: ConfigError / EncoderError / CoreError when the config, the model or a setting is bad.
    """

    def __init__(self, *, context: Any = None, parameter_overrides: list[Any] | None = None) -> None:
        super().__init__(NODE_NAME, context=context, parameter_overrides=parameter_overrides)
        for name, (default, description) in PARAMETERS.items():
            self.declare_parameter(name, default, ParameterDescriptor(description=description))
        p = {name: self.get_parameter(name).value for name in PARAMETERS}

        cfg = load_vins_config(resolve_config_path(str(p["config_file"])))
        cfg = apply_overrides(cfg, {k: p[k] for k in OVERRIDABLE_KEYS})
        layout = str(p["output_layout"]) or cfg.dialect
        if layout not in LAYOUTS:
            raise ConfigError(f"parameter output_layout must be one of {LAYOUTS} or '', got {layout!r}")
        reject = int(p["reject_with_f"])
        use_imu = bool(p["use_imu_prediction"])
        if use_imu and not cfg.imu_topic:
            self.get_logger().warning("use_imu_prediction is on but the config names no imu_topic: disabled")
            use_imu = False
        overrides = {
            "method": str(p["method"]),
            "model_path": str(p["model_path"]) or None,
            "num_threads": int(p["num_threads"]) or None,
            "reject_with_f": layout == "mono" if reject < 0 else bool(reject),
            "use_imu_prediction": use_imu,
        }
        self.config: VinsConfig = cfg
        self.layout = layout
        mask_path = str(p["fisheye_mask"]) or None
        self.tracker = FeatureTracker.from_vins_config(cfg, overrides, fisheye_mask=mask_path)

        self.stats: Counter[str] = Counter()
        self.latencies_ms: deque[float] = deque(maxlen=2000)
        self._logged_causes: set[str] = set()
        self._pending: tuple[dict[int, Any], dict[int, Any]] = ({}, {})
        self._gyro = GyroBuffer() if use_imu else None
        # VINS-Mono front-end state (first image, restart, freq throttling).
        self._first_image = True
        self._first_time = 0.0
        self._last_time = 0.0
        self._pub_count = 1
        self._init_pub = False

        self._feature_pub = self.create_publisher(PointCloud, str(p["feature_topic"]), FEATURE_QOS)
        self._restart_pub = self.create_publisher(Bool, str(p["restart_topic"]), FEATURE_QOS)
        self._track_pub = (
            self.create_publisher(Image, str(p["image_track_topic"]), 10) if cfg.show_track else None
        )
        self._subs = [
            self.create_subscription(
                Image, topic, lambda m, i=i: self._on_image(i, m), qos_profile_sensor_data
            )
            for i, topic in enumerate(cfg.image_topics)
        ]
        if self._gyro is not None:
            self._subs.append(self.create_subscription(Imu, cfg.imu_topic, self._on_imu, IMU_QOS))
        s = self.tracker.settings
        self.get_logger().info(
            f"{cfg.dialect} config {cfg.path} ({'stereo' if s.stereo else 'mono'}, {cfg.image_width}x"
            f"{cfg.image_height}); method {s.method}, layout {layout}, max_cnt {s.max_cnt}, min_dist "
            f"{s.min_dist:g}, flow_back {s.flow_back}, F-RANSAC {s.reject_with_f}, IMU prediction {use_imu}; "
            f"images on {', '.join(cfg.image_topics)}, features on {p['feature_topic']}"
        )

    # -- inputs ----------------------------------------------------------------------------------------

    def _bad(self, cause: str, message: str) -> None:
        """Log a bad frame once per cause; count every occurrence."""
        self.stats["bad_frames"] += 1
        self.stats[f"bad:{cause}"] += 1
        if cause not in self._logged_causes:
            self._logged_causes.add(cause)
            self.get_logger().error(f"skipping frame: {message} (further frames like it are only counted)")

    def _on_imu(self, msg: Imu) -> None:
        w = msg.angular_velocity
        self._gyro.add(stamp_to_s(msg.header.stamp), (w.x, w.y, w.z))  # type: ignore[union-attr]

    def _on_image(self, cam: int, msg: Image) -> None:
        t_recv = time.perf_counter()
        self.stats["images_in"] += 1
        try:
            img = image_to_numpy(msg)
        except ImageDecodeError as err:
            self._bad(err.cause, f"camera {cam}: {err}")
            return
        if not self.tracker.settings.stereo:
            self._frame(msg.header, img, None, t_recv)
            return
        key = stamp_to_ns(msg.header.stamp)
        other = self._pending[1 - cam].pop(key, None)
        if other is None:
            pending = self._pending[cam]
            pending[key] = (msg.header, img)
            while len(pending) > MAX_PENDING:  # the partner never came
                pending.pop(min(pending))
                self.stats["unpaired_images"] += 1
            return
        left, right = ((msg.header, img), other) if cam == 0 else (other, (msg.header, img))
        self._frame(left[0], left[1], right[1], t_recv)

    # -- one frame -------------------------------------------------------------------------------------

    def _mono_gate(self, stamp: float) -> bool | None:
        """VINS-Mono's img_callback bookkeeping: None = skip the frame, else whether to publish it."""
        if self._first_image:
            self._first_image = False
            self._first_time = self._last_time = stamp
            return None
        if stamp - self._last_time > RESTART_GAP_S or stamp < self._last_time:
            self.get_logger().warning(f"image stamp discontinuity ({self._last_time:.3f} -> {stamp:.3f} s): "
                                      "restarting the estimator")
            self._first_image = True
            self._last_time = 0.0
            self._pub_count = 1
            self._restart_pub.publish(Bool(data=True))
            self.tracker.reset()
            self.stats["restarts"] += 1
            return None
        self._last_time = stamp
        freq = self.config.freq
        rate = self._pub_count / (stamp - self._first_time)
        if round(rate) <= freq:
            if abs(rate - freq) < 0.01 * freq:  # reset the frequency control near the target
                self._first_time = stamp
                self._pub_count = 0
            return True
        return False

    def _frame(self, header: Any, img0: np.ndarray, img1: np.ndarray | None, t_recv: float) -> None:
        stamp = stamp_to_s(header.stamp)
        last = self.tracker.last_stamp
        if last is not None and stamp == last:
            self._bad("duplicate_stamp", f"stamp {stamp:.9f} repeats the previous frame's")
            return
        publish = True
        if self.layout == "mono":
            gate = self._mono_gate(stamp)
            if gate is None:
                return
            publish = gate
        elif last is not None and stamp < last:
            self.get_logger().warning(f"time went backwards ({last:.3f} -> {stamp:.3f} s): tracks reset")
            self.tracker.reset()
            self.stats["resets"] += 1
        gyro = None
        if self._gyro is not None and self.tracker.last_stamp is not None:
            gyro = self._gyro.window(self.tracker.last_stamp, stamp)
        try:
            frame = self.tracker.process(stamp, img0, img1, gyro, detect=publish)
        except CoreError as err:
            self._bad(f"tracker:{err}", str(err))
            return
        self.stats["frames"] += 1
        if self._gyro is not None:
            self._gyro.prune(stamp)
        if self.layout == "mono":
            if not publish:
                return
            self._pub_count += 1
            if not self._init_pub:  # VINS-Mono skips the first published frame
                self._init_pub = True
                return
        self._publish(header, frame)
        self.latencies_ms.append((time.perf_counter() - t_recv) * 1e3)
        if self._track_pub is not None:
            self._publish_track(header, frame, img0, img1)

    # -- outputs ---------------------------------------------------------------------------------------

    def _publish(self, header: Any, frame: FrameFeatures) -> None:
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
        self._feature_pub.publish(msg)
        self.stats["published"] += 1

    def _publish_track(
        self, header: Any, frame: FrameFeatures, img0: np.ndarray, img1: np.ndarray | None
    ) -> None:
        fields = numpy_to_image_fields(draw_tracks(frame, img0, img1), "bgr8")
        msg = Image(height=fields["height"], width=fields["width"], encoding="bgr8", is_bigendian=0,
                    step=fields["step"])
        msg.header = header
        msg.data = fields["data"]
        self._track_pub.publish(msg)  # type: ignore[union-attr]

    def summary(self) -> str:
        """One line of counters (frames, published, bad frames by cause)."""
        return ", ".join(f"{k} {v}" for k, v in sorted(self.stats.items())) or "no images received"


def main(args: list[str] | None = None) -> int:
    """Entry point of ``ros2 run nsflow_ros tracker``; returns the exit code (1 on a start-up error)."""
    keep_large_buffers()  # per-frame buffers stay on the heap (nsflow_ros.allocator)
    rclpy.init(args=args)
    node: TrackerNode | None = None
    code = 0
    try:
        node = TrackerNode()
        rclpy.spin(node)
    except NSFlowError as err:
        print(f"{NODE_NAME}: error: {err}", file=sys.stderr)
        code = 1
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        if node is not None:
            node.get_logger().info(f"shutting down: {node.summary()}")
            node.destroy_node()
        if rclpy.ok():
            rclpy.shutdown()
    return code


if __name__ == "__main__":
    sys.exit(main())
