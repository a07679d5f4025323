"""Writers for the three on-disk forms of a sequence: EuRoC ASL folders, ROS 2 bags and ROS 1 bags.

Every writer creates its output from scratch: an existing path is an error.
"""

from __future__ import annotations

import os
import shutil
import uuid
from collections.abc import Iterable, Sequence
from pathlib import Path
from types import TracebackType
from typing import Any, TextIO

import cv2
import numpy as np
from rosbags.rosbag1 import Writer as Writer1
from rosbags.rosbag1 import WriterError as WriterError1
from rosbags.rosbag2 import StoragePlugin, WriterError
from rosbags.rosbag2 import Writer as Writer2

from nsflow_ros.data.camera import PinholeRadtan
from nsflow_ros.data.errors import DataError
from nsflow_ros.data.messages import (
    IMAGE,
    IMU,
    POINT_CLOUD,
    POINT_STAMPED,
    image_message,
    imu_message,
    point_cloud_message,
    point_message,
    record_to_message,
    ros1_store,
    ros2_store,
    serialize,
)
from nsflow_ros.data.motion import ImuNoise
from nsflow_ros.data.records import Record

__all__ = [
    "ASL_CAMERA_HEADER",
    "ASL_GROUNDTRUTH_HEADER",
    "ASL_IMU_HEADER",
    "AslWriter",
    "BagWriter",
    "groundtruth_row",
    "temp_sibling",
    "write_ros2_bag",
]

ASL_CAMERA_HEADER = "#timestamp [ns],filename"
ASL_IMU_HEADER = ("#timestamp [ns],w_RS_S_x [rad s^-1],w_RS_S_y [rad s^-1],w_RS_S_z [rad s^-1],"
                  "a_RS_S_x [m s^-2],a_RS_S_y [m s^-2],a_RS_S_z [m s^-2]")
ASL_GROUNDTRUTH_HEADER = (
    "#timestamp, p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], q_RS_w [], q_RS_x [], q_RS_y [], q_RS_z [], "
    "v_RS_R_x [m s^-1], v_RS_R_y [m s^-1], v_RS_R_z [m s^-1], b_w_RS_S_x [rad s^-1], b_w_RS_S_y [rad s^-1], "
    "b_w_RS_S_z [rad s^-1], b_a_RS_S_x [m s^-2], b_a_RS_S_y [m s^-2], b_a_RS_S_z [m s^-2]"
)


def _num(x: float) -> str:
    # repr is the shortest string that parses back to the same float: the CSV loses nothing.
    return repr(float(x))


def _matrix_yaml(T: np.ndarray) -> str:
    rows = ",\n         ".join(", ".join(_num(v) for v in row) for row in np.asarray(T))
    return f"  cols: 4\n  rows: 4\n  data: [{rows}]\n"


def groundtruth_row(stamp_ns: int, p: Any, q_wxyz: Any, v: Any, bw: Any, ba: Any) -> str:
    """One line of EuRoC's state_groundtruth_estimate0/data.csv (with its newline)."""
    vals = ",".join(_num(x) for part in (p, q_wxyz, v, bw, ba) for x in np.ravel(part))
    return f"{int(stamp_ns)},{vals}\n"


