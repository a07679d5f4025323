"""VINS-Fusion and VINS-Mono configuration files (OpenCV FileStorage YAML), read as they are.

* VINS-Fusion: ``num_of_cam`` (1 or 2), ``image0_topic`` / ``image1_topic``, ``imu`` (0/1), camodocal camera
  files ``cam0_calib`` / ``cam1_calib`` relative to the config's folder, ``body_T_cam0`` / ``body_T_cam1``.
* VINS-Mono: one camera on ``image_topic`` with its camodocal keys inline, extrinsics as
  ``extrinsicRotation`` / ``extrinsicTranslation``, always an IMU; ``freq``, ``equalize`` and ``fisheye``.
* Either: OpenVINS's static mask keys ``mask0`` / ``mask1`` (mask images relative to the config's folder)
  and ``use_mask`` (0 ignores them; absent = use them when given).

Optional keys take the value VINS gives a missing key (0 / false), except the tracker settings with
documented defaults (max_cnt 150, min_dist 30, F_threshold 1.0, freq 0 -> 100). Unlike VINS, a missing
required key or a value of the wrong type is an error naming the file and the key.
"""

from __future__ import annotations

import dataclasses
import math
import os
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np

from nsflow_ros.core.camera import CameraError, CameraModel, camera_from_dict, load_camera
from nsflow_ros.core.opencv_yaml import OpenCVYamlError, read_opencv_yaml
from nsflow_ros.vins.errors import ConfigError
from nsflow_ros.vins.settings import KEEP, SETTINGS, VINS_KEYS

__all__ = [
    "DEFAULT_FREQ",
    "OVERRIDABLE_KEYS",
    "Dialect",
    "VinsConfig",
    "apply_overrides",
    "load_vins_config",
]

Dialect = Literal["fusion", "mono"]

DEFAULT_FREQ = 100
"""Publishing rate (Hz) that ``freq: 0`` stands for, as in VINS-Mono (in effect: every image)."""

OVERRIDABLE_KEYS: tuple[str, ...] = VINS_KEYS
"""Tracker settings :func:`apply_overrides` accepts, by their VINS config key (from the settings table)."""

_ROTATION_TOL = 1e-6  # |R R^T - I| bound for an extrinsic rotation
_FUSION_KEYS = ("image0_topic", "num_of_cam", "cam0_calib")
_MONO_KEYS = ("image_topic", "model_type")
_MISSING = object()


@dataclass(frozen=True, eq=False)
class VinsConfig:
    """What the front-end needs from a VINS-Fusion or VINS-Mono config file.

    Attributes:
        path: the config file (absolute).
        dialect: "fusion" (VINS-Fusion) or "mono" (VINS-Mono).
        image0_topic: left / only camera topic (VINS-Mono ``image_topic``). Topics may be "" (VINS-Fusion's
            KITTI configs, read from files rather than ROS); a missing topic key is an error.
        image1_topic: right camera topic; "" when absent (VINS-Fusion keeps it in mono configs too).
        imu_topic: IMU topic; "" when the config has no IMU and names none.
        use_imu: VINS-Fusion ``imu``; always true for VINS-Mono.
        num_of_cam: 1 or 2 (always 1 for VINS-Mono).
        cameras: one camera model per camera, cam0 first.
        body_T_cam: per camera, the 4x4 float64 transform from camera to body (IMU) frame, read-only;
            identity when ``estimate_extrinsic`` is 2 (VINS then has no prior either).
        image_width, image_height: image size in pixels (VINS ``COL`` / ``ROW``).
        max_cnt: most features tracked per image.
        min_dist: minimum distance between features (pixels).
        F_threshold: RANSAC threshold (pixels) of the fundamental-matrix check.
        flow_back: track backwards and drop points that do not come back (VINS-Fusion).
        show_track: publish the debug image.
        freq: publishing rate in Hz; a 0 in the file reads as :data:`DEFAULT_FREQ`.
        equalize: apply CLAHE before tracking (VINS-Mono).
        fisheye: apply the fisheye mask (VINS-Mono).
        mask0, mask1: the absolute path of each camera's static mask image (OpenVINS keys); "" = none.
        output_path: where VINS writes its trajectory, as written in the file (not expanded).
    """

    path: Path
    dialect: Dialect
    image0_topic: str
    image1_topic: str
    imu_topic: str
    use_imu: bool
    num_of_cam: int
    cameras: tuple[CameraModel, ...]
    body_T_cam: tuple[np.ndarray, ...]  # noqa: N815 (the VINS key body_T_cam0 / body_T_cam1)
    image_width: int
    image_height: int
    max_cnt: int = 150
    min_dist: int = 30
    F_threshold: float = 1.0
    flow_back: bool = False
    show_track: bool = False
    freq: int = DEFAULT_FREQ
    equalize: bool = False
    fisheye: bool = False
    mask0: str = ""
    mask1: str = ""
    output_path: str = ""

    @property
    def stereo(self) -> bool:
        """True for two cameras."""
        return self.num_of_cam == 2

    @property
    def image_topics(self) -> tuple[str, ...]:
        """The image topic of each camera, cam0 first."""
        return (self.image0_topic, self.image1_topic)[: self.num_of_cam]

    def tracker_settings(self) -> dict[str, int | float | bool]:
        """The value of every key in :data:`OVERRIDABLE_KEYS`."""
        return {key: getattr(self, key) for key in OVERRIDABLE_KEYS}

    def tracker_fields(self) -> dict[str, Any]:
        """The TrackerSettings fields this config sets, by field name: its settings with a VINS key, in
        the tracker's types, and ``stereo``."""
        out: dict[str, Any] = {}
        for s in SETTINGS:
            if s.tracker and s.vins_key is not None:
                value = getattr(self, s.vins_key)
                out[s.name] = bool(value) if s.switch else (s.tracker_type or s.type)(value)
        out["stereo"] = self.stereo
        return out


