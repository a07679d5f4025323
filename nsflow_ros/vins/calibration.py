"""VINS-Fusion config folders from the calibrations a robot comes with: Kalibr outputs and ROS camera_info.

Readers (:func:`read_kalibr_camchain`, :func:`read_kalibr_imu`, :func:`read_camera_info`) turn each source
into one :class:`Calibration`; :func:`write_vins_config` writes it laid out as ``config/euroc/``: the config
YAML plus one camodocal camera file per camera. docs/calibration.md tabulates how each key maps.
"""

from __future__ import annotations

import math
import os
import re
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from nsflow_ros.core.camera import (
    CameraError,
    CameraModel,
    KannalaBrandtCamera,
    MeiCamera,
    PinholeCamera,
)
from nsflow_ros.vins.errors import ConfigError

__all__ = [
    "KALIBR_MODELS",
    "Calibration",
    "CameraCalibration",
    "ImuCalibration",
    "parse_transform",
    "read_camera_info",
    "read_camera_infos",
    "read_kalibr_camchain",
    "read_kalibr_imu",
    "render_vins_config",
    "write_vins_config",
]

KALIBR_MODELS: dict[tuple[str, str], str] = {
    ("pinhole", "radtan"): "PINHOLE",
    ("pinhole", "none"): "PINHOLE",
    ("pinhole", "equidistant"): "KANNALA_BRANDT",
    ("pinhole", "equi"): "KANNALA_BRANDT",
    ("omni", "radtan"): "MEI",
    ("omni", "none"): "MEI",
}
"""Kalibr (camera_model, distortion_model) -> camodocal model_type, the pairs camodocal can represent."""

_ROTATION_TOL = 1e-6  # |R R^T - I| bound, as the config reader checks body_T_cam
_TOPIC = re.compile(r"^[A-Za-z0-9_/~{}]*$")  # ROS name characters: nothing that needs YAML quoting
_MAX_CAMERAS = 2  # VINS-Fusion: num_of_cam is 1 or 2


@dataclass(frozen=True, eq=False)
class CameraCalibration:
    """One camera of a calibration.

    Attributes:
        camera: the camodocal camera model.
        topic: its image topic ("" when the source names none).
        body_T_cam: 4x4 transform from the camera frame to the body (IMU) frame; None when the source has
            no extrinsics for it.
    """

    camera: CameraModel
    topic: str = ""
    body_T_cam: np.ndarray | None = None  # noqa: N815 (the VINS key body_T_cam0 / body_T_cam1)


@dataclass(frozen=True)
class ImuCalibration:
    """IMU noise in VINS's terms (continuous-time densities and bias random walks, SI units).

    Attributes:
        acc_n: accelerometer noise density.
        gyr_n: gyroscope noise density.
        acc_w: accelerometer bias random walk.
        gyr_w: gyroscope bias random walk.
        topic: the IMU topic ("" when the source names none).
    """

    acc_n: float
    gyr_n: float
    acc_w: float
    gyr_w: float
    topic: str = ""

    def scaled(self, factor: float) -> ImuCalibration:
        """The noise multiplied by ``factor`` (VINS configs usually inflate datasheet values)."""
        return ImuCalibration(self.acc_n * factor, self.gyr_n * factor, self.acc_w * factor,
                              self.gyr_w * factor, self.topic)


@dataclass(frozen=True, eq=False)
class Calibration:
    """Everything :func:`write_vins_config` needs.

    Attributes:
        cameras: cam0 first, one or two cameras, each with ``body_T_cam`` set (None only for cam0 when
            ``estimate_extrinsic`` is 2).
        imu: the IMU, or None for a visual-only (stereo) configuration.
        td: camera-to-IMU time offset in seconds (image stamp + td = IMU clock).
        estimate_extrinsic: VINS's 0 (trust body_T_cam), 1 (refine) or 2 (no prior).
        settings: other config keys written after the defaults, e.g. ``{"max_cnt": 200}``.
    """

    cameras: tuple[CameraCalibration, ...]
    imu: ImuCalibration | None = None
    td: float = 0.0
    estimate_extrinsic: int = 0
    settings: dict[str, Any] = field(default_factory=dict)


