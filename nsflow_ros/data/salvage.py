"""Read what is readable from a damaged bag, in file order, by scanning it from the start.

rosbags needs a bag's index (ROS 1), summary (MCAP) or an intact database (sqlite3), which a truncated file
no longer has; these scanners walk the records from the front and raise :class:`DataError` where the data
ends or stops making sense, after yielding every message before it. Supported: ROS 1 bags v2.0 (chunks
uncompressed, bz2 or lz4), MCAP with uncompressed chunks, sqlite3. Messages come as
``(topic, msgtype, log_time_ns, raw_bytes)`` with rosbags-style type names.
"""

from __future__ import annotations

import bz2
import sqlite3
import struct
from collections.abc import Iterator
from io import BytesIO
from pathlib import Path
from typing import BinaryIO

from nsflow_ros.data.errors import DataError

__all__ = ["SalvagedMessage", "salvage_mcap", "salvage_ros1", "salvage_sqlite3"]

SalvagedMessage = tuple[str, str, int, bytes]

_ROS1_MAGIC = b"#ROSBAG V2.0\n"
_MCAP_MAGIC = b"\x89MCAP0\r\n"


class _End(Exception):  # noqa: N818 - control flow, not an error for callers
    """The data ends (or is inconsistent) here; carries a description."""


def _read(bio: BinaryIO, n: int) -> bytes:
    data = bio.read(n)
    if len(data) != n:
        raise _End(f"needed {n} bytes at offset {bio.tell() - len(data)}, file has {len(data)}")
    return data


def _ros1_type(name: str) -> str:
    # ROS 1 names types pkg/Type; rosbags uses pkg/msg/Type for both ROS versions.
    parts = name.split("/")
    return f"{parts[0]}/msg/{parts[1]}" if len(parts) == 2 else name


def _ros1_fields(blob: bytes) -> dict[str, bytes]:
    fields, pos = {}, 0
    while pos < len(blob):
        if pos + 4 > len(blob):
            raise _End("truncated record header")
        (n,) = struct.unpack_from("<I", blob, pos)
        pos += 4
        if pos + n > len(blob):
            raise _End("record header field runs past its header")
        key, sep, value = blob[pos:pos + n].partition(b"=")
        if not sep:
            raise _End("record header field without '='")
        fields[key.decode("ascii", "replace")] = value
        pos += n
    return fields


def _ros1_head(bio: BinaryIO) -> tuple[dict[str, bytes], int] | None:
    """Next (header fields, data length) of a ROS 1 record, None at a clean end of file."""
    head = bio.read(4)
    if not head:
        return None
    if len(head) < 4:
        raise _End("file ends inside a record length")
    (hlen,) = struct.unpack("<I", head)
    header = _ros1_fields(_read(bio, hlen))
    (dlen,) = struct.unpack("<I", _read(bio, 4))
    return header, dlen


def _ros1_record(bio: BinaryIO) -> tuple[dict[str, bytes], bytes] | None:
    """Next (header fields, data) of a ROS 1 record, None at a clean end of file."""
    head = _ros1_head(bio)
    if head is None:
        return None
    header, dlen = head
    return header, _read(bio, dlen)


def salvage_ros1(path: Path) -> Iterator[SalvagedMessage]:
    """Messages of a (possibly truncated) ROS 1 bag, in file order.

    Raises:
        DataError: where the file stops being readable (after yielding everything before), or at the start
            when it is not a ROS 1 bag v2.0.
    """
    conns: dict[int, tuple[str, str]] = {}
    try:
        with path.open("rb") as f:
            if f.read(len(_ROS1_MAGIC)) != _ROS1_MAGIC:
                raise DataError(f"{path} is not a ROS 1 bag v2.0 (bad magic)")
            while True:
                head = _ros1_head(f)
                if head is None:
                    return
                header, dlen = head
                data = f.read(dlen)  # lenient: a cut record is handled below
                op = header.get("op", b"\x00")[:1]
                whole = len(data) == dlen
                if op == b"\x05" and (whole or header.get("compression", b"none") == b"none"):
                    # An uncompressed chunk that was cut still holds whole messages: keep them.
                    yield from _ros1_chunk(header, data, conns, whole)
                elif op == b"\x07" and whole:
                    _ros1_connection(header, data, conns)
                if not whole:
                    at = f.tell() - len(data)
                    raise _End(f"record at offset {at} cut short ({len(data)} of {dlen} bytes)")
    except _End as end:
        raise DataError(f"bag {path} is truncated or corrupt: {end}") from None
    except OSError as err:
        raise DataError(f"cannot read bag {path}: {err}") from None


def _ros1_connection(header: dict[str, bytes], data: bytes, conns: dict[int, tuple[str, str]]) -> None:
    (cid,) = struct.unpack("<I", header["conn"])
    info = _ros1_fields(data)
    conns[cid] = (header["topic"].decode(), _ros1_type(info.get("type", b"").decode()))