# ----------------------------------------------------------------------------------------------------------
# Typed access to the parsed file


def _describe(value: Any) -> str:
    if isinstance(value, np.ndarray):
        return f"a {value.shape[0]}x{value.shape[1]} matrix"
    if isinstance(value, dict):
        return "a map"
    if isinstance(value, list):
        return "a sequence"
    return f"{type(value).__name__} {value!r}"


class _Keys:
    """Read keys of one parsed config, raising ConfigError that names the file and the key."""

    def __init__(self, data: dict[str, Any], path: Path) -> None:
        self.data = data
        self.path = path

    def error(self, key: str, problem: str) -> ConfigError:
        return ConfigError(f"{self.path}: key '{key}' {problem}")

    def _get(self, key: str, default: Any) -> Any:
        value = self.data.get(key)
        if value is None:
            if default is _MISSING:
                raise ConfigError(f"{self.path}: missing required key '{key}'")
            return default
        return value

    def string(self, key: str, default: Any = _MISSING, *, non_empty: bool = False) -> str:
        value = self._get(key, default)
        if not isinstance(value, str):
            raise self.error(key, f"must be a string, got {_describe(value)}")
        if non_empty and not value:
            raise self.error(key, "must not be empty")
        return value

    def integer(self, key: str, default: Any = _MISSING, *, minimum: int | None = None) -> int:
        value = self._get(key, default)
        if isinstance(value, float) and value.is_integer():
            value = int(value)
        if isinstance(value, bool) or not isinstance(value, int):
            raise self.error(key, f"must be an integer, got {_describe(value)}")
        if minimum is not None and value < minimum:
            raise self.error(key, f"must be >= {minimum}, got {value}")
        return value

    def real(self, key: str, default: Any = _MISSING, *, positive: bool = False) -> float:
        value = self._get(key, default)
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise self.error(key, f"must be a number, got {_describe(value)}")
        value = float(value)
        if not math.isfinite(value):
            raise self.error(key, f"must be finite, got {value}")
        if positive and value <= 0.0:
            raise self.error(key, f"must be > 0, got {value}")
        return value

    def flag(self, key: str, default: bool = False) -> bool:
        """An integer switch; non-zero is true, as VINS reads it."""
        return self.integer(key, int(default)) != 0

    def matrix(self, key: str, shape: tuple[int, int], default: Any = _MISSING) -> np.ndarray:
        value = self._get(key, default)
        rows, cols = shape
        if not isinstance(value, np.ndarray):
            raise self.error(key, f"must be a {rows}x{cols} !!opencv-matrix, got {_describe(value)}")
        if value.size == rows * cols and value.shape in ((rows, cols), (cols, rows)) and 1 in shape:
            value = value.reshape(shape)  # a translation may be written 3x1 or 1x3
        if value.shape != shape:
            raise self.error(key, f"must be a {rows}x{cols} !!opencv-matrix, got {_describe(value)}")
        if not np.all(np.isfinite(value)):
            raise self.error(key, "must hold finite numbers")
        return np.array(value, dtype=np.float64)


