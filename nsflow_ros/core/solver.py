"""The paper's Levenberg-Marquardt Lucas-Kanade solver (Algorithm 1), batched over points, in NumPy.

For each point x with flow u the solver minimises S(u) = 1/2 sum_window ||D2(x + u) - D1(x)||^2 over a
square window and all descriptor channels, coarse to fine over a pyramid (the flow doubled between
levels). An iteration solves (J^T J + lambda I) du = -J^T f in closed form per point, accepts the step if
S dropped (lambda /= nu) or rejects it (lambda *= nu), and stops a point when ||du|| < eps (1 + ||u||) or
||J^T f||_inf < eps, or after K_max iterations.

Sampling is exact bilinear with replicated borders: one ``cv2.remap`` per chunk of up to 4 channels fetches a
(window + 2)^2 patch per point, all patches side by side in one image, and J is their Scharr derivative,
reduced to J^T J, J^T f and S at once, so nothing window-sized outlives an iteration. A point ends with
``status`` False when its window leaves the image, is degenerate (flat or saturated texture) or its
result is not finite.
"""

from __future__ import annotations

import enum
import functools
from dataclasses import dataclass, field, fields, replace
from typing import Any, ClassVar

import cv2
import numpy as np

from nsflow_ros.core.errors import CoreError
from nsflow_ros.core.pyramid import DescriptorPyramid, build_pyramid, sampling_source, split_channels

__all__ = [
    "IterationRecord", "Jacobian", "LMConfig", "TrackResult", "sample_windows", "track", "window_centres",
]


class Jacobian(enum.Enum):
    """Which derivative the LM step uses for J (the accept test, the stop tests and S are the same).

    * ``FORWARD``: the paper's, the derivative of D2 at x + u.
    * ``ESM``: the mean of that and the template's derivative at x (Benhimane and Malis 2004): far from
      the answer the template's derivative still points the right way, so the basin is wider.
    """

    FORWARD = "forward"
    ESM = "esm"


@dataclass(frozen=True)
class LMConfig:
    """Settings of the LM solver; the defaults are the paper's Algorithm 1 (docs/design.md has the
    measurement behind each departure).

    Attributes:
        window: side of the square window in pixels (odd).
        coarse_window: window side from level ``coarse_from`` up, to see more of the image while the
            flow is still far off; None = ``window`` on every level.
        coarse_from: the first pyramid level (>= 1) that uses ``coarse_window``.
        jacobian: the derivative the step uses.
        levels: pyramid levels (1 = single scale, as in training).
        max_iterations: K_max, the iteration limit per level.
        eps: tolerance of both stop tests.
        min_eigen: smallest eigenvalue of J^T J per window element (window^2 * C) below which a point's
            window is degenerate (status False).
        lambda_scale: tau of the per-point initial damping max(``lambda_init``, tau max(diag J^T J)) at
            each level's start (Madsen, Nielsen and Tingleff), so a rejected step bites at once; 0 =
            ``lambda_init`` for every point.
        margin: how far (px) a point must stay from the image edge in both frames for status True;
            None = half the window.
        tail_share: a level's loop ends once at most this share of its points still iterate after
            ``tail_passes`` passes, so that stragglers do not set its time; 0 = Algorithm 1 as written.
        tail_passes: the passes a level runs before ``tail_share`` may end it.
        zero_mean: compare windows up to a constant per channel, so a lighting change's offset costs
            nothing (not the paper's cost).
        gain: with ``zero_mean``, also compare windows up to a positive gain per channel: each candidate
            window is scaled by its least-squares gain onto the template (clipped to [1/4, 4]) before the
            comparison, so the cost stays in the template's units and a flat candidate gains nothing (bias
            and gain Lucas-Kanade; the step's Jacobian is projected off the gain's direction).
        gain_levels: with ``gain``, how many of the finest levels use it (None = all): the gain's
            residual narrows the basin of a solve from far off, so coarse levels can do without it.

    Class attributes (Algorithm 1's): ``lambda_init``, the initial damping, and ``nu``, lambda's factor.

    Raises:
        CoreError: a value out of range (named in the message).
    """

    lambda_init: ClassVar[float] = 1e-2
    nu: ClassVar[float] = 10.0

    window: int = 11
    coarse_window: int | None = None
    coarse_from: int = 1
    jacobian: Jacobian = Jacobian.FORWARD
    levels: int = 3
    max_iterations: int = 12
    eps: float = 1e-2
    min_eigen: float = 1e-5
    lambda_scale: float = 0.1
    margin: int | None = None
    tail_share: float = 0.0
    tail_passes: int = 3
    zero_mean: bool = False
    gain: bool = False
    gain_levels: int | None = None

    def __post_init__(self) -> None:
        if self.window < 3 or self.window % 2 == 0:
            raise CoreError(f"LMConfig.window must be odd and >= 3, got {self.window}")
        if self.coarse_window is not None and (self.coarse_window < 3 or self.coarse_window % 2 == 0):
            raise CoreError(f"LMConfig.coarse_window must be odd and >= 3 or None, got {self.coarse_window}")
        if self.coarse_from < 1:
            raise CoreError(f"LMConfig.coarse_from must be >= 1, got {self.coarse_from}")
        if not isinstance(self.jacobian, Jacobian):
            raise CoreError(f"LMConfig.jacobian must be a Jacobian, got {self.jacobian!r}")
        if self.levels < 1:
            raise CoreError(f"LMConfig.levels must be >= 1, got {self.levels}")
        if self.max_iterations < 1:
            raise CoreError(f"LMConfig.max_iterations must be >= 1, got {self.max_iterations}")
        if not self.eps > 0:
            raise CoreError(f"LMConfig.eps must be > 0, got {self.eps}")
        if self.min_eigen < 0:
            raise CoreError(f"LMConfig.min_eigen must be >= 0, got {self.min_eigen}")
        if self.lambda_scale < 0:
            raise CoreError(f"LMConfig.lambda_scale must be >= 0, got {self.lambda_scale}")
        if not 0.0 <= self.tail_share < 1.0:
            raise CoreError(f"LMConfig.tail_share must be in [0, 1), got {self.tail_share}")
        if self.tail_passes < 1:
            raise CoreError(f"LMConfig.tail_passes must be >= 1, got {self.tail_passes}")
        if self.margin is not None and self.margin < 0:
            raise CoreError(f"LMConfig.margin must be >= 0 or None, got {self.margin}")
        if not isinstance(self.zero_mean, bool):
            raise CoreError(f"LMConfig.zero_mean must be a bool, got {self.zero_mean!r}")
        if not isinstance(self.gain, bool):
            raise CoreError(f"LMConfig.gain must be a bool, got {self.gain!r}")
        if self.gain and not self.zero_mean:
            raise CoreError("LMConfig.gain needs zero_mean=True (the gain is fitted to centred windows)")
        if self.gain_levels is not None and self.gain_levels < 1:
            raise CoreError(f"LMConfig.gain_levels must be >= 1 or None, got {self.gain_levels}")

    def gain_at(self, level: int) -> bool:
        """Whether the solver uses the bias-and-gain residual on pyramid level ``level``."""
        return self.gain and (self.gain_levels is None or level < self.gain_levels)

    def as_dict(self) -> dict[str, int | float | str | None]:
        """The settings as plain values (the Jacobian by its name), e.g. for a JSON report."""
        return {f.name: getattr(self, f.name) for f in fields(self)} | {"jacobian": self.jacobian.value}

    def window_at(self, level: int) -> int:
        """The window side the solver uses on pyramid level ``level`` (0 = full resolution)."""
        return self.window if level < self.coarse_from or self.coarse_window is None else self.coarse_window

    def at_level(self, level: int) -> LMConfig:
        """The settings of one level's solve on its own: its window as ``window``, no coarse window."""
        return replace(self, window=self.window_at(level), coarse_window=None, coarse_from=1,
                       gain=self.gain_at(level), gain_levels=None)


