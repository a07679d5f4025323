"""sensor_msgs/Image -> NumPy: the one decoder of the node, the replayer, the offline run and the feature bag.

Records keep the pixels as the encoding stores them (:func:`decode_image`), so they can be re-serialised;
the tracker gets colour as BGR rather than a gray copy (:func:`tracker_image`), so a colour encoder sees
colour and the debug image stays in colour. CompressedImage (JPEG, PNG) decodes to the same arrays. Any
object with the message fields works, so no ROS import is needed.
"""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np

from nsflow_ros.data.errors import DataError

__all__ = [
    "CODECS",
    "ENCODINGS",
    "ImageDecodeError",
    "compressed_for_tracker",
    "compressed_format",
    "decode_compressed",
    "decode_image",
    "encode_compressed",
    "image_for_tracker",
    "to_gray",
    "tracker_image",
]

ENCODINGS: dict[str, tuple[np.dtype, int]] = {
    "mono8": (np.dtype(np.uint8), 1),
    "8UC1": (np.dtype(np.uint8), 1),
    "mono16": (np.dtype(np.uint16), 1),
    "16UC1": (np.dtype(np.uint16), 1),
    "bgr8": (np.dtype(np.uint8), 3),
    "rgb8": (np.dtype(np.uint8), 3),
    "bgra8": (np.dtype(np.uint8), 4),
    "rgba8": (np.dtype(np.uint8), 4),
}
"""The accepted encodings, with (dtype, channels)."""

_TO_BGR = {"rgb8": cv2.COLOR_RGB2BGR, "bgra8": cv2.COLOR_BGRA2BGR, "rgba8": cv2.COLOR_RGBA2BGR}
_TO_GRAY = {"bgr8": cv2.COLOR_BGR2GRAY, "rgb8": cv2.COLOR_RGB2GRAY, "bgra8": cv2.COLOR_BGRA2GRAY,
            "rgba8": cv2.COLOR_RGBA2GRAY}


class ImageDecodeError(DataError):
    """An image message cannot be decoded.

    Attributes:
        cause: a short key of the failure kind ("encoding:<name>", "size", "step", "truncated",
            "oversized"; for compressed images "format:<name>", "truncated:<codec>" and "corrupt:<codec>"),
            for counting failures by kind.
    """

    def __init__(self, message: str, cause: str) -> None:
        super().__init__(message)
        self.cause = cause


def decode_image(msg: Any, topic: str = "") -> tuple[np.ndarray, str]:
    """Pixels of a sensor_msgs/Image, honouring ``step`` (padded rows) and ``is_bigendian``.

    Args:
        msg: the message (fields encoding, height, width, step, is_bigendian, data).
        topic: named in error messages.

    Returns:
        ``(image, encoding)``: a writable C-contiguous copy in native byte order.

    Raises:
        ImageDecodeError: an unsupported encoding, zero size, a step shorter than a row, or data shorter or
            longer than step x height.

    Shape:
        image: (H, W) for mono encodings, (H, W, C) for colour ones; uint8, or uint16 for 16-bit ones.
    """
    enc = str(msg.encoding)
    where = f"{topic}: " if topic else ""
    if enc not in ENCODINGS:
        raise ImageDecodeError(
            f"{where}unsupported image encoding {enc!r}; accepted: {', '.join(ENCODINGS)}", f"encoding:{enc}"
        )
    dtype, ch = ENCODINGS[enc]
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    if h <= 0 or w <= 0:
        raise ImageDecodeError(f"{where}{enc} image has zero size: {w}x{h}", "size")
    row = w * ch * dtype.itemsize
    if step < row:
        raise ImageDecodeError(
            f"{where}{enc} image {w}x{h}: step {step} is shorter than a row ({w} px x {ch * dtype.itemsize} "
            f"bytes = {row})",
            "step",
        )
    data = msg.data if isinstance(msg.data, np.ndarray) else np.frombuffer(msg.data, dtype=np.uint8)
    data = data.reshape(-1).view(np.uint8)
    expected = step * h
    if data.size < expected:
        raise ImageDecodeError(
            f"{where}{enc} image {w}x{h}, step {step}: data is truncated, {data.size} bytes instead of "
            f"{expected}",
            "truncated",
        )
    if data.size > expected:
        raise ImageDecodeError(
            f"{where}{enc} image {w}x{h}, step {step}: data has {data.size} bytes, more than step x height = "
            f"{expected}",
            "oversized",
        )
    rows = data.reshape(h, step)[:, :row]
    wire = dtype.newbyteorder(">" if msg.is_bigendian else "<")
    pixels = np.ascontiguousarray(rows).view(wire).astype(dtype)  # a copy in native order
    return pixels.reshape((h, w) if ch == 1 else (h, w, ch)), enc


