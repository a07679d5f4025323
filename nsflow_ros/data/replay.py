"""What a replay publishes, independent of ROS: the (optionally perturbed, remapped, compressed) stream.

:mod:`nsflow_ros.ros.replay_node` only paces and publishes what :func:`replay_stream` yields, so the stream
and its reproducibility from a seed are tested without middleware.
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, replace
from pathlib import Path

from nsflow_ros.data.errors import DataError
from nsflow_ros.data.images import CODECS, encode_compressed
from nsflow_ros.data.messages import (
    COMPRESSED_IMAGE,
    compressed_image_message,
    record_to_cdr,
    ros2_store,
    serialize,
)
from nsflow_ros.data.perturb import PERTURBATIONS, make_perturber, perturb_records
from nsflow_ros.data.records import ImageRecord, RawMessage, Record
from nsflow_ros.data.sources import SensorSource

__all__ = ["COMPRESSIONS", "ReplayError", "ReplayOptions", "parse_remaps", "replay_records", "replay_stream"]

COMPRESSIONS = ("none", *CODECS)
"""What ``ReplayOptions.compress`` takes: ``none`` (sensor_msgs/Image) or a codec of CompressedImage."""


class ReplayError(DataError):
    """Bad replay options (remap syntax, rate)."""


@dataclass(frozen=True)
class ReplayOptions:
    """Settings of a replay.

    Attributes:
        path: bag file/folder or ASL folder.
        topics: topics to replay (None = the EuRoC / UMA-VI camera and IMU topics present).
        start: seconds skipped from the start.
        duration: seconds replayed (None = to the end).
        rate: playback speed factor (1.0 = real time; 0 = as fast as possible).
        perturb: a perturbation of :data:`~nsflow_ros.data.perturb.PERTURBATIONS`: ``none``, the
            illumination levels ``small`` / ``large``, or ``dark`` (low light with sensor noise).
        seed: seed of the perturbation processes.
        remap: topic renames, source topic -> published topic.
        compress: ``none``, or publish camera images as sensor_msgs/CompressedImage of this codec
            (``jpeg`` / ``png``) on ``<published topic>/compressed``.
        jpeg_quality: JPEG quality (1..100) with ``compress="jpeg"``.
    """

    path: Path
    topics: Sequence[str] | None = None
    start: float = 0.0
    duration: float | None = None
    rate: float = 1.0
    perturb: str = "none"
    seed: int = 0
    remap: Mapping[str, str] | None = None
    compress: str = "none"
    jpeg_quality: int = 90

    def __post_init__(self) -> None:
        if self.rate < 0:
            raise ReplayError(f"rate must be >= 0 (0 = as fast as possible), got {self.rate}")
        if self.perturb not in PERTURBATIONS:
            raise ReplayError(f"perturb must be one of {', '.join(PERTURBATIONS)}, got {self.perturb!r}")
        if self.compress not in COMPRESSIONS:
            raise ReplayError(f"compress must be one of {', '.join(COMPRESSIONS)}, got {self.compress!r}")
        if not 1 <= self.jpeg_quality <= 100:
            raise ReplayError(f"JPEG quality must be in 1..100, got {self.jpeg_quality}")


def parse_remaps(items: Sequence[str]) -> dict[str, str]:
    """Parse ``from:=to`` topic remaps (ROS syntax).

    Raises:
        ReplayError: naming the malformed item.
    """
    out: dict[str, str] = {}
    for item in items:
        src, sep, dst = item.partition(":=")
        if not sep or not src.startswith("/") or not dst.startswith("/"):
            raise ReplayError(f"bad remap {item!r}: expected /from_topic:=/to_topic")
        out[src] = dst
    return out


def replay_stream(opts: ReplayOptions) -> Iterator[RawMessage]:
    """The messages of a replay, in time order, as ROS 2 CDR bytes on their published topics.

    Without perturbation or compression the source's bytes pass through (any topic type); with either,
    images are decoded, perturbed from (seed, stamp) and re-serialised, compressed on
    ``<topic>/compressed``.

    Raises:
        DataError: from the source (missing path or topic, damaged bag after the last good message).
    """
    source = _source(opts)
    remap = dict(opts.remap or {})
    if opts.perturb == "none" and opts.compress == "none":
        for msg in source.raw_messages():
            yield RawMessage(remap.get(msg.topic, msg.topic), msg.msgtype, msg.stamp_ns, msg.cdr)
        return
    store = ros2_store()
    for rec in _records(source, remap, opts):
        if opts.compress != "none" and isinstance(rec, ImageRecord):
            fmt, data = encode_compressed(rec.image, rec.encoding, opts.compress, opts.jpeg_quality)
            msg = compressed_image_message(store, rec.stamp_ns, rec.frame_id, fmt, data)
            cdr = serialize(store, msg, COMPRESSED_IMAGE)
            yield RawMessage(f"{rec.topic}/compressed", COMPRESSED_IMAGE, rec.stamp_ns, cdr)
            continue
        msgtype, cdr = record_to_cdr(rec)
        yield RawMessage(rec.topic, msgtype, rec.stamp_ns, cdr)


def replay_records(opts: ReplayOptions) -> Iterator[Record]:
    """Decoded image and IMU records of a replay, perturbed and remapped.

    Raises:
        DataError: from the source.
    """
    yield from _records(_source(opts), dict(opts.remap or {}), opts)


def _source(opts: ReplayOptions) -> SensorSource:
    return SensorSource(opts.path, topics=opts.topics, start=opts.start, duration=opts.duration)


def _records(source: SensorSource, remap: Mapping[str, str], opts: ReplayOptions) -> Iterator[Record]:
    """The source's records, perturbed as ``opts`` says, on their remapped topics."""
    perturber = None if opts.perturb == "none" else make_perturber(opts.perturb, opts.seed)
    records: Iterator[Record] = source.records()
    if perturber is not None:
        records = perturb_records(records, perturber)
    for rec in records:
        yield replace(rec, topic=remap.get(rec.topic, rec.topic))
