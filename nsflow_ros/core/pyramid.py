"""Descriptor pyramids: what the solver samples.

Each level holds the descriptor map as float32 (H, W, K) chunks of at most 4 channels, since ``cv2.remap``
is fast only on contiguous maps and exact only up to 4 channels. A chunk of 1 or 4 channels is C-contiguous;
one of 2 or 3 is the leading channels of a padded C-contiguous 4-channel buffer
(:func:`sampling_source`): OpenCV 5's remap has exact fast paths for 1 and 4 interleaved channels, samples 2
channels at 1/32 px (as OpenCV 4 does all float maps) and 2 or 3 more slowly than 4 (docs/design.md,
"One channel"). No derivative maps are stored (the
solver differentiates sampled patches). Coarser levels are ``cv2.pyrDown`` of the map, far
cheaper than encoding a smaller image. Optional Gaussian smoothing (:class:`Smoothing`) widens the
solver's basin on a learned map, whose narrow autocorrelation leaves it a narrow one.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import cv2
import numpy as np

from nsflow_ros.core.errors import CoreError

__all__ = [
    "DescriptorPyramid",
    "Smoothing",
    "build_pyramid",
    "descriptor_gradients",
    "gaussian_kernel",
    "sampling_source",
    "split_channels",
]

_BORDER = cv2.BORDER_REPLICATE


def descriptor_gradients(desc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The x- and y-derivatives (dx, dy) of a (H, W, C) float32 map: Scharr / 32, replicated border.

    The reference the solver's J equals and the torch training layer mirrors; not on the tracking path.
    """
    dx = cv2.Scharr(desc, cv2.CV_32F, 1, 0, scale=1.0 / 32.0, borderType=_BORDER)
    dy = cv2.Scharr(desc, cv2.CV_32F, 0, 1, scale=1.0 / 32.0, borderType=_BORDER)
    if desc.ndim == 3 and dx.ndim == 2:  # cv2 drops a trailing singleton channel
        dx, dy = dx[..., None], dy[..., None]
    return dx, dy


MAX_CHUNK = 4


def gaussian_kernel(sigma: float) -> np.ndarray:
    """The 1-D float32 smoothing kernel for ``sigma`` (px, > 0): taps within 2 sigma, normalised to sum 1."""
    if not (math.isfinite(sigma) and sigma > 0):
        raise CoreError(f"smoothing sigma must be a finite number > 0, got {sigma}")
    radius = math.ceil(2.0 * sigma)
    x = np.arange(-radius, radius + 1, dtype=np.float64)
    k = np.exp(-0.5 * (x / sigma) ** 2)
    return (k / k.sum()).astype(np.float32)


