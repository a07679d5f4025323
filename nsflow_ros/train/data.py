"""Training and validation pairs with exact ground-truth flow, made from real photos (nothing downloaded).

A pair is two views of one bundled photo: frame 1 a random similarity crop, frame 2 the same crop seen
through a random homography P of frame-1 pixels, so a frame-1 point x moves exactly to P(x). Each frame
gets its own illumination change (``nsflow_ros.data.perturb.perturb_pair``), which breaks the brightness
constancy classical LK assumes. The photos are split once (:mod:`nsflow_ros.data.photos`):
:data:`TRAIN_IMAGES` for training, :data:`HELDOUT_IMAGES` for validation and evaluation.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from nsflow_ros.core.detector import detect_corners
from nsflow_ros.data.errors import DataError
from nsflow_ros.data.perturb import perturb_pair
from nsflow_ros.data.photos import HELDOUT_IMAGES, TRAIN_IMAGES, load_photo
from nsflow_ros.train.errors import TrainError

__all__ = [
    "HELDOUT_IMAGES",
    "INIT_MODES",
    "TRAIN_IMAGES",
    "Pair",
    "PairConfig",
    "initial_flow",
    "inside",
    "load_image",
    "make_pair",
    "perturb_frames",
    "render_views",
]


INIT_MODES = ("normal", "uniform", "zero")


def inside(points: Any, width: int, height: int, radius: int) -> Any:
    """Which points keep a window of ``radius`` inside a ``width`` x ``height`` image (NumPy or torch).

    Shape:
        points: (N, 2). Returns (N,) bool.
    """
    x, y = points[:, 0], points[:, 1]
    return (x >= radius) & (x <= width - 1 - radius) & (y >= radius) & (y <= height - 1 - radius)


def load_image(name: str) -> np.ndarray:
    """A bundled photo as an (H, W) uint8 gray image, cached: do not modify it in place.

    Args:
        name: a scikit-image data file stem (e.g. "astronaut") or "grace_hopper" (matplotlib).

    Raises:
        TrainError: an unknown photo.
    """
    try:
        return load_photo(name)
    except DataError as err:
        raise TrainError(str(err)) from err


@dataclass(frozen=True)
class PairConfig:
    """How pairs are made.

    Attributes:
        width, height: frame size in pixels.
        corner_jitter: max displacement of each frame corner by the homography P, pixels.
        translation: max common translation of P, pixels.
        max_points: GFTT corners per pair (at most).
        min_distance: GFTT minimum distance between corners.
        window: solver window; points whose window (in frame 1 or at the GT target) leaves the image drop.
        init_sigma: size of the initial error in pixels (its meaning depends on ``init_mode``).
        init_mode: training pairs' initial flow: "normal" = GT + N(0, init_sigma^2) per axis; "uniform" =
            GT + an error of length uniform in [0, init_sigma] in a random direction; "zero" = zero flow.
        light_min: the training pairs' illumination change has a strength uniform in [light_min, 1]
            (0 = as often none as the strongest; higher = stronger augmentation).
    """

    width: int = 320
    height: int = 240
    corner_jitter: float = 6.0
    translation: float = 8.0
    max_points: int = 200
    min_distance: float = 7.0
    window: int = 11
    init_sigma: float = 2.5
    init_mode: str = "normal"
    light_min: float = 0.0

    def __post_init__(self) -> None:
        if self.init_mode not in INIT_MODES:
            raise TrainError(f"PairConfig.init_mode must be one of {INIT_MODES}, got {self.init_mode!r}")
        if self.init_sigma < 0:
            raise TrainError(f"PairConfig.init_sigma must be >= 0, got {self.init_sigma}")
        if not 0.0 <= self.light_min <= 1.0:
            raise TrainError(f"PairConfig.light_min must be in [0, 1], got {self.light_min}")


@dataclass(frozen=True)
class Pair:
    """One training pair.

    Attributes:
        image1, image2: (H, W) uint8 frames (after perturbation).
        points: (N, 2) float64 GFTT corners of frame 1.
        flow_gt: (N, 2) float64 exact flow.
        flow0: (N, 2) float64 initial flow.
        homography: (3, 3) P mapping frame-1 pixels to frame-2 pixels (NaN when the motion is not one).
    """

    image1: np.ndarray
    image2: np.ndarray
    points: np.ndarray
    flow_gt: np.ndarray
    flow0: np.ndarray
    homography: np.ndarray


def render_views(
    src: np.ndarray, rng: np.random.Generator, cfg: PairConfig
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """An unperturbed pair of views of an (H, W) uint8 photo: (frame1, frame2, homography x1 -> x2)."""
    w, h = cfg.width, cfg.height
    sh, sw = src.shape[:2]
    fit = min(sw / w, sh / h)  # source pixels per frame pixel at which the frame just fits
    scale = fit * rng.uniform(0.45, 0.9)
    theta = np.deg2rad(rng.uniform(-15.0, 15.0))
    cos, sin = np.cos(theta) * scale, np.sin(theta) * scale
    half = 0.5 * scale * np.hypot(w, h)
    cx = rng.uniform(half, sw - half) if sw > 2 * half else sw / 2
    cy = rng.uniform(half, sh - half) if sh > 2 * half else sh / 2
    # frame-1 pixel -> photo pixel
    m1 = np.array([[cos, -sin, cx], [sin, cos, cy], [0, 0, 1]]) @ np.array(
        [[1, 0, -w / 2], [0, 1, -h / 2], [0, 0, 1]]
    )
    corners = np.float32([[0, 0], [w - 1, 0], [w - 1, h - 1], [0, h - 1]])
    moved = corners + rng.uniform(-cfg.corner_jitter, cfg.corner_jitter, (4, 2)).astype(np.float32)
    moved += rng.uniform(-cfg.translation, cfg.translation, 2).astype(np.float32)
    p = cv2.getPerspectiveTransform(corners, moved).astype(np.float64)
    flags = cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP
    f1 = cv2.warpPerspective(src, m1, (w, h), flags=flags, borderMode=cv2.BORDER_REFLECT_101)
    f2 = cv2.warpPerspective(
        src, m1 @ np.linalg.inv(p), (w, h), flags=flags, borderMode=cv2.BORDER_REFLECT_101
    )
    return f1, f2, p


def perturb_frames(
    img1: np.ndarray, img2: np.ndarray, rng: np.random.Generator, strength: float
) -> tuple[np.ndarray, np.ndarray]:
    """Both frames perturbed independently (``nsflow_ros.data.perturb.perturb_pair``), strength clipped to
    [0, 1]."""
    strength = float(np.clip(strength, 0.0, 1.0))
    return perturb_pair(img1, img2, rng, strength)


def initial_flow(
    gt: np.ndarray, rng: np.random.Generator, cfg: PairConfig, init_error: float | None = None
) -> np.ndarray:
    """The initial flow of a pair's points.

    Args:
        gt: (N, 2) ground-truth flow.
        rng: random generator.
        cfg: ``init_mode`` and ``init_sigma``.
        init_error: when given, GT plus an error of exactly this length in a random direction
            (evaluation), whatever ``cfg`` says.
    """
    if init_error is None and cfg.init_mode == "normal":
        return gt + rng.normal(0.0, cfg.init_sigma, gt.shape)
    if init_error is None and cfg.init_mode == "zero":
        return np.zeros_like(gt)
    ang = rng.uniform(0.0, 2 * np.pi, len(gt))
    length = rng.uniform(0.0, cfg.init_sigma, len(gt)) if init_error is None else init_error
    return gt + np.asarray(length)[..., None] * np.stack([np.cos(ang), np.sin(ang)], 1)


def make_pair(
    src: np.ndarray,
    rng: np.random.Generator,
    cfg: PairConfig | None = None,
    strength: float = 1.0,
    init_error: float | None = None,
) -> Pair:
    """Make one pair with GFTT points, exact flow and an initial flow.

    Args:
        src: (H, W) uint8 photo.
        rng: random generator (geometry, perturbation, points' initial error).
        cfg: pair settings; ``PairConfig()`` when None.
        strength: illumination perturbation strength (0 = none).
        init_error: as in :func:`initial_flow`.

    Returns:
        the :class:`Pair` (possibly with zero points).

    Raises:
        TrainError: ``src`` is not an (H, W) uint8 image.
    """
    cfg = cfg or PairConfig()
    if src.ndim != 2 or src.dtype != np.uint8:
        raise TrainError(f"source photo must be (H, W) uint8, got {src.shape} {src.dtype}")
    f1, f2, p = render_views(src, rng, cfg)
    f1, f2 = perturb_frames(f1, f2, rng, strength)
    pts = detect_corners(f1, cfg.max_points, min_distance=cfg.min_distance)
    target = cv2.perspectiveTransform(pts[None], p)[0] if len(pts) else pts.copy()
    frame = (cfg.width, cfg.height, cfg.window // 2)
    keep = inside(pts, *frame) & inside(target, *frame)
    pts, target = pts[keep], target[keep]
    gt = target - pts
    return Pair(f1, f2, pts, gt, initial_flow(gt, rng, cfg, init_error), p)
