"""Tracking a large camera on decimated images: the images, masks, calibration and pixels at both scales.

A tracker with ``downsample`` d > 1 tracks on images d times smaller in each direction and publishes in the
camera's full-resolution calibration. Every conversion between the two goes through this module, with
one pixel-centre convention, that of ``cv2.resize``: pixel i of the small image covers pixels d i .. d i +
d - 1 of the large one, so ``x_small = (x_full + 0.5) / d - 0.5`` and ``x_full = (x_small + 0.5) d - 0.5``.

Images are decimated by ``cv2.resize`` with ``INTER_AREA``, which for an integer factor is the mean of each
d x d block: exactly that convention, anti-aliased, and about as cheap as ``cv2.pyrDown`` (whose 5x5
Gaussian puts pixel i at 2 i, half a pixel off this convention; measured in docs/design.md).
"""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np

from nsflow_ros.core.camera import CameraModel, KannalaBrandtCamera, MeiCamera, PinholeCamera
from nsflow_ros.core.errors import CoreError

__all__ = [
    "DOWNSAMPLE_FACTORS",
    "check_downsample",
    "downsample_camera",
    "downsample_image",
    "downsample_mask",
    "resize_camera",
    "to_full_resolution",
    "to_tracking_resolution",
]

DOWNSAMPLE_FACTORS: tuple[int, ...] = (1, 2, 4)
"""The decimation factors a tracker takes (as OpenVINS's downsample_cameras, plus 4 for very large
cameras)."""

# per model: (focal-length parameters, principal-point parameters), in pixels
_PIXEL_PARAMETERS: dict[type[CameraModel], tuple[tuple[str, str], tuple[str, str]]] = {
    PinholeCamera: (("fx", "fy"), ("cx", "cy")),
    KannalaBrandtCamera: (("mu", "mv"), ("u0", "v0")),
    MeiCamera: (("gamma1", "gamma2"), ("u0", "v0")),
}


def check_downsample(factor: object) -> int:
    """``factor`` as an int when it is one of :data:`DOWNSAMPLE_FACTORS`.

    Raises:
        CoreError: naming the value and the factors allowed.
    """
    integer = isinstance(factor, int | np.integer) and not isinstance(factor, bool)
    if not integer or int(factor) not in DOWNSAMPLE_FACTORS:  # type: ignore[call-overload]
        allowed = ", ".join(map(str, DOWNSAMPLE_FACTORS))
        raise CoreError(f"downsample must be one of {allowed}, got {factor!r}")
    return int(factor)


def _check_size(width: int, height: int, factor: int, what: str) -> None:
    if width % factor or height % factor:
        raise CoreError(
            f"downsample {factor} needs {what} sizes divisible by {factor}, got {width}x{height}"
        )


def resize_camera(camera: CameraModel, width: int, height: int) -> CameraModel:
    """The camera as its images resized to ``width`` x ``height`` by ``cv2.resize`` see it.

    Per axis with ``s = new size / old size``: focal lengths times s, principal point
    ``(c + 0.5) s - 0.5``; the distortion acts on normalised coordinates and stays. Benchmarks use it for
    up-sampled copies of the sample (a stand-in for a larger camera).
    """
    focal, centre = _PIXEL_PARAMETERS[type(camera)]
    scale = (width / camera.width, height / camera.height)
    changes: dict[str, float | int] = {"width": int(width), "height": int(height)}
    for key, sc in zip(focal, scale, strict=True):
        changes[key] = getattr(camera, key) * sc
    for key, sc in zip(centre, scale, strict=True):
        changes[key] = (getattr(camera, key) + 0.5) * sc - 0.5
    return dataclasses.replace(camera, **changes)


def downsample_camera(camera: CameraModel, factor: int) -> CameraModel:
    """The camera as its images decimated by ``factor`` see it (the convention of the module docstring).

    Focal lengths are divided by ``factor``, the principal point maps as a pixel does, distortion (which
    acts on normalised coordinates) is unchanged; so a point lifts to the same normalised coordinates
    from either camera. ``factor`` 1 returns ``camera`` itself.

    Raises:
        CoreError: a factor not in :data:`DOWNSAMPLE_FACTORS` or an image size it does not divide.
    """
    d = check_downsample(factor)
    if d == 1:
        return camera
    _check_size(camera.width, camera.height, d, f"camera ({camera.name})")
    return resize_camera(camera, camera.width // d, camera.height // d)


def downsample_image(image: np.ndarray, factor: int) -> np.ndarray:
    """The image decimated by ``factor`` with ``cv2.resize`` ``INTER_AREA`` (block means); 1 = itself.

    Shape:
        (H, W) or (H, W, C) -> (H / factor, W / factor[, C]), same dtype.

    Raises:
        CoreError: a bad factor or a size it does not divide.
    """
    d = check_downsample(factor)
    if d == 1:
        return image
    h, w = image.shape[:2]
    _check_size(w, h, d, "image")
    return cv2.resize(image, (w // d, h // d), interpolation=cv2.INTER_AREA)


def downsample_mask(mask: np.ndarray, factor: int) -> np.ndarray:
    """A full-resolution mask (uint8, 255 = usable) at the tracking resolution of ``factor``.

    A small pixel is usable only when every full-resolution pixel it covers is: nothing the full-resolution
    mask excludes can be tracked or detected. ``factor`` 1 returns the mask itself.

    Shape:
        (H, W) uint8 -> (H / factor, W / factor) uint8 (0 / 255).

    Raises:
        CoreError: a bad factor, a mask that is not 2-D uint8, or a size the factor does not divide.
    """
    d = check_downsample(factor)
    if not isinstance(mask, np.ndarray) or mask.ndim != 2 or mask.dtype != np.uint8:
        got = f"{mask.dtype} {mask.shape}" if isinstance(mask, np.ndarray) else type(mask).__name__
        raise CoreError(f"mask must be a 2-D uint8 array, got {got}")
    if d == 1:
        return mask
    h, w = mask.shape
    _check_size(w, h, d, "mask")
    usable = (mask > 127).reshape(h // d, d, w // d, d).all(axis=(1, 3))
    return np.where(usable, 255, 0).astype(np.uint8)


def to_full_resolution(pixels: np.ndarray, factor: int) -> np.ndarray:
    """Pixels of the decimated image in full-resolution pixels: ``(x + 0.5) factor - 0.5``.

    Shape:
        (N, 2) -> (N, 2) float64 (NaN stays NaN).
    """
    return (np.asarray(pixels, np.float64) + 0.5) * factor - 0.5


def to_tracking_resolution(pixels: np.ndarray, factor: int) -> np.ndarray:
    """Full-resolution pixels in pixels of the decimated image: ``(x + 0.5) / factor - 0.5``.

    Shape:
        (N, 2) -> (N, 2) float64.
    """
    return (np.asarray(pixels, np.float64) + 0.5) / factor - 0.5
