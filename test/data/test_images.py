"""The image decoders: encodings, step, truncation, compressed formats, and the same array on every path."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from sensor_msgs.msg import CompressedImage, Image

from nsflow_ros.data.images import (
    CODECS,
    ImageDecodeError,
    compressed_for_tracker,
    decode_compressed,
    decode_image,
    encode_compressed,
    image_for_tracker,
)
from nsflow_ros.data.messages import (
    COMPRESSED_IMAGE,
    IMAGE,
    image_message,
    message_to_record,
    ros2_store,
    serialize,
)

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


# -- sensor_msgs/CompressedImage -------------------------------------------------------------------------

SMOOTH = cv2.GaussianBlur(RNG.integers(0, 256, (48, 64), dtype=np.uint8), (7, 7), 2.0)
SMOOTH_BGR = np.dstack([SMOOTH, np.flipud(SMOOTH), np.fliplr(SMOOTH)])
WIDE = (SMOOTH.astype(np.uint16) << 8) | 0x5A


def _compressed(encoding: str, image: np.ndarray, codec: str, quality: int = 90) -> CompressedImage:
    fmt, data = encode_compressed(image, encoding, codec, quality)
    msg = CompressedImage(format=fmt)
    msg.data = data
    return msg


@pytest.mark.parametrize(
    ("encoding", "image", "fmt"),
    [
        ("mono8", SMOOTH, "mono8; png compressed mono8"),
        ("bgr8", SMOOTH_BGR, "bgr8; png compressed bgr8"),
        ("rgb8", np.ascontiguousarray(SMOOTH_BGR[..., ::-1]), "rgb8; png compressed bgr8"),
        ("16UC1", WIDE, "16UC1; png compressed mono16"),
        ("mono16", WIDE, "mono16; png compressed mono16"),
    ],
)
def test_png_gives_what_the_raw_path_gives(encoding, image, fmt):
    msg = _compressed(encoding, image, "png")
    assert msg.format == fmt
    raw = _msg(image, encoding)
    np.testing.assert_array_equal(compressed_for_tracker(msg), image_for_tracker(raw))
    pixels, enc = decode_compressed(msg)
    assert enc == ("mono16" if image.dtype == np.uint16 else "mono8" if image.ndim == 2 else "bgr8")
    if image.dtype == np.uint16:
        np.testing.assert_array_equal(pixels, WIDE)  # all 16 bits kept


@pytest.mark.parametrize(
    ("encoding", "image", "fmt"),
    [
        ("mono8", SMOOTH, "mono8; jpeg compressed mono8"),
        ("bgr8", SMOOTH_BGR, "bgr8; jpeg compressed bgr8"),
        ("16UC1", WIDE, "16UC1; jpeg compressed mono8"),
    ],
)
def test_jpeg_is_close_to_the_raw_path_with_its_shape_and_dtype(encoding, image, fmt):
    msg = _compressed(encoding, image, "jpeg", quality=95)
    assert msg.format == fmt
    want = image_for_tracker(_msg(image, encoding))
    got = compressed_for_tracker(msg)
    assert got.shape == want.shape and got.dtype == np.uint8
    assert np.abs(got.astype(int) - want).mean() < 4.0 and not np.array_equal(got, want)  # lossy, close


@pytest.mark.parametrize("fmt", ["jpeg", "png", "jpg", ""])
def test_bare_and_empty_formats_as_older_publishers_write_them(fmt):
    codec = "png" if fmt == "png" else "jpeg"
    msg = _compressed("mono8", SMOOTH, codec)
    msg.format = fmt
    if not fmt:  # the codec is read from the data's signature
        for c in ("jpeg", "png"):
            msg.data = _compressed("mono8", SMOOTH, c).data
            assert compressed_for_tracker(msg).shape == SMOOTH.shape
    else:
        assert compressed_for_tracker(msg).shape == SMOOTH.shape


def test_a_mono_source_stored_in_colour_stays_mono():
    _, data = encode_compressed(SMOOTH_BGR, "bgr8", "png")
    msg = CompressedImage(format="mono8; png compressed bgr8")
    msg.data = data
    out = compressed_for_tracker(msg)
    np.testing.assert_array_equal(out, cv2.cvtColor(SMOOTH_BGR, cv2.COLOR_BGR2GRAY))


@pytest.mark.parametrize(
    ("fmt", "data", "cause", "match"),
    [
        ("bgr8; jpeg compressed bgr8", b"\xff\xd8 not a jpeg" * 4, "truncated:jpeg", "cut short: JPEG"),
        ("bgr8; jpeg compressed bgr8", b"\xff\xd8 no jpeg" * 4 + b"\xff\xd9", "corrupt:jpeg", "not valid"),
        ("mono8; png compressed mono8", b"", "corrupt:png", "0 bytes"),
        ("16UC1; compressedDepth png", b"\x00" * 20, "format:compressedDepth png", "'16UC1; compressedDepth"),
        ("bgr8; qoi compressed bgr8", b"qoif", "format:qoi", "unsupported compressed image format"),
        ("tiff", b"II*\x00", "format:tiff", "'tiff'"),
        ("", b"GIF89a", "format:", "neither JPEG nor PNG"),
    ],
)
def test_corrupt_or_unsupported_compressed_data_names_the_problem(fmt, data, cause, match):
    msg = CompressedImage(format=fmt)
    msg.data = data
    with pytest.raises(ImageDecodeError, match=match) as info:
        compressed_for_tracker(msg, "/cam0/image_raw/compressed")
    assert info.value.cause == cause and "/cam0/image_raw/compressed" in str(info.value)


def test_truncated_png_and_jpeg_are_refused_before_the_decoder_writes_to_stderr(capfd):
    for codec in CODECS:
        msg = _compressed("mono8", SMOOTH, codec)
        data = bytes(msg.data)
        for cut in (100, len(data) // 2, len(data) - 1):
            msg.data = data[:cut]
            with pytest.raises(ImageDecodeError, match=f"cut short: {codec.upper()} data without") as info:
                decode_compressed(msg)
            assert info.value.cause == f"truncated:{codec}"
    assert capfd.readouterr().err == ""  # libpng writes a line per truncated PNG it is given


def test_16_bit_colour_png_is_refused_with_what_it_decodes_to():
    _, buf = cv2.imencode(".png", np.dstack([WIDE] * 3))
    msg = CompressedImage(format="bgr16; png compressed bgr16")
    msg.data = buf.tobytes()
    with pytest.raises(ImageDecodeError, match="3-channel uint16"):
        decode_compressed(msg)


def test_compressed_record_and_node_decode_the_same_array():
    store = ros2_store()
    msg = _compressed("bgr8", SMOOTH_BGR, "jpeg")
    header = image_message(store, 7, "cam0", SMOOTH).header
    data = np.frombuffer(msg.data, np.uint8)
    ros = store.types[COMPRESSED_IMAGE](header=header, format=msg.format, data=data)
    back = store.deserialize_cdr(serialize(store, ros, COMPRESSED_IMAGE), COMPRESSED_IMAGE)
    record = message_to_record("/cam0/image_raw/compressed", COMPRESSED_IMAGE, back)
    np.testing.assert_array_equal(record.for_tracker(), compressed_for_tracker(msg))


def test_encode_compressed_refuses_bad_arguments():
    from nsflow_ros.data.errors import DataError

    with pytest.raises(DataError, match="'webp'"):
        encode_compressed(SMOOTH, "mono8", "webp")
    with pytest.raises(DataError, match="quality"):
        encode_compressed(SMOOTH, "mono8", "jpeg", quality=0)