# ----------------------------------------------------------------------------------------------------------
# Reading


def _load_yaml(path: Path, what: str) -> dict[str, Any]:
    import yaml

    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ConfigError(f"{path}: {what} does not exist") from None
    except (OSError, UnicodeDecodeError) as err:
        raise ConfigError(f"{path}: cannot read {what}: {getattr(err, 'strerror', None) or err}") from err
    if text.startswith("%YAML:"):  # OpenCV writes "%YAML:1.0", which PyYAML rejects
        text = text.split("\n", 1)[1] if "\n" in text else ""
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as err:
        mark = getattr(err, "problem_mark", None)
        where = f" (line {mark.line + 1})" if mark is not None else ""
        raise ConfigError(f"{path}: {what} is not valid YAML{where}") from err
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: {what} must be a mapping of keys, got {type(data).__name__}")
    return data


class _Reader:
    """Typed access to one parsed YAML block; errors name the file and the key path."""

    def __init__(self, data: dict[str, Any], path: Path, prefix: str = "") -> None:
        self.data = data
        self.path = path
        self.prefix = prefix

    def error(self, key: str, problem: str) -> ConfigError:
        return ConfigError(f"{self.path}: key '{self.prefix}{key}' {problem}")

    def get(self, key: str) -> Any:
        if self.data.get(key) is None:
            raise ConfigError(f"{self.path}: missing key '{self.prefix}{key}'")
        return self.data[key]

    def child(self, key: str) -> _Reader:
        value = self.get(key)
        if not isinstance(value, dict):
            raise self.error(key, f"must be a map, got {type(value).__name__}")
        return _Reader(value, self.path, f"{self.prefix}{key}/")

    def string(self, key: str, default: str | None = None) -> str:
        if default is not None and self.data.get(key) is None:
            return default
        value = self.get(key)
        if not isinstance(value, str):
            raise self.error(key, f"must be a string, got {value!r}")
        return value

    def real(self, key: str, *, positive: bool = False, default: float | None = None) -> float:
        if default is not None and self.data.get(key) is None:
            return default
        value = self.get(key)
        if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
            raise self.error(key, f"must be a finite number, got {value!r}")
        if positive and value <= 0:
            raise self.error(key, f"must be > 0, got {value!r}")
        return float(value)

    def numbers(self, key: str, counts: Sequence[int]) -> list[float]:
        """A flat list of finite numbers whose length is one of ``counts``."""
        value = self.get(key)
        if isinstance(value, dict):  # camera_info's {rows, cols, data}
            if value.get("data") is None:
                raise ConfigError(f"{self.path}: missing key '{self.prefix}{key}/data'")
            value = value["data"]
        if isinstance(value, list) and value and all(isinstance(row, list) for row in value):
            value = [x for row in value for x in row]  # Kalibr's 4x4 as a list of rows
        wanted = " or ".join(str(c) for c in counts)
        if not isinstance(value, list) or len(value) not in counts:
            got = f"{len(value)} values" if isinstance(value, list) else repr(value)
            raise self.error(key, f"must hold {wanted} numbers, got {got}")
        if not all(isinstance(x, int | float) and not isinstance(x, bool) and math.isfinite(x)
                   for x in value):
            raise self.error(key, f"must hold {wanted} finite numbers, got {value!r}")
        return [float(x) for x in value]


