"""Build, serialise and decode the sensor messages the data layer handles, with rosbags typestores.

ROS 1 and ROS 2 differ in the header (ROS 1 has ``seq``) and in serialisation, so every builder takes the
typestore to build for, :func:`ros2_store` (Jazzy) or :func:`ros1_store` (Noetic).
"""

from __future__ import annotations

from collections.abc import Sequence
from functools import cache
from typing import Any, NamedTuple

import numpy as np
from rosbags.typesys import Stores, get_typestore

from nsflow_ros.data.errors import DataError
from nsflow_ros.data.images import ENCODINGS, decode_compressed, decode_image
from nsflow_ros.data.records import ImageRecord, ImuRecord, Record
from nsflow_ros.stamps import stamp_to_ns

__all__ = [
    "COMPRESSED_IMAGE",
    "IMAGE",
    "IMU",
    "POINT_CLOUD",
    "POINT_STAMPED",
    "ImageFields",
    "compressed_image_message",
    "decode_compressed",
    "default_encoding",
    "image_fields",
    "image_message",
    "imu_message",
    "is_ros1",
    "message_to_record",
    "point_cloud_message",
    "point_message",
    "record_to_cdr",
    "record_to_message",
    "ros1_store",
    "ros2_store",
    "serialize",
]

IMAGE = "sensor_msgs/msg/Image"
COMPRESSED_IMAGE = "sensor_msgs/msg/CompressedImage"
IMU = "sensor_msgs/msg/Imu"
POINT_STAMPED = "geometry_msgs/msg/PointStamped"
POINT_CLOUD = "sensor_msgs/msg/PointCloud"

def default_encoding(dtype: np.dtype, channels: int) -> str | None:
    """The encoding OpenCV-style pixels get by default: mono8, mono16, bgr8, bgra8 or None."""
    u8, u16 = np.dtype(np.uint8), np.dtype(np.uint16)
    table = {(u8, 1): "mono8", (u16, 1): "mono16", (u8, 3): "bgr8", (u8, 4): "bgra8"}
    return table.get((np.dtype(dtype), channels))


@cache
def ros2_store() -> Any:
    """The ROS 2 Jazzy typestore (shared, built once)."""
    return get_typestore(Stores.ROS2_JAZZY)


@cache
def ros1_store() -> Any:
    """The ROS 1 Noetic typestore (shared, built once)."""
    return get_typestore(Stores.ROS1_NOETIC)


def is_ros1(store: Any) -> bool:
    """Whether a typestore has ROS 1 headers (with ``seq``)."""
    return any(name == "seq" for name, _ in store.fielddefs["std_msgs/msg/Header"][1])


