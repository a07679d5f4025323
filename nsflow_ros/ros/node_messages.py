"""The ``tracker`` node's messages: QoS, image transports, the config's path and the feature cloud.

What the node sends and takes apart from its logic: :data:`FEATURE_QOS` (as VINS's estimators subscribe),
:data:`IMAGE_TRANSPORTS` (raw or compressed images), :func:`rclpy_image` (the debug image) and
:func:`feature_cloud` (a frame's features as VINS's PointCloud); :func:`resolve_config_path` finds the VINS
config. Re-exported by :mod:`nsflow_ros.ros.tracker_node`.
"""

from __future__ import annotations

from array import array
from pathlib import Path
from typing import Any

import numpy as np
from geometry_msgs.msg import Point32
from rclpy.qos import QoSHistoryPolicy, QoSProfile, QoSReliabilityPolicy
from sensor_msgs.msg import ChannelFloat32, CompressedImage, Image, PointCloud

from nsflow_ros.core.tracker import FrameFeatures
from nsflow_ros.data.images import compressed_for_tracker, image_for_tracker
from nsflow_ros.data.messages import image_fields
from nsflow_ros.errors import NSFlowError
from nsflow_ros.ros.errors import ParameterError
from nsflow_ros.vins.errors import ConfigError
from nsflow_ros.vins.messages import FeatureCloud, encode

__all__ = [
    "FEATURE_QOS", "IMAGE_TRANSPORTS", "IMU_QOS", "feature_cloud", "image_transport", "rclpy_image",
    "resolve_config_path",
]

FEATURE_QOS = QoSProfile(
    depth=2000, reliability=QoSReliabilityPolicy.RELIABLE, history=QoSHistoryPolicy.KEEP_LAST
)
"""The features: reliable, keep-last 2000, as VINS's estimators subscribe."""
IMU_QOS = QoSProfile(
    depth=400, reliability=QoSReliabilityPolicy.BEST_EFFORT, history=QoSHistoryPolicy.KEEP_LAST
)
"""The IMU for the gyro prediction: best effort, 2 s at 200 Hz."""

IMAGE_TRANSPORTS: dict[str, tuple[type, Any, str]] = {
    "raw": (Image, image_for_tracker, ""),
    "compressed": (CompressedImage, compressed_for_tracker, "/compressed"),
}
"""image_transport -> (message type, decoder to the tracker's array, suffix of the image topic)."""


def image_transport(name: str) -> tuple[type, Any, str]:
    """The :data:`IMAGE_TRANSPORTS` entry of ``image_transport``.

    Raises:
        ParameterError: an unknown transport, naming the known ones.
    """
    if name not in IMAGE_TRANSPORTS:
        raise ParameterError(
            f"parameter image_transport: got {name!r}, expected one of {', '.join(IMAGE_TRANSPORTS)}"
        )
    return IMAGE_TRANSPORTS[name]


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


def feature_cloud(header: Any, frame: FrameFeatures, layout: str, num_of_cam: int) -> PointCloud:
    """A frame's features as the PointCloud VINS's estimator reads, in ``layout`` (fusion / mono)."""
    cloud: FeatureCloud = encode(frame, layout, num_of_cam)  # type: ignore[arg-type]
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