def _check_transform(keys: _Keys, key: str, transform: np.ndarray) -> np.ndarray:
    rotation = transform[:3, :3]
    if np.abs(rotation @ rotation.T - np.eye(3)).max() > _ROTATION_TOL or np.linalg.det(rotation) <= 0.0:
        raise keys.error(key, f"is not a rigid transform: its rotation part is not a rotation\n{rotation}")
    if transform.shape == (4, 4) and not np.allclose(transform[3], [0.0, 0.0, 0.0, 1.0], atol=1e-9):
        raise keys.error(key, f"is not a rigid transform: last row must be [0, 0, 0, 1], got {transform[3]}")
    transform.setflags(write=False)
    return transform


def _identity() -> np.ndarray:
    out = np.eye(4)
    out.setflags(write=False)
    return out


def _detect_dialect(keys: _Keys) -> Dialect:
    if any(key in keys.data for key in _FUSION_KEYS):
        return "fusion"
    if any(key in keys.data for key in _MONO_KEYS):
        return "mono"
    raise ConfigError(
        f"{keys.path}: not a VINS config: it has none of the VINS-Fusion keys {', '.join(_FUSION_KEYS)} "
        f"nor the VINS-Mono keys {', '.join(_MONO_KEYS)}"
    )


def _calibration(keys: _Keys, index: int) -> CameraModel:
    key = f"cam{index}_calib"
    name = keys.string(key, non_empty=True)
    calib = keys.path.parent / name  # VINS-Fusion: relative to the config's folder
    if not calib.is_file():
        what = "is not a file" if calib.exists() else "does not exist"
        raise keys.error(key, f"names camera file {calib}, which {what}")
    try:
        return load_camera(calib)
    except CameraError as err:
        raise keys.error(key, f"names an unusable camera file: {err}") from err


def _mask_files(keys: _Keys, num_of_cam: int) -> dict[str, str]:
    """OpenVINS's mask0 / mask1 keys, as absolute paths of existing files ("" = none)."""
    out = {"mask0": "", "mask1": ""}
    if "use_mask" in keys.data and not keys.flag("use_mask"):
        return out
    for index in range(2):
        key = f"mask{index}"
        name = keys.string(key, "")
        if not name:
            continue
        if index >= num_of_cam:
            raise keys.error(key, f"names a mask of camera {index}, but the config has {num_of_cam} camera")
        path = keys.path.parent / Path(name).expanduser()  # an absolute name stays as it is
        if not path.is_file():
            what = "is not a file" if path.exists() else "does not exist"
            raise keys.error(key, f"names mask image {path}, which {what}")
        out[key] = str(path)
    return out


def _estimate_extrinsic(keys: _Keys) -> int:
    mode = keys.integer("estimate_extrinsic", 0)
    if mode not in (0, 1, 2):
        raise keys.error("estimate_extrinsic", f"must be 0, 1 or 2, got {mode}")
    return mode


def _read_fusion(keys: _Keys) -> dict[str, Any]:
    num_of_cam = keys.integer("num_of_cam")
    if num_of_cam not in (1, 2):
        raise keys.error("num_of_cam", f"must be 1 or 2, got {num_of_cam}")
    stereo = num_of_cam == 2
    use_imu = keys.flag("imu")
    cameras = tuple(_calibration(keys, i) for i in range(num_of_cam))
    if _estimate_extrinsic(keys) == 2:  # VINS-Fusion starts cam0 from identity and ignores body_T_cam0
        body_T_cam = [_identity()]
    else:
        body_T_cam = [_check_transform(keys, "body_T_cam0", keys.matrix("body_T_cam0", (4, 4)))]
    if stereo:  # VINS-Fusion reads body_T_cam1 whatever estimate_extrinsic says
        body_T_cam.append(_check_transform(keys, "body_T_cam1", keys.matrix("body_T_cam1", (4, 4))))
    return {
        "image0_topic": keys.string("image0_topic"),
        "image1_topic": keys.string("image1_topic") if stereo else keys.string("image1_topic", ""),
        "imu_topic": keys.string("imu_topic") if use_imu else keys.string("imu_topic", ""),
        "use_imu": use_imu,
        "num_of_cam": num_of_cam,
        "cameras": cameras,
        "body_T_cam": tuple(body_T_cam),
    }