def _header(store: Any, stamp_ns: int, frame_id: str, seq: int) -> Any:
    stamp = store.types["builtin_interfaces/msg/Time"](sec=int(stamp_ns // 1_000_000_000),
                                                        nanosec=int(stamp_ns % 1_000_000_000))
    Header = store.types["std_msgs/msg/Header"]
    if is_ros1(store):
        return Header(seq=int(seq), stamp=stamp, frame_id=frame_id)
    return Header(stamp=stamp, frame_id=frame_id)


class ImageFields(NamedTuple):
    """The layout fields of a sensor_msgs/Image (header aside), the same in ROS 1 and ROS 2."""

    height: int
    width: int
    encoding: str
    step: int
    data: np.ndarray
    """(height * step,) uint8, little-endian pixels (``is_bigendian`` = 0)."""


def image_fields(image: np.ndarray, encoding: str | None = None, *, step: int | None = None) -> ImageFields:
    """The sensor_msgs/Image layout of pixels, with no typestore (rclpy publishers use it directly).

    Args:
        image: (H, W) or (H, W, C) uint8 / uint16 pixels.
        encoding: a key of :data:`nsflow_ros.data.images.ENCODINGS`; None = :func:`default_encoding`.
        step: row length in bytes, larger than the packed row to pad rows (None = packed).

    Raises:
        DataError: when the image does not match the encoding or ``step`` is too small.
    """
    img = np.asarray(image)
    channels = 1 if img.ndim == 2 else (img.shape[2] if img.ndim == 3 else -1)
    if encoding is None:
        encoding = default_encoding(img.dtype, channels) or ""
    if encoding not in ENCODINGS:
        raise DataError(f"cannot encode image of dtype {img.dtype} and shape {img.shape} as {encoding!r}; "
                        f"supported encodings: {', '.join(ENCODINGS)}")
    dtype, want = ENCODINGS[encoding]
    if img.dtype != dtype or channels != want:
        raise DataError(f"image for encoding {encoding}: expected dtype {dtype} with {want} channel(s), "
                        f"got dtype {img.dtype} and shape {img.shape}")
    h, w = img.shape[:2]
    row = w * want * dtype.itemsize
    step = row if step is None else int(step)
    if step < row:
        raise DataError(f"image step {step} is smaller than a packed row of {row} bytes")
    little = np.ascontiguousarray(img).astype(dtype.newbyteorder("<"), copy=False)  # is_bigendian = 0
    packed = little.view(np.uint8).reshape(h, row)
    if step > row:
        padded = np.zeros((h, step), np.uint8)
        padded[:, :row] = packed
        packed = padded
    return ImageFields(h, w, encoding, step, packed.reshape(-1))


def image_message(store: Any, stamp_ns: int, frame_id: str, image: np.ndarray, encoding: str | None = None,
                  *, seq: int = 0, step: int | None = None) -> Any:
    """A sensor_msgs/Image of the typestore's ROS version; the layout is :func:`image_fields`'.

    Args:
        seq: ROS 1 header sequence number (ignored for ROS 2).

    Raises:
        DataError: as :func:`image_fields`.
    """
    f = image_fields(image, encoding, step=step)
    return store.types[IMAGE](header=_header(store, stamp_ns, frame_id, seq), height=f.height, width=f.width,
                              encoding=f.encoding, is_bigendian=0, step=f.step, data=f.data)


def compressed_image_message(store: Any, stamp_ns: int, frame_id: str, fmt: str, data: bytes, *,
                             seq: int = 0) -> Any:
    """A sensor_msgs/CompressedImage of the ``(fmt, data)`` that :func:`.images.encode_compressed` returns."""
    return store.types[COMPRESSED_IMAGE](header=_header(store, stamp_ns, frame_id, seq), format=fmt,
                                          data=np.frombuffer(data, np.uint8))


def imu_message(store: Any, stamp_ns: int, frame_id: str, gyro: Any, accel: Any, *, seq: int = 0) -> Any:
    """A sensor_msgs/Imu with no orientation (``orientation_covariance[0] = -1``, the ROS convention)."""
    t = store.types
    ocov = np.zeros(9)
    ocov[0] = -1.0
    g = np.asarray(gyro, dtype=np.float64).reshape(3)
    a = np.asarray(accel, dtype=np.float64).reshape(3)
    return t[IMU](
        header=_header(store, stamp_ns, frame_id, seq),
        orientation=t["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
        orientation_covariance=ocov,
        angular_velocity=t["geometry_msgs/msg/Vector3"](x=float(g[0]), y=float(g[1]), z=float(g[2])),
        angular_velocity_covariance=np.zeros(9),
        linear_acceleration=t["geometry_msgs/msg/Vector3"](x=float(a[0]), y=float(a[1]), z=float(a[2])),
        linear_acceleration_covariance=np.zeros(9),
    )


def point_message(store: Any, stamp_ns: int, frame_id: str, xyz: Any, *, seq: int = 0) -> Any:
    """A geometry_msgs/PointStamped."""
    p = np.asarray(xyz, dtype=np.float64).reshape(3)
    point = store.types["geometry_msgs/msg/Point"](x=float(p[0]), y=float(p[1]), z=float(p[2]))
    return store.types[POINT_STAMPED](header=_header(store, stamp_ns, frame_id, seq), point=point)


def point_cloud_message(store: Any, stamp_ns: int, frame_id: str, points: np.ndarray, channels: np.ndarray,
                        names: Sequence[str], *, seq: int = 0) -> Any:
    """A sensor_msgs/PointCloud (the VINS feature message): one channel per row of ``channels``.

    Raises:
        DataError: when the shapes do not agree.

    Shape:
        points: (N, 3). channels: (C, N).
    """
    pts = np.asarray(points, dtype=np.float32)
    chans = np.asarray(channels, dtype=np.float32)
    if pts.ndim != 2 or pts.shape[1] != 3 or chans.ndim != 2 or chans.shape[1] != pts.shape[0] \
            or chans.shape[0] != len(names):
        raise DataError(f"point cloud: points {pts.shape}, channels {chans.shape} and {len(names)} channel "
                        "names do not agree (expected (N, 3), (C, N) and C names)")
    t = store.types
    point = t["geometry_msgs/msg/Point32"]
    channel = t["sensor_msgs/msg/ChannelFloat32"]
    return t[POINT_CLOUD](
        header=_header(store, stamp_ns, frame_id, seq),
        points=[point(x=x, y=y, z=z) for x, y, z in pts.tolist()],
        channels=[channel(name=str(n), values=chans[k].copy()) for k, n in enumerate(names)],
    )


def serialize(store: Any, msg: Any, msgtype: str) -> bytes:
    """Serialise for the typestore's ROS version: ROS 1 wire format or CDR (little endian)."""
    if is_ros1(store):
        return bytes(store.serialize_ros1(msg, msgtype))
    return bytes(store.serialize_cdr(msg, msgtype))


def record_to_message(store: Any, record: Record, seq: int = 0) -> tuple[str, Any]:
    """Message object for a record: ``(msgtype, message)`` for the given typestore."""
    if isinstance(record, ImageRecord):
        msg = image_message(store, record.stamp_ns, record.frame_id, record.image, record.encoding, seq=seq)
        return IMAGE, msg
    if isinstance(record, ImuRecord):
        msg = imu_message(store, record.stamp_ns, record.frame_id, record.gyro, record.accel, seq=seq)
        return IMU, msg
    raise DataError(f"cannot serialise a {type(record).__name__}; expected ImageRecord or ImuRecord")


def record_to_cdr(record: Record) -> tuple[str, bytes]:
    """``(msgtype, cdr)`` of a record for a raw rclpy publisher, the CDR with its encapsulation header."""
    msgtype, msg = record_to_message(ros2_store(), record)
    return msgtype, serialize(ros2_store(), msg, msgtype)


def _image_from_msg(msg: Any, msgtype: str, topic: str) -> tuple[np.ndarray, str]:
    if msgtype == COMPRESSED_IMAGE:
        return decode_compressed(msg, topic)
    return decode_image(msg, topic)


def message_to_record(topic: str, msgtype: str, msg: Any) -> Record:
    """Record of a deserialised Image / CompressedImage / Imu message.

    Raises:
        DataError: for another message type or a bad image.
    """
    if msgtype in (IMAGE, COMPRESSED_IMAGE):
        img, enc = _image_from_msg(msg, msgtype, topic)
        return ImageRecord(topic, stamp_to_ns(msg.header.stamp), img, enc, str(msg.header.frame_id))
    if msgtype == IMU:
        av, la = msg.angular_velocity, msg.linear_acceleration
        return ImuRecord(topic, stamp_to_ns(msg.header.stamp), np.array([av.x, av.y, av.z], dtype=np.float64),
                         np.array([la.x, la.y, la.z], dtype=np.float64), str(msg.header.frame_id))
    raise DataError(f"topic {topic} has type {msgtype}; expected {IMAGE}, {COMPRESSED_IMAGE} or {IMU}")