def _ros1_chunk(header: dict[str, bytes], data: bytes, conns: dict[int, tuple[str, str]],
                whole: bool) -> Iterator[SalvagedMessage]:
    comp = header.get("compression", b"none").decode()
    if comp == "bz2":
        data = bz2.decompress(data)
    elif comp == "lz4":
        try:
            import lz4.frame
        except ImportError:  # pragma: no cover - lz4 ships with rosbags
            raise _End("lz4 chunk and no lz4 module") from None
        data = lz4.frame.decompress(data)
    elif comp != "none":
        raise _End(f"unknown chunk compression {comp!r}")
    bio = BytesIO(data)
    while True:
        try:
            rec = _ros1_record(bio)
        except _End:
            if whole:
                raise
            return  # the cut: the caller reports it
        if rec is None:
            return
        h, d = rec
        op = h.get("op", b"\x00")[:1]
        if op == b"\x07":
            _ros1_connection(h, d, conns)
        elif op == b"\x02":
            (cid,) = struct.unpack("<I", h["conn"])
            sec, nsec = struct.unpack("<II", h["time"])
            if cid not in conns:
                raise _End(f"message on unknown connection {cid}")
            topic, msgtype = conns[cid]
            yield topic, msgtype, sec * 1_000_000_000 + nsec, d


def _mcap_str(rec: BinaryIO) -> str:
    (n,) = struct.unpack("<I", _read(rec, 4))
    return _read(rec, n).decode()


def salvage_mcap(path: Path) -> Iterator[SalvagedMessage]:
    """Messages of a (possibly truncated) MCAP file with uncompressed chunks, in file order.

    Raises:
        DataError: where the file stops being readable (after yielding everything before).
    """
    schemas: dict[int, str] = {}
    channels: dict[int, tuple[str, str]] = {}
    try:
        with path.open("rb") as f:
            if f.read(8) != _MCAP_MAGIC:
                raise DataError(f"{path} is not an MCAP file (bad magic)")
            yield from _mcap_records(f, schemas, channels, top=True)
    except _End as end:
        raise DataError(f"bag {path} is truncated or corrupt: {end}") from None
    except OSError as err:
        raise DataError(f"cannot read bag {path}: {err}") from None


def _mcap_records(bio: BinaryIO, schemas: dict[int, str], channels: dict[int, tuple[str, str]],
                  top: bool) -> Iterator[SalvagedMessage]:
    while True:
        opb = bio.read(1)
        if not opb:
            if top:
                raise _End("file ends before the MCAP footer")
            return
        op = opb[0]
        (length,) = struct.unpack("<Q", _read(bio, 8))
        if op == 0x02:  # footer: a complete file
            return
        if op == 0x06 and top:
            # Chunk: parse its records from the bytes present (a cut chunk still holds whole messages).
            head = _read(bio, 8 * 3 + 4)
            comp = _mcap_str(bio)
            (size,) = struct.unpack("<Q", _read(bio, 8))
            if comp:
                raise _End(f"compressed ({comp}) chunk; cannot salvage compressed MCAP chunks")
            del head
            payload = bio.read(size)
            yield from _mcap_records(BytesIO(payload), schemas, channels, top=False)
            if len(payload) != size:
                raise _End(f"chunk cut short ({len(payload)} of {size} bytes)")
            continue
        body = bio.read(length)
        if len(body) != length:
            if top:
                raise _End(f"record 0x{op:02x} cut short ({len(body)} of {length} bytes)")
            return  # the chunk was cut: the caller reports it
        rec = BytesIO(body)
        if op == 0x03:  # schema
            (sid,) = struct.unpack("<H", _read(rec, 2))
            schemas[sid] = _mcap_str(rec)
        elif op == 0x04:  # channel
            cid, sid = struct.unpack("<HH", _read(rec, 4))
            channels[cid] = (_mcap_str(rec), schemas.get(sid, ""))
        elif op == 0x05:  # message
            cid, _seq, log_time, _pub = struct.unpack("<HIQQ", _read(rec, 22))
            if cid not in channels:
                raise _End(f"message on unknown channel {cid}")
            topic, msgtype = channels[cid]
            yield topic, msgtype, log_time, body[22:]


def salvage_sqlite3(path: Path) -> Iterator[SalvagedMessage]:
    """Messages of a (possibly damaged) rosbag2 sqlite3 database, in row order.

    Raises:
        DataError: where the database stops being readable (after yielding everything before).
    """
    try:
        con = sqlite3.connect(f"file:{path}?mode=ro", uri=True)
    except sqlite3.Error as err:
        raise DataError(f"cannot open bag database {path}: {err}") from None
    try:
        topics = {tid: (name, typ) for tid, name, typ in con.execute("SELECT id, name, type FROM topics")}
        for tid, stamp, data in con.execute("SELECT topic_id, timestamp, data FROM messages ORDER BY id"):
            if tid not in topics:
                raise DataError(f"bag {path}: message on unknown topic id {tid}")
            yield topics[tid][0], topics[tid][1], int(stamp), bytes(data)
    except sqlite3.Error as err:
        raise DataError(f"bag {path} is truncated or corrupt: {err}") from None
    finally:
        con.close()
