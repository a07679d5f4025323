"""sensor_msgs/Image encode / decode: encodings, padded rows, byte order, CDR for ROS 2."""

from __future__ import annotations

import numpy as np
import pytest

from nsflow_ros.data.errors import DataError
from nsflow_ros.data.images import decode_image, to_gray
from nsflow_ros.data.messages import (
    IMAGE,
    image_message,
    record_to_cdr,
    ros1_store,
    ros2_store,
    serialize,
)
from nsflow_ros.data.records import ImageRecord, ImuRecord

RNG = np.random.default_rng(0)
SAMPLES = {
    "mono8": RNG.integers(0, 256, (5, 7), dtype=np.uint8),
    "8UC1": RNG.integers(0, 256, (5, 7), dtype=np.uint8),
    "mono16": RNG.integers(0, 65536, (5, 7), dtype=np.uint16),
    "bgr8": RNG.integers(0, 256, (5, 7, 3), dtype=np.uint8),
    "rgb8": RNG.integers(0, 256, (5, 7, 3), dtype=np.uint8),
    "bgra8": RNG.integers(0, 256, (5, 7, 4), dtype=np.uint8),
    "rgba8": RNG.integers(0, 256, (5, 7, 4), dtype=np.uint8),
}


@pytest.mark.parametrize("encoding", sorted(SAMPLES))
@pytest.mark.parametrize("pad", [0, 9])
@pytest.mark.parametrize("ros1", [False, True])
def test_encodings_round_trip_through_serialisation_with_padded_rows(encoding, pad, ros1):
    img = SAMPLES[encoding]
    store = ros1_store() if ros1 else ros2_store()
    row = img.shape[1] * img.itemsize * (1 if img.ndim == 2 else img.shape[2])
    msg = image_message(store, 5_000_000_001, "cam0", img, encoding, step=row + pad)
    assert msg.step == row + pad and msg.data.size == (row + pad) * img.shape[0]
    raw = serialize(store, msg, IMAGE)
    back = store.deserialize_ros1(raw, IMAGE) if ros1 else store.deserialize_cdr(raw, IMAGE)
    out, enc = decode_image(back, "/cam0/image_raw")
    assert enc == encoding and out.dtype == img.dtype and np.array_equal(out, img)
    assert out.flags.writeable and out.flags.c_contiguous


def test_big_endian_mono16_is_decoded():
    img = SAMPLES["mono16"]
    msg = image_message(ros2_store(), 0, "cam0", img, "mono16")
    msg.is_bigendian = 1
    msg.data = img.astype(">u2").view(np.uint8).reshape(-1)
    out, _ = decode_image(msg)
    assert np.array_equal(out, img) and out.dtype == np.uint16


def test_decode_errors_name_topic_and_value():
    msg = image_message(ros2_store(), 0, "cam0", SAMPLES["mono8"], "mono8")
    msg.encoding = "yuv422"
    with pytest.raises(DataError, match=r"/cam7/image_raw: unsupported image encoding 'yuv422'"):
        decode_image(msg, "/cam7/image_raw")
    msg.encoding, msg.step = "mono8", 3
    with pytest.raises(DataError, match="step 3 is shorter than a row"):
        decode_image(msg)
    msg.step, msg.data = 7, msg.data[:20]
    with pytest.raises(DataError, match="data is truncated, 20 bytes instead of 35"):
        decode_image(msg)
    with pytest.raises(DataError, match="expected dtype uint8 with 3 channel"):
        image_message(ros2_store(), 0, "cam0", SAMPLES["mono8"], "bgr8")


def test_to_gray_and_cdr_for_raw_publishing():
    assert np.array_equal(to_gray(SAMPLES["mono16"], "mono16"), (SAMPLES["mono16"] >> 8).astype(np.uint8))
    rgb = SAMPLES["rgb8"]
    assert np.array_equal(to_gray(rgb, "rgb8"), to_gray(rgb[:, :, ::-1].copy(), "bgr8"))
    rec = ImageRecord("/cam0/image_raw", 1_500_000_000, SAMPLES["mono8"], "mono8", "cam0")
    msgtype, cdr = record_to_cdr(rec)
    assert msgtype == IMAGE and isinstance(cdr, bytes) and cdr[:4] == b"\x00\x01\x00\x00"  # CDR little endian
    msg = ros2_store().deserialize_cdr(cdr, msgtype)
    assert (msg.header.stamp.sec, msg.header.stamp.nanosec, msg.header.frame_id) == (1, 500_000_000, "cam0")
    msgtype, cdr = record_to_cdr(ImuRecord("/imu0", 7, np.array([1.0, 2, 3]), np.array([4.0, 5, 6])))
    imu = ros2_store().deserialize_cdr(cdr, msgtype)
    assert imu.angular_velocity.z == 3.0 and imu.linear_acceleration.x == 4.0
    assert imu.orientation_covariance[0] == -1.0  # no orientation estimate