def _check_encoding(encoding: str) -> None:
    if encoding not in ENCODINGS:
        raise DataError(f"unknown image encoding {encoding!r}; supported: {', '.join(ENCODINGS)}")


def to_gray(image: np.ndarray, encoding: str) -> np.ndarray:
    """8-bit gray version of decoded pixels. Shape: (H, W[, C]) -> (H, W) uint8.

    Raises:
        DataError: for an unknown encoding.
    """
    _check_encoding(encoding)
    if ENCODINGS[encoding][0].itemsize == 2:
        return (image >> 8).astype(np.uint8)
    if encoding in _TO_GRAY:
        return cv2.cvtColor(image, _TO_GRAY[encoding])
    return image


def tracker_image(image: np.ndarray, encoding: str) -> np.ndarray:
    """What the tracker is given for decoded pixels: mono8 as it is, 16-bit shifted to 8 bits, colour as BGR.

    Raises:
        DataError: for an unknown encoding.

    Shape:
        (H, W[, C]) -> (H, W) uint8 for mono encodings, (H, W, 3) uint8 BGR for colour ones.
    """
    _check_encoding(encoding)
    if ENCODINGS[encoding][1] == 1:
        return to_gray(image, encoding)
    if encoding in _TO_BGR:
        return cv2.cvtColor(np.ascontiguousarray(image), _TO_BGR[encoding])
    return image


def image_for_tracker(msg: Any, topic: str = "") -> np.ndarray:
    """Decode a sensor_msgs/Image into the array the tracker is given (:func:`tracker_image`).

    Raises:
        ImageDecodeError: as :func:`decode_image`.
    """
    return tracker_image(*decode_image(msg, topic))


CODECS = ("jpeg", "png")
"""The compressed formats decoded: those of image_transport's ``compressed`` plugin."""

_DECODED = {(np.dtype(np.uint8), 1): "mono8", (np.dtype(np.uint16), 1): "mono16",
            (np.dtype(np.uint8), 3): "bgr8", (np.dtype(np.uint8), 4): "bgra8"}
_MONO = ("mono8", "8UC1", "mono16", "16UC1")


def _codec(fmt: str, data: bytes, where: str) -> tuple[str, str]:
    """``(codec, original encoding or "")`` of a CompressedImage ``format`` field.

    Accepts image_transport's ``"<encoding>; <codec> compressed [<target>]"``, the older bare ``"jpeg"`` /
    ``"png"``, and an empty field (the codec is then read from the data's signature).
    """
    original, sep, rest = fmt.partition(";")
    if sep:
        words = rest.split()
        codec = words[0].lower() if len(words) >= 2 and words[1] == "compressed" else rest.strip()
        original = original.strip()
    else:
        codec, original = fmt.strip().lower(), ""
        if not codec:
            codec = "jpeg" if data[:2] == b"\xff\xd8" else "png" if data[:8] == b"\x89PNG\r\n\x1a\n" else ""
            if not codec:
                raise ImageDecodeError(
                    f"{where}compressed image with an empty format whose data is neither JPEG nor PNG",
                    "format:",
                )
    codec = "jpeg" if codec == "jpg" else codec
    if codec not in CODECS:
        raise ImageDecodeError(
            f"{where}unsupported compressed image format {fmt!r}; accepted: JPEG or PNG as image_transport's "
            "'compressed' plugin writes them (e.g. 'bgr8; jpeg compressed bgr8', 'mono16; png compressed "
            "mono16', or plain 'jpeg' / 'png')",
            f"format:{codec}",
        )
    return codec, original


_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_ENDS = (("PNG", _PNG_SIGNATURE, b"IEND\xaeB`\x82"), ("JPEG", b"\xff\xd8", b"\xff\xd9"))
"""(name, start signature, end marker): a PNG ends with its IEND chunk, a JPEG with its EOI marker."""


def _cut_short(data: np.ndarray) -> str:
    """The codec name ("PNG", "JPEG") of data that starts as one but lacks its end marker, else "".

    Checked before decoding because libpng writes one line straight to stderr for every truncated image,
    and a few bytes' comparison costs nothing beside the decode.
    """
    head, tail = data[:8].tobytes(), data[-32:].tobytes()
    for name, start, end in _ENDS:
        if head.startswith(start) and end not in tail:
            return name
    return ""


