"""The one sensor_msgs/Image decoder: encodings, step, truncation, and the same array on every path."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from sensor_msgs.msg import Image

from nsflow_ros.data.images import ImageDecodeError, decode_image, image_for_tracker
from nsflow_ros.data.messages import IMAGE, image_message, message_to_record, ros2_store, serialize
from nsflow_ros.ros.image_conv import numpy_to_image_fields

RNG = np.random.default_rng(0)
BGR = RNG.integers(0, 256, (5, 7, 3), dtype=np.uint8)
GRAY = RNG.integers(0, 256, (5, 7), dtype=np.uint8)


def _msg(arr: np.ndarray, encoding: str, pad: int = 0, bigendian: bool = False) -> Image:
    h, w = arr.shape[:2]
    row = arr.reshape(h, -1).view(np.uint8) if arr.dtype != np.uint8 else arr.reshape(h, -1)
    padded = np.zeros((h, row.shape[1] + pad), np.uint8)
    padded[:, : row.shape[1]] = row
    m = Image(height=h, width=w, encoding=encoding, is_bigendian=int(bigendian), step=padded.shape[1])
    m.data = padded.tobytes()
    return m


@pytest.mark.parametrize("encoding", ["mono8", "8UC1"])
def test_mono8_with_and_without_row_padding(encoding):
    for pad in (0, 5):
        out = image_for_tracker(_msg(GRAY, encoding, pad))
        np.testing.assert_array_equal(out, GRAY)
        assert out.flags.c_contiguous and out.flags.writeable


@pytest.mark.parametrize(
    ("encoding", "make"),
    [
        ("bgr8", lambda a: a),
        ("rgb8", lambda a: a[..., ::-1]),
        ("bgra8", lambda a: np.dstack([a, np.full(a.shape[:2], 9, np.uint8)])),
        ("rgba8", lambda a: np.dstack([a[..., ::-1], np.full(a.shape[:2], 9, np.uint8)])),
    ],
)
def test_colour_encodings_become_bgr(encoding, make):
    for pad in (0, 3):
        msg = _msg(np.ascontiguousarray(make(BGR)), encoding, pad)
        np.testing.assert_array_equal(image_for_tracker(msg), BGR)


@pytest.mark.parametrize("bigendian", [False, True])
def test_mono16_keeps_the_high_byte_in_either_byte_order(bigendian):
    values = (GRAY.astype(np.uint16) << 8) | 0x7F
    arr = values.astype(">u2" if bigendian else "<u2")
    out = image_for_tracker(_msg(arr, "mono16", pad=2, bigendian=bigendian))
    np.testing.assert_array_equal(out, GRAY)


@pytest.mark.parametrize(
    ("mutate", "cause", "match"),
    [
        (lambda m: setattr(m, "encoding", "bayer_rggb8"), "encoding:bayer_rggb8", "unsupported image enc"),
        (lambda m: setattr(m, "encoding", "32FC1"), "encoding:32FC1", "32FC1"),
        (lambda m: setattr(m, "step", 6), "step", "step 6 is shorter than a row"),
        (lambda m: setattr(m, "data", bytes(m.data)[:-1]), "truncated", "34 bytes instead of 35"),
        (lambda m: setattr(m, "data", bytes(m.data) + b"x"), "oversized", "more than step x height"),
        (lambda m: setattr(m, "width", 0), "size", "zero size"),
    ],
)
def test_bad_messages_name_the_problem(mutate, cause, match):
    m = _msg(GRAY, "mono8")
    mutate(m)
    with pytest.raises(ImageDecodeError, match=match) as info:
        image_for_tracker(m)
    assert info.value.cause == cause


def test_round_trip_through_the_field_helper():
    fields = numpy_to_image_fields(BGR)
    assert fields["encoding"] == "bgr8" and fields["step"] == 21
    m = Image(**{k: v for k, v in fields.items() if k != "data"})
    m.data = fields["data"]
    np.testing.assert_array_equal(image_for_tracker(m), BGR)
    assert cv2.cvtColor(image_for_tracker(m), cv2.COLOR_BGR2GRAY).shape == (5, 7)


@pytest.mark.parametrize(
    ("encoding", "image"),
    [
        ("mono8", GRAY),
        ("mono16", (GRAY.astype(np.uint16) << 8) | 0x31),
        ("16UC1", (GRAY.astype(np.uint16) << 8) | 0x31),
        ("bgr8", BGR),
        ("rgb8", np.ascontiguousarray(BGR[..., ::-1])),
        ("bgra8", np.dstack([BGR, np.full(BGR.shape[:2], 9, np.uint8)])),
    ],
)
def test_node_offline_and_feature_bag_decode_a_message_to_the_same_array(encoding, image):
    # the node decodes the rclpy message; offline and the feature bag read records of the same message
    store = ros2_store()
    msg = image_message(store, 7, "cam0", image, encoding, step=image.strides[0] + 4)
    back = store.deserialize_cdr(serialize(store, msg, IMAGE), IMAGE)
    node = Image(height=back.height, width=back.width, encoding=back.encoding, is_bigendian=back.is_bigendian,
                 step=back.step)
    node.data = bytes(back.data)
    from_node = image_for_tracker(node)
    record = message_to_record("/cam0/image_raw", IMAGE, back)
    np.testing.assert_array_equal(record.for_tracker(), from_node)
    assert from_node.dtype == np.uint8 and from_node.ndim == (2 if image.ndim == 2 else 3)
    pixels, enc = decode_image(back)
    assert enc == encoding and np.array_equal(pixels, image)
