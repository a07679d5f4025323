"""The last sub-pixel step on the image itself: affine-photometric Lucas-Kanade after the descriptor solve.

The learned map is robust to light but blurrier than the image, so its solution is less precise than
intensity's where the light is steady (docs/design.md). One short LM solve on the full-resolution gray
image, started at the descriptor solution and comparing windows up to a gain and an offset (the solver's
``zero_mean`` and ``gain`` residual), recovers intensity's precision; it is kept only where it stays close
to the descriptor solution and its own residual says the windows match, so under a lighting change the
descriptors' answer stands.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from nsflow_ros.core.errors import CoreError

# The gain's clip is the descriptor solver's bias-and-gain residual's, so both steps accept the same lights.
from nsflow_ros.core.solver import _GAIN_HI, _GAIN_LO, _sample_level, sample_windows, window_centres

__all__ = ["IntensityRefinement", "RefineResult", "StepTemplate", "gray_level", "refine", "step_template"]


@dataclass(frozen=True)
class IntensityRefinement:
    """Settings of the intensity step.

    Attributes:
        window: window side (odd, px) of the intensity solve.
        iterations: Gauss-Newton iterations (the start is within a pixel or two).
        max_shift: the step is kept only when it moves the point less than this (px): a larger move is
            the image disagreeing with the descriptors, not a refinement.
        max_residual: the step is kept only when its residual ratio (the residual's energy over the
            template's contrast, after gain and offset) is below this: above it the light changed inside
            the window in a way a gain and an offset do not explain.
        min_eigen: the smallest eigenvalue of the window's gradient matrix per pixel below which the image
            does not pin the point down (a flat or edge-only window): the descriptors' answer stands.
        coarse_eps: the stop tolerance of the descriptor levels before the step (the LM solver's ``eps``):
            they need only bring the point within the step's reach.
        checks: the reverse checks end with the step too, so that a track is judged at the optimum it was
            placed at (off: a point the image moved from the descriptors' optimum may fail its descriptor
            check; on costs more CPU per frame, docs/design.md).

    Raises:
        CoreError: a value out of range (named in the message).
    """

    window: int = 15
    iterations: int = 2
    max_shift: float = 2.0
    max_residual: float = 0.2
    min_eigen: float = 1e-5
    coarse_eps: float = 0.2
    checks: bool = False

    def __post_init__(self) -> None:
        if self.window < 3 or self.window % 2 == 0:
            raise CoreError(f"IntensityRefinement.window must be odd and >= 3, got {self.window}")
        if self.iterations < 1:
            raise CoreError(f"IntensityRefinement.iterations must be >= 1, got {self.iterations}")
        for name in ("max_shift", "max_residual", "coarse_eps"):
            if not getattr(self, name) > 0:
                raise CoreError(f"IntensityRefinement.{name} must be > 0, got {getattr(self, name)}")
        if not self.min_eigen >= 0:
            raise CoreError(f"IntensityRefinement.min_eigen must be >= 0, got {self.min_eigen}")


@dataclass(frozen=True)
class RefineResult:
    """Output of :func:`refine`.

    Attributes:
        positions: (N, 2) the refined positions where ``kept``, else the given ones.
        kept: (N,) where the intensity step replaced the descriptor solution.
        hessian: (N, 3) the template's gradient matrix [h11, h12, h22] (zero-mean, per window).
        cost: (N,) half the residual energy at the last iterate, after gain and offset.
        contrast: (N,) the template's energy about its mean.
    """

    positions: np.ndarray
    kept: np.ndarray
    hessian: np.ndarray
    cost: np.ndarray
    contrast: np.ndarray


def gray_level(gray: np.ndarray) -> tuple[np.ndarray, ...]:
    """A uint8 gray image as the one-chunk pyramid level the intensity step samples: (H, W, 1) float32 in
    [0, 1]."""
    if gray.ndim != 2 or gray.dtype != np.uint8:
        raise CoreError(f"the intensity step needs a (H, W) uint8 gray image, got {gray.dtype} {gray.shape}")
    return ((gray.astype(np.float32) * np.float32(1.0 / 255.0))[..., None],)


@dataclass(frozen=True)
class StepTemplate:
    """Frame 1's side of the step at given points, from :func:`step_template`: all a refinement needs of
    the template, so that it can be read once and used by several refinements from the same image.

    Attributes:
        points: (M, 2) the points it was read at.
        centres: (M, 2) the windows' centres (moved inward near the border).
        rows: (M, 3, w^2) float32 the zero-mean template and its zero-mean Scharr gradients (/32):
            [t, gx, gy].
        gram: (M, 3, 3) float64 the rows against each other.
    """

    points: np.ndarray
    centres: np.ndarray
    rows: np.ndarray
    gram: np.ndarray

    def __getitem__(self, sel: np.ndarray) -> StepTemplate:
        return StepTemplate(self.points[sel], self.centres[sel], self.rows[sel], self.gram[sel])


def step_template(image1: tuple[np.ndarray, ...], pts: np.ndarray, window: int) -> StepTemplate:
    """Read the step's template at ``pts`` in ``image1`` (a :func:`gray_level`); each point's rows depend on
    that point only, so a subset of the result is the template of the subset.

    Shape:
        pts: (M, 2).
    """
    h, w = image1[0].shape[:2]
    # A translation moves the whole window alike: near the border it is moved inward, so that it compares
    # image pixels rather than replicated ones.
    centres = window_centres(pts, (h, w), window)
    m, size = len(centres), window + 2
    # The patches side by side in one row, as the sampler lays them out: each inner pixel's 3x3
    # neighbourhood stays inside its own patch, and one wide filter call is faster than one per patch.
    patches = _sample_level(image1, centres, size)[0][..., 0]  # (size, M, size)
    wide = patches.reshape(size, m * size)
    grads = [cv2.Scharr(wide, cv2.CV_32F, dx, 1 - dx, scale=1.0 / 32.0).reshape(size, m, size)
             for dx in (1, 0)]
    # Each of [t, gx, gy] copied straight into its (M, w, w) place: a stack and one transposed copy of
    # the three moves rows of w floats in six times the time.
    rows = np.empty((m, 3, window, window), np.float32)
    for k, plane in enumerate((patches, *grads)):
        rows[:, k] = plane[1:-1, :, 1:-1].transpose(1, 0, 2)
    rows = rows.reshape(m, 3, window * window)
    rows -= rows.mean(axis=2, keepdims=True)  # a contiguous last axis: a fast mean
    # float32 products (225 terms of order 1e-2 each), float64 from here on
    gram = np.matmul(rows, rows.transpose(0, 2, 1)).astype(np.float64)  # [t, gx, gy] against each other
    return StepTemplate(np.array(pts, dtype=np.float64, copy=True), centres, rows, gram)


def refine(
    image1: tuple[np.ndarray, ...],
    image2: tuple[np.ndarray, ...],
    pts: np.ndarray,
    positions: np.ndarray,
    status: np.ndarray,
    config: IntensityRefinement,
    template: StepTemplate | None = None,
) -> RefineResult:
    """Refine tracked positions on the images: Gauss-Newton on intensity from each descriptor solution.

    The residual is g (w - mean w) - (t - mean t) per window, g the ratio of the template's spread to the
    candidate's, with the sign of their correlation (clipped to [1/4, 4]); J is the template's gradient, so
    J^T J is formed once (as OpenCV's LK does) and an iteration costs one sampling of the candidate windows.
    The least-squares gain would be pulled below 1 by the candidate's own noise, and g - 1 times the
    window's own gradient term moves a point the same way in every frame: tracks of a camera standing still
    drifted 2-3x as far as OpenCV's LK (docs/design.md). The spread ratio has the noise of both windows
    alike and so no such pull.

    Args:
        image1, image2: the frames' gray levels from :func:`gray_level`.
        pts: the points in frame 1.
        positions: their descriptor solutions in frame 2.
        status: where the descriptor solve succeeded (only those are refined).
        config: the step's settings.
        template: :func:`step_template` of ``image1`` at ``pts`` in ``config.window``; None = read here.

    Returns:
        the refined positions, where the step was kept, and its J^T J, cost and contrast for a covariance.

    Shape:
        pts, positions: (N, 2). status: (N,).
    """
    n, win = len(pts), config.window
    out = RefineResult(positions.copy(), np.zeros(n, bool), np.zeros((n, 3)), np.zeros(n), np.zeros(n))
    idx = np.flatnonzero(status)
    if idx.size == 0:
        return out
    h, w = image1[0].shape[:2]
    p = pts[idx]
    tmpl = step_template(image1, p, win) if template is None else template[idx]
    centres, rows, gram = tmpl.centres, tmpl.rows, tmpl.gram
    flow = positions[idx] - p
    cols = rows.transpose(0, 2, 1)
    contrast, (sxx, sxy, syy) = gram[:, 0, 0], (gram[:, 1, 1], gram[:, 1, 2], gram[:, 2, 2])
    det = sxx * syy - sxy * sxy
    cost = np.zeros(len(idx))
    npix = float(win * win)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = np.where(det > 0, 1.0 / det, 0.0)
        for _ in range(config.iterations):
            cand = sample_windows(image2, centres + flow, win).reshape(len(idx), 1, win * win)
            # The columns are zero-mean, so the candidate needs no centring against them; its own energy
            # about its mean comes from its sum and its sum of squares.
            dots = np.matmul(cand, cols)[:, 0].astype(np.float64)  # [c.t, c.gx, c.gy]
            csum = cand.sum(axis=2)[:, 0].astype(np.float64)
            cc = np.einsum("mip,mip->m", cand, cand).astype(np.float64) - csum * csum / npix
            gain = np.copysign(np.sqrt(contrast / cc), dots[:, 0])
            gain = np.clip(np.where(np.isfinite(gain), gain, 1.0), _GAIN_LO, _GAIN_HI)  # a flat window: 1
            # r = g (c - mean c) - t: its energy and J^T r (J = the template's gradient) from the dots.
            cost = 0.5 * np.maximum(gain * gain * cc - 2.0 * gain * dots[:, 0] + contrast, 0.0)
            bx = gain * dots[:, 1] - gram[:, 0, 1]
            by = gain * dots[:, 2] - gram[:, 0, 2]
            flow[:, 0] -= (syy * bx - sxy * by) * inv
            flow[:, 1] -= (sxx * by - sxy * bx) * inv
        ratio = np.where(contrast > 0, 2.0 * cost / contrast, np.inf)
    new = p + flow
    min_eig = 0.5 * (sxx + syy - np.sqrt((sxx - syy) ** 2 + 4.0 * sxy * sxy))
    inside = (new[:, 0] >= 0) & (new[:, 0] <= w - 1) & (new[:, 1] >= 0) & (new[:, 1] <= h - 1)
    kept = (np.isfinite(new).all(axis=1) & inside & (min_eig / (win * win) >= config.min_eigen)
            & (np.hypot(*(new - positions[idx]).T) < config.max_shift) & (ratio <= config.max_residual))
    out.positions[idx[kept]] = new[kept]
    out.kept[idx] = kept
    out.hessian[idx] = np.stack([sxx, sxy, syy], axis=1)
    out.cost[idx], out.contrast[idx] = cost, contrast
    return out
