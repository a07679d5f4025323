"""One streaming interface over ROS 1 bags, ROS 2 bags (sqlite3, mcap) and EuRoC / UMA-VI ASL folders.

A :class:`SensorSource` yields image and IMU records one at a time, never loading a bag whole, or the same
stream as ROS 2 CDR bytes for a replayer. Default topics: ``/cam0/image_raw``, ``/cam1/image_raw`` (those
present) and ``/imu0`` (EuRoC) or ``/imu0/data`` (UMA-VI); an ASL folder's ``camN`` is ``/camN/image_raw``
and its ``imuN`` is ``/imuN`` (alias ``/imuN/data``).

Records come in record time order (bag receive time, or the CSV stamp; ties keep the bag's order, IMU before
cameras in ASL folders); ``start`` and ``duration`` select a window from the first selected record. A
damaged bag is read from the front as far as it is intact, and the error comes after the last good record.
"""

from __future__ import annotations

import heapq
import sqlite3
import struct
from collections.abc import Callable, Iterator, Sequence
from itertools import chain
from pathlib import Path
from typing import Any, Literal

import cv2
import numpy as np
from rosbags.highlevel import AnyReader, AnyReaderError
from rosbags.rosbag1 import ReaderError as ReaderError1
from rosbags.rosbag2 import ReaderError as ReaderError2
from rosbags.serde import SerdeError

from nsflow_ros.data.errors import DataError
from nsflow_ros.data.messages import (
    COMPRESSED_IMAGE,
    IMAGE,
    IMU,
    default_encoding,
    message_to_record,
    record_to_cdr,
    ros1_store,
    ros2_store,
)
from nsflow_ros.data.records import ImageRecord, ImuRecord, RawMessage, Record
from nsflow_ros.data.salvage import SalvagedMessage, salvage_mcap, salvage_ros1, salvage_sqlite3

__all__ = [
    "IMAGE_TOPICS",
    "IMU_TOPICS",
    "SensorSource",
    "SourceKind",
    "detect_kind",
    "read_raw_messages",
    "read_records",
]

IMAGE_TOPICS = ("/cam0/image_raw", "/cam1/image_raw")
IMU_TOPICS = ("/imu0", "/imu0/data")
SourceKind = Literal["ros1", "ros2", "asl"]
_DECODABLE = (IMAGE, COMPRESSED_IMAGE, IMU)
# What rosbags (and the storage libraries under it) raise on damaged data.
# A file of random bytes named .bag fails in rosbags' header check with a UnicodeDecodeError.
_BAG_ERRORS = (AnyReaderError, ReaderError1, ReaderError2, SerdeError, struct.error, sqlite3.Error, OSError,
               EOFError, UnicodeDecodeError)


def _asl_root(path: Path) -> Path | None:
    """The ``mav0`` folder of an ASL data set given it or its parent, None if ``path`` is not one."""
    for cand in (path / "mav0", path):
        if cand.is_dir() and any((d / "data.csv").is_file() for d in cand.iterdir() if d.is_dir()):
            return cand
    return None


def detect_kind(path: str | Path) -> SourceKind:
    """Which kind of data set ``path`` is: a ``.bag`` file, a ROS 2 bag file or folder, or an ASL folder.

    Raises:
        DataError: when the path does not exist or is none of these.
    """
    p = Path(path)
    if not p.exists():
        raise DataError(f"data set not found: {p}")
    if p.is_file():
        if p.suffix == ".bag":
            return "ros1"
        if p.suffix in (".mcap", ".db3"):
            return "ros2"
        raise DataError(f"{p} is not a bag (expected a .bag, .mcap or .db3 file, or a folder)")
    if (p / "metadata.yaml").is_file() or any(p.glob("*.mcap")) or any(p.glob("*.db3")):
        return "ros2"
    if _asl_root(p) is not None:
        return "asl"
    raise DataError(f"{p} is neither a ROS 2 bag folder (no metadata.yaml) "
                    "nor an ASL folder (no mav0/*/data.csv)")