def _rigid(transform: np.ndarray, where: str) -> np.ndarray:
    rotation = transform[:3, :3]
    if np.abs(rotation @ rotation.T - np.eye(3)).max() > _ROTATION_TOL or np.linalg.det(rotation) <= 0.0:
        raise ConfigError(f"{where} is not a rigid transform: its rotation part is not a rotation")
    if not np.allclose(transform[3], [0.0, 0.0, 0.0, 1.0], atol=1e-9):
        raise ConfigError(f"{where} is not a rigid transform: last row must be 0 0 0 1, got {transform[3]}")
    return transform


def _invert(transform: np.ndarray) -> np.ndarray:
    """Inverse of a rigid transform: (R^T, -R^T t), so inverting twice gives the rotation back bit for bit."""
    out = np.eye(4)
    out[:3, :3] = transform[:3, :3].T
    out[:3, 3] = -transform[:3, :3].T @ transform[:3, 3]
    return out


def _topic(reader: _Reader, key: str) -> str:
    value = reader.string(key, "")
    if not _TOPIC.match(value):
        raise reader.error(key, f"is not a ROS topic name: {value!r}")
    return value


def _build(cls: type[CameraModel], reader: _Reader, key: str, **kwargs: Any) -> CameraModel:
    try:
        return cls(**kwargs)
    except CameraError as err:
        raise reader.error(key, f"gives an invalid camera: {err}") from err


def _kalibr_camera(reader: _Reader, index: int) -> CameraModel:
    model = reader.string("camera_model")
    distortion = reader.string("distortion_model", "none")
    model_type = KALIBR_MODELS.get((model, distortion))
    if model_type is None:
        supported = ", ".join(f"{m}-{d}" for m, d in KALIBR_MODELS if d not in ("none", "equi"))
        key = "camera_model" if model not in {m for m, _ in KALIBR_MODELS} else "distortion_model"
        raise reader.error(key, f"{model}-{distortion} has no camodocal model (supported: {supported})")
    width, height = reader.numbers("resolution", (2,))
    if not (width.is_integer() and height.is_integer() and width >= 1 and height >= 1):
        raise reader.error("resolution", f"must be two positive integers, got {[width, height]}")
    coeffs = [0.0] * 4 if distortion == "none" else reader.numbers("distortion_coeffs", (4,))
    common: dict[str, Any] = {"width": int(width), "height": int(height), "name": f"cam{index}"}
    if model == "omni":
        xi, fu, fv, pu, pv = reader.numbers("intrinsics", (5,))
        k1, k2, p1, p2 = coeffs
        return _build(MeiCamera, reader, "intrinsics", xi=xi, gamma1=fu, gamma2=fv, u0=pu, v0=pv,
                      k1=k1, k2=k2, p1=p1, p2=p2, **common)
    fu, fv, pu, pv = reader.numbers("intrinsics", (4,))
    if model_type == "KANNALA_BRANDT":
        k1, k2, k3, k4 = coeffs
        return _build(KannalaBrandtCamera, reader, "intrinsics", mu=fu, mv=fv, u0=pu, v0=pv,
                      k2=k1, k3=k2, k4=k3, k5=k4, **common)
    k1, k2, p1, p2 = coeffs
    return _build(PinholeCamera, reader, "intrinsics", fx=fu, fy=fv, cx=pu, cy=pv,
                  k1=k1, k2=k2, p1=p1, p2=p2, **common)


def _matrix(reader: _Reader, key: str) -> np.ndarray:
    values = reader.numbers(key, (16,))
    return _rigid(np.array(values).reshape(4, 4), f"{reader.path}: key '{reader.prefix}{key}'")