class AslWriter:
    """Writes an EuRoC ASL folder (``.../mav0``): camN/, imu0/, state_groundtruth_estimate0/.

    Args:
        root: the ``mav0`` folder to create (or an empty one).
        png_compression: zlib level of the lossless PNG files (0-9).

    Raises:
        DataError: when ``root`` exists and is not empty.
    """

    def __init__(self, root: str | Path, *, png_compression: int = 1) -> None:
        self.root = Path(root)
        if self.root.exists() and any(self.root.iterdir()):
            raise DataError(f"ASL folder {self.root} exists and is not empty; not overwriting")
        self.root.mkdir(parents=True, exist_ok=True)
        # Huffman-only: faster than zlib's match search and, on noisy camera images, smaller too.
        self._png = [cv2.IMWRITE_PNG_COMPRESSION, int(png_compression),
                     cv2.IMWRITE_PNG_STRATEGY, cv2.IMWRITE_PNG_STRATEGY_HUFFMAN_ONLY]
        self._files: dict[str, TextIO] = {}

    def _csv(self, folder: str, header: str) -> TextIO:
        if folder not in self._files:
            (self.root / folder).mkdir(parents=True, exist_ok=True)
            f = (self.root / folder / "data.csv").open("w", newline="\n")
            f.write(header + "\n")
            self._files[folder] = f
        return self._files[folder]

    def add_camera(self, folder: str, camera: PinholeRadtan, rate_hz: float) -> None:
        """Create ``folder`` (e.g. ``cam0``) with its data.csv and an EuRoC-style sensor.yaml."""
        self._csv(folder, ASL_CAMERA_HEADER)
        (self.root / folder / "data").mkdir(exist_ok=True)
        yaml = (
            "# General sensor definitions.\n"
            "sensor_type: camera\n"
            f"comment: synthetic {camera.name} (nsflow_ros sample sequence)\n\n"
            "# Sensor extrinsics wrt. the body-frame.\n"
            f"T_BS:\n{_matrix_yaml(camera.T_BS)}\n"
            "# Camera specific definitions.\n"
            f"rate_hz: {_num(rate_hz)}\n"
            f"resolution: [{camera.width}, {camera.height}]\n"
            "camera_model: pinhole\n"
            f"intrinsics: [{', '.join(_num(v) for v in (camera.fx, camera.fy, camera.cx, camera.cy))}]"
            " #fu, fv, cu, cv\n"
            "distortion_model: radial-tangential\n"
            f"distortion_coefficients: [{', '.join(_num(v) for v in camera.dist)}]\n"
        )
        (self.root / folder / "sensor.yaml").write_text(yaml)

    def add_imu(self, rate_hz: float, noise: ImuNoise, folder: str = "imu0") -> None:
        """Create the IMU folder with its data.csv and sensor.yaml (noise densities)."""
        self._csv(folder, ASL_IMU_HEADER)
        yaml = (
            "# General sensor definitions.\n"
            "sensor_type: imu\n"
            "comment: synthetic IMU (nsflow_ros sample sequence)\n\n"
            "# Sensor extrinsics wrt. the body-frame.\n"
            f"T_BS:\n{_matrix_yaml(np.eye(4))}\n"
            f"rate_hz: {_num(rate_hz)}\n\n"
            "# inertial sensor noise model parameters (static)\n"
            f"gyroscope_noise_density: {_num(noise.gyro_noise)}     # [ rad / s / sqrt(Hz) ]\n"
            f"gyroscope_random_walk: {_num(noise.gyro_walk)}       # [ rad / s^2 / sqrt(Hz) ]\n"
            f"accelerometer_noise_density: {_num(noise.accel_noise)}  # [ m / s^2 / sqrt(Hz) ]\n"
            f"accelerometer_random_walk: {_num(noise.accel_walk)}    # [ m / s^3 / sqrt(Hz) ]\n"
        )
        (self.root / folder / "sensor.yaml").write_text(yaml)

    def encode(self, image: np.ndarray) -> bytes:
        """PNG bytes of an image (thread-safe; lets callers encode in parallel)."""
        ok, buf = cv2.imencode(".png", image, self._png)
        if not ok:
            raise DataError(f"cannot encode an image of shape {image.shape} and dtype {image.dtype} as PNG")
        return buf.tobytes()

    def write_image(self, folder: str, stamp_ns: int, image: np.ndarray | bytes) -> None:
        """Append an image, pixels or PNG bytes from :meth:`encode`: ``folder/data/<stamp>.png`` and a row.

        Raises:
            DataError: when the folder was not added or the PNG cannot be written.
        """
        if folder not in self._files:
            raise DataError(f"ASL camera folder {folder!r} was not added (call add_camera first)")
        name = f"{int(stamp_ns)}.png"
        path = self.root / folder / "data" / name
        data = image if isinstance(image, bytes) else self.encode(image)
        try:
            path.write_bytes(data)
        except OSError as err:
            raise DataError(f"cannot write {path}: {err}") from None
        self._files[folder].write(f"{int(stamp_ns)},{name}\n")

    def write_imu(self, stamp_ns: int, gyro: Any, accel: Any, folder: str = "imu0") -> None:
        """Append an IMU row."""
        if folder not in self._files:
            raise DataError(f"ASL IMU folder {folder!r} was not added (call add_imu first)")
        vals = ",".join(_num(v) for v in (*np.ravel(gyro), *np.ravel(accel)))
        self._files[folder].write(f"{int(stamp_ns)},{vals}\n")

    def write_groundtruth(self, stamp_ns: int, p: Any, q_wxyz: Any, v: Any, bw: Any, ba: Any) -> None:
        """Append a ground-truth row: position, quaternion (w, x, y, z), velocity, gyro / accel bias."""
        f = self._csv("state_groundtruth_estimate0", ASL_GROUNDTRUTH_HEADER)
        f.write(groundtruth_row(stamp_ns, p, q_wxyz, v, bw, ba))

    def close(self) -> None:
        """Flush and close the CSV files."""
        for f in self._files.values():
            f.close()
        self._files.clear()