class SensorSource:
    """Time-ordered image and IMU records from a bag or an ASL folder.

    Args:
        path: ROS 1 ``.bag`` file, ROS 2 bag folder (or its ``.mcap`` / ``.db3`` file), or ASL folder
            (the folder holding ``mav0``, or ``mav0`` itself).
        topics: topics to read, each of which must exist; None for the defaults.
        start: seconds to skip from the first selected record.
        duration: seconds to read from there; None reads to the end.

    Raises:
        DataError: an unknown path, a negative start or a non-positive duration (topic problems are raised
            when iteration starts).

    Example:
        ``for rec in SensorSource("MH_01_easy.bag", duration=10.0): ...``
    """

    def __init__(self, path: str | Path, *, topics: Sequence[str] | None = None, start: float = 0.0,
                 duration: float | None = None) -> None:
        self.path = Path(path)
        self.kind: SourceKind = detect_kind(self.path)
        if isinstance(topics, str):
            topics = [topics]
        self.requested = None if topics is None else list(dict.fromkeys(topics))
        if start < 0:
            raise DataError(f"start must be >= 0 seconds, got {start}")
        if duration is not None and duration <= 0:
            raise DataError(f"duration must be > 0 seconds, got {duration}")
        self._start_ns = round(start * 1e9)
        self._dur_ns = None if duration is None else round(duration * 1e9)

    # -- public -----------------------------------------------------------------------------------------

    def __iter__(self) -> Iterator[Record]:
        return self.records()

    def records(self) -> Iterator[Record]:
        """Decoded :class:`ImageRecord` / :class:`ImuRecord`, in time order.

        Raises:
            DataError: a missing topic (naming the topics present), a topic of another type, an unknown
                image encoding, or a damaged source (after the last good record).
        """
        if self.kind == "asl":
            return self._asl_records()
        return self._bag_items(raw=False)

    def raw_messages(self) -> Iterator[RawMessage]:
        """The stream as ROS 2 CDR bytes per message, for a raw rclpy publisher; any topic type is allowed.

        Raises:
            DataError: as :meth:`records`, and for ROS 1 types unknown to ROS 2 Jazzy.
        """
        if self.kind == "asl":
            return (_raw_of(rec) for rec in self._asl_records())
        return self._bag_items(raw=True)

    # -- topic selection --------------------------------------------------------------------------------

    def _resolve(self, present: dict[str, str], raw: bool, where: Path | None = None,
                 aliases: dict[str, str] | None = None) -> list[str]:
        """The topics to read; requested ones may also be ``aliases`` (name -> type) of present ones."""
        listing = ", ".join(f"{t} ({present[t]})" for t in sorted(present)) or "none"
        if self.requested is not None:
            known = {**present, **(aliases or {})}
            missing = [t for t in self.requested if t not in known]
            if missing:
                raise DataError(f"topic(s) {', '.join(missing)} not found in {where or self.path}; "
                                f"topics present: {listing}")
            if not raw:
                for t in self.requested:
                    if known[t] not in _DECODABLE:
                        raise DataError(f"topic {t} in {self.path} has type {present[t]}; records can "
                                        f"be read only from {', '.join(_DECODABLE)} "
                                        "(use raw_messages for others)")
            return list(self.requested)
        cams = [t for t in IMAGE_TOPICS if t in present]
        if not cams:
            raise DataError(f"no camera topic ({', '.join(IMAGE_TOPICS)}) in {self.path}; "
                            f"topics present: {listing}; name the topics to read")
        imu = [t for t in IMU_TOPICS if t in present][:1]
        return cams + imu

    def _window(self, t0: int) -> tuple[int, int | None]:
        lo = t0 + self._start_ns
        return lo, (None if self._dur_ns is None else lo + self._dur_ns)

    # -- bags -------------------------------------------------------------------------------------------

    def _open_reader(self) -> AnyReader:
        try:
            reader = AnyReader([self.path], default_typestore=ros2_store())
            reader.open()
        except (FileNotFoundError, *_BAG_ERRORS) as err:
            raise DataError(f"cannot open bag {self.path}: {err}") from err
        return reader

    def _bag_items(self, raw: bool) -> Iterator[Any]:
        try:
            reader = self._open_reader()
        except DataError as err:
            # Damaged beyond what rosbags opens: scan from the front instead.
            yield from self._salvage(raw, err)
            return
        count = 0
        try:
            present = {c.topic: c.msgtype for c in reader.connections}
            topics = self._resolve(present, raw)
            conns = [c for c in reader.connections if c.topic in topics]
            first_gen = reader.messages(connections=conns)
            first = next(first_gen, None)
            if first is None:
                return
            lo, hi = self._window(first[1])
            if self._start_ns:
                first_gen.close()
                stream: Iterator[Any] = reader.messages(connections=conns, start=lo, stop=hi)
            else:
                stream = chain([first], first_gen)
            ros1 = not reader.is2
            for conn, t, data in stream:
                if hi is not None and t >= hi:
                    break
                if raw:
                    yield _raw_message(conn.topic, conn.msgtype, t, data, ros1)
                else:
                    yield _decode(conn.topic, conn.msgtype, data, reader.deserialize)
                count += 1
        except _BAG_ERRORS as err:
            raise DataError(f"bag {self.path} is unreadable after {count} record(s): {err}") from err
        finally:
            reader.close()

    def _salvage_files(self) -> list[Callable[[], Iterator[SalvagedMessage]]]:
        p = self.path
        if self.kind == "ros1":
            return [lambda: salvage_ros1(p)]
        files = [p] if p.is_file() else sorted([*p.glob("*.mcap"), *p.glob("*.db3")])
        fns = {".mcap": salvage_mcap, ".db3": salvage_sqlite3}
        return [lambda f=f: fns[f.suffix](f) for f in files]

    def _salvage(self, raw: bool, cause: DataError) -> Iterator[Any]:
        files = self._salvage_files()
        if not files:
            raise cause
        ros1 = self.kind == "ros1"
        store = ros1_store() if ros1 else ros2_store()
        deser = store.deserialize_ros1 if ros1 else store.deserialize_cdr
        # The topic list is unknown until scanned: take the defaults under either IMU name.
        wanted = set(self.requested) if self.requested is not None else {*IMAGE_TOPICS, *IMU_TOPICS}
        lo = hi = None
        try:
            for make in files:
                for topic, msgtype, t, data in make():
                    if topic not in wanted:
                        continue
                    if lo is None:
                        lo, hi = self._window(t)
                    if t < lo:
                        continue
                    if hi is not None and t >= hi:
                        return
                    if raw:
                        yield _raw_message(topic, msgtype, t, data, ros1)
                    else:
                        yield _decode(topic, msgtype, data, deser)
        except DataError as err:
            raise DataError(f"{err} (rosbags could not open it: {cause})") from err
        except (SerdeError, KeyError, struct.error, ValueError) as err:
            raise DataError(f"bag {self.path}: cannot deserialise a salvaged message: {err}") from err

    # -- ASL folders ------------------------------------------------------------------------------------

    def _asl_topics(self) -> list[tuple[str, str]]:
        root = _asl_root(self.path)
        assert root is not None
        out = []
        for d in sorted(root.iterdir()):
            if not (d / "data.csv").is_file():
                continue
            if d.name.startswith("cam"):
                out.append((f"/{d.name}/image_raw", IMAGE))
            elif d.name.startswith("imu"):
                out.append((f"/{d.name}", IMU))
        return out

    def _asl_records(self) -> Iterator[Record]:
        root = _asl_root(self.path)
        assert root is not None
        present = dict(self._asl_topics())
        # /imuN/data (UMA-VI's bag name) is accepted for an ASL folder's imuN.
        aliases = {f"{t}/data": t for t, typ in present.items() if typ == IMU}
        lookup = {**present, **{a: IMU for a in aliases}}
        topics = self._resolve(present, raw=False, where=root, aliases=lookup)
        streams = []
        # IMU first at equal stamps: a consumer then has the inertial data up to an image's time.
        order = sorted(topics, key=lambda t: (lookup[t] != IMU, t))
        for prio, topic in enumerate(order):
            folder = root / aliases.get(topic, topic).strip("/").split("/")[0]
            if lookup[topic] == IMU:
                rows: list[tuple[int, Any]] = list(_read_imu_csv(folder / "data.csv"))
            else:
                rows = [(s, (folder, name)) for s, name in _read_camera_csv(folder / "data.csv")]
            streams.append([(s, prio, topic, payload) for s, payload in rows])
        merged = heapq.merge(*streams, key=lambda x: (x[0], x[1]))
        first = next(merged, None)
        if first is None:
            return
        lo, hi = self._window(first[0])
        for stamp, _prio, topic, payload in chain([first], merged):
            if stamp < lo:
                continue
            if hi is not None and stamp >= hi:
                return
            if isinstance(payload, tuple):
                folder, name = payload
                img, enc = _read_png(folder / "data" / name)
                yield ImageRecord(topic, stamp, img, enc, folder.name)
            else:
                yield ImuRecord(topic, stamp, payload[:3].copy(), payload[3:].copy(),
                                aliases.get(topic, topic).strip("/").split("/")[0])