def read_kalibr_camchain(
    path: str | os.PathLike[str],
    body_T_cam: Sequence[np.ndarray | None] = (),
    *,
    num_of_cam: int | None = None,
) -> tuple[tuple[CameraCalibration, ...], float]:
    """Read a Kalibr camchain (``camchain-imucam.yaml`` or ``camchain.yaml``).

    Args:
        body_T_cam: per camera, a 4x4 camera-to-body transform that replaces the file's (None: the file's).
        num_of_cam: read the first ``num_of_cam`` cameras only (None: every camera).

    Returns:
        ``(cameras, td)``: the cameras in order, and cam0's ``timeshift_cam_imu`` (0 when absent).

    Raises:
        ConfigError: a missing file or key, an unsupported model, a bad value, or more cameras than
            VINS-Fusion takes; the message names file and key.
    """
    path = Path(path)
    data = _load_yaml(path, "Kalibr camchain")
    names = [f"cam{i}" for i in range(len(data)) if f"cam{i}" in data]
    if not names:
        raise ConfigError(f"{path}: missing key 'cam0' (not a Kalibr camchain)")
    count = len(names) if num_of_cam is None else num_of_cam
    if not 1 <= count <= min(len(names), _MAX_CAMERAS):
        raise ConfigError(f"{path}: has {len(names)} camera(s); a VINS-Fusion config takes 1 or 2, "
                          f"{count} asked")
    root = _Reader(data, path)
    cameras: list[CameraCalibration] = []
    td = 0.0
    for index, name in enumerate(names[:count]):
        reader = root.child(name)
        camera = _kalibr_camera(reader, index)
        given = body_T_cam[index] if index < len(body_T_cam) else None
        if given is not None:
            transform = np.array(given, dtype=np.float64)
        elif reader.data.get("T_cam_imu") is not None:
            transform = _invert(_matrix(reader, "T_cam_imu"))
        elif index > 0 and reader.data.get("T_cn_cnm1") is not None and cameras[-1].body_T_cam is not None:
            transform = cameras[-1].body_T_cam @ _invert(_matrix(reader, "T_cn_cnm1"))
        else:
            chained = index > 0 and cameras[-1].body_T_cam is not None
            raise ConfigError(_missing_transform(path, name, index, chained=chained))
        if index == 0:
            td = reader.real("timeshift_cam_imu", default=0.0)
        cameras.append(CameraCalibration(camera, _topic(reader, "rostopic"), transform))
    return tuple(cameras), td


def _missing_transform(path: Path, name: str, index: int, *, chained: bool) -> str:
    """The message for a camera without a transform to the body: the Kalibr key that was looked for, and
    the option that gives it instead (nsflow-config is the reader's one caller)."""
    option = f"or give the cam{index} -> body transform with --body-T-cam{index}"
    if chained:  # Kalibr without an IMU writes cam<n>/T_cn_cnm1, the transform from the camera before it
        return (f"{path}: missing key '{name}/T_cn_cnm1' (the transform from cam{index - 1}; "
                f"nor is there '{name}/T_cam_imu'), {option}")
    return f"{path}: missing key '{name}/T_cam_imu' ({option})"


def read_kalibr_imu(path: str | os.PathLike[str]) -> ImuCalibration:
    """Read a Kalibr IMU file (``imu.yaml`` as given to Kalibr, or the ``imu0`` block it writes).

    Raises:
        ConfigError: a missing file or key, or a value that is not a positive number.
    """
    path = Path(path)
    data = _load_yaml(path, "Kalibr IMU file")
    reader = _Reader(data, path).child("imu0") if "imu0" in data else _Reader(data, path)
    return ImuCalibration(
        acc_n=reader.real("accelerometer_noise_density", positive=True),
        gyr_n=reader.real("gyroscope_noise_density", positive=True),
        acc_w=reader.real("accelerometer_random_walk", positive=True),
        gyr_w=reader.real("gyroscope_random_walk", positive=True),
        topic=_topic(reader, "rostopic"),
    )


