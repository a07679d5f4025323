"""Real photos bundled with scikit-image and matplotlib, and their fixed train / held-out split.

Torch-free, so training and evaluation read the same photos and the same split; nothing is downloaded.
"""

from __future__ import annotations

import functools
import os
from pathlib import Path

import cv2
import numpy as np

from nsflow_ros.data.errors import DataError
from nsflow_ros.optional import require

__all__ = ["HELDOUT_IMAGES", "TRAIN_IMAGES", "load_photo"]

TRAIN_IMAGES = (
    "astronaut",
    "camera",
    "brick",
    "grass",
    "gravel",
    "rocket",
    "motorcycle_left",
    "coins",
    "moon",
    "page",
    "clock_motion",
    "hubble_deep_field",
)
# scenes that appear in no training image: validation and every NSFlow-vs-classical evaluation
HELDOUT_IMAGES = ("coffee", "chelsea", "grace_hopper")


@functools.cache
def load_photo(name: str) -> np.ndarray:
    """A bundled photo as (H, W) uint8 gray, cached: do not modify it in place.

    Args:
        name: a scikit-image data file stem (e.g. "astronaut") or "grace_hopper" (matplotlib).

    Raises:
        DataError: no such bundled photo, or it cannot be read.
    """
    if name == "grace_hopper":
        matplotlib = require("matplotlib", "the grace_hopper photo (bundled with matplotlib)")
        path = Path(matplotlib.get_data_path()) / "sample_data" / "grace_hopper.jpg"
    else:
        skimage = require("skimage", f"the photo {name!r} (bundled with scikit-image)")
        folder = Path(os.path.dirname(skimage.__file__)) / "data"
        matches = sorted(folder.glob(f"{name}.*"))
        if not matches:
            raise DataError(f"no bundled image named {name!r} in {folder}")
        path = matches[0]
    img = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    if img is None:
        raise DataError(f"cannot read image {path}")
    return img
