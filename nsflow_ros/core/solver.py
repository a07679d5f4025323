"""The paper's Levenberg-Marquardt Lucas-Kanade solver (Algorithm 1), batched over points, in NumPy.

For each point x with flow u the solver minimises S(u) = 1/2 sum_window ||D2(x + u) - D1(x)||^2 over a
square window and all descriptor channels. One iteration, for every still-active point at once:

1. J and f at u^(k) (J = the x/y derivative maps of D2 sampled at x + u, f = D2(x + u) - D1(x));
2. solve (J^T J + lambda I) du = -J^T f in closed form (2x2 per point);
3. evaluate S at u + du; accept (lambda /= nu) if it dropped, else reject (lambda *= nu);
4. stop when ||du|| < eps (1 + ||u^(k)||) or ||J^T f||_inf < eps, or after K_max iterations.

Sampling is exact bilinear interpolation with replicated borders. Frame-2 quantities at a candidate are
fetched by one ``cv2.remap`` call per 4 descriptor channels over a (window + 2)^2 patch; J is the Scharr
derivative of that patch (equal to sampling the Scharr derivative maps, see :func:`_normal_equations`),
and J^T J, J^T f and S are reduced from it immediately, so nothing window-sized is kept between
iterations.
Points that have stopped leave the active set, so late iterations cost only what is left.

Coarse-to-fine: the solver runs on each pyramid level from the coarsest, scaling the flow by 2 between
levels. A point ends with ``status`` False when its window (in frame 1 at x, or in frame 2 at x + u) is
not inside the full-resolution image, when its window is degenerate (the smallest eigenvalue of J^T J per
window element is below ``min_eigen``: flat or saturated texture), or when the result is not finite.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field

import cv2
import numpy as np

from nsflow_ros.core.errors import CoreError
from nsflow_ros.core.pyramid import DescriptorPyramid, build_pyramid, split_channels

__all__ = ["IterationRecord", "LMConfig", "TrackResult", "sample_windows", "track"]


@dataclass(frozen=True)
class LMConfig:
    """Settings of the LM solver.

    Attributes:
        window: side of the square window in pixels (odd). The paper uses 11.
        levels: pyramid levels (1 = single scale, as in training).
        max_iterations: K_max, the iteration limit per level.
        lambda_init: initial damping lambda^(0), reset at the start of each level.
        nu: factor by which lambda shrinks after an accepted step and grows after a rejected one.
        eps: tolerance of both stop tests, ||du|| < eps (1 + ||u||) and ||J^T f||_inf < eps.
        min_eigen: smallest eigenvalue of J^T J divided by the number of window elements (window^2 * C)
            below which a point's window counts as degenerate (flat, saturated) and its status is False.
            With descriptors in [0, 1] this is a mean squared gradient of 1e-4 per pixel.

    The defaults were chosen by measurement on real-texture pairs with known sub-pixel shifts (150 GFTT
    points, intensity descriptors, 3 levels): nu=10 / eps=1e-2 / lambda_init=1e-2 reach a median error of
    0.026 px in 7 iterations per point, where nu=2 / eps=1e-3 reach 0.024 px in 34 (4x the time).
    K_max = 12 per level (not 30) on the held-out photo pairs at 5 px initial error, 3 levels: the same
    errors for both modes (NSFlow 0.059 / 0.132 px median clean / perturbed, within 1 px 99.5 / 96.4 %),
    while the batched loop, which runs until its slowest point stops, made 35 instead of 69 passes. At one
    level from 5 px, 30 iterations help a little (intensity 0.147 vs 0.172 px median): set it there.
    """

    window: int = 11
    levels: int = 3
    max_iterations: int = 12
    lambda_init: float = 1e-2
    nu: float = 10.0
    eps: float = 1e-2
    min_eigen: float = 1e-4

    def __post_init__(self) -> None:
        if self.window < 3 or self.window % 2 == 0:
            raise CoreError(f"LMConfig.window must be odd and >= 3, got {self.window}")
        if self.levels < 1:
            raise CoreError(f"LMConfig.levels must be >= 1, got {self.levels}")
        if self.max_iterations < 1:
            raise CoreError(f"LMConfig.max_iterations must be >= 1, got {self.max_iterations}")
        if not self.lambda_init > 0:
            raise CoreError(f"LMConfig.lambda_init must be > 0, got {self.lambda_init}")
        if not self.nu > 1:
            raise CoreError(f"LMConfig.nu must be > 1, got {self.nu}")
        if not self.eps > 0:
            raise CoreError(f"LMConfig.eps must be > 0, got {self.eps}")
        if self.min_eigen < 0:
            raise CoreError(f"LMConfig.min_eigen must be >= 0, got {self.min_eigen}")


@dataclass(frozen=True)
class IterationRecord:
    """One LM iteration at one level, for all points (recorded only when asked for).

    Attributes:
        level: pyramid level (0 = full resolution).
        flow: flow of every point after the iteration, in level-0 pixels, shape (N, 2).
        lam: damping after the iteration, shape (N,).
        cost: S after the iteration, shape (N,).
        accepted: whether the iteration's step was accepted, shape (N,).
        active: whether the point took part in the iteration, shape (N,).
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
        flow: estimated flow u, shape (N, 2), float64; the new position is points + flow.
        status: True where the point was tracked, shape (N,).
        cost: final S(u) = 1/2 ||f||^2 at level 0, shape (N,).
        iterations: LM iterations summed over levels, shape (N,).
        history: per-iteration records when ``record=True``, else empty.
    """

    flow: np.ndarray
    status: np.ndarray
    cost: np.ndarray
    iterations: np.ndarray
    history: list[IterationRecord] = field(default_factory=list)


@functools.cache
def _remap_is_exact() -> bool:
    """Whether cv2.remap interpolates float32 images at full precision.

    OpenCV 4.x quantises the sub-pixel position to 1/32 px inside remap; 5.x does not for images of up
    to 4 channels. With a quantising OpenCV the exact NumPy sampler is used instead (slower, same results).
    """
    img = np.tile(np.arange(8, dtype=np.float32), (8, 1))
    mx = np.array([[3.0 + 1.0 / 256.0]], np.float32)
    val = cv2.remap(img, mx, np.full_like(mx, 3.0), cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return abs(float(val[0, 0]) - float(mx[0, 0])) < 1e-5


_REMAP_MAX_ROWS = 32766
_REPLICATE = cv2.BORDER_REPLICATE


def _window_offsets(window: int) -> np.ndarray:
    r = window // 2
    return np.arange(-r, r + 1, dtype=np.float32)


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
    """cv2.remap maps of M square grids of side ``size`` centred on ``centers``, stacked vertically."""
    m = centers.shape[0]
    off = _window_offsets(size)
    c = centers.astype(np.float32)
    mapx = np.empty((m * size, size), np.float32)
    mapy = np.empty((m * size, size), np.float32)
    mapx.reshape(m, size, size)[...] = c[:, 0, None, None] + off[None, None, :]
    mapy.reshape(m, size, size)[...] = c[:, 1, None, None] + off[None, :, None]
    return mapx, mapy


def _sample_chunk(
    chunk: np.ndarray, centers: np.ndarray, size: int, maps: tuple[np.ndarray, np.ndarray] | None
) -> np.ndarray:
    """Windows of side ``size`` of one chunk of at most 4 channels: (M, size, size, K)."""
    m = centers.shape[0]
    if maps is None:
        return _sample_numpy(chunk, centers, size)
    mapx, mapy = maps
    # cv2.remap refuses maps of SHRT_MAX (32767) rows or more: sample many points in blocks.
    step = (_REMAP_MAX_ROWS // size) * size
    parts = [
        cv2.remap(chunk, mapx[i : i + step], mapy[i : i + step], cv2.INTER_LINEAR, borderMode=_REPLICATE)
        for i in range(0, mapx.shape[0], step)
    ]
    out = parts[0] if len(parts) == 1 else np.concatenate(parts, axis=0)
    return out.reshape(m, size, size, chunk.shape[2])


def sample_windows(
    level: np.ndarray | tuple[np.ndarray, ...], centers: np.ndarray, window: int
) -> np.ndarray:
    """Sample square windows of a multi-channel map with exact bilinear interpolation.

    Args:
        level: map to sample, replicated beyond its border: one (H, W, K) array, or a pyramid level's
            tuple of contiguous chunks of at most 4 channels (the fast path).
        centers: window centres (x, y) in pixels of ``level``.
        window: odd window side.

    Returns:
        the windows, rows then columns then channels.

    Shape:
        level: (H, W, K) float32. centers: (M, 2). Returns (M, window, window, K).
    """
    chunks = split_channels(level) if isinstance(level, np.ndarray) else level
    m = centers.shape[0]
    ch = sum(c.shape[2] for c in chunks)
    if m == 0:
        return np.zeros((0, window, window, ch), np.float32)
    maps = _scatter_maps(centers, window) if _remap_is_exact() else None
    parts = [_sample_chunk(chunk, centers, window, maps) for chunk in chunks]
    return parts[0] if len(parts) == 1 else np.concatenate(parts, axis=3)


def _template(level: tuple[np.ndarray, ...], pts: np.ndarray, window: int) -> list[np.ndarray]:
    """Frame-1 descriptor windows D1(x) per chunk, flattened per point: [(N, window^2 * K_chunk)]."""
    n = pts.shape[0]
    maps = _scatter_maps(pts, window) if _remap_is_exact() else None
    return [_sample_chunk(chunk, pts, window, maps).reshape(n, -1) for chunk in level]


_dot = functools.partial(np.einsum, "ij,ij->i")


def _normal_equations(
    level: tuple[np.ndarray, ...],
    centers: np.ndarray,
    template: list[np.ndarray],
    window: int,
    below: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """S, J^T J as (h11, h12, h22) and J^T f per point, with D2 and J sampled at ``centers``.

    J is the normalised Scharr derivative of D2 at x + u. Every pixel of a window shares the centre's
    sub-pixel offset, and filtering commutes with such a shift, so Scharr applied to a bilinearly
    sampled (window + 2)^2 patch equals sampling the Scharr derivative maps (to float rounding) wherever
    the window lies inside the image, border pixels included (remap and the filter both replicate).
    Beyond the image it is the derivative of the replicated map, 0 across the edge; such points end with
    status False anyway. One remap per 4 channels thus gives D2 and J together, and the pyramid needs no
    derivative maps. Sums are additive over channels, so chunks are reduced one at a time.

    With ``below`` (the current costs), J^T J and J^T f are computed only where S < below, i.e. for the
    candidates LM will accept, and left 0 elsewhere: the solver discards them for rejected steps, which
    are about two thirds of all steps with the learned descriptors.
    """
    m = centers.shape[0]
    size = window + 2
    maps = _scatter_maps(centers, size) if _remap_is_exact() else None
    patches = [_sample_chunk(chunk, centers, size, maps) for chunk in level]
    resid = [p[:, 1:-1, 1:-1].reshape(m, -1) - t for p, t in zip(patches, template, strict=True)]
    cost = 0.5 * sum(_dot(f, f).astype(np.float64) for f in resid)
    hess = np.zeros((m, 3))
    grad = np.zeros((m, 2))
    rows = None if below is None else np.flatnonzero(cost < below)
    if rows is not None and rows.size == 0:
        return cost, hess, grad
    h_sub = np.zeros((m if rows is None else rows.size, 3))
    g_sub = np.zeros((h_sub.shape[0], 2))
    for p, f in zip(patches, resid, strict=True):
        if rows is not None:
            p, f = p[rows], f[rows]
        k = p.shape[0]
        # Scharr [-1 0 1] x [3 10 3]; the 1/32 normalisation is applied to the sums below.
        cx = p[:, :, 2:] - p[:, :, :-2]
        jx = (3.0 * (cx[:, :-2] + cx[:, 2:]) + 10.0 * cx[:, 1:-1]).reshape(k, -1)
        cy = p[:, 2:] - p[:, :-2]
        jy = (3.0 * (cy[:, :, :-2] + cy[:, :, 2:]) + 10.0 * cy[:, :, 1:-1]).reshape(k, -1)
        h_sub += np.stack([_dot(jx, jx), _dot(jx, jy), _dot(jy, jy)], axis=1)
        g_sub += np.stack([_dot(jx, f), _dot(jy, f)], axis=1)
    if rows is None:
        return cost, h_sub * (1.0 / 1024.0), g_sub * (1.0 / 32.0)
    hess[rows] = h_sub * (1.0 / 1024.0)
    grad[rows] = g_sub * (1.0 / 32.0)
    return cost, hess, grad


def _solve_level(
    level1: tuple[np.ndarray, ...],
    level2: tuple[np.ndarray, ...],
    pts: np.ndarray,
    u: np.ndarray,
    cfg: LMConfig,
    level_index: int,
    iterations: np.ndarray,
    history: list[IterationRecord] | None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Run Algorithm 1 on one pyramid level for all points; returns (u, cost, [h11, h12, h22])."""
    n = pts.shape[0]
    win = cfg.window
    template = _template(level1, pts, win)
    cost, hess, grad = _normal_equations(level2, pts + u, template, win)
    u = u.copy()
    lam = np.full(n, cfg.lambda_init)
    # Working copies restricted to the still-active points; finished points are written back.
    idx = np.arange(n)
    p_a, u_a, lam_a, t_a = pts, u.copy(), lam.copy(), template
    c_a, h_a, g_a = cost.copy(), hess.copy(), grad.copy()
    scale = 2.0**level_index
    for _ in range(cfg.max_iterations):
        if idx.size == 0:
            break
        # Closed-form solve of the 2x2 system (H + lambda I) du = -J^T f.
        a11 = h_a[:, 0] + lam_a
        a22 = h_a[:, 2] + lam_a
        a12 = h_a[:, 1]
        det = a11 * a22 - a12 * a12
        du = np.empty_like(u_a)
        with np.errstate(divide="ignore", invalid="ignore"):
            du[:, 0] = -(a22 * g_a[:, 0] - a12 * g_a[:, 1]) / det
            du[:, 1] = -(a11 * g_a[:, 1] - a12 * g_a[:, 0]) / det
        du[~np.isfinite(du)] = 0.0
        cand = u_a + du
        c_cost, c_hess, c_grad = _normal_equations(level2, p_a + cand, t_a, win, below=c_a)
        accept = c_cost < c_a
        step_small = np.hypot(du[:, 0], du[:, 1]) < cfg.eps * (1.0 + np.hypot(u_a[:, 0], u_a[:, 1]))
        grad_small = np.abs(g_a).max(axis=1) < cfg.eps
        u_a = np.where(accept[:, None], cand, u_a)
        c_a = np.where(accept, c_cost, c_a)
        h_a = np.where(accept[:, None], c_hess, h_a)
        g_a = np.where(accept[:, None], c_grad, g_a)
        lam_a = np.where(accept, lam_a / cfg.nu, lam_a * cfg.nu)
        iterations[idx] += 1
        stop = step_small | grad_small
        if history is not None:
            u[idx], cost[idx], hess[idx], grad[idx], lam[idx] = u_a, c_a, h_a, g_a, lam_a
            was_active = np.zeros(n, bool)
            was_active[idx] = True
            accepted = np.zeros(n, bool)
            accepted[idx[accept]] = True
            history.append(
                IterationRecord(level_index, u * scale, lam.copy(), cost.copy(), accepted, was_active)
            )
        if stop.any():
            done = idx[stop]
            u[done], cost[done], hess[done] = u_a[stop], c_a[stop], h_a[stop]
            keep = ~stop
            idx, p_a, u_a, lam_a, c_a, h_a, g_a, t_a = (
                idx[keep], p_a[keep], u_a[keep], lam_a[keep], c_a[keep], h_a[keep], g_a[keep],
                [t[keep] for t in t_a],
            )
    u[idx], cost[idx], hess[idx] = u_a, c_a, h_a
    return u, cost, hess


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
) -> TrackResult:
    """Track points from frame 1 to frame 2 with the descriptor LM-LK solver.

    Args:
        desc1: frame-1 descriptor map, or its pyramid from :func:`build_pyramid`.
        desc2: frame-2 descriptor map or pyramid (same size and channels as ``desc1``).
        points: (x, y) pixel positions in frame 1.
        flow0: initial flow (e.g. a prediction); zeros when None.
        config: solver settings; ``LMConfig()`` when None.
        record: keep a per-iteration history (for convergence analysis; costs time).

    Returns:
        a :class:`TrackResult`; points[i] + flow[i] is the position in frame 2 where status[i].

    Raises:
        CoreError: on mismatched maps, a wrong points/flow0 shape, or non-finite input.

    Shape:
        desc1, desc2: (H, W, C) float. points: (N, 2). flow0: (N, 2).
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
    iterations = np.zeros(n, np.int64)
    history: list[IterationRecord] | None = [] if record else None
    if n == 0:
        empty = np.zeros(0)
        return TrackResult(np.zeros((0, 2)), np.zeros(0, bool), empty, iterations, history or [])

    nlev = min(cfg.levels, pyr1.num_levels, pyr2.num_levels)
    ch = pyr1.channels
    u = flow / 2.0 ** (nlev - 1)
    cost = np.zeros(n)
    hess = np.zeros((n, 3))
    for lev in range(nlev - 1, -1, -1):
        s = 2.0**lev
        u, cost, hess = _solve_level(
            pyr1.levels[lev], pyr2.levels[lev], pts / s, u, cfg, lev, iterations, history
        )
        if lev > 0:
            u = u * 2.0
    status = _valid(pts, u, hess, pyr1.shape, ch, cfg)
    return TrackResult(u, status, cost, iterations, history or [])


def _valid(
    pts: np.ndarray, u: np.ndarray, hess: np.ndarray, shape: tuple[int, int], channels: int, cfg: LMConfig
) -> np.ndarray:
    h, w = shape
    r = cfg.window // 2

    def inside(p: np.ndarray) -> np.ndarray:
        return (p[:, 0] >= r) & (p[:, 0] <= w - 1 - r) & (p[:, 1] >= r) & (p[:, 1] <= h - 1 - r)

    new = pts + u
    finite = np.isfinite(new).all(axis=1)
    # Smallest eigenvalue of the symmetric 2x2 J^T J, per window element.
    tr = hess[:, 0] + hess[:, 2]
    diff = hess[:, 0] - hess[:, 2]
    min_eig = 0.5 * (tr - np.sqrt(diff * diff + 4.0 * hess[:, 1] ** 2))
    textured = min_eig / (cfg.window**2 * channels) >= cfg.min_eigen
    return finite & inside(pts) & inside(np.where(finite[:, None], new, -1e9)) & textured
