"""The last sub-pixel step on the image itself: affine-photometric Lucas-Kanade after the descriptor solve.

The learned map is robust to light but blurrier than the image, so its solution is less precise than
intensity's where the light is steady (docs/design.md). One short LM solve on the full-resolution gray
image, started at the descriptor solution and comparing windows up to a gain and an offset (the solver's
``zero_mean`` and ``gain`` residual), recovers intensity's precision; it is kept only where it stays close
to the descriptor solution and its own residual says the windows match, so under a lighting change the
descriptors' answer stands.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, replace

import cv2
import numpy as np

from nsflow_ros.core.errors import CoreError

# The gain's clip is the descriptor solver's bias-and-gain residual's, so both steps accept the same lights.
from nsflow_ros.core.solver import (
    _GAIN_HI,
    _GAIN_LO,
    _REMAP_MAX_COLS,
    _sample_level,
    _window_offsets,
    sample_windows,
    window_centres,
)

__all__ = [
    "IntensityRefinement",
    "RefineResult",
    "StepTemplate",
    "blurred_level",
    "gray_level",
    "refine",
    "step_template",
]


@dataclass(frozen=True)
class IntensityRefinement:
    """Settings of the intensity step.

    Attributes:
        window: window side (odd, px) of the intensity solve.
        iterations: Gauss-Newton iterations (the start is within a pixel or two).
        max_shift: the step is kept only when it moves the point less than this (px): a larger move is
            the image disagreeing with the descriptors, not a refinement. A stereo match's limit.
        temporal_max_shift: ``max_shift`` of a temporal solve (previous frame to this one), whose
            quarter-resolution start may be 2-4 px off where the step still converges: kept there, the
            step's answer was as precise as the descriptors' remaining levels (docs/design.md).
        retrack_refused: a temporal point the step refuses is solved on the descriptors' remaining
            levels (True) instead of ending its track there (False; the detector fills its place). Those
            points, 2-5 % a frame, track several times worse than the rest, and their solve costs a fixed
            price per frame whatever their number (docs/design.md). A stereo match the step refuses always
            gets the descriptors' levels: ending those lost 7 % of the matches.
        max_residual: the step is kept only when its residual ratio (the residual's energy over the
            template's contrast, after gain and offset) is below this: above it the light changed inside
            the window in a way a gain and an offset do not explain.
        residual_floor: ``max_residual`` is raised to this many times the median ratio of the solve's
            points, up to ``residual_ceiling``: sensor noise raises every window's ratio alike (in the
            ``dark`` perturbation the median is 11x the clean one), and within 5x of it the step was as
            precise as the descriptors' remaining levels; 0 = ``max_residual`` alone. The tracker
            applies it to temporal solves only, whose refused points would end (a stereo match gets the
            descriptors' levels, more precise there).
        residual_ceiling: the most the floor raises the limit to, so that windows of other content
            (ratio about 1) are refused even where every window is.
        noisy_blur: the Gaussian blur (sigma, px) of both images of every step while the stream is noisy
            (its temporal step's median residual ratio over ``noisy_ratio``); 0 = none. Sensor noise then
            makes gross errors, which cost the estimator more than the blur's loss of median precision
            (docs/design.md).
        noisy_blur_ratio: what the blur does to a step's residual ratio (0.30-0.35 at sigma 0.7, clean and
            ``dark`` sequences alike): a blurred step's ratio is divided by it, so that the stream's noise
            reads in the plain images' units whichever images its last step compared.
        noisy_window: the window side (odd, >= ``window``) of the stereo step while the stream is noisy
            (more pixels average the noise; ``window`` = the same as in clean images: with the blur the
            estimator did better, docs/design.md).
        noisy_temporal: the temporal step takes ``noisy_window`` too.
        noisy_ratio: the median residual ratio of a temporal step above which the stream is noisy (per
            frame under the affine step: clean images and the light perturbations 0.003-0.012, the
            ``dark`` perturbation 0.03-0.10); once noisy it stays so while above half of this, so that a
            dark stream's frames near the limit do not switch the images back and forth; inf = never.
        min_eigen: the smallest eigenvalue of the window's gradient matrix per pixel below which the image
            does not pin the point down (a flat or edge-only window): the descriptors' answer stands.
        coarse_eps: the stop tolerance of the descriptor levels before the step (the LM solver's ``eps``):
            they need only bring the point within the step's reach.
        checks: the reverse checks end with the step too, so that a track is judged at the optimum it was
            placed at (off: a point the image moved from the descriptors' optimum may fail its descriptor
            check; on costs more CPU per frame, docs/design.md).
        affine: the window's warp is affine, not a translation. A translation fitted to a window that
            turns or scales is pulled toward where the window's texture lies, by the same amount in every
            frame while the camera keeps turning, so a track drifts from its point over its life
            (docs/design.md); the affine warp measures the turn and the scale and leaves the point alone.
        from_level: the descriptor pyramid's level the step starts from (without the IMU's prediction):
            2 leaves the step a quarter-resolution answer, within its two iterations' reach, and saves the
            descriptors' half-resolution level (the scenes grids measured 2; 1 is as fast and a little
            more precise per frame, docs/design.md).

    Raises:
        CoreError: a value out of range (named in the message).
    """

    window: int = 15
    noisy_blur: float = 0.7
    noisy_blur_ratio: float = 0.33
    noisy_window: int = 15
    noisy_ratio: float = 0.05
    noisy_temporal: bool = False
    iterations: int = 2
    max_shift: float = 2.0
    temporal_max_shift: float = 4.0
    retrack_refused: bool = False
    max_residual: float = 0.2
    residual_floor: float = 5.0
    residual_ceiling: float = 0.4
    min_eigen: float = 1e-5
    coarse_eps: float = 0.2
    checks: bool = False
    affine: bool = True
    from_level: int = 2

    def __post_init__(self) -> None:
        if self.window < 3 or self.window % 2 == 0:
            raise CoreError(f"IntensityRefinement.window must be odd and >= 3, got {self.window}")
        if self.noisy_window < self.window or self.noisy_window % 2 == 0:
            raise CoreError(f"IntensityRefinement.noisy_window must be odd and >= window ({self.window}), "
                            f"got {self.noisy_window}")
        if not self.noisy_ratio > 0:
            raise CoreError(f"IntensityRefinement.noisy_ratio must be > 0, got {self.noisy_ratio}")
        if not self.noisy_blur >= 0:
            raise CoreError(f"IntensityRefinement.noisy_blur must be >= 0, got {self.noisy_blur}")
        if not 0 < self.noisy_blur_ratio <= 1:
            raise CoreError(f"IntensityRefinement.noisy_blur_ratio must be in (0, 1], "
                            f"got {self.noisy_blur_ratio}")
        if self.iterations < 1:
            raise CoreError(f"IntensityRefinement.iterations must be >= 1, got {self.iterations}")
        if self.from_level < 1:
            raise CoreError(f"IntensityRefinement.from_level must be >= 1, got {self.from_level}")
        for name in ("max_shift", "temporal_max_shift", "max_residual", "coarse_eps"):
            if not getattr(self, name) > 0:
                raise CoreError(f"IntensityRefinement.{name} must be > 0, got {getattr(self, name)}")
        if not self.residual_floor >= 0:
            raise CoreError(f"IntensityRefinement.residual_floor must be >= 0, got {self.residual_floor}")
        if not self.residual_ceiling >= self.max_residual:
            raise CoreError(f"IntensityRefinement.residual_ceiling must be >= max_residual "
                            f"({self.max_residual}), got {self.residual_ceiling}")
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
        median_ratio: the median residual ratio (2 cost / contrast) of the refined points: the images'
            noise, which the noise floor and the next steps' window go by; nan where none was refined.
    """

    positions: np.ndarray
    kept: np.ndarray
    hessian: np.ndarray
    cost: np.ndarray
    contrast: np.ndarray
    median_ratio: float = float("nan")