def decode_compressed(msg: Any, topic: str = "") -> tuple[np.ndarray, str]:
    """Pixels of a sensor_msgs/CompressedImage (JPEG or PNG), decoded by OpenCV.

    Colour decodes as BGR, as image_transport's plugin stores it; a mono source (the ``format`` field's
    first part is mono8 / mono16 / 8UC1 / 16UC1) stays mono even when stored with three channels.

    Args:
        msg: the message (fields format, data).
        topic: named in error messages.

    Returns:
        ``(image, encoding)``: encoding mono8, mono16, bgr8 or bgra8.

    Raises:
        ImageDecodeError: a format other than JPEG / PNG, data cut short (no end marker; refused before the
            decoder, which would write to stderr), data that does not decode, or pixels with no raw encoding
            (16-bit colour).

    Shape:
        image: (H, W) uint8 / uint16 for mono, (H, W, 3|4) uint8 for colour.
    """
    where = f"{topic}: " if topic else ""
    data = msg.data if isinstance(msg.data, np.ndarray) else np.frombuffer(bytes(msg.data), dtype=np.uint8)
    data = data.reshape(-1).view(np.uint8)
    fmt = str(msg.format)
    codec, original = _codec(fmt, data[:8].tobytes(), where)
    cut = _cut_short(data)
    if cut:
        raise ImageDecodeError(
            f"{where}compressed image ({fmt!r}, {data.size} bytes) is cut short: {cut} data without its end "
            "marker", f"truncated:{cut.lower()}",
        )
    try:
        img = cv2.imdecode(data, cv2.IMREAD_UNCHANGED) if data.size else None
    except cv2.error:
        img = None
    if img is None:
        raise ImageDecodeError(
            f"{where}compressed image ({fmt!r}, {data.size} bytes) is not valid {codec.upper()} data",
            f"corrupt:{codec}",
        )
    channels = 1 if img.ndim == 2 else img.shape[2]
    if original in _MONO and channels > 1:
        img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY if channels == 3 else cv2.COLOR_BGRA2GRAY)
        channels = 1
    encoding = _DECODED.get((img.dtype, channels))
    if encoding is None:
        raise ImageDecodeError(
            f"{where}compressed image ({fmt!r}) decodes to {channels}-channel {img.dtype}; accepted: 8 or "
            "16-bit mono, 8-bit colour",
            f"encoding:{img.dtype}x{channels}",
        )
    return img, encoding


def compressed_for_tracker(msg: Any, topic: str = "") -> np.ndarray:
    """Decode a sensor_msgs/CompressedImage into the array the tracker is given (:func:`tracker_image`).

    Raises:
        ImageDecodeError: as :func:`decode_compressed`.
    """
    return tracker_image(*decode_compressed(msg, topic))


def compressed_format(encoding: str, codec: str) -> str:
    """The ``format`` field image_transport's ``compressed`` plugin writes for an image of ``encoding``.

    Raises:
        DataError: for an unknown encoding or codec.
    """
    _check_encoding(encoding)
    if codec not in CODECS:
        raise DataError(f"unknown compression {codec!r}; supported: {', '.join(CODECS)}")
    dtype, channels = ENCODINGS[encoding]
    depth = 8 if codec == "jpeg" else 8 * dtype.itemsize  # JPEG stores 8 bits
    return f"{encoding}; {codec} compressed {'bgr' if channels > 1 else 'mono'}{depth}"


def encode_compressed(image: np.ndarray, encoding: str, codec: str, quality: int = 90) -> tuple[str, bytes]:
    """Compress decoded pixels as image_transport's ``compressed`` plugin does: ``(format, data)``.

    Colour goes in as BGR (alpha dropped); 16-bit mono goes into PNG as 16 bits and into JPEG as its 8 most
    significant bits, the bits the tracker uses.

    Args:
        image: pixels as :func:`decode_image` returns them.
        encoding: a key of :data:`ENCODINGS`.
        codec: one of :data:`CODECS`.
        quality: JPEG quality, 1..100.

    Raises:
        DataError: for an unknown encoding or codec, or a quality out of range.
    """
    fmt = compressed_format(encoding, codec)
    if not 1 <= quality <= 100:
        raise DataError(f"JPEG quality must be in 1..100, got {quality}")
    pixels = image
    if ENCODINGS[encoding][1] > 1:
        pixels = tracker_image(image, encoding)
    elif codec == "jpeg" and ENCODINGS[encoding][0].itemsize == 2:
        pixels = to_gray(image, encoding)
    params = [cv2.IMWRITE_JPEG_QUALITY, int(quality)] if codec == "jpeg" else [cv2.IMWRITE_PNG_COMPRESSION, 1]
    ok, buf = cv2.imencode(".jpg" if codec == "jpeg" else ".png", pixels, params)
    if not ok:
        raise DataError(f"OpenCV could not encode a {encoding} image of shape {image.shape} as {codec}")
    return fmt, buf.tobytes()