def _read_mono(keys: _Keys) -> dict[str, Any]:
    try:
        camera = camera_from_dict(keys.data, source=str(keys.path))
    except CameraError as err:
        raise ConfigError(f"{err} (VINS-Mono inline camera intrinsics)") from err
    if _estimate_extrinsic(keys) == 2:
        transform = _identity()
    else:
        transform = np.eye(4)
        transform[:3, :3] = keys.matrix("extrinsicRotation", (3, 3))
        transform[:3, 3] = keys.matrix("extrinsicTranslation", (3, 1))[:, 0]
        transform = _check_transform(keys, "extrinsicRotation", transform)
    return {
        "image0_topic": keys.string("image_topic"),
        "image1_topic": "",
        "imu_topic": keys.string("imu_topic"),
        "use_imu": True,
        "num_of_cam": 1,
        "cameras": (camera,),
        "body_T_cam": (transform,),
    }


def load_vins_config(path: str | os.PathLike[str]) -> VinsConfig:
    """Read a VINS-Fusion or VINS-Mono config file, the dialect detected from the keys present.

    Raises:
        ConfigError: the file (or a camera file) is missing or malformed, a required key is missing, or a
            value has the wrong type or range; the message names the file and the key.
    """
    path = Path(path).expanduser().absolute()
    try:
        data = read_opencv_yaml(path)
    except OpenCVYamlError as err:
        raise ConfigError(f"VINS config {err}") from err
    keys = _Keys(data, path)
    dialect = _detect_dialect(keys)
    specific = _read_fusion(keys) if dialect == "fusion" else _read_mono(keys)
    freq = keys.integer("freq", 0, minimum=0)
    return VinsConfig(
        path=path,
        dialect=dialect,
        image_width=keys.integer("image_width", minimum=1),
        image_height=keys.integer("image_height", minimum=1),
        max_cnt=keys.integer("max_cnt", 150, minimum=1),
        min_dist=keys.integer("min_dist", 30, minimum=0),
        F_threshold=keys.real("F_threshold", 1.0, positive=True),
        flow_back=keys.flag("flow_back"),
        show_track=keys.flag("show_track"),
        freq=freq or DEFAULT_FREQ,
        equalize=keys.flag("equalize"),
        fisheye=keys.flag("fisheye"),
        output_path=keys.string("output_path", ""),
        **_mask_files(keys, specific["num_of_cam"]),
        **specific,
    )


# ----------------------------------------------------------------------------------------------------------
# Overrides


_BY_VINS_KEY = {s.vins_key: s for s in SETTINGS if s.vins_key is not None}


def apply_overrides(config: VinsConfig, overrides: Mapping[str, Any]) -> VinsConfig:
    """A copy of ``config`` with tracker settings replaced.

    Args:
        overrides: values by VINS key (:data:`OVERRIDABLE_KEYS`), typed and ranged as the settings table
            says; None or :data:`~nsflow_ros.vins.settings.KEEP` keeps the config's value, ``freq`` 0 means
            :data:`DEFAULT_FREQ`.

    Raises:
        ConfigError: an unknown key, or a value of the wrong type or out of range; the message names the key.
    """
    if not isinstance(overrides, Mapping):
        raise ConfigError(f"tracker overrides must be a mapping of key -> value, got {_describe(overrides)}")
    changes: dict[str, Any] = {}
    for key, value in overrides.items():
        if key not in OVERRIDABLE_KEYS:
            raise ConfigError(f"unknown tracker setting {key!r} (overridable: {', '.join(OVERRIDABLE_KEYS)})")
        keep = not isinstance(value, bool) and isinstance(value, int | float) and value == KEEP
        if value is None or keep:
            continue
        changes[key] = _BY_VINS_KEY[key].check(value)
        if key == "freq":
            changes[key] = changes[key] or DEFAULT_FREQ
    return dataclasses.replace(config, **changes) if changes else config