def gray_level(gray: np.ndarray) -> tuple[np.ndarray, ...]:
    """A uint8 gray image as the one-chunk pyramid level the intensity step samples: (H, W, 1) float32 in
    [0, 1]."""
    if gray.ndim != 2 or gray.dtype != np.uint8:
        raise CoreError(f"the intensity step needs a (H, W) uint8 gray image, got {gray.dtype} {gray.shape}")
    return ((gray.astype(np.float32) * np.float32(1.0 / 255.0))[..., None],)


def blurred_level(level: tuple[np.ndarray, ...], sigma: float) -> tuple[np.ndarray, ...]:
    """A :func:`gray_level` under a Gaussian blur of ``sigma`` px (OpenCV's, borders reflected)."""
    return (cv2.GaussianBlur(level[0][..., 0], (0, 0), sigma)[..., None],)


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
        system: for the affine warp, its six steepest-descent rows' means (M, 6) and the inverse of their
            J^T J with the ridge (M, 6, 6), float64; None for a translation step.
    """

    points: np.ndarray
    centres: np.ndarray
    rows: np.ndarray
    gram: np.ndarray
    system: tuple[np.ndarray, np.ndarray] | None = None

    def __getitem__(self, sel: np.ndarray) -> StepTemplate:
        system = None if self.system is None else (self.system[0][sel], self.system[1][sel])
        return StepTemplate(self.points[sel], self.centres[sel], self.rows[sel], self.gram[sel], system)


def step_template(
    image1: tuple[np.ndarray, ...], pts: np.ndarray, window: int, affine: bool = True
) -> StepTemplate:
    """Read the step's template at ``pts`` in ``image1`` (a :func:`gray_level`); each point's rows depend on
    that point only, so a subset of the result is the template of the subset (its window sums to float32
    rounding: a BLAS product's rounding may depend on how many rows it multiplies). With ``affine`` it
    carries the affine warp's normal equations, formed once for every refinement from it (a stereo
    solve's and the next frame's temporal one).

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
    prods, sums = _row_products(rows, window)
    gram = sums[:, _SYM3, 0]  # [t, gx, gy] against each other
    points = np.array(pts, dtype=np.float64, copy=True)
    system = _affine_system(rows, prods, sums, points, centres, window) if affine else None
    return StepTemplate(points, centres, rows, gram, system)