@dataclass(frozen=True)
class Smoothing:
    """Gaussian smoothing of the descriptor pyramid's levels (sigma 0 = none).

    Attributes:
        fine: sigma at level 0, in pixels; the coarser levels are made from the smoothed map.
        coarse: sigma at every coarser level, in that level's pixels.
    """

    fine: float = 0.0
    coarse: float = 0.0

    def __post_init__(self) -> None:
        for name in ("fine", "coarse"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
                raise CoreError(f"Smoothing.{name} must be a finite number >= 0, got {v!r}")


def _padded(chunk: np.ndarray) -> np.ndarray:
    """A 2-3 channel map as the leading channels of a padded C-contiguous 4-channel float32 buffer (what
    the extra channels hold is never read)."""
    chunk = np.ascontiguousarray(chunk, np.float32)
    if chunk.shape[2] == 3:  # OpenCV's SIMD conversion; the fourth channel is 1
        return cv2.cvtColor(chunk, cv2.COLOR_BGR2BGRA)[..., :3]
    buf = np.zeros((*chunk.shape[:2], MAX_CHUNK), np.float32)
    # A pixel's two float32 as one complex64: a strided copy of 8-byte items, not of 2-float rows.
    buf.view(np.complex64)[..., 0] = chunk.view(np.complex64)[..., 0]
    return buf[..., :2]


def sampling_source(chunk: np.ndarray) -> np.ndarray:
    """The array ``cv2.remap`` samples for a pyramid chunk: the chunk itself, or for a padded 2-3 channel
    chunk the 4-channel buffer whose leading channels it is (the extra channels are sampled and dropped)."""
    base = chunk.base
    if (
        1 < chunk.shape[2] < MAX_CHUNK
        and isinstance(base, np.ndarray)
        and base.shape == (*chunk.shape[:2], MAX_CHUNK)
        and base.dtype == np.float32
        and base.flags.c_contiguous
        and base.ctypes.data == chunk.ctypes.data
    ):
        return base
    return chunk


def split_channels(level: np.ndarray) -> tuple[np.ndarray, ...]:
    """Split an (H, W, K) map into float32 chunks of at most 4 channels, as a pyramid level holds them: a
    1 or 4 channel chunk C-contiguous, a 2-3 channel one padded (:func:`sampling_source`)."""
    out = []
    for i in range(0, level.shape[2], MAX_CHUNK):
        part = level[..., i : i + MAX_CHUNK]
        out.append(_padded(part) if 1 < part.shape[2] < MAX_CHUNK else np.ascontiguousarray(part, np.float32))
    return tuple(out)


def _level(desc: np.ndarray) -> tuple[np.ndarray, ...]:
    return (desc,) if desc.shape[2] == MAX_CHUNK else split_channels(desc)


@dataclass(frozen=True)
class DescriptorPyramid:
    """A frame's descriptor maps at every pyramid level.

    Attributes:
        levels: level 0 first (full resolution); each a tuple of float32 chunks (H_l, W_l, K) with
            K <= 4, together the C descriptor channels in order (2-3 channel chunks padded in memory to 4,
            :func:`sampling_source`).
        channels: C, the descriptor dimension.
        image: the frame's gray image as a one-chunk level ((H, W, 1) float32 in [0, 1]) for a method that
            refines on intensity (:mod:`~nsflow_ros.core.refine`); None = none kept.
    """

    levels: tuple[tuple[np.ndarray, ...], ...]
    channels: int
    image: tuple[np.ndarray, ...] | None = None

    @property
    def shape(self) -> tuple[int, int]:
        """(H, W) of level 0."""
        h, w = self.levels[0][0].shape[:2]
        return h, w

    @property
    def num_levels(self) -> int:
        return len(self.levels)

    def level(self, index: int) -> np.ndarray:
        """Level ``index`` as one (H_l, W_l, C) descriptor map."""
        chunks = self.levels[index]
        return chunks[0] if len(chunks) == 1 else np.concatenate(chunks, axis=2)


def _check_map(desc: np.ndarray) -> np.ndarray:
    if not isinstance(desc, np.ndarray):
        raise CoreError(f"descriptor map must be a numpy array, got {type(desc).__name__}")
    if desc.ndim == 2:
        desc = desc[..., None]
    if desc.ndim != 3:
        raise CoreError(f"descriptor map must have shape (H, W, C), got {desc.shape}")
    if desc.shape[0] < 2 or desc.shape[1] < 2 or desc.shape[2] < 1:
        raise CoreError(f"descriptor map is empty or degenerate: shape {desc.shape}")
    if not np.issubdtype(desc.dtype, np.floating):
        raise CoreError(f"descriptor map must be floating point, got dtype {desc.dtype}")
    if desc.dtype == np.float32 and sampling_source(desc) is not desc:
        return desc  # already padded (an encoder's output): no copy
    return np.ascontiguousarray(desc, dtype=np.float32)


@functools.lru_cache(maxsize=8)
def _kernel(sigma: float) -> np.ndarray:
    """:func:`gaussian_kernel`, made once per sigma (every frame smooths with the same few)."""
    k = gaussian_kernel(sigma)
    k.flags.writeable = False
    return k


def _smooth(level: np.ndarray, sigma: float) -> np.ndarray:
    k = _kernel(sigma)
    out = cv2.sepFilter2D(level, cv2.CV_32F, k, k, borderType=_BORDER)
    return out[..., None] if out.ndim == 2 else out


def build_pyramid(desc: np.ndarray, levels: int = 3, smoothing: Smoothing | None = None) -> DescriptorPyramid:
    """Build the solver's pyramid from a full-resolution descriptor map.

    Args:
        desc: the descriptor map of one frame.
        levels: number of levels (1 = single scale); levels smaller than 8 px are not built.
        smoothing: ``fine`` smooths level 0 before the coarser levels are made from it, ``coarse`` each
            coarser level afterwards; None = none.

    Returns:
        the pyramid, level 0 first; without smoothing, level 0 shares memory with a C-contiguous
        float32 ``desc`` of at most 4 channels (of 2-3 channels: an encoder's padded output).

    Raises:
        CoreError: on a wrong shape or dtype (floating (H, W, C) or (H, W)), or ``levels < 1``.
    """
    if levels < 1:
        raise CoreError(f"levels must be >= 1, got {levels}")
    if smoothing is not None and not isinstance(smoothing, Smoothing):
        raise CoreError(f"smoothing must be a Smoothing or None, got {type(smoothing).__name__}")
    current = _check_map(desc)
    channels = current.shape[2]
    if 1 < channels < MAX_CHUNK:
        # Made, smoothed and sampled as the padded 4-channel block: no copy per level.
        current = sampling_source(current if sampling_source(current) is not current else _padded(current))
    if smoothing is not None and smoothing.fine > 0:
        current = _smooth(current, smoothing.fine)
    maps = [current]
    for _ in range(1, levels):
        h, w = current.shape[:2]
        if min(h, w) // 2 < 8:
            break
        current = cv2.pyrDown(current, borderType=_BORDER)
        if current.ndim == 2:
            current = current[..., None]
        maps.append(current)
    if smoothing is not None and smoothing.coarse > 0:
        maps = maps[:1] + [_smooth(m, smoothing.coarse) for m in maps[1:]]
    if channels < MAX_CHUNK:
        return DescriptorPyramid(levels=tuple((m[..., :channels],) for m in maps), channels=channels)
    return DescriptorPyramid(levels=tuple(_level(m) for m in maps), channels=channels)