@dataclass(frozen=True)
class IterationRecord:
    """One LM iteration at one level, for all points (recorded only when asked for).

    Attributes:
        level: pyramid level (0 = full resolution).
        flow: (N, 2) flow of every point after the iteration, in level-0 pixels.
        lam, cost: (N,) damping and S after the iteration.
        accepted: (N,) whether the iteration's step was accepted.
        active: (N,) whether the point took part in the iteration.
    """

    level: int
    flow: np.ndarray
    lam: np.ndarray
    cost: np.ndarray
    accepted: np.ndarray
    active: np.ndarray


@dataclass(frozen=True)
class TrackResult:
    """Output of :func:`track`.

    Attributes:
        flow: (N, 2) float64 flow u; the new position is points + flow.
        status: (N,) True where the point was tracked.
        cost: (N,) final S(u) at level 0.
        iterations: (N,) LM iterations summed over levels.
        contrast: (N,) the level-0 template's squared deviation from its window mean, summed over window
            and channels (2 cost / contrast = 0: a perfect match).
        history: per-iteration records when ``record=True``, else empty.
        hessian: (N, 3) the solver's own level-0 J^T J at the final flow, [h11, h12, h22] (the Gauss-Newton
            matrix the last step used: a per-feature covariance needs no second pass over the window).
    """

    flow: np.ndarray
    status: np.ndarray
    cost: np.ndarray
    iterations: np.ndarray
    contrast: np.ndarray
    history: list[IterationRecord] = field(default_factory=list)
    hessian: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))