def read_camera_info(path: str | os.PathLike[str], index: int = 0) -> CameraModel:
    """Read a ROS camera_info YAML as a camodocal camera (``cam<index>`` unless it has a ``camera_name``).

    Raises:
        ConfigError: a missing file or key, an unsupported distortion model, a camera matrix with skew,
            or a plumb_bob k3 that is not 0; the message names the file and the key.
    """
    path = Path(path)
    reader = _Reader(_load_yaml(path, "camera_info file"), path)
    width = reader.get("image_width")
    height = reader.get("image_height")
    for key, value in (("image_width", width), ("image_height", height)):
        if isinstance(value, bool) or not isinstance(value, int) or value < 1:
            raise reader.error(key, f"must be a positive integer, got {value!r}")
    name = reader.string("camera_name", f"cam{index}") or f"cam{index}"
    k = reader.numbers("camera_matrix", (9,))
    if k[1] != 0.0 or k[3] != 0.0 or k[6:] != [0.0, 0.0, 1.0]:
        raise reader.error("camera_matrix", f"must be [fx 0 cx; 0 fy cy; 0 0 1] (camodocal has no skew), "
                           f"got {k}")
    fx, cx, fy, cy = k[0], k[2], k[4], k[5]
    model = reader.string("distortion_model")
    common: dict[str, Any] = {"width": width, "height": height, "name": name}
    if model == "plumb_bob":
        d = reader.numbers("distortion_coefficients", (4, 5))
        if len(d) == 5 and d[4] != 0.0:
            raise reader.error("distortion_coefficients", f"has k3 = {d[4]!r}; camodocal's PINHOLE has no k3 "
                               "(calibrate with k3 fixed to 0)")
        return _build(PinholeCamera, reader, "camera_matrix", fx=fx, fy=fy, cx=cx, cy=cy,
                      k1=d[0], k2=d[1], p1=d[2], p2=d[3], **common)
    if model == "equidistant":
        d = reader.numbers("distortion_coefficients", (4,))
        return _build(KannalaBrandtCamera, reader, "camera_matrix", mu=fx, mv=fy, u0=cx, v0=cy,
                      k2=d[0], k3=d[1], k4=d[2], k5=d[3], **common)
    raise reader.error("distortion_model", f"{model!r} is not supported (plumb_bob, equidistant)")


def read_camera_infos(
    paths: Sequence[str | os.PathLike[str]],
    body_T_cam: Sequence[np.ndarray | None],
    topics: Sequence[str] = (),
) -> tuple[CameraCalibration, ...]:
    """Read one or two camera_info files (cam0 first) as the cameras of a calibration.

    Args:
        body_T_cam: per camera, the 4x4 camera-to-body transform; None leaves it unset.
        topics: per camera, the image topic; missing ones are ``/cam<i>/image_raw``.

    Raises:
        ConfigError: as :func:`read_camera_info`, or a bad topic name.
    """
    if not 1 <= len(paths) <= _MAX_CAMERAS:
        raise ConfigError(f"a VINS-Fusion config takes 1 or 2 camera_info files, got {len(paths)}")
    out = []
    for i, path in enumerate(paths):
        topic = topics[i] if i < len(topics) else f"/cam{i}/image_raw"
        if not _TOPIC.match(topic):
            raise ConfigError(f"image{i}_topic: {topic!r} is not a ROS topic name")
        transform = body_T_cam[i] if i < len(body_T_cam) else None
        out.append(CameraCalibration(read_camera_info(path, i), topic, transform))
    return tuple(out)