class BagWriter:
    """Writes messages to a new ROS 1 bag or ROS 2 bag; one connection per topic, added on first use.

    Args:
        path: bag file (ROS 1) or bag directory (ROS 2) to create.
        ros1: write ROS 1 (Noetic typestore) instead of ROS 2 (Jazzy).
        storage: ROS 2 storage plugin, ``"mcap"`` or ``"sqlite3"``.

    Raises:
        DataError: when the path exists or the storage is unknown.
    """

    def __init__(self, path: str | Path, *, ros1: bool = False, storage: str = "mcap") -> None:
        self.path = Path(path)
        if self.path.exists():
            raise DataError(f"bag {self.path} exists already; not overwriting")
        self.ros1 = ros1
        self.store = ros1_store() if ros1 else ros2_store()
        try:
            if ros1:
                self._writer: Any = Writer1(self.path)
            else:
                plugin = {"mcap": StoragePlugin.MCAP, "sqlite3": StoragePlugin.SQLITE3}[storage]
                self._writer = Writer2(self.path, version=9, storage_plugin=plugin)
        except KeyError:
            raise DataError(f"unknown ROS 2 storage {storage!r}; expected 'mcap' or 'sqlite3'") from None
        except (WriterError, WriterError1) as err:
            raise DataError(f"cannot create bag {self.path}: {err}") from None
        self._conns: dict[str, Any] = {}
        self._seq: dict[str, int] = {}
        self.count = 0

    def open(self) -> None:
        """Open the bag for writing."""
        try:
            self._writer.open()
        except (OSError, WriterError, WriterError1) as err:
            raise DataError(f"cannot open bag {self.path} for writing: {err}") from None

    def close(self) -> None:
        """Write the index and close."""
        self._writer.close()

    def abort(self) -> None:
        """Close without finishing the bag (after an error; the caller removes it)."""
        self._writer.abort()

    def __enter__(self) -> BagWriter:
        self.open()
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()

    def _connection(self, topic: str, msgtype: str) -> Any:
        conn = self._conns.get(topic)
        if conn is None:
            conn = self._writer.add_connection(topic, msgtype, typestore=self.store)
            self._conns[topic] = conn
        elif conn.msgtype != msgtype:
            raise DataError(f"topic {topic} already carries {conn.msgtype}, cannot write a {msgtype}")
        return conn

    def _next_seq(self, topic: str) -> int:
        seq = self._seq.get(topic, 0)
        self._seq[topic] = seq + 1
        return seq

    def write_message(self, topic: str, msgtype: str, stamp_ns: int, msg: Any) -> None:
        """Serialise a message object (built for :attr:`store`) and write it at bag time ``stamp_ns``."""
        data = serialize(self.store, msg, msgtype)
        self._writer.write(self._connection(topic, msgtype), int(stamp_ns), data)
        self.count += 1

    def write_image(self, topic: str, stamp_ns: int, image: np.ndarray, frame_id: str,
                    encoding: str | None = None) -> None:
        """Write a sensor_msgs/Image stamped (header and bag time) ``stamp_ns``."""
        msg = image_message(self.store, stamp_ns, frame_id, image, encoding, seq=self._next_seq(topic))
        self.write_message(topic, IMAGE, stamp_ns, msg)

    def write_imu(self, topic: str, stamp_ns: int, gyro: Any, accel: Any, frame_id: str = "imu0") -> None:
        """Write a sensor_msgs/Imu."""
        msg = imu_message(self.store, stamp_ns, frame_id, gyro, accel, seq=self._next_seq(topic))
        self.write_message(topic, IMU, stamp_ns, msg)

    def write_point(self, topic: str, stamp_ns: int, xyz: Any, frame_id: str = "world") -> None:
        """Write a geometry_msgs/PointStamped."""
        msg = point_message(self.store, stamp_ns, frame_id, xyz, seq=self._next_seq(topic))
        self.write_message(topic, POINT_STAMPED, stamp_ns, msg)

    def write_point_cloud(self, topic: str, stamp_ns: int, points: np.ndarray, channels: np.ndarray,
                          names: Sequence[str], frame_id: str = "world") -> None:
        """Write a sensor_msgs/PointCloud (e.g. VINS features) stamped ``stamp_ns``.

        Shape:
            points: (N, 3). channels: (C, N).
        """
        msg = point_cloud_message(self.store, stamp_ns, frame_id, points, channels, names,
                                  seq=self._next_seq(topic))
        self.write_message(topic, POINT_CLOUD, stamp_ns, msg)

    def write_record(self, record: Record) -> None:
        """Write an :class:`ImageRecord` or :class:`ImuRecord` at its own stamp."""
        msgtype, msg = record_to_message(self.store, record, seq=self._next_seq(record.topic))
        self.write_message(record.topic, msgtype, record.stamp_ns, msg)


def temp_sibling(path: Path) -> Path:
    """A hidden, unique name beside ``path`` to build it under before renaming it into place."""
    return path.with_name(f".{path.name}.tmp-{os.getpid()}-{uuid.uuid4().hex[:8]}")


def write_ros2_bag(path: str | Path, records: Iterable[Record], *, storage: str = "mcap") -> int:
    """Write image and IMU records, in order, as a new ROS 2 bag; returns the number of messages written.

    The bag is built under a hidden name beside ``path`` and renamed when complete, so an interrupted run
    never leaves a bag at ``path``.

    Raises:
        DataError: when ``path`` exists, or on a record that cannot be serialised (the partial bag is
            removed, as it is when ``records`` itself raises).
    """
    path = Path(path)
    if path.exists():
        raise DataError(f"bag {path} exists already; not overwriting")
    # the storage file is named after the bag folder: build under the final name inside the sibling
    tmp = temp_sibling(path)
    tmp.mkdir(parents=True)
    try:
        with BagWriter(tmp / path.name, storage=storage) as bag:
            for rec in records:
                bag.write_record(rec)
        (tmp / path.name).rename(path)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return bag.count
