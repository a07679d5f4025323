"""Feature masks: per camera, where features may be (255) and where none may be (0).

A mask in the tracker is a uint8 (H, W) image holding only 0 and 255, as VINS-Mono's ``fisheye_mask``
(255 = usable): no corner is detected on a 0 and a track that lands on one is dropped. Masks of other
origins become that form here, once: :func:`binarize` reads a mask image in either convention of
:data:`MASK_CONVENTIONS`, :func:`check_mask` guards its size and :func:`combine` intersects the masks that
apply to one camera in one frame (a static mask and a per-frame one). Masks are given at the camera's full
resolution; the tracker takes them to its tracking resolution with
:func:`~nsflow_ros.core.downsample.downsample_mask`.
"""

from __future__ import annotations

import numpy as np

from nsflow_ros.core.errors import CoreError

__all__ = [
    "MASK_CONVENTIONS",
    "USABLE",
    "binarize",
    "check_mask",
    "combine",
    "usable_at",
]

USABLE = 255
"""The value of a pixel where features may be (every other pixel of a tracker mask is 0)."""

MASK_CONVENTIONS: dict[str, bool] = {
    "vins": True,
    "openvins": False,
}
"""Mask image conventions by name -> whether a set pixel (> 127) marks a usable one: ``vins`` = 255 where
features may be (VINS-Mono's fisheye_mask), ``openvins`` = 255 where none may be (OpenVINS mask0 / mask1)."""

_THRESHOLD = 127  # a pixel above it is set: JPEG masks carry compression noise around 0 and 255


def binarize(raw: np.ndarray, convention: str = "vins") -> np.ndarray:
    """A tracker mask (255 usable, 0 not) from an 8-bit mask image of the given convention.

    Args:
        raw: the mask image as read or received; a pixel > 127 counts as set.
        convention: a key of :data:`MASK_CONVENTIONS`.

    Raises:
        CoreError: an unknown convention, or not a 2-D uint8 array.

    Shape:
        raw: (H, W) uint8. Returns (H, W) uint8 of 0 and 255.
    """
    if convention not in MASK_CONVENTIONS:
        raise CoreError(f"mask convention must be one of {tuple(MASK_CONVENTIONS)}, got {convention!r}")
    _check_array(raw, "mask")
    set_is_usable = MASK_CONVENTIONS[convention]
    return np.where((raw > _THRESHOLD) == set_is_usable, USABLE, 0).astype(np.uint8)


def _check_array(mask: object, what: str) -> None:
    if not isinstance(mask, np.ndarray) or mask.ndim != 2:
        got = f"shape {mask.shape}" if isinstance(mask, np.ndarray) else type(mask).__name__
        raise CoreError(f"{what} must be a 2-D uint8 array, got {got}")
    if mask.dtype != np.uint8:
        raise CoreError(f"{what} must be uint8 (0 / 255), got dtype {mask.dtype}")


def check_mask(
    mask: np.ndarray, size: tuple[int, int], what: str = "mask", against: str = "the image"
) -> np.ndarray:
    """A mask checked against an image size, as 0 / 255 (a pixel > 127 counts as usable).

    Args:
        size: (width, height) the mask must have.
        what: how error messages name the mask, e.g. "mask1" or "mask file m.png".
        against: how they name what has ``size``, e.g. "camera 0 (cam0)".

    Raises:
        CoreError: not a 2-D uint8 array, or another size; the message names both sizes.
    """
    _check_array(mask, what)
    w, h = size
    if mask.shape != (h, w):
        mh, mw = mask.shape
        raise CoreError(f"{what} is {mw}x{mh} but {against} is {w}x{h}")
    return np.where(mask > _THRESHOLD, USABLE, 0).astype(np.uint8)


def combine(*masks: np.ndarray | None) -> np.ndarray | None:
    """The pixels usable in every given mask (None entries are ignored); None when none is given."""
    given = [m for m in masks if m is not None]
    if not given:
        return None
    out = given[0]
    for m in given[1:]:
        out = np.minimum(out, m)  # 0 / 255 masks: the minimum is the intersection
    return out


def usable_at(mask: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """True where a point's rounded pixel lies inside the mask and is usable.

    Shape:
        pts: (N, 2) pixel positions (x, y). Returns (N,) bool.
    """
    h, w = mask.shape
    out = np.zeros(pts.shape[0], bool)
    with np.errstate(invalid="ignore"):
        r = np.rint(pts)
        inside = (r[:, 0] >= 0) & (r[:, 0] < w) & (r[:, 1] >= 0) & (r[:, 1] < h)
    idx = np.flatnonzero(inside)
    out[idx] = mask[r[idx, 1].astype(np.int64), r[idx, 0].astype(np.int64)] == USABLE
    return out
