"""A :class:`~nsflow_ros.core.tracker.FeatureTracker` built the VINS way: from a config file's settings.

The VINS file conventions live here, not in the core: the config keys that become tracker settings,
``body_T_cam0`` as the gyro prediction's extrinsic, VINS-Mono's fisheye mask file beside the config and the
static mask images of each camera (``mask0`` / ``mask1``, checked against the config's image size).
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from nsflow_ros.core.encoder import Encoder
from nsflow_ros.core.errors import CoreError
from nsflow_ros.core.masks import binarize, check_mask, combine
from nsflow_ros.core.tracker import FeatureTracker, TrackerSettings
from nsflow_ros.vins.config import VinsConfig
from nsflow_ros.vins.errors import ConfigError

__all__ = ["FISHEYE_MASK_NAME", "find_fisheye_mask", "load_mask", "load_static_masks", "tracker_from_config"]

FISHEYE_MASK_NAME = "fisheye_mask.jpg"
"""VINS-Mono's fisheye mask file name."""


def find_fisheye_mask(config_path: str | os.PathLike[str]) -> Path:
    """VINS-Mono's fisheye mask for a config: ``fisheye_mask.jpg`` in the config's folder or its parent.

    Raises:
        ConfigError: naming the places looked at when neither exists.
    """
    folder = Path(config_path).parent
    candidates = [folder / FISHEYE_MASK_NAME, folder.parent / FISHEYE_MASK_NAME]
    for cand in candidates:
        if cand.is_file():
            return cand
    looked = ", ".join(str(c) for c in candidates)
    raise ConfigError(
        f"{config_path}: fisheye is 1 but no fisheye mask was found (looked at {looked}); "
        "give its path (tracker parameter fisheye_mask) or set fisheye: 0"
    )


def load_mask(path: str | os.PathLike[str], convention: str = "vins") -> np.ndarray:
    """Read a mask image as uint8 0 / 255, 255 where features may be (a pixel > 127 counts as set:
    VINS-Mono's masks are JPEGs).

    Args:
        convention: how the file marks usable pixels (:data:`~nsflow_ros.core.masks.MASK_CONVENTIONS`).

    Raises:
        ConfigError: when the file is missing or not an image, or the convention is unknown.
    """
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"mask image not found: {path}")
    img = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    if img is None:
        raise ConfigError(f"cannot read mask image {path}")
    try:
        return binarize(img, convention)
    except CoreError as err:
        raise ConfigError(str(err)) from err


def load_static_masks(
    config: VinsConfig,
    mask0: str | os.PathLike[str] | None = None,
    mask1: str | os.PathLike[str] | None = None,
    convention: str = "vins",
) -> tuple[np.ndarray | None, np.ndarray | None]:
    """Each camera's static mask at the images' full size: the files given, else the config's mask0 / mask1.

    Args:
        mask0, mask1: mask image files; None or "" = the config's key (none when it has none).
        convention: how the files mark usable pixels.

    Returns:
        (camera 0's, camera 1's), uint8 0 / 255 of the config's image size, or None where there is none.

    Raises:
        ConfigError: a file that does not exist or is no image, a mask of another size than the config's
            images, or a mask1 for a mono config; the message names the file.
    """
    size = (config.image_width, config.image_height)
    out: list[np.ndarray | None] = []
    for index, given in enumerate((mask0, mask1)):
        path = str(given) if given else getattr(config, f"mask{index}")
        if not path:
            out.append(None)
            continue
        if index >= config.num_of_cam:
            raise ConfigError(f"mask{index} {path} given, but {config.path} has one camera")
        mask = load_mask(path, convention)
        try:
            out.append(check_mask(mask, size, f"mask{index} {path}", f"the image size of {config.path}"))
        except CoreError as err:
            raise ConfigError(str(err)) from err
    return out[0], out[1]


def tracker_from_config(
    config: VinsConfig,
    overrides: Mapping[str, Any] | None = None,
    *,
    fisheye_mask: str | os.PathLike[str] | None = None,
    masks: Sequence[np.ndarray | None] = (),
    encoder: Encoder | None = None,
) -> FeatureTracker:
    """Build a tracker from a VINS config's cameras, ``body_T_cam0`` and the settings it has a key for.

    Args:
        overrides: TrackerSettings fields to replace, e.g. ``{"method": "classical", "max_cnt": 200}``.
        fisheye_mask: the mask image for a config with ``fisheye: 1``; None = :func:`find_fisheye_mask`.
        masks: static masks per camera at the images' full size (:func:`load_static_masks`); camera 0's
            applies with the fisheye mask, camera 1's only when the tracker is stereo.
        encoder: descriptor encoder instead of the one the method selects (tests, benchmarks).

    Raises:
        ConfigError: when ``fisheye: 1`` and no usable mask is found.
        CoreError: an unknown or bad setting (or a mask of the wrong size); EncoderError: the model cannot
            be loaded.
    """
    settings = TrackerSettings(**config.tracker_fields()).with_overrides(overrides or {})
    body_r = np.asarray(config.body_T_cam[0], dtype=np.float64)[:3, :3] if config.body_T_cam else None
    cams = list(config.cameras)
    fisheye = None
    if config.fisheye:
        fisheye = load_mask(fisheye_mask if fisheye_mask is not None else find_fisheye_mask(config.path))
        full = (config.image_width, config.image_height)
        fisheye = check_mask(fisheye, full, "mask", f"camera 0 ({cams[0].name})")
    static = [*masks, None, None]
    # full-resolution masks: the tracker takes them to its tracking resolution with ``downsample``
    mask = combine(fisheye, static[0])
    mask1 = static[1] if settings.stereo else None
    stereo_pose = None
    if settings.stereo and len(config.body_T_cam) >= 2:  # camera 0 in camera 1's frame
        body = [np.asarray(t, dtype=np.float64) for t in config.body_T_cam[:2]]
        stereo_pose = np.linalg.solve(body[1], body[0])
    return FeatureTracker(cams, settings, encoder=encoder, body_R_cam0=body_r, mask=mask, mask1=mask1,
                          cam1_T_cam0=stereo_pose)