def parse_transform(text: str, what: str = "transform") -> np.ndarray:
    """Parse a 4x4 rigid transform: 16 numbers row-major, or a file holding them.

    In a file, text before a ``data:`` key is skipped, so a VINS config's matrix block or a EuRoC
    ``sensor.yaml``'s ``T_BS`` can be pasted as it is; ``what`` names the value in error messages.

    Raises:
        ConfigError: not 16 numbers, an unreadable file, or not a rigid transform.
    """
    source = text
    path = Path(text)
    if not re.fullmatch(r"[\s\d.,;\[\]eE+-]*", text):
        try:
            is_file = path.is_file()
        except OSError:  # e.g. a name too long for the file system
            is_file = False
        if not is_file:
            shown = text if len(text) <= 60 else text[:57] + "..."
            raise ConfigError(f"{what}: {shown!r} is neither 16 numbers nor an existing file")
        try:
            source = path.read_text(encoding="utf-8")
        except (OSError, UnicodeDecodeError) as err:
            raise ConfigError(f"{what}: cannot read {text}: {getattr(err, 'strerror', None) or err}") from err
        if "data:" in source:
            source = source.split("data:", 1)[1]
        what = f"{what} ({text})"
    values = [v for v in re.split(r"[\s,;\[\]]+", source) if v]
    try:
        numbers = [float(v) for v in values[:16]]
    except ValueError as err:
        raise ConfigError(f"{what}: expected 16 numbers, got {err}") from None
    if len(numbers) != 16 or not all(math.isfinite(v) for v in numbers):
        raise ConfigError(f"{what}: expected 16 finite numbers (a row-major 4x4), got {len(numbers)}")
    return _rigid(np.array(numbers).reshape(4, 4), what)


# ----------------------------------------------------------------------------------------------------------
# Writing


def _real(value: float) -> str:
    """Shortest text that reads back as the same double (and as a real, not an integer, in FileStorage)."""
    text = repr(float(value))
    return text if any(c in text for c in ".eE") or "n" in text else text + ".0"


def _matrix_block(key: str, transform: np.ndarray) -> list[str]:
    rows = [", ".join(_real(v) for v in row) for row in transform]
    data = ",\n           ".join(rows)
    return [f"{key}: !!opencv-matrix", "   rows: 4", "   cols: 4", "   dt: d", f"   data: [ {data} ]", ""]


def _camera_file(index: int, camera: CameraModel) -> str:
    return f"cam{index}_{camera.model_type.lower()}.yaml"