def _raw_of(rec: Record) -> RawMessage:
    msgtype, cdr = record_to_cdr(rec)
    return RawMessage(rec.topic, msgtype, rec.stamp_ns, cdr)


def _decode(topic: str, msgtype: str, data: Any, deser: Callable[[Any, str], Any]) -> Record:
    if msgtype not in _DECODABLE:
        raise DataError(f"topic {topic} has type {msgtype}; expected one of {', '.join(_DECODABLE)}")
    return message_to_record(topic, msgtype, deser(data, msgtype))


def _raw_message(topic: str, msgtype: str, t: int, data: Any, ros1: bool) -> RawMessage:
    if not ros1:
        return RawMessage(topic, msgtype, t, bytes(data))
    try:
        return RawMessage(topic, msgtype, t, bytes(ros2_store().ros1_to_cdr(data, msgtype)))
    except KeyError:
        raise DataError(f"topic {topic}: ROS 1 type {msgtype} has no ROS 2 Jazzy equivalent to convert to"
                        ) from None


def _csv_rows(path: Path) -> Iterator[tuple[int, list[str]]]:
    if not path.is_file():
        raise DataError(f"ASL file not found: {path}")
    with path.open() as f:
        for lineno, line in enumerate(f, 1):
            line = line.strip()
            if line and not line.startswith("#"):
                yield lineno, [c.strip() for c in line.split(",")]


