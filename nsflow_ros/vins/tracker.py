"""A :class:`~nsflow_ros.core.tracker.FeatureTracker` built the VINS way: from a config file's settings.

The VINS file conventions live here, not in the core: the config keys that become tracker settings,
``body_T_cam0`` as the gyro prediction's extrinsic, and VINS-Mono's fisheye mask file beside the config.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from nsflow_ros.core.encoder import Encoder
from nsflow_ros.core.tracker import FeatureTracker, TrackerSettings
from nsflow_ros.vins.config import VinsConfig
from nsflow_ros.vins.errors import ConfigError
from nsflow_ros.vins.settings import config_tracker_fields

__all__ = ["FISHEYE_MASK_NAME", "find_fisheye_mask", "load_mask", "tracker_from_config"]

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


def load_mask(path: str | os.PathLike[str]) -> np.ndarray:
    """Read a mask image as uint8 0 / 255 (gray > 127 counts as usable: VINS-Mono's masks are JPEGs).

    Raises:
        ConfigError: when the file is missing or not an image.
    """
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"mask image not found: {path}")
    img = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    if img is None:
        raise ConfigError(f"cannot read mask image {path}")
    return np.where(img > 127, 255, 0).astype(np.uint8)


def tracker_from_config(
    config: VinsConfig,
    overrides: Mapping[str, Any] | None = None,
    *,
    fisheye_mask: str | os.PathLike[str] | None = None,
    encoder: Encoder | None = None,
) -> FeatureTracker:
    """Build a tracker from a VINS config's cameras, ``body_T_cam0`` and the settings it has a key for.

    Args:
        overrides: TrackerSettings fields to replace, e.g. ``{"method": "classical", "max_cnt": 200}``.
        fisheye_mask: the mask image for a config with ``fisheye: 1``; None = :func:`find_fisheye_mask`.
        encoder: descriptor encoder instead of the one the method selects (tests, benchmarks).

    Raises:
        ConfigError: when ``fisheye: 1`` and no usable mask is found.
        CoreError: an unknown or bad setting (or a mask of the wrong size); EncoderError: the model cannot
            be loaded.
    """
    settings = TrackerSettings(**config_tracker_fields(config)).with_overrides(overrides or {})
    body_r = np.asarray(config.body_T_cam[0], dtype=np.float64)[:3, :3] if config.body_T_cam else None
    mask = None
    if config.fisheye:
        mask = load_mask(fisheye_mask if fisheye_mask is not None else find_fisheye_mask(config.path))
    return FeatureTracker(list(config.cameras), settings, encoder=encoder, body_R_cam0=body_r, mask=mask)
