"""The records a sensor stream is made of: images, IMU samples and raw serialised messages."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from nsflow_ros.data.images import to_gray, tracker_image

__all__ = ["ImageRecord", "ImuRecord", "RawMessage", "Record"]


@dataclass(frozen=True, eq=False)
class ImageRecord:
    """One camera image.

    Attributes:
        topic: topic it was recorded on (ASL folders map ``camN`` to ``/camN/image_raw``).
        stamp_ns: capture time (header stamp) in nanoseconds.
        image: decoded pixels: (H, W) for mono encodings, (H, W, 3|4) for colour ones, in the channel
            order the encoding names (``rgb8`` stays RGB). uint8, or uint16 for 16-bit encodings.
        encoding: the sensor_msgs/Image encoding, e.g. ``mono8``.
        frame_id: header frame id, e.g. ``cam0``.
    """

    topic: str
    stamp_ns: int
    image: np.ndarray = field(repr=False)
    encoding: str = "mono8"
    frame_id: str = ""

    def gray(self) -> np.ndarray:
        """The image as 8-bit gray, shape (H, W) (16-bit is scaled down, colour converted)."""
        return to_gray(self.image, self.encoding)

    def for_tracker(self) -> np.ndarray:
        """The array the node gives the tracker (:func:`~nsflow_ros.data.images.tracker_image`)."""
        return tracker_image(self.image, self.encoding)


@dataclass(frozen=True, eq=False)
class ImuRecord:
    """One IMU sample.

    Attributes:
        topic: topic it was recorded on (``/imu0`` for EuRoC, ``/imu0/data`` for UMA-VI bags).
        stamp_ns: sample time (header stamp) in nanoseconds.
        gyro: (3,) float64 angular velocity in the IMU frame (rad/s).
        accel: (3,) float64 specific force in the IMU frame (m/s^2).
        frame_id: header frame id.
    """

    topic: str
    stamp_ns: int
    gyro: np.ndarray
    accel: np.ndarray
    frame_id: str = "imu0"


Record = ImageRecord | ImuRecord


@dataclass(frozen=True)
class RawMessage:
    """A message as ROS 2 serialised bytes, ready for ``Publisher.publish`` of a raw publisher.

    Attributes:
        topic: topic name.
        msgtype: ROS 2 type name, e.g. ``sensor_msgs/msg/Image``.
        stamp_ns: time the message was recorded at (bag time) in nanoseconds.
        cdr: CDR bytes including the 4-byte encapsulation header.
    """

    topic: str
    msgtype: str
    stamp_ns: int
    cdr: bytes = field(repr=False)