def _read_camera_csv(path: Path) -> list[tuple[int, str]]:
    """(stamp, file name) rows of camN/data.csv; extra columns (UMA-VI's exposure) are ignored."""
    rows = []
    for lineno, cols in _csv_rows(path):
        try:
            rows.append((int(cols[0]), cols[1]))
        except (ValueError, IndexError):
            raise DataError(f"{path}:{lineno}: expected 'timestamp [ns],filename', "
                            f"got {','.join(cols)!r}") from None
    rows.sort(key=lambda r: r[0])
    return rows


def _read_imu_csv(path: Path) -> list[tuple[int, np.ndarray]]:
    """(stamp, [wx, wy, wz, ax, ay, az]) rows of imuN/data.csv."""
    rows = []
    for lineno, cols in _csv_rows(path):
        try:
            vals = np.array([float(c) for c in cols[1:7]], dtype=np.float64)
            if vals.size != 6:
                raise ValueError
            rows.append((int(cols[0]), vals))
        except (ValueError, IndexError):
            raise DataError(f"{path}:{lineno}: expected a timestamp and 6 numbers, "
                            f"got {','.join(cols)!r}") from None
    rows.sort(key=lambda r: r[0])
    return rows


def _read_png(path: Path) -> tuple[np.ndarray, str]:
    if not path.is_file():  # before OpenCV, which would print its own warning first
        raise DataError(f"image {path} named in {path.parent.parent / 'data.csv'} does not exist")
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise DataError(f"cannot read image {path} (not an image)")
    ch = 1 if img.ndim == 2 else img.shape[2]
    enc = default_encoding(img.dtype, ch)
    if enc is None:
        raise DataError(f"image {path}: unsupported pixel format {img.dtype} with {ch} channel(s)")
    return img, enc


def read_records(path: str | Path, *, topics: Sequence[str] | None = None, start: float = 0.0,
                 duration: float | None = None) -> Iterator[Record]:
    """Shorthand for ``SensorSource(path, ...).records()``."""
    return SensorSource(path, topics=topics, start=start, duration=duration).records()


def read_raw_messages(path: str | Path, *, topics: Sequence[str] | None = None, start: float = 0.0,
                      duration: float | None = None) -> Iterator[RawMessage]:
    """Shorthand for ``SensorSource(path, ...).raw_messages()``."""
    return SensorSource(path, topics=topics, start=start, duration=duration).raw_messages()
