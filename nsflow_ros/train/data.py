"""Training and validation pairs with exact ground-truth flow, made from real photos (nothing downloaded).

A pair is two views of one photo (scikit-image's and matplotlib's bundled images): frame 1 is a random
similarity crop of the photo, frame 2 the same crop seen through a random homography P of frame-1 pixel
coordinates (corner jitter plus translation), both rendered with ``cv2.warpPerspective`` from the
full-resolution photo. A frame-1 point x moves to P(x), so the ground-truth flow is exact.

Illumination perturbation (the paper's absolute and relative intensity changes driven by random
variables, plus local shading, gamma and sensor noise) is applied to each frame independently, so the
brightness-constancy assumption of classical LK is broken between the two frames. The project's shared
``nsflow_ros.data.perturb.perturb_pair`` is used (the shipped model was trained and evaluated with it);
:func:`perturb_illumination` here is a stand-alone alternative for single frames (pairs do not use it).

Source images are split once and for all (in the torch-free :mod:`nsflow_ros.data.photos`, shared with
the evaluation suite): :data:`TRAIN_IMAGES` for training, :data:`HELDOUT_IMAGES` (coffee, chelsea,
grace_hopper: scenes that appear in no training image) for validation and for the NSFlow-vs-classical
evaluation.
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
    "perturb_illumination",
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
    """Load a bundled photo as an (H, W) uint8 gray image (:func:`nsflow_ros.data.photos.load_photo`).

    Args:
        name: a scikit-image data file stem (e.g. "astronaut") or "grace_hopper" (matplotlib).

    Returns:
        the gray image (cached: do not modify it in place).
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
        init_mode: how training pairs' initial flow is made: "normal" = GT + N(0, init_sigma^2) per axis
            (the shipped model's); "uniform" = GT + an error whose length is uniform in [0, init_sigma]
            in a random direction (each point is solved on its own, so this is zero flow on
            displacements up to init_sigma, spread evenly over that range); "zero" = zero flow (the
            displacement is the homography's: set ``translation`` for the range).
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

    def __post_init__(self) -> None:
        if self.init_mode not in INIT_MODES:
            raise TrainError(f"PairConfig.init_mode must be one of {INIT_MODES}, got {self.init_mode!r}")
        if self.init_sigma < 0:
            raise TrainError(f"PairConfig.init_sigma must be >= 0, got {self.init_sigma}")


@dataclass(frozen=True)
class Pair:
    """One training pair.

    Attributes:
        image1, image2: (H, W) uint8 frames (after perturbation).
        points: (N, 2) float64 GFTT corners of frame 1.
        flow_gt: (N, 2) float64 exact flow.
        flow0: (N, 2) float64 initial flow (GT + noise).
        homography: (3, 3) P mapping frame-1 pixels to frame-2 pixels.
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
    """Render an unperturbed pair of views of a photo.

    Args:
        src: (H, W) uint8 photo.
        rng: random generator.
        cfg: frame size and motion ranges.

    Returns:
        (frame1, frame2, P): uint8 (height, width) frames and the 3x3 homography x1 -> x2.
    """
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


def perturb_illumination(image: np.ndarray, rng: np.random.Generator, strength: float) -> np.ndarray:
    """Change the illumination of one frame.

    Relative change (gain a), absolute change (offset b), a smooth local shading field (a linear ramp
    plus a Gaussian light spot), a gamma curve and Gaussian sensor noise, all drawn at random with
    ranges scaled by ``strength`` (0 = unchanged, 1 = strong).

    Args:
        image: (H, W) uint8 frame.
        rng: random generator.
        strength: perturbation strength in [0, 1+].

    Returns:
        the perturbed (H, W) uint8 frame.
    """
    if strength <= 0:
        return image.copy()
    h, w = image.shape
    x = image.astype(np.float32) / 255.0
    gain = rng.uniform(1.0 - 0.5 * strength, 1.0 + 0.5 * strength)
    offset = rng.uniform(-0.15, 0.15) * strength
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    xx, yy = xx / w - 0.5, yy / h - 0.5
    ramp = rng.normal(0, 1, 2) * 0.35 * strength
    spot_c = rng.uniform(-0.5, 0.5, 2)
    spot_r = rng.uniform(0.15, 0.5)
    spot = (
        rng.uniform(-0.5, 0.5)
        * strength
        * np.exp(-((xx - spot_c[0]) ** 2 + (yy - spot_c[1]) ** 2) / spot_r**2)
    )
    shading = np.clip(1.0 + ramp[0] * xx + ramp[1] * yy + spot, 0.2, 3.0)
    x = np.clip((gain * x + offset) * shading, 0.0, 1.0)
    gamma = float(np.exp(rng.uniform(-0.5, 0.5) * strength))
    x = x**gamma
    noise = rng.uniform(0.0, 4.0 / 255.0) * strength
    x = x + rng.normal(0.0, 1.0, x.shape).astype(np.float32) * noise
    return np.clip(np.rint(x * 255.0), 0, 255).astype(np.uint8)


def perturb_frames(
    img1: np.ndarray, img2: np.ndarray, rng: np.random.Generator, strength: float
) -> tuple[np.ndarray, np.ndarray]:
    """Perturb both frames independently with ``nsflow_ros.data.perturb.perturb_pair`` (the project's shared
    training perturbation), strength clipped to [0, 1]."""
    strength = float(np.clip(strength, 0.0, 1.0))
    return perturb_pair(img1, img2, rng, strength)


def initial_flow(
    gt: np.ndarray, rng: np.random.Generator, cfg: PairConfig, init_error: float | None = None
) -> np.ndarray:
    """The initial flow of a pair's points.

    Args:
        gt: (N, 2) ground-truth flow.
        rng: random generator.
        cfg: ``init_mode`` and ``init_sigma`` (see :class:`PairConfig`).
        init_error: when given, GT plus an error of exactly this length in a random direction
            (evaluation), whatever ``cfg`` says.

    Returns:
        (N, 2) float64 initial flow.
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
        init_error: when given, the initial flow is GT plus an error of exactly this length in a random
            direction (evaluation); otherwise as ``cfg.init_mode`` says (training).

    Returns:
        the :class:`Pair` (possibly with zero points).
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