def render_vins_config(calibration: Calibration, *, output_path: str = "/tmp/vins_output/") -> str:
    """The VINS-Fusion config YAML for ``calibration``, with the shipped EuRoC configs' other settings.

    Raises:
        ConfigError: no camera or more than two, one camera without an IMU (VINS-Fusion needs one of
            stereo or IMU), or a camera after cam0 without ``body_T_cam``.
    """
    cams = calibration.cameras
    if not 1 <= len(cams) <= _MAX_CAMERAS:
        raise ConfigError(f"a VINS-Fusion config takes 1 or 2 cameras, got {len(cams)}")
    if len(cams) == 1 and calibration.imu is None:
        raise ConfigError("one camera without an IMU: VINS-Fusion needs stereo or an IMU (give the IMU file)")
    if calibration.estimate_extrinsic not in (0, 1, 2):
        raise ConfigError(f"estimate_extrinsic must be 0, 1 or 2, got {calibration.estimate_extrinsic}")
    for i, cam in enumerate(cams):
        if cam.body_T_cam is None and (i > 0 or calibration.estimate_extrinsic != 2):
            raise ConfigError(f"cam{i} has no extrinsics (body_T_cam{i})")
        if (cam.camera.width, cam.camera.height) != (cams[0].camera.width, cams[0].camera.height):
            raise ConfigError(f"cam{i} is {cam.camera.width}x{cam.camera.height} but cam0 is "
                              f"{cams[0].camera.width}x{cams[0].camera.height}; VINS-Fusion takes one "
                              "image size")
    if calibration.imu is not None and not calibration.imu.topic:
        raise ConfigError("imu_topic is empty: the IMU file names no rostopic (give the IMU topic)")
    for i, cam in enumerate(cams):
        if not cam.topic:
            raise ConfigError(f"image{i}_topic is empty: the calibration names no image topic for cam{i}")
    strings = {"output_path": output_path}
    strings.update((k, v) for k, v in calibration.settings.items() if isinstance(v, str))
    for key, value in strings.items():
        if any(c in value for c in '"\\\n'):
            raise ConfigError(f"{key} must not hold quotes, backslashes or line breaks, got {value!r}")
    imu = calibration.imu
    width, height = cams[0].camera.width, cams[0].camera.height
    lines = [
        "%YAML:1.0",
        "# VINS-Fusion config written by nsflow-config from a calibration; camera files beside it.",
        "",
        f"imu: {int(imu is not None)}",
        f"num_of_cam: {len(cams)}",
        "",
        f'imu_topic: "{imu.topic if imu else ""}"',
    ]
    lines += [f'image{i}_topic: "{cam.topic}"' for i, cam in enumerate(cams)]
    lines += [f'output_path: "{output_path}"', ""]
    lines += [f'cam{i}_calib: "{_camera_file(i, cam.camera)}"' for i, cam in enumerate(cams)]
    lines += [f"image_width: {width}", f"image_height: {height}", "",
              "# 0: trust body_T_cam*, 1: refine them online, 2: no prior (start from identity).",
              f"estimate_extrinsic: {calibration.estimate_extrinsic}", "",
              "# camera frame -> body (IMU) frame"]
    for i, cam in enumerate(cams):
        lines += _matrix_block(f"body_T_cam{i}", np.eye(4) if cam.body_T_cam is None else cam.body_T_cam)
    settings: dict[str, Any] = {
        "multiple_thread": 1,
        "max_cnt": 150,
        "min_dist": 30,
        "freq": 10,
        "F_threshold": 1.0,
        "show_track": 1,
        "flow_back": 1,
        "max_solver_time": 0.04,
        "max_num_iterations": 8,
        "keyframe_parallax": 10.0,
    }
    if imu is not None:
        settings.update(acc_n=imu.acc_n, gyr_n=imu.gyr_n, acc_w=imu.acc_w, gyr_w=imu.gyr_w, g_norm=9.81007)
    settings.update(estimate_td=0, td=calibration.td, load_previous_pose_graph=0,
                    pose_graph_save_path=output_path.rstrip("/") + "/pose_graph/", save_image=0)
    settings.update(calibration.settings)
    for key, value in settings.items():
        if isinstance(value, str):
            lines.append(f'{key}: "{value}"')
        elif isinstance(value, float):
            lines.append(f"{key}: {_real(value)}")
        else:
            lines.append(f"{key}: {int(value)}")
    return "\n".join(lines) + "\n"


def write_vins_config(
    folder: str | os.PathLike[str],
    calibration: Calibration,
    *,
    name: str = "vins_config.yaml",
    output_path: str = "/tmp/vins_output/",
    overwrite: bool = False,
) -> list[Path]:
    """Write a VINS-Fusion config folder: ``<folder>/<name>`` and ``cam<i>_<model>.yaml`` per camera.

    Args:
        folder: the folder (created when missing).
        output_path: VINS-Fusion's ``output_path`` (where it writes vio.csv).
        overwrite: replace files that exist (otherwise they are an error, and nothing is written).

    Returns:
        The files written, the config first.

    Raises:
        ConfigError: as :func:`render_vins_config`, an existing file without ``overwrite``, or a folder
            that cannot be written.
    """
    folder = Path(folder)
    text = render_vins_config(calibration, output_path=output_path)
    files = [folder / name] + [folder / _camera_file(i, c.camera) for i, c in enumerate(calibration.cameras)]
    if not overwrite:
        existing = [str(f) for f in files if f.exists()]
        if existing:
            raise ConfigError(f"{existing[0]} exists (overwrite to replace it)")
    try:
        folder.mkdir(parents=True, exist_ok=True)
        files[0].write_text(text, encoding="utf-8")
    except OSError as err:
        raise ConfigError(f"cannot write {err.filename or folder}: {err.strerror or err}") from err
    for path, cam in zip(files[1:], calibration.cameras, strict=True):
        try:
            cam.camera.save_yaml(path)
        except CameraError as err:
            raise ConfigError(str(err)) from err
    return files