@functools.cache
def _remap_is_exact() -> bool:
    """Whether cv2.remap interpolates float32 at full precision (OpenCV 4.x quantises to 1/32 px, 5.x does
    not up to 4 channels); if not, the slower exact NumPy sampler is used."""
    img = np.tile(np.arange(8, dtype=np.float32), (8, 1))
    mx = np.array([[3.0 + 1.0 / 256.0]], np.float32)
    val = cv2.remap(img, mx, np.full_like(mx, 3.0), cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return abs(float(val[0, 0]) - float(mx[0, 0])) < 1e-5


_REMAP_MAX_COLS = 32766
# 1/32 per Scharr factor: J^T J terms take it twice, J^T f once.
_SCHARR_NORM = np.array([1 / 1024, 1 / 1024, 1 / 1024, 1 / 32, 1 / 32])
# ESM sums two unnormalised Scharr derivatives: half of each, 1/64 per factor.
_ESM_NORM = _SCHARR_NORM * np.array([1 / 4, 1 / 4, 1 / 4, 1 / 2, 1 / 2])
_REPLICATE = cv2.BORDER_REPLICATE
_LINEAR = cv2.INTER_LINEAR


@functools.cache
def _window_offsets(window: int) -> np.ndarray:
    r = window // 2
    out = np.arange(-r, r + 1, dtype=np.float32)
    out.flags.writeable = False
    return out


def _sample_numpy(level: np.ndarray, centers: np.ndarray, window: int) -> np.ndarray:
    # Exact bilinear sampling: every pixel of one window shares the centre's fractional offset.
    h, w = level.shape[:2]
    r = window // 2
    base = np.floor(centers)
    frac = (centers - base).astype(np.float32)
    ib = base.astype(np.int64)
    off = np.arange(-r, r + 2)
    xs = np.clip(ib[:, 0, None] + off[None, :], 0, w - 1)
    ys = np.clip(ib[:, 1, None] + off[None, :], 0, h - 1)
    patch = level[ys[:, :, None], xs[:, None, :]]  # (M, window+1, window+1, ch)
    a = frac[:, 0, None, None, None]
    b = frac[:, 1, None, None, None]
    horiz = patch[:, :, :-1] + a * (patch[:, :, 1:] - patch[:, :, :-1])
    return horiz[:, :-1] + b * (horiz[:, 1:] - horiz[:, :-1])


def _scatter_maps(centers: np.ndarray, size: int) -> tuple[np.ndarray, np.ndarray]:
    """cv2.remap maps (size, M * size) of M square grids centred on ``centers``, side by side in one row,
    so that one OpenCV filter call differentiates all patches."""
    m = centers.shape[0]
    off = _window_offsets(size)
    c = centers.astype(np.float32)
    mapx = np.empty((size, m * size), np.float32)
    mapy = np.empty((size, m * size), np.float32)
    # Every row of x is the first one, and y is a row offset plus the centres' y: contiguous rows, each
    # written once (a broadcast into the (size, M, size) layout costs as much as the remap itself).
    np.add(c[:, 0, None], off, out=mapx[0].reshape(m, size))
    mapx[1:] = mapx[0]
    np.add(off[:, None], c[:, 1].repeat(size), out=mapy)
    return mapx, mapy


def _sample_chunk(
    chunk: np.ndarray, centers: np.ndarray, size: int, maps: tuple[np.ndarray, np.ndarray] | None
) -> np.ndarray:
    """Windows of side ``size`` of one chunk of at most 4 channels, side by side: (size, M, size, K)."""
    m = centers.shape[0]
    k = chunk.shape[2]
    if maps is None:
        return np.ascontiguousarray(_sample_numpy(chunk, centers, size).transpose(1, 0, 2, 3))
    mapx, mapy = maps
    src = sampling_source(chunk)  # a padded 2-3 channel chunk is sampled as its 4-channel buffer
    # cv2.remap refuses maps of SHRT_MAX (32767) columns or more: sample many points in blocks.
    step = (_REMAP_MAX_COLS // size) * size
    blocks = [slice(i, i + step) for i in range(0, mapx.shape[1], step)]
    parts = [cv2.remap(src, mapx[:, b], mapy[:, b], _LINEAR, borderMode=_REPLICATE) for b in blocks]
    out = parts[0] if len(parts) == 1 else np.concatenate(parts, axis=1)
    if src is not chunk:  # drop the padding (NumPy copies rows of 2 or 3 floats slowly: whole pixels)
        if k == 2:
            out = np.ascontiguousarray(out.view(np.complex64)[..., 0]).view(np.float32)
        else:
            out = cv2.cvtColor(out, cv2.COLOR_BGRA2BGR)
    return out.reshape(size, m, size, k)


def sample_windows(
    level: np.ndarray | tuple[np.ndarray, ...], centers: np.ndarray, window: int
) -> np.ndarray:
    """Sample square windows (rows, columns, channels) of a map, bilinear, replicated beyond its border.

    ``level`` is one (H, W, K) array or a pyramid level's tuple of chunks of at most 4 channels (faster).

    Shape:
        level: (H, W, K) float32. centers: (M, 2). Returns (M, window, window, K).
    """
    chunks = split_channels(level) if isinstance(level, np.ndarray) else level
    m = centers.shape[0]
    ch = sum(c.shape[2] for c in chunks)
    if m == 0:
        return np.zeros((0, window, window, ch), np.float32)
    parts = _sample_level(chunks, centers, window)
    out = parts[0] if len(parts) == 1 else np.concatenate(parts, axis=3)
    return np.ascontiguousarray(out.transpose(1, 0, 2, 3))


def _sample_level(level: tuple[np.ndarray, ...], centers: np.ndarray, size: int) -> list[np.ndarray]:
    """Windows of side ``size`` at ``centers`` per chunk, in the solver's layout: [(size, M, size, K)]."""
    maps = _scatter_maps(centers, size) if _remap_is_exact() else None
    return [_sample_chunk(chunk, centers, size, maps) for chunk in level]


def _take(template: list[np.ndarray], keep: np.ndarray) -> list[np.ndarray]:
    """The templates of the points where ``keep`` is True (np.compress: twice as fast as ``t[:, keep]``)."""
    return [np.compress(keep, t, axis=1) for t in template]


def _scharr_xy(patches: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unnormalised Scharr x / y derivatives of (size, M, size, K) patches, window pixels only."""
    size, k, _, ch = patches.shape
    flat = patches.reshape(size, k * size, ch) if ch > 1 else patches.reshape(size, k * size)
    jx = cv2.Scharr(flat, cv2.CV_32F, 1, 0).reshape(patches.shape)[1:-1, :, 1:-1]
    jy = cv2.Scharr(flat, cv2.CV_32F, 0, 1).reshape(patches.shape)[1:-1, :, 1:-1]
    return jx, jy


def _templates(
    level: tuple[np.ndarray, ...], pts: np.ndarray, window: int, jacobian: Jacobian
) -> tuple[list[np.ndarray], list[np.ndarray] | None]:
    """The frame-1 templates D1(x) per chunk, and for ESM the (window + 2)^2 patches around them.

    Scharr is linear, so ESM's J is the Scharr of the sum of the D2 and D1 patches, halved: one filter pass.
    """
    if jacobian is Jacobian.FORWARD:
        return _sample_level(level, pts, window), None
    patches = _sample_level(level, pts, window + 2)
    return [np.ascontiguousarray(p[1:-1, :, 1:-1]) for p in patches], patches


_SUM = "imjk,imjk->m"  # per point: sum over window rows, columns and channels


def _window_sums(a: np.ndarray) -> np.ndarray:
    """Per point and channel, the window sum of (window, M, window, K) values: (M, K) (rows first: NumPy
    sums strided middle axes slowly)."""
    return np.einsum("mjk->mk", a.sum(axis=0))


@functools.lru_cache(maxsize=8)
def _sum_weights(size: int, channels: int) -> tuple[np.ndarray, np.ndarray]:
    """Row weights (3, size) and column weights (3, size * channels, channels) of :func:`_patch_sums`."""
    inner = np.zeros(size, np.float32)
    inner[1:-1] = 1.0
    smooth = np.convolve(inner, [3.0, 10.0, 3.0], mode="same").astype(np.float32)  # [3 10 3] over the window
    diff = np.zeros(size, np.float32)  # the central difference summed over the window telescopes to the edges
    diff[:2], diff[-2:] = -1.0, 1.0
    eye = np.eye(channels, dtype=np.float32)
    cols = np.stack([np.kron(c[:, None], eye) for c in (inner, diff, smooth)])
    return np.stack([inner, smooth, diff]), cols


def _patch_sums(patches: np.ndarray) -> np.ndarray:
    """Per point and channel, window sums of a (window + 2)^2 patch's inner values and of its unnormalised
    Scharr x / y derivatives, as (3, M, K) [S, Sx, Sy].

    Each sum is a separable weighting of the patch, so two small matrix products give all three without
    computing a derivative.

    Shape:
        patches: (window + 2, M, window + 2, K). Returns (3, M, K).
    """
    size, m, _, k = patches.shape
    rows, cols = _sum_weights(size, k)
    by_rows = (rows @ patches.reshape(size, -1)).reshape(3, m, size * k)
    if m == 1:
        # NumPy multiplies a one-row matrix by another path (vector x matrix) that rounds differently;
        # two rows keep a point's sums independent of its batch, as the rest of the solve is.
        return np.matmul(np.repeat(by_rows, 2, axis=1), cols)[:, :1]
    return np.matmul(by_rows, cols)


def _template_sums(template: list[np.ndarray], template_patch: list[np.ndarray] | None) -> list[np.ndarray]:
    """Per chunk, the template's part of the zero-mean window sums (3, M, K): [-sum t, Jx, Jy sums] (the
    forward J has no template derivative: zeros); :func:`_normal_equations` adds the candidate's."""
    if template_patch is not None:
        out = [_patch_sums(tp) for tp in template_patch]
    else:
        out = [np.zeros((3, t.shape[1], t.shape[3]), t.dtype) for t in template]
        for o, t in zip(out, template, strict=True):
            o[0] = _window_sums(t)
    for o in out:
        o[0] *= -1.0
    return out


# The zero-mean corrections of [h11, h12, h22, g1, g2] are these products of [sum f, sum Jx, sum Jy].
_ZM_A, _ZM_B = np.array([1, 1, 2, 1, 2]), np.array([1, 2, 2, 0, 0])


def _normal_equations(
    level: tuple[np.ndarray, ...],
    centers: np.ndarray,
    template: list[np.ndarray],
    window: int,
    below: np.ndarray | None = None,
    template_patch: list[np.ndarray] | None = None,
    template_sums: list[np.ndarray] | None = None,
) -> np.ndarray:
    """S, J^T J and J^T f per point as (M, 6) columns [S, h11, h12, h22, g1, g2], at ``centers``.

    Every pixel of a window shares the centre's sub-pixel offset, and filtering commutes with such a
    shift, so the Scharr of a bilinearly sampled (window + 2)^2 patch equals sampling the Scharr
    derivative maps wherever the window lies inside the image. ``template_patch`` (ESM) adds the
    template's derivative. With ``below`` (the current costs), J^T J and J^T f are computed only where
    S < below (the candidates LM will accept) and left 0 elsewhere. With ``template_sums`` (zero mean)
    every sum is of window-centred factors, corrected from window sums
    (sum (a - mean a)(b - mean b) = sum ab - sum a sum b / n) instead of centred copies.
    """
    m = centers.shape[0]
    size = window + 2
    patches = _sample_level(level, centers, size)
    resid = [p[1:-1, :, 1:-1] - t for p, t in zip(patches, template, strict=True)]
    count = float(window * window)
    gram = None
    if template_sums is not None:
        # Zero mean: the products of the window sums [f, Jx, Jy] (J unnormalised) per point, summed over
        # channels and divided by the window size, are what centring takes off each sum below. The
        # patch's sums are taken before ESM adds the template patch to it.
        for p, ts in zip(patches, template_sums, strict=True):
            js = _patch_sums(p)
            js += ts
            g = np.einsum("amk,bmk->mab", js, js)  # (M, 3, 3)
            gram = g if gram is None else gram + g
        gram /= count
    sums = np.zeros((m, 6))
    cost = sums[:, 0]
    for f in resid:
        cost += np.einsum(_SUM, f, f)
    if gram is not None:
        cost -= gram[:, 0, 0]
    cost *= 0.5
    rows = None if below is None else np.flatnonzero(cost < below)
    if rows is not None and rows.size == 0:
        return sums
    part = rows is not None and rows.size < m
    terms = np.zeros((rows.size, 5)) if part else sums[:, 1:]
    for c, (p, f) in enumerate(zip(patches, resid, strict=True)):
        if part:
            p, f = np.take(p, rows, axis=1), np.take(f, rows, axis=1)
        if template_patch is not None:  # ESM: differentiate D2 + D1 patches at once (Scharr is linear)
            tp = template_patch[c]
            # p is this call's own sampled (or taken) patch and f is already formed from it: add in place.
            np.add(p, np.take(tp, rows, axis=1) if part else tp, out=p)
        # Unnormalised Scharr ([-3 0 3; -10 0 10; -3 0 3]); the 1/32 is applied to the sums below.
        jx, jy = _scharr_xy(p)
        terms[:, 0] += np.einsum(_SUM, jx, jx)
        terms[:, 1] += np.einsum(_SUM, jx, jy)
        terms[:, 2] += np.einsum(_SUM, jy, jy)
        terms[:, 3] += np.einsum(_SUM, jx, f)
        terms[:, 4] += np.einsum(_SUM, jy, f)
    if gram is not None:
        terms -= (gram[rows] if part else gram)[:, _ZM_A, _ZM_B]
    terms *= _SCHARR_NORM if template_patch is None else _ESM_NORM
    if part:
        sums[rows, 1:] = terms
    return sums


_GAIN_LO, _GAIN_HI = 0.25, 4.0

# The gain's equations from products of rows. Per point and channel, the candidate's rows P = [w, Jx, Jy]
# (its window and unnormalised Scharr derivatives) are multiplied once against themselves and against the
# template's rows [1, t, Jxt, Jyt] (Jt zero for the forward J): Z = P [P; T]^T, 3 x 7. With f = g w - t and
# J = g Jp + Jt, each raw sum the step needs is a polynomial of degree 2 in the gain g of Z's entries and of
# the template's own products, so an iteration costs two small matrix products and a few operations per
# point, whatever the window: a handful of points costs NumPy's per-call price, which is what it saves.
_W, _JX, _JY, _ONE, _T, _JXT, _JYT = range(7)  # Z's columns; its rows are the first three
# The raw sums, in order: sum J (x, y), sum J w (x, y), sum J J (xx, xy, yy), sum J f (x, y), sum f f, sum f.
_SX, _QX, _HXX, _GX, _FF, _SF, _NSUMS = 0, 2, 4, 7, 9, 10, 11


def _gain_coefficients() -> np.ndarray:
    """(21, 3 * 11): Z's entries (row-major) to each raw sum's coefficients of g^0, g^1 and g^2."""
    coef = np.zeros((3, 7, 3, _NSUMS))  # Z row, Z column, power of g, sum
    terms = [  # (sum, power of g, Z row, Z column, factor)
        (_SX, 1, 1, _ONE, 1), (_SX + 1, 1, 2, _ONE, 1),
        (_QX, 1, 0, _JX, 1), (_QX, 0, 0, _JXT, 1), (_QX + 1, 1, 0, _JY, 1), (_QX + 1, 0, 0, _JYT, 1),
        (_HXX, 2, 1, _JX, 1), (_HXX, 1, 1, _JXT, 2),
        (_HXX + 1, 2, 1, _JY, 1), (_HXX + 1, 1, 1, _JYT, 1), (_HXX + 1, 1, 2, _JXT, 1),
        (_HXX + 2, 2, 2, _JY, 1), (_HXX + 2, 1, 2, _JYT, 2),
        (_GX, 2, 1, _W, 1), (_GX, 1, 1, _T, -1), (_GX, 1, 0, _JXT, 1),
        (_GX + 1, 2, 2, _W, 1), (_GX + 1, 1, 2, _T, -1), (_GX + 1, 1, 0, _JYT, 1),
        (_FF, 2, 0, _W, 1), (_FF, 1, 0, _T, -2),
        (_SF, 1, 0, _ONE, 1),
    ]
    for total, power, row, col, factor in terms:
        coef[row, col, power, total] += factor
    coef = coef.reshape(21, 3 * _NSUMS)
    coef.flags.writeable = False
    return coef


_GAIN_COEF = _gain_coefficients()


def _template_part() -> np.ndarray:
    """(16, 11): the template's products [1, t, Jxt, Jyt] x [1, t, Jxt, Jyt] (row-major) to each raw sum's
    part that needs no candidate (its g^0 coefficient)."""
    part = np.zeros((4, 4, _NSUMS))
    terms = [  # (sum, row, column, factor): rows and columns 1, t, Jxt, Jyt
        (_SX, 0, 2, 1), (_SX + 1, 0, 3, 1), (_HXX, 2, 2, 1), (_HXX + 1, 2, 3, 1), (_HXX + 2, 3, 3, 1),
        (_GX, 1, 2, -1), (_GX + 1, 1, 3, -1), (_FF, 1, 1, 1), (_SF, 0, 1, -1),
    ]
    for total, row, col, factor in terms:
        part[row, col, total] = factor
    part = part.reshape(16, _NSUMS)
    part.flags.writeable = False
    return part


_TEMPLATE_PART = _template_part()
# The sums' pairs (x, x), (x, y), (y, y) of the Gauss-Newton matrix.
_PAIR_A, _PAIR_B = [0, 0, 1], [0, 1, 1]


@dataclass(frozen=True)
class _GainTemplate:
    """One chunk's template side of :func:`_gain_equations`, read once per level.

    Attributes:
        rows: (M, K, 4, n) float64 [1, t, Jxt, Jyt] per point and channel (n = window^2).
        const: (M, K, 11) the template's own part (g^0) of each raw sum.
        total: (M, K) sum t.
        scale: J's normalisation: 1/64 for ESM (the mean of two Scharr derivatives), 1/32 forward.
    """

    rows: np.ndarray
    const: np.ndarray
    total: np.ndarray
    scale: float

    @functools.cached_property
    def factors(self) -> np.ndarray:
        """What the channel sums of [2 S, J^T J (3), J^T f (2)] are multiplied by: 1/2, J's scale^2, J's."""
        return np.array([0.5] + [self.scale * self.scale] * 3 + [self.scale] * 2)

    def take(self, keep: np.ndarray) -> _GainTemplate:
        """The template of the points where ``keep`` is True."""
        rows, const, total = (np.compress(keep, a, axis=0) for a in (self.rows, self.const, self.total))
        return _GainTemplate(rows, const, total, self.scale)

    def contrast(self, window: int) -> np.ndarray:
        """Per point, the template's squared deviation from its window mean, summed over channels."""
        return (self.const[..., _FF] - self.total * self.total / (window * window)).sum(axis=1)


def _gain_templates(
    template: list[np.ndarray], template_patch: list[np.ndarray] | None
) -> list[_GainTemplate]:
    """Per chunk, the :class:`_GainTemplate` of the solver's templates (and ESM patches)."""
    out = []
    for c, t in enumerate(template):
        win, m, _, k = t.shape
        rows = np.zeros((m, k, 4, win, win))
        rows[:, :, 0] = 1.0
        rows[:, :, 1] = t.transpose(1, 3, 0, 2)
        if template_patch is not None:
            jx, jy = _scharr_xy(template_patch[c])
            rows[:, :, 2] = jx.transpose(1, 3, 0, 2)
            rows[:, :, 3] = jy.transpose(1, 3, 0, 2)
        rows = rows.reshape(m, k, 4, win * win)
        tt = rows @ rows.swapaxes(-1, -2)  # [1, t, Jxt, Jyt] against each other
        const = tt.reshape(m, k, 16) @ _TEMPLATE_PART
        scale = 1 / 64 if template_patch is not None else 1 / 32
        out.append(_GainTemplate(rows, const, tt[..., 0, 1], scale))
    return out


def _gain_equations(
    level: tuple[np.ndarray, ...],
    centers: np.ndarray,
    template: list[_GainTemplate],
    window: int,
    below: np.ndarray | None = None,
) -> np.ndarray:
    """:func:`_normal_equations` (``template`` from :func:`_gain_templates`) for the bias and gain residual
    r = g (w - mean w) - (t - mean t) per channel, g the least-squares gain of the candidate window w onto
    the template t (clipped).

    The cost is then min over g of the zero-mean cost, so its gradient is g J_w^T r at the fitted g
    (envelope theorem); where g is not clipped the Gauss-Newton matrix takes J's part along the centred
    window off (Kaufman's variable projection), since the gain re-fits as the window moves. ESM's J is the
    mean of g J_w and the template's J. Every centred sum is taken from raw sums in float64
    (sum (a - mean a)(b - mean b) = sum ab - sum a sum b / n), which the float32 samples' products fit
    exactly, so no centred copy is formed. With ``below``, J^T J and J^T f are left 0 where S >= below.
    """
    m = centers.shape[0]
    n = float(window * window)
    out = np.zeros((m, 6))
    for p, tm in zip(_sample_level(level, centers, window + 2), template, strict=True):
        k = p.shape[3]
        jx, jy = _scharr_xy(p)
        rows = np.empty((m, k, 3, window, window))
        for r, a in enumerate((p[1:-1, :, 1:-1], jx, jy)):
            rows[:, :, r] = a.transpose(1, 3, 0, 2)
        rows = rows.reshape(m, k, 3, -1)
        z = np.concatenate((rows @ rows.swapaxes(-1, -2), rows @ tm.rows.swapaxes(-1, -2)), axis=-1)
        s1 = z[..., 0, _ONE]
        sww = z[..., 0, _W] - s1 * s1 / n
        # g = sum (w - mean w)(t - mean t) / sum (w - mean w)^2; a flat window (0 / 0): 1
        g = np.divide(z[..., 0, _T] - s1 * tm.total / n, sww, out=np.ones_like(sww), where=sww != 0)
        free = (g > _GAIN_LO) & (g < _GAIN_HI) & (sww > 0)
        g = np.minimum(np.maximum(g, _GAIN_LO), _GAIN_HI)
        proj = np.divide(1.0, sww, out=np.zeros_like(sww), where=free)
        poly = (z.reshape(m, k, 21) @ _GAIN_COEF).reshape(m, k, 3, _NSUMS)
        gc = g[..., None]
        raw = tm.const + poly[..., 0, :] + gc * (poly[..., 1, :] + gc * poly[..., 2, :])
        sj, sf = raw[..., _SX : _SX + 2], raw[..., _SF : _SF + 1]
        qj = raw[..., _QX : _QX + 2] - s1[..., None] * sj / n  # sum J (w - mean w)
        hess = (raw[..., _HXX : _HXX + 3] - sj[..., _PAIR_A] * sj[..., _PAIR_B] / n
                - proj[..., None] * qj[..., _PAIR_A] * qj[..., _PAIR_B])
        grad = raw[..., _GX : _GX + 2] - sj * sf / n  # sum J r, r = f - mean f
        cost = raw[..., _FF : _FF + 1] - sf * sf / n  # 2 S
        out += np.concatenate((cost, hess, grad), axis=2).sum(axis=1) * tm.factors
    if below is not None:
        out[~(out[:, 0] < below), 1:] = 0.0
    return out


# Columns of the per-point LM state: flow u, cost S, J^T J (h11, h12, h22), J^T f (g1, g2).
_U, _COST, _HESS, _GRAD, _TERMS = slice(0, 2), 2, slice(3, 6), slice(6, 8), slice(2, 8)


def _solve_level(
    level1: tuple[np.ndarray, ...],
    level2: tuple[np.ndarray, ...],
    pts: np.ndarray,
    u: np.ndarray,
    cfg: LMConfig,
    level_index: int,
    iterations: np.ndarray,
    history: list[IterationRecord] | None,
) -> tuple[np.ndarray, np.ndarray]:
    """Run Algorithm 1 on one pyramid level for all points: the final (N, 8) LM state and each template's
    contrast energy (level 0 only, zeros on coarser levels)."""
    n = pts.shape[0]
    win = cfg.window_at(level_index)
    # The Jacobian kind is settled here, once per level: ESM carries the template's patches.
    template, tpatch = _templates(level1, pts, win, cfg.jacobian)
    contrast = np.zeros(n)
    # The residual is settled here too: the template side each kind of equations reads, how to evaluate
    # them at candidates and how to keep a subset of points.
    if cfg.gain_at(level_index):
        tmpl: Any = _gain_templates(template, tpatch)
        if level_index == 0:  # only level 0's contrast is reported
            contrast = sum(t.contrast(win) for t in tmpl)

        def evaluate(centers: np.ndarray, t: Any, below: np.ndarray | None) -> np.ndarray:
            return _gain_equations(level2, centers, t, win, below)

        def take(t: Any, keep: np.ndarray) -> Any:
            return [c.take(keep) for c in t]
    else:
        tsums = _template_sums(template, tpatch) if cfg.zero_mean else None
        tmpl = (template, tpatch, tsums)
        if level_index == 0:
            # Per channel, sum (t - mean)^2 = sum t^2 - (sum t)^2 / count.
            for c, t in enumerate(template):
                sums = -tsums[c][0] if tsums is not None else _window_sums(t)
                contrast += np.einsum(_SUM, t, t) - np.einsum("mk,mk->m", sums, sums) / (win * win)

        def evaluate(centers: np.ndarray, t: Any, below: np.ndarray | None) -> np.ndarray:
            return _normal_equations(level2, centers, t[0], win, below, t[1], t[2])

        def take(t: Any, keep: np.ndarray) -> Any:
            return tuple(None if part is None else _take(part, keep) for part in t)
    state = np.empty((n, 8))
    state[:, _U] = u
    state[:, _TERMS] = evaluate(pts + u, tmpl, None)
    lam = np.full(n, cfg.lambda_init)
    if cfg.lambda_scale > 0:
        lam = np.maximum(lam, cfg.lambda_scale * np.maximum(state[:, 3], state[:, 5]))
    # Working copies restricted to the still-active points; finished points are written back.
    idx = np.arange(n)
    p_a, s_a, lam_a, t_a = pts, state.copy(), lam.copy(), tmpl
    scale = 2.0**level_index
    passes = 0
    with np.errstate(divide="ignore", invalid="ignore"):
        while passes < cfg.max_iterations and idx.size:
            # The batched pass costs the same fixed price for a handful of points as for all of them.
            if passes >= cfg.tail_passes and idx.size <= cfg.tail_share * n:
                break
            passes += 1
            # Closed-form solve of the 2x2 system (H + lambda I) du = -J^T f (one column per unknown:
            # a handful of points costs NumPy's per-call price, so every operation counts).
            h11, h12, h22, g1, g2 = s_a[:, 3], s_a[:, 4], s_a[:, 5], s_a[:, 6], s_a[:, 7]
            a11 = h11 + lam_a
            a22 = h22 + lam_a
            inv = 1.0 / (a11 * a22 - h12 * h12)
            inv[~np.isfinite(inv)] = 0.0  # a degenerate system takes no step
            du0 = (h12 * g2 - a22 * g1) * inv
            du1 = (h12 * g1 - a11 * g2) * inv
            # The stop tests look at u^(k), its J^T f and the step, all known before the candidate.
            step_small = np.hypot(du0, du1) < cfg.eps * (1.0 + np.hypot(s_a[:, 0], s_a[:, 1]))
            stop = step_small | (np.maximum(np.abs(g1), np.abs(g2)) < cfg.eps)
            # J at a candidate serves the next iteration, and at level 0 the final degeneracy test; on a
            # coarser level a point that stops now never uses it, so only its cost is evaluated.
            below = s_a[:, _COST] if level_index == 0 else np.where(stop, -np.inf, s_a[:, _COST])
            cand = np.empty_like(s_a)
            np.add(s_a[:, 0], du0, out=cand[:, 0])
            np.add(s_a[:, 1], du1, out=cand[:, 1])
            cand[:, _TERMS] = evaluate(p_a + cand[:, _U], t_a, below)
            accept = cand[:, _COST] < s_a[:, _COST]
            s_a = np.where(accept[:, None], cand, s_a)
            lam_a = lam_a * np.where(accept, 1.0 / cfg.nu, cfg.nu)
            if history is not None:
                state[idx], lam[idx] = s_a, lam_a
                was_active = np.zeros(n, bool)
                was_active[idx] = True
                accepted = np.zeros(n, bool)
                accepted[idx[accept]] = True
                flow, cost = state[:, _U] * scale, state[:, _COST].copy()
                history.append(IterationRecord(level_index, flow, lam.copy(), cost, accepted, was_active))
            if stop.any():
                # A point's iteration count is the number of passes it took part in.
                done = idx[stop]
                state[done] = s_a[stop]
                iterations[done] += passes
                keep = ~stop
                idx, p_a, s_a, lam_a, t_a = idx[keep], p_a[keep], s_a[keep], lam_a[keep], take(t_a, keep)
    state[idx] = s_a
    iterations[idx] += passes
    return state, contrast


def window_centres(points: np.ndarray, shape: tuple[int, int], window: int) -> np.ndarray:
    """Where a coarse level's windows go: each point, moved inward until its window fits in the level.

    The flow is a translation, so a window need only move with its point; one reaching past the border
    would compare replicated pixels, and points near it tracked from zero flow go astray. A level smaller
    than the window centres it on the level.

    Args:
        points: positions in the level's pixels.
        shape: the level's (height, width).
        window: the level's window side.

    Shape:
        points: (N, 2). Returns (N, 2).
    """
    h, w = shape
    r = window // 2
    mid = np.array([(w - 1) / 2, (h - 1) / 2])
    return np.clip(points, np.minimum(r, mid), np.maximum(np.array([w - 1 - r, h - 1 - r]), mid))


def _as_pyramid(desc: np.ndarray | DescriptorPyramid, levels: int, name: str) -> DescriptorPyramid:
    if isinstance(desc, DescriptorPyramid):
        return desc
    if not isinstance(desc, np.ndarray):
        kind = type(desc).__name__
        raise CoreError(f"{name} must be an (H, W, C) array or a DescriptorPyramid, got {kind}")
    return build_pyramid(desc, levels)


def track(
    desc1: np.ndarray | DescriptorPyramid,
    desc2: np.ndarray | DescriptorPyramid,
    points: np.ndarray,
    flow0: np.ndarray | None = None,
    config: LMConfig | None = None,
    *,
    record: bool = False,
    first_level: np.ndarray | None = None,
    finest_level: int = 0,
) -> TrackResult:
    """Track points from frame 1 to frame 2 with the descriptor LM-LK solver.

    Args:
        desc1: frame-1 descriptor map, or its pyramid from :func:`build_pyramid`.
        desc2: frame-2 descriptor map or pyramid (same size and channels as ``desc1``).
        points: (x, y) pixel positions in frame 1.
        flow0: initial flow; zeros when None.
        config: solver settings; ``LMConfig()`` when None.
        record: keep a per-iteration history (costs time).
        first_level: per point, the coarsest level it is solved on (a trusted start needs fewer); None =
            all levels. Points share the passes of the levels they have in common.
        finest_level: the last level solved (0 = full resolution); above 0 the result's cost and J^T J
            are that level's (J^T J zero where a point stopped), its contrast is zero and the status tests
            no texture, for a caller that finishes the solve itself.

    Raises:
        CoreError: on mismatched maps, a wrong points/flow0 shape, or non-finite input.

    Shape:
        desc1, desc2: (H, W, C) float. points: (N, 2). flow0: (N, 2). first_level: (N,) int.
    """
    cfg = config or LMConfig()
    pyr1 = _as_pyramid(desc1, cfg.levels, "desc1")
    pyr2 = _as_pyramid(desc2, cfg.levels, "desc2")
    if pyr1.shape != pyr2.shape or pyr1.channels != pyr2.channels:
        raise CoreError(
            f"descriptor maps differ: desc1 {pyr1.shape}x{pyr1.channels}, desc2 {pyr2.shape}x{pyr2.channels}"
        )
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 2:
        raise CoreError(f"points must have shape (N, 2), got {pts.shape}")
    n = pts.shape[0]
    if flow0 is None:
        flow = np.zeros((n, 2))
    else:
        flow = np.asarray(flow0, dtype=np.float64)
        if flow.shape != (n, 2):
            raise CoreError(f"flow0 must have shape ({n}, 2) like points, got {flow.shape}")
    if not (np.isfinite(pts).all() and np.isfinite(flow).all()):
        raise CoreError("points and flow0 must be finite")
    if finest_level < 0:
        raise CoreError(f"finest_level must be >= 0, got {finest_level}")
    iterations = np.zeros(n, np.int64)
    history: list[IterationRecord] | None = [] if record else None
    if n == 0:
        empty = np.zeros(0)
        return TrackResult(np.zeros((0, 2)), np.zeros(0, bool), empty, iterations, empty, history or [])

    nlev = min(cfg.levels, pyr1.num_levels, pyr2.num_levels)
    finest = min(finest_level, nlev - 1)
    if first_level is None:
        first = np.full(n, nlev - 1)
    else:
        first = np.asarray(first_level)
        if first.shape != (n,) or not np.issubdtype(first.dtype, np.integer):
            raise CoreError(f"first_level must be ({n},) integers, got {first.dtype} {first.shape}")
        first = np.minimum(first, nlev - 1)
    first = np.maximum(first, finest)
    # u in level-0 pixels (scaling by powers of two is exact); a point joins at its first level, so
    # coarse passes carry only those that need them.
    u = flow.copy()
    for lev in range(int(first.max(initial=0)), finest - 1, -1):
        s = 2.0**lev
        sel = first >= lev
        part = sel.all()
        p_l = (pts if part else pts[sel]) / s
        if lev:
            p_l = window_centres(p_l, pyr1.levels[lev][0].shape[:2], cfg.window_at(lev))
        u_l = (u if part else u[sel]) / s
        it = iterations if part else np.zeros(int(sel.sum()), np.int64)
        state, contrast = _solve_level(pyr1.levels[lev], pyr2.levels[lev], p_l, u_l, cfg, lev, it, history)
        if part:
            u = state[:, _U] * s
        else:
            u[sel] = state[:, _U] * s
            iterations[sel] += it
    # the finest level holds every point
    # A coarse level skips J^T J for points that stop (their J is never used): no texture test there.
    status = _valid(pts, u, state[:, _HESS] if finest == 0 else None, pyr1.shape, pyr1.channels, cfg)
    return TrackResult(u, status, state[:, _COST], iterations, contrast, history or [], state[:, _HESS])


def _valid(
    pts: np.ndarray, u: np.ndarray, hess: np.ndarray | None, shape: tuple[int, int], channels: int,
    cfg: LMConfig,
) -> np.ndarray:
    h, w = shape
    r = cfg.window // 2 if cfg.margin is None else cfg.margin
    # Both positions inside the margin; a NaN or infinite one fails its comparisons.
    both = np.concatenate((pts, pts + u), axis=1)
    ok = ((both >= r) & (both <= np.array([w - 1 - r, h - 1 - r] * 2))).all(axis=1)
    if hess is None:  # no J^T J to test
        return ok
    # Smallest eigenvalue of the symmetric 2x2 J^T J, per window element.
    tr = hess[:, 0] + hess[:, 2]
    diff = hess[:, 0] - hess[:, 2]
    min_eig = 0.5 * (tr - np.sqrt(diff * diff + 4.0 * hess[:, 1] ** 2))
    return ok & (min_eig / (cfg.window**2 * channels) >= cfg.min_eigen)