def _warped_windows(image: np.ndarray, centres: np.ndarray, affine: np.ndarray, window: int) -> np.ndarray:
    """Bilinear samples of ``image`` at each centre + A (x, y) over the window's offsets (x, y), replicated
    beyond the border.

    Shape:
        image: (H, W) float32. centres: (M, 2). affine: (M, 2, 2). Returns (M, window^2) float32.
    """
    m = centres.shape[0]
    off = _window_offsets(window)
    # rows y, points, columns x: one remap call for all windows side by side (its column limit in blocks)
    a = affine.astype(np.float32)
    c = centres.astype(np.float32)
    mapx = (c[:, 0, None] + a[:, 0, 0, None] * off)[None] + (a[:, 0, 1, None] * off[:, None, None])
    mapy = (c[:, 1, None] + a[:, 1, 0, None] * off)[None] + (a[:, 1, 1, None] * off[:, None, None])
    mapx, mapy = mapx.reshape(window, m * window), mapy.reshape(window, m * window)
    step = (_REMAP_MAX_COLS // window) * window
    parts = [cv2.remap(image, mapx[:, i:i + step], mapy[:, i:i + step], cv2.INTER_LINEAR,
                       borderMode=cv2.BORDER_REPLICATE) for i in range(0, m * window, step)]
    out = parts[0] if len(parts) == 1 else np.concatenate(parts, axis=1)
    return out.reshape(window, m, window).transpose(1, 0, 2).reshape(m, window * window)


# The ridge on the deformation terms, per unit of the window's gradient energy (J^T J of the translation
# is about 1/19 of the deformation terms' in a 15 px window): a prior that a window turns and scales little
# between two frames. On the sample's image with sensor noise it takes a pure shift's p90 error from 0.106
# to 0.092 px and keeps a 1.5 degree, 2 % turn-and-scale at 0.05 px in the median (docs/design.md).
_RIDGE = 3.0
# The affine warp's steepest-descent rows are each image gradient times one of (x, y, 1): row k is
# gradient _GRAD[k] (0: x, 1: y) times coordinate _COORD[k] (0: 1, 1: x, 2: y), in the order of the
# parameters [A11 - 1, A12, A21, A22 - 1, tx, ty].
_GRAD = np.array([0, 0, 1, 1, 0, 1])
_COORD = np.array([1, 2, 1, 2, 0, 0])
# A product of two rows is gradient pair _PAIR (0: xx, 1: xy, 2: yy) times a coordinate monomial (index
# into 1, x, y, x^2, xy, y^2).
# Where entry (i, j) of a symmetric 3x3 matrix is among its six upper-triangle entries, row by row
# (np.triu_indices(3) order).
_SYM3 = np.array([[0, 1, 2], [1, 3, 4], [2, 4, 5]])
_PAIR = _GRAD[:, None] + _GRAD[None, :]
_MONO = _SYM3[_COORD[:, None], _COORD[None, :]]
# The template's six products of its rows [t, gx, gy]: row _ROW_I[k] times row _ROW_J[k] (tt, t gx, t gy,
# gx gx, gx gy, gy gy); entry (i, j) of their gram is product _SYM3[i, j].
_ROW_I, _ROW_J = np.triu_indices(3)


@functools.cache
def _monomials(window: int) -> tuple[np.ndarray, np.ndarray]:
    """The (window^2, 3) float32 monomials [1, x, y] and [x^2, xy, y^2] of each window pixel's offset,
    row-major (two products of three columns each: one of six is above OpenBLAS's threading threshold,
    and its threads cost far more than the product on a busy machine)."""
    off = _window_offsets(window)
    x, y = np.tile(off, window), np.repeat(off, window)
    return (np.stack([np.ones_like(x), x, y], axis=1).astype(np.float32),
            np.stack([x * x, x * y, y * y], axis=1).astype(np.float32))


def _row_products(rows: np.ndarray, window: int) -> tuple[np.ndarray, np.ndarray]:
    """The template rows' six products pixel by pixel (6, M, w^2) float32 (``_ROW_I`` x ``_ROW_J``) and their
    sums against (1, x, y) (M, 6, 3) float64: the gram is the sums' first column, the affine system needs
    the rest (float32 products of 225 terms of order 1e-2 each, float64 from here on).

    Shape:
        rows: (M, 3, w^2) [t, gx, gy].
    """
    m = rows.shape[0]
    prods = np.empty((6, m, window * window), np.float32)
    for k, (i, j) in enumerate(zip(_ROW_I, _ROW_J, strict=True)):
        np.multiply(rows[:, i], rows[:, j], out=prods[k])
    # two products of 3 M rows, each below OpenBLAS's threading threshold (see _monomials)
    mono3 = _monomials(window)[0]
    sums = np.concatenate([prods[:3].reshape(3 * m, -1) @ mono3, prods[3:].reshape(3 * m, -1) @ mono3])
    return prods, sums.reshape(6, m, 3).transpose(1, 0, 2).astype(np.float64)


def _affine_system(
    rows: np.ndarray, prods: np.ndarray, sums: np.ndarray, points: np.ndarray, centres: np.ndarray,
    window: int,
) -> tuple[np.ndarray, np.ndarray]:
    """The affine warp's steepest-descent rows' means (M, 6) and the inverse of their J^T J about those
    means, with the ridge (M, 6, 6): from :func:`_row_products` of the template ``rows``, the gradient
    pairs also against (x^2, xy, y^2) here, two small matrix products, without forming the rows."""
    m, npix = rows.shape[0], float(window * window)
    mono3, mono_hi = _monomials(window)
    hi = (prods[3:].reshape(3 * m, -1) @ mono_hi).reshape(3, m, 3).transpose(1, 0, 2).astype(np.float64)
    second = np.concatenate([sums[:, 3:], hi], axis=2)  # (M, 3 gradient pairs, 6 monomials)
    first = (rows[:, 1:].reshape(2 * m, -1) @ mono3).reshape(m, 2, 3).astype(np.float64)
    mean = first[:, _GRAD, _COORD] / npix  # (M, 6) each row's mean
    hess = second[:, _PAIR, _MONO] - npix * mean[:, :, None] * mean[:, None, :]
    # The ridge also keeps a window with structure in one direction only solvable: its translation is
    # what the point needs.
    ridge = _RIDGE * (sums[:, 3, 0] + sums[:, 5, 0])  # gx gx + gy gy
    # A window moved inward at the border may reach past it in frame 2, where replicated rows would read
    # as a deformation that its point, off the window's centre, then follows: it stays a translation.
    ridge[(points != centres).any(axis=1)] *= 1e9
    hess[:, range(4), range(4)] += ridge[:, None]
    hess[:, range(6), range(6)] += 1e-12  # a flat window: solvable (and then refused by min_eigen)
    return mean, np.linalg.inv(hess)


def _gain_and_cost(contrast: np.ndarray, cc: np.ndarray, ct: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The step's gain (the template's spread over the candidate's, with the sign of their correlation,
    clipped; 1 for a flat window) and the cost 0.5 |g (c - mean c) - t|^2, from the template's energy
    ``contrast``, the candidate's ``cc`` about its mean and their product ``ct``."""
    gain = np.copysign(np.sqrt(contrast / cc), ct)
    gain = np.clip(np.where(np.isfinite(gain), gain, 1.0), _GAIN_LO, _GAIN_HI)
    return gain, 0.5 * np.maximum(gain * gain * cc - 2.0 * gain * ct + contrast, 0.0)


def _refine_affine(
    image2: tuple[np.ndarray, ...], tmpl: StepTemplate, flow: np.ndarray, config: IntensityRefinement
) -> tuple[np.ndarray, np.ndarray]:
    """Inverse-compositional Gauss-Newton on an affine warp of each window, with the gain and offset
    residual of :func:`refine`: (the points' flows, the cost at the last iterate).

    The steepest-descent rows [x gx, y gx, x gy, y gy, gx, gy] are never formed: their J^T J is the
    template's (:func:`_affine_system`, kept with it), and J^T r per iteration comes from the gradients times
    r against (1, x, y), one small matrix product. An iteration samples the warped candidates, solves and
    composes the inverse update.

    Shape:
        flow: (M, 2) the points' starting flows. Returns (M, 2), (M,).
    """
    gray = image2[0][..., 0]
    win = config.window
    rows, gram = tmpl.rows, tmpl.gram
    m, npix = rows.shape[0], float(win * win)
    t, grads = rows[:, 0], rows[:, 1:]  # (M, w^2), (M, 2, w^2) zero-mean
    mono3 = _monomials(win)[0]
    mean, inverse = tmpl.system or _affine_system(rows, *_row_products(rows, win), tmpl.points,
                                                  tmpl.centres, win)
    contrast = gram[:, 0, 0]
    warp = np.broadcast_to(np.eye(2), (m, 2, 2)).copy()
    trans = tmpl.centres + flow  # where each window's centre goes
    cost = np.zeros(m)
    for _ in range(config.iterations):
        cand = _warped_windows(gray, trans, warp, win)
        csum = cand.sum(axis=1, dtype=np.float64)
        cc = np.einsum("mp,mp->m", cand, cand).astype(np.float64) - csum * csum / npix
        ct = np.einsum("mp,mp->m", cand, t).astype(np.float64)
        with np.errstate(divide="ignore", invalid="ignore"):
            gain, cost = _gain_and_cost(contrast, cc, ct)
        r = cand * gain[:, None].astype(np.float32) - t  # r = g c - t; its sum is g sum(c) (t is zero-mean)
        jr = ((grads * r[:, None]).reshape(2 * m, -1) @ mono3).reshape(m, 2, 3).astype(np.float64)
        jtr = jr[:, _GRAD, _COORD] - mean * (gain * csum)[:, None]
        dp = np.matmul(inverse, jtr[..., None])[..., 0]
        # W <- W o dW^-1, dW(x) = (I + D) x + d; (I + D)^-1 in closed form
        a, b, c, d = 1.0 + dp[:, 0], dp[:, 1], dp[:, 2], 1.0 + dp[:, 3]
        undo = np.stack([d, -b, -c, a], axis=1).reshape(m, 2, 2) / (a * d - b * c)[:, None, None]
        warp = np.matmul(warp, undo)
        trans = trans - np.matmul(warp, dp[:, 4:, None])[..., 0]
    # the point sits off its window's centre near the border: it moves with the warp too
    point = trans + np.matmul(warp, (tmpl.points - tmpl.centres)[:, :, None])[..., 0]
    return point - tmpl.points, cost


def _refine_translation(
    image2: tuple[np.ndarray, ...], tmpl: StepTemplate, flow: np.ndarray, config: IntensityRefinement
) -> tuple[np.ndarray, np.ndarray]:
    """Gauss-Newton on a translation of each window with the gain and offset residual of :func:`refine`:
    (the points' flows, the cost at the last iterate). J is the template's gradient, so J^T J is formed
    once (as OpenCV's LK does) and an iteration costs one sampling of the candidate windows.

    Shape:
        flow: (M, 2) the points' starting flows. Returns (M, 2), (M,).
    """
    win, m = config.window, len(flow)
    rows, gram, centres = tmpl.rows, tmpl.gram, tmpl.centres
    cols = rows.transpose(0, 2, 1)
    contrast, (sxx, sxy, syy) = gram[:, 0, 0], (gram[:, 1, 1], gram[:, 1, 2], gram[:, 2, 2])
    det = sxx * syy - sxy * sxy
    inv = np.where(det > 0, 1.0 / np.where(det > 0, det, 1.0), 0.0)
    npix = float(win * win)
    flow = flow.copy()
    cost = np.zeros(m)
    for _ in range(config.iterations):
        cand = sample_windows(image2, centres + flow, win).reshape(m, 1, win * win)
        # The columns are zero-mean, so the candidate needs no centring against them; its own energy
        # about its mean comes from its sum and its sum of squares.
        dots = np.matmul(cand, cols)[:, 0].astype(np.float64)  # [c.t, c.gx, c.gy]
        csum = cand.sum(axis=2)[:, 0].astype(np.float64)
        cc = np.einsum("mip,mip->m", cand, cand).astype(np.float64) - csum * csum / npix
        # r = g (c - mean c) - t: its energy and J^T r (J = the template's gradient) from the dots.
        gain, cost = _gain_and_cost(contrast, cc, dots[:, 0])
        bx = gain * dots[:, 1] - gram[:, 0, 1]
        by = gain * dots[:, 2] - gram[:, 0, 2]
        flow[:, 0] -= (syy * bx - sxy * by) * inv
        flow[:, 1] -= (sxx * by - sxy * bx) * inv
    return flow, cost


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
    candidate's, with the sign of their correlation (clipped to [1/4, 4]); the window's warp is affine
    (``config.affine``, except a window moved inward at the border) or a translation. The least-squares
    gain would be pulled below 1 by the candidate's own noise, and g - 1 times the window's own gradient
    term moves a point the same way in every frame: tracks of a camera standing still drifted 2-3x as far
    as OpenCV's LK (docs/design.md). The spread ratio has the noise of both windows alike and so no such
    pull.

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
    tmpl = step_template(image1, p, win, config.affine) if template is None else template[idx]
    gram = tmpl.gram
    flow = positions[idx] - p
    contrast, (sxx, sxy, syy) = gram[:, 0, 0], (gram[:, 1, 1], gram[:, 1, 2], gram[:, 2, 2])
    with np.errstate(divide="ignore", invalid="ignore"):
        solve = _refine_affine if config.affine else _refine_translation
        flow, cost = solve(image2, tmpl, flow, config)
        ratio = np.where(contrast > 0, 2.0 * cost / contrast, np.inf)
    new = p + flow
    min_eig = 0.5 * (sxx + syy - np.sqrt((sxx - syy) ** 2 + 4.0 * sxy * sxy))
    inside = (new[:, 0] >= 0) & (new[:, 0] <= w - 1) & (new[:, 1] >= 0) & (new[:, 1] <= h - 1)
    finite = ratio[np.isfinite(ratio)]
    median_ratio = float(np.median(finite)) if finite.size else float("nan")
    limit = config.max_residual
    if config.residual_floor > 0 and finite.size:  # the solve's own noise floor
        limit = max(limit, min(config.residual_floor * median_ratio, config.residual_ceiling))
    kept = (np.isfinite(new).all(axis=1) & inside & (min_eig / (win * win) >= config.min_eigen)
            & (np.hypot(*(new - positions[idx]).T) < config.max_shift) & (ratio <= limit))
    out.positions[idx[kept]] = new[kept]
    out.kept[idx] = kept
    out.hessian[idx] = np.stack([sxx, sxy, syy], axis=1)
    out.cost[idx], out.contrast[idx] = cost, contrast
    return replace(out, median_ratio=median_ratio)
