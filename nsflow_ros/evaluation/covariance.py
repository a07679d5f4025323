"""The per-feature covariance: is it calibrated, does it rank bad features, does weighting by it help?

Data with exact ground truth, held out from the calibration's fit: the homography pairs of the held-out photos
(:mod:`~nsflow_ros.evaluation.pairs`, both subsets, every strength level) and consecutive frame pairs of
the sample sequence (seed 0) under every illumination perturbation level. GFTT points of frame 1 are
tracked into frame 2 by each method's forward solve from zero flow (the tracker's solve without a prior)
with its covariance (:meth:`~nsflow_ros.core.methods.TrackingMethod.solve_with_covariance`), and tracked
back by the flow-back check's solve. Against the truth:

* calibration on inliers (error < 2 px): share inside the 68 % / 95 % ellipses (d^2 <= 2.279 / 5.991),
  RMS error over predicted sigma per decile of sigma, Gaussian NLL against the best constant sigma; on all
  the data, and on what the tracker would publish (the method's track check passed), since a check that
  ends the widest tracks leaves a different top decile;
* ranking of all tracked points by sigma (trace of Sigma) and by the signals the tracker already has
  (final cost, minus the Shi-Tomasi minimum eigenvalue, forward-backward distance): AUSE over random's
  (sparsification by mean endpoint error, Ilg et al. 2018) and the AUROC of errors over 1 px;
* use: the relative rotation of each sample-sequence frame pair (5-point RANSAC, then a Sampson
  refinement over its inliers) with isotropic weights against weights from Sigma.

The covariance measured is the one the tracker publishes
(:meth:`~nsflow_ros.core.covariance.CovarianceScale.expected`, with its tail above the check's limit); the
track check reads it without the tail, as the tracker's does.

``python -m nsflow_ros.evaluation.covariance fit [--model M] [--keep-scale]`` fits each method's scale,
variance floor and tail on training data (the training photos' pairs and a sample sequence of another
seed) and writes the model's beside it (:func:`~nsflow_ros.core.covariance.sidecar_path`).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from nsflow_ros.core.covariance import CovarianceScale, sidecar_path
from nsflow_ros.core.errors import CoreError
from nsflow_ros.core.methods import KLTMethod, LMMethod, SolveKind
from nsflow_ros.evaluation.context import EvalContext, new_figure, sample_sequence, save_figure
from nsflow_ros.evaluation.errors import EvaluationError
from nsflow_ros.evaluation.methods import EvalMethod
from nsflow_ros.evaluation.section import HeadlineRow, Section, quick_note

__all__ = [
    "CHI2_68",
    "CHI2_95",
    "FULL",
    "INLIER_PX",
    "KEY",
    "QUICK",
    "CovarianceSetup",
    "Samples",
    "auroc",
    "ause_ratio",
    "calibration",
    "collect",
    "fit_calibration",
    "fit_scale",
    "fit_tail",
    "main",
    "run",
    "weighted_rotation_error",
]

KEY = "covariance"
INLIER_PX = 2.0
"""Calibration is measured on points tracked within this (px) of the truth."""
BAD_PX = 1.0
"""Ranking: an error over this (px) is a bad feature."""
CHI2_68, CHI2_95 = 2.279, 5.991
"""Squared Mahalanobis distance within which 68 % / 95 % of a 2-D Gaussian's mass lies."""
LEVELS = ("none", "small", "large")
TARGETS = {
    "inside_68": (0.60, 0.76), "inside_95": (0.90, 0.98), "decile_ratio": (0.8, 1.25), "nll_gain": 0.15,
    "ause_ratio": 0.5, "auroc": 0.90, "auroc_margin": 0.02,
}
"""The targets the report checks each figure against."""
SIGNALS = ("sigma", "cost", "min_eigen", "fb_distance")
"""Uncertainty signals ranked: the covariance, then the three the tracker already has."""


@dataclass(frozen=True)
class CovarianceSetup:
    """Which data one run uses.

    Attributes:
        photos: photos of the homography pairs.
        pair_size: (width, height) of the pairs.
        pair_levels: strength levels per subset; per_level: pairs per photo and level.
        max_points, min_distance: GFTT keypoints per frame pair.
        sequence_seed: seed of the sample sequence; duration (s, 20 Hz) and scale of its frames.
        stride: every how many frames a frame pair starts.
        seed: seed of the pairs and perturbations.
    """

    photos: tuple[str, ...]
    pair_size: tuple[int, int] = (480, 360)
    pair_levels: int = 5
    per_level: int = 1
    max_points: int = 400
    min_distance: float = 8.0
    sequence_seed: int = 0
    duration: float = 4.0
    scale: float = 0.5
    stride: int = 2
    seed: int = 0


def _heldout() -> tuple[str, ...]:
    from nsflow_ros.data.photos import HELDOUT_IMAGES

    return HELDOUT_IMAGES


def _training() -> tuple[str, ...]:
    from nsflow_ros.data.photos import TRAIN_IMAGES

    return TRAIN_IMAGES


FULL = CovarianceSetup(photos=())  # photos filled in at run time: the held-out ones
QUICK = CovarianceSetup(photos=(), pair_size=(200, 150), pair_levels=2, max_points=80, duration=0.6,
                        scale=0.3, stride=1)
FIT = CovarianceSetup(photos=(), sequence_seed=1, seed=1)
"""The fit's data: the training photos and a sample sequence of another scene (seed 1)."""


@dataclass
class Samples:
    """Per tracked point (status True, truth visible) of one method on one group of frame pairs.

    Attributes:
        error: (N, 2) tracked minus true position (px). cov: (N, 3) [uu, uv, vv] px^2 with the method's
        scale. cost: (N,) final window cost. min_eigen: (N,) Shi-Tomasi minimum eigenvalue at the point.
        fb: (N,) forward-backward distance (px, inf where the check solve lost it).
        published: (N,) what the tracker would publish: the method's track check passed (its covariance
        check, else the 0.5 px flow-back check).
        rotation: per sample-sequence frame pair, (isotropic, weighted) rotation error in degrees.
    """

    error: list[np.ndarray] = field(default_factory=list)
    cov: list[np.ndarray] = field(default_factory=list)
    cost: list[np.ndarray] = field(default_factory=list)
    min_eigen: list[np.ndarray] = field(default_factory=list)
    fb: list[np.ndarray] = field(default_factory=list)
    published: list[np.ndarray] = field(default_factory=list)
    rotation: list[tuple[float, float]] = field(default_factory=list)

    def arrays(self) -> dict[str, np.ndarray]:
        """The per-point lists joined."""
        def cat(x: list[np.ndarray], width: int) -> np.ndarray:
            return np.concatenate(x) if x else np.zeros((0, width) if width else 0)

        return {"error": cat(self.error, 2), "cov": cat(self.cov, 3), "cost": cat(self.cost, 0),
                "min_eigen": cat(self.min_eigen, 0), "fb": cat(self.fb, 0),
                "published": cat(self.published, 0).astype(bool)}


@dataclass(frozen=True)
class _Pair:
    group: str  # "viewpoint 3", "sequence large", ...
    image1: np.ndarray
    image2: np.ndarray
    points: np.ndarray
    truth: np.ndarray  # (N, 2) true position in frame 2
    rotation: np.ndarray | None = None  # sequence pairs: camera-1 -> camera-2 rotation
    camera: Any = None


def _pairs(setup: CovarianceSetup, source: Any) -> Iterator[_Pair]:
    """The homography pairs, then the sequence's frame pairs per perturbation level."""
    from nsflow_ros.data.perturb import IlluminationPerturber
    from nsflow_ros.evaluation import pairs as hp

    cfg = hp.PairSetConfig(width=setup.pair_size[0], height=setup.pair_size[1], photos=setup.photos,
                           levels=setup.pair_levels, per_level=setup.per_level, max_points=setup.max_points,
                           min_distance=setup.min_distance)
    for subset in hp.SUBSETS:
        for p in hp.make_pairs(subset, cfg, setup.seed):
            pts = hp.keypoints(p.image1, cfg.max_points, cfg.min_distance)
            pts, flow = hp.keep_inside(pts, hp.true_flow(pts, p.homography), cfg.width, cfg.height)
            yield _Pair(f"{subset} {p.level}", p.image1, p.image2, pts, pts + flow)
    if source is None:
        return
    from nsflow_ros.core.detector import detect_corners

    w, h = source.size
    for level in LEVELS:
        perturb = IlluminationPerturber(level, seed=setup.seed)
        for i in range(0, len(source) - 1, setup.stride):
            im1 = perturb(source.image(i), source.time(i))
            im2 = perturb(source.image(i + 1), source.time(i + 1))
            pts = detect_corners(im1, setup.max_points, min_distance=setup.min_distance)
            flow, visible = source.flow(i, i + 1, pts)
            truth = pts + flow
            keep = visible & hp.inside(truth, w, h, 10) & hp.inside(pts, w, h, 10)
            yield _Pair(f"sequence {level}", im1, im2, pts[keep], truth[keep],
                        source.relative_rotation(i, i + 1), source.camera)


def _cost_and_cov(method: EvalMethod, f1: Any, f2: Any, pts: np.ndarray) -> tuple[np.ndarray, ...]:
    """The forward solve from zero flow: positions, status, covariance and the final window cost."""
    core = method.core
    if isinstance(core, LMMethod):
        new, status, res = core.solve_result(SolveKind.FORWARD, f1, f2, pts)
        return new, status, core.result_covariance(res, f2), res.cost
    if not isinstance(core, KLTMethod):
        raise EvaluationError(f"{method.name}: no covariance for {type(core).__name__}")
    new, status, cov = core.solve_with_covariance(SolveKind.FORWARD, f1, f2, pts)
    cost = np.zeros(len(pts))
    if status.any():
        cost[status] = _klt_cost(f1, f2, pts[status], new[status], core.window[0])
    return new, status, cov, cost


def _klt_cost(f1: np.ndarray, f2: np.ndarray, pts: np.ndarray, new: np.ndarray, window: int) -> np.ndarray:
    """1/2 the sum of squared window differences at the solution (OpenCV's LK keeps none)."""
    from nsflow_ros.core.solver import sample_windows

    def as_map(img: np.ndarray) -> np.ndarray:
        f = np.asarray(img, dtype=np.float32)
        return f[:, :, None] if f.ndim == 2 else f

    t = sample_windows(as_map(f1), pts, window)
    p = sample_windows(as_map(f2), np.where(np.isfinite(new), new, pts), window)
    return 0.5 * ((p - t) ** 2).sum(axis=(1, 2, 3)).astype(np.float64)


def _min_eigen(image: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Shi-Tomasi minimum eigenvalue (GFTT's block 3) of the gray image at each point, bilinear."""
    gray = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    eig = cv2.cornerMinEigenVal(gray, 3)
    from nsflow_ros.core.solver import sample_windows

    return sample_windows(eig[:, :, None], pts, 1).reshape(-1).astype(np.float64)


def _normalised_cov(cov: np.ndarray, camera: Any) -> np.ndarray:
    """Pixel covariances in normalised image coordinates (pinhole focal lengths)."""
    out = cov.copy()
    out[:, 0] /= camera.fx**2
    out[:, 1] /= camera.fx * camera.fy
    out[:, 2] /= camera.fy**2
    return out


def _sampson(params: np.ndarray, r0: np.ndarray, x1: np.ndarray, x2: np.ndarray, cov2: np.ndarray,
             var1: float) -> np.ndarray:
    """Sampson residuals x2^T E x1 / sqrt(var) of E = [t]x R for R = R0 exp(w), t on the unit sphere."""
    rot = r0 @ cv2.Rodrigues(params[:3])[0]
    theta, phi = params[3], params[4]
    t = np.array([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)])
    tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    e = tx @ rot
    h1 = np.c_[x1, np.ones(len(x1))]
    h2 = np.c_[x2, np.ones(len(x2))]
    l2 = h1 @ e.T  # epipolar lines in image 2
    l1 = h2 @ e  # in image 1
    r = (l2 * h2).sum(axis=1)
    var = (l2[:, 0] ** 2 * cov2[:, 0] + 2 * l2[:, 0] * l2[:, 1] * cov2[:, 1] + l2[:, 1] ** 2 * cov2[:, 2]
           + var1 * (l1[:, 0] ** 2 + l1[:, 1] ** 2))
    return r / np.sqrt(np.maximum(var, 1e-30))


def _refine(r0: np.ndarray, t0: np.ndarray, x1: np.ndarray, x2: np.ndarray, cov2: np.ndarray,
            var1: float, iterations: int = 15) -> np.ndarray:
    """Gauss-Newton (LM-damped, numeric Jacobian) on the Sampson residuals from (R0, t0); returns R."""
    t0 = t0 / np.linalg.norm(t0)
    p = np.array([0.0, 0.0, 0.0, np.arccos(np.clip(t0[2], -1, 1)), np.arctan2(t0[1], t0[0])])
    lam = 1e-3
    res = _sampson(p, r0, x1, x2, cov2, var1)
    cost = float(res @ res)
    for _ in range(iterations):
        jac = np.empty((len(res), 5))
        for k in range(5):
            d = np.zeros(5)
            d[k] = 1e-6
            jac[:, k] = (_sampson(p + d, r0, x1, x2, cov2, var1) - res) / 1e-6
        a = jac.T @ jac
        g = jac.T @ res
        step = np.linalg.solve(a + lam * np.diag(np.diag(a) + 1e-12), -g)
        cand = p + step
        res_c = _sampson(cand, r0, x1, x2, cov2, var1)
        if float(res_c @ res_c) < cost:
            p, res, cost, lam = cand, res_c, float(res_c @ res_c), lam / 10
        else:
            lam *= 10
    return r0 @ cv2.Rodrigues(p[:3])[0]


def weighted_rotation_error(
    x1: np.ndarray, x2: np.ndarray, cov2: np.ndarray, r_true: np.ndarray, threshold: float, seed: int = 0
) -> tuple[float, float] | None:
    """Rotation error (deg) of the relative pose of one frame pair, isotropic and weighted by Sigma.

    A 5-point RANSAC essential matrix (the sequences section's) gives the inliers and the start; each
    estimate then minimises the Sampson error over the same inliers: with one variance for every point
    (the mean of the covariances' traces) or with each point's covariance in frame 2. Frame-1 points are
    corners detected there (variance 1/12 px^2 on both axes, in normalised units).

    Args:
        x1, x2: normalised points. cov2: frame-2 covariances in normalised units.
        r_true: the true rotation (camera 1 -> camera 2). threshold: RANSAC threshold (normalised).

    Returns:
        (isotropic, weighted) errors in degrees, or None when the pair has no pose.

    Shape:
        x1, x2: (N, 2). cov2: (N, 3). r_true: (3, 3).
    """
    from nsflow_ros.evaluation.sequences import MIN_MATCHES, rotation_angle_deg

    if len(x1) < MIN_MATCHES:
        return None
    cv2.setRNGSeed(int(seed))
    eye = np.eye(3)
    e, mask = cv2.findEssentialMat(x1, x2, eye, method=cv2.RANSAC, prob=0.999, threshold=float(threshold))
    if e is None or e.shape[0] < 3:
        return None
    n_good, r0, t0, _ = cv2.recoverPose(e[:3], x1, x2, eye, mask=mask.copy())[:4]
    inl = mask.reshape(-1).astype(bool)
    if n_good == 0 or inl.sum() < MIN_MATCHES:
        return None
    a, b, c = x1[inl], x2[inl], cov2[inl]
    var1 = threshold**2 / 12.0  # 1/12 px^2 in normalised units: the threshold is 1 px over the focal length
    iso = np.zeros_like(c)
    iso[:, 0] = iso[:, 2] = float(np.mean(c[:, 0] + c[:, 2])) / 2.0
    out = []
    for cov in (iso, c):
        r = _refine(r0, t0.reshape(3), a, b, cov, var1)
        out.append(rotation_angle_deg(r @ np.asarray(r_true).T))
    return out[0], out[1]


def collect(
    ctx: EvalContext, setup: CovarianceSetup, *, scaled: bool = True
) -> dict[str, dict[str, Samples]]:
    """Track every pair with every method of ``ctx``: ``{method: {group: Samples}}``.

    ``scaled`` False undoes each covariance's current calibration (the raw Gauss-Newton one, for the
    fit); True gives the published one, the tail included.

    Raises:
        EvaluationError: a method or the sample sequence fails.
    """
    from nsflow_ros.core.tracker import FLOW_BACK_THRESHOLD_PX
    from nsflow_ros.evaluation.sequences import F_THRESHOLD_PX, FrameSource

    seq = sample_sequence(ctx, KEY, setup.sequence_seed, setup.duration, stereo=False, images=False,
                          progress=False)
    source = FrameSource(seq, setup.scale)
    out: dict[str, dict[str, Samples]] = {m.name: {} for m in ctx.methods}
    pairs = list(_pairs(setup, source))
    for pair in ctx.bar(pairs, "covariance", unit="pair"):
        if len(pair.points) == 0:
            continue
        min_eig = _min_eigen(pair.image1, pair.points)
        for m in ctx.methods:
            try:
                f1, f2 = m.prepare(pair.image1), m.prepare(pair.image2)
                new, status, cov, cost = _cost_and_cov(m, f1, f2, pair.points)
                if not scaled:
                    cov = m.core.covariance_scale.raw(cov)
                fb = np.full(len(new), np.inf)
                if status.any():
                    back, ok = m.core.solve(SolveKind.FLOW_BACK, f2, f1, new[status], pair.points[status])
                    fb[status] = np.where(ok, np.hypot(*(back - pair.points[status]).T), np.inf)
                check = m.core.spec.check
                passed = (check.keep(cov, status) if check is not None else fb <= FLOW_BACK_THRESHOLD_PX)
                if scaled:  # the check read it without the tail, as the tracker's does
                    cov = m.core.covariance_scale.expected(cov)
            except CoreError as err:
                raise EvaluationError(f"{m.name}: {err}") from err
            s = out[m.name].setdefault(pair.group, Samples())
            ok = status & np.isfinite(cov).all(axis=1)
            s.error.append(new[ok] - pair.truth[ok])
            s.cov.append(cov[ok])
            s.cost.append(cost[ok])
            s.min_eigen.append(min_eig[ok])
            s.fb.append(fb[ok])
            s.published.append(passed[ok])
            if pair.rotation is not None:
                cam = pair.camera
                used = ok & passed
                x1, x2 = cam.lift(pair.points[used]), cam.lift(new[used])
                thr = F_THRESHOLD_PX / float(np.mean([cam.fx, cam.fy]))
                got = weighted_rotation_error(x1, x2, _normalised_cov(cov[used], cam), pair.rotation, thr,
                                              setup.seed)
                if got is not None:
                    s.rotation.append(got)
    return out


# -- metrics ------------------------------------------------------------------------------------------


def _mahalanobis(error: np.ndarray, cov: np.ndarray) -> np.ndarray:
    det = cov[:, 0] * cov[:, 2] - cov[:, 1] ** 2
    ex, ey = error[:, 0], error[:, 1]
    with np.errstate(divide="ignore", invalid="ignore"):
        return (cov[:, 2] * ex * ex - 2 * cov[:, 1] * ex * ey + cov[:, 0] * ey * ey) / det


def _inliers(error: np.ndarray, cov: np.ndarray, what: str) -> tuple[np.ndarray, np.ndarray]:
    """The errors under 2 px with a finite covariance, and those covariances; EvaluationError naming
    ``what`` was to be fitted when there is none."""
    inl = (np.hypot(*error.T) < INLIER_PX) & np.isfinite(cov).all(axis=1)
    if not inl.any():
        raise EvaluationError(f"no inlier to fit the {what} on")
    return error[inl], cov[inl]


def fit_scale(error: np.ndarray, cov: np.ndarray) -> float:
    """The scale s that minimises the Gaussian NLL of the inliers' errors under s * cov: mean(d^2) / 2.

    Shape:
        error: (N, 2). cov: (N, 3). Raises EvaluationError with no inlier.
    """
    inl = np.hypot(*error.T) < INLIER_PX
    d2 = _mahalanobis(error[inl], cov[inl])
    d2 = d2[np.isfinite(d2)]
    if d2.size == 0:
        raise EvaluationError("no inlier to fit the covariance scale on")
    return float(np.mean(d2) / 2.0)


def _nll(e: np.ndarray, c: np.ndarray, scale: float, floor: float) -> float:
    """Mean Gaussian NLL (without the constant) of errors ``e`` under scale * c + floor * I."""
    a, b, d = scale * c[:, 0] + floor, scale * c[:, 1], scale * c[:, 2] + floor
    det = np.maximum(a * d - b * b, 1e-300)
    d2 = (d * e[:, 0] ** 2 - 2 * b * e[:, 0] * e[:, 1] + a * e[:, 1] ** 2) / det
    return float(np.mean(0.5 * np.log(det) + 0.5 * d2))


def _golden(f: Any, lo: float, hi: float, iterations: int = 32) -> float:
    """The minimum of a unimodal ``f`` on [lo, hi] by golden-section search."""
    g = (np.sqrt(5.0) - 1.0) / 2.0
    a, b = lo, hi
    c, d = b - g * (b - a), a + g * (b - a)
    fc, fd = f(c), f(d)
    for _ in range(iterations):
        if fc < fd:
            b, d, fd = d, c, fc
            c = b - g * (b - a)
            fc = f(c)
        else:
            a, c, fc = c, d, fd
            d = a + g * (b - a)
            fd = f(d)
    return (a + b) / 2.0


def fit_calibration(error: np.ndarray, cov: np.ndarray) -> tuple[float, float]:
    """The scale s and floor f (px^2) of Sigma = s * cov + f * I that maximise the likelihood of the
    inliers' errors.

    Maximum likelihood rather than matching the coverages: it uses every error's size, not only which side
    of two ellipses it falls, weighs the small-sigma and the large-sigma features by how much data each
    has, and with f = 0 it is :func:`fit_scale` exactly (an older scale-only fit is its special case).
    Searched on log s for each f (golden section, nested), f from 0 to the errors' own mean variance.

    Returns:
        (s, f); f = 0 where a floor does not raise the likelihood.

    Shape:
        error: (N, 2). cov: (N, 3). Raises EvaluationError with no inlier.
    """
    e, c = _inliers(error, cov, "covariance calibration")
    s0 = fit_scale(e, c)
    top = float(np.mean(e**2))  # a floor beyond the errors' own variance cannot help

    def best_scale(floor: float) -> float:
        return float(np.exp(_golden(lambda ls: _nll(e, c, float(np.exp(ls)), floor),
                                    np.log(s0) - 12.0, np.log(s0) + 2.0)))

    def profile(floor: float) -> float:
        return _nll(e, c, best_scale(floor), floor)

    floor = _golden(profile, 0.0, top)  # 32 steps: a bracket of 2e-7 of the range, in f and in log s
    if profile(0.0) <= profile(floor):
        return s0, 0.0
    return best_scale(floor), floor


def fit_tail(error: np.ndarray, cov: np.ndarray, knee: float, top: float = 3.0) -> float:
    """The power p of the tail above ``knee`` (:meth:`~nsflow_ros.core.covariance.CovarianceScale.expected`)
    that maximises the likelihood of the inliers' errors under calibrated covariances ``cov`` (scale and
    floor applied), searched on [0, ``top``] (golden section).

    Returns:
        p; 0 where a tail does not raise the likelihood or no inlier lies above the knee.

    Shape:
        error: (N, 2). cov: (N, 3). Raises EvaluationError with no inlier.
    """
    e, c = _inliers(error, cov, "covariance tail")

    def nll(power: float) -> float:
        return _nll(e, CovarianceScale(knee=knee, power=power).expected(c), 1.0, 0.0)

    power = _golden(nll, 0.0, top)
    return power if nll(power) < nll(0.0) else 0.0


def calibration(error: np.ndarray, cov: np.ndarray) -> dict[str, Any]:
    """Coverage, reliability per decile and NLL against the best constant sigma, on the inliers.

    Returns:
        ``inliers``, ``inside_68``, ``inside_95``, ``deciles`` (predicted and RMS sigma per axis, px, per
        decile of predicted sigma), ``decile_ratio_min/max``, ``nll``, ``nll_constant``, ``nll_gain`` (nat
        per feature, constant minus covariance).
    """
    inl = np.hypot(*error.T) < INLIER_PX
    e, c = error[inl], cov[inl]
    n = len(e)
    if n < 10:
        return {"inliers": n}
    d2 = _mahalanobis(e, c)
    sigma = np.sqrt((c[:, 0] + c[:, 2]) / 2.0)  # per-axis predicted sigma
    order = np.argsort(sigma)
    deciles = []
    for part in np.array_split(order, 10):
        pred = float(np.sqrt(np.mean(sigma[part] ** 2)))
        rms = float(np.sqrt(np.mean((e[part] ** 2).sum(axis=1) / 2.0)))
        deciles.append((pred, rms))
    ratios = [r / p for p, r in deciles]
    det = c[:, 0] * c[:, 2] - c[:, 1] ** 2
    nll = float(np.mean(np.log(2 * np.pi) + 0.5 * np.log(det) + 0.5 * d2))
    var0 = float(np.mean((e**2).sum(axis=1)) / 2.0)
    nll0 = float(np.log(2 * np.pi) + np.log(var0) + 1.0)
    return {
        "inliers": n, "inside_68": float(np.mean(d2 <= CHI2_68)), "inside_95": float(np.mean(d2 <= CHI2_95)),
        "deciles": deciles, "decile_ratio_min": float(min(ratios)), "decile_ratio_max": float(max(ratios)),
        "nll": nll, "nll_constant": nll0, "nll_gain": nll0 - nll,
    }


def auroc(score: np.ndarray, bad: np.ndarray) -> float:
    """Area under the ROC of ``score`` (higher = more uncertain) for the ``bad`` points (Mann-Whitney U,
    ties counted half); nan without both classes."""
    pos, neg = int(bad.sum()), int((~bad).sum())
    if pos == 0 or neg == 0:
        return float("nan")
    s = np.where(np.isfinite(score), score, np.finfo(np.float64).max)
    ranks = _average_ranks(s)
    return float((ranks[bad].sum() - pos * (pos + 1) / 2.0) / (pos * neg))


def _average_ranks(x: np.ndarray) -> np.ndarray:
    order = np.argsort(x, kind="stable")
    ranks = np.empty(len(x))
    xs = x[order]
    i = 0
    while i < len(x):
        j = i
        while j + 1 < len(x) and xs[j + 1] == xs[i]:
            j += 1
        ranks[order[i:j + 1]] = (i + j) / 2.0 + 1.0
        i = j + 1
    return ranks


def sparsification(score: np.ndarray, error: np.ndarray, steps: int = 20) -> np.ndarray:
    """Mean error of the points left after removing the most uncertain fraction k / steps, k = 0..steps-1."""
    s = np.where(np.isfinite(score), score, np.finfo(np.float64).max)
    order = np.argsort(-s, kind="stable")
    e = error[order]
    n = len(e)
    return np.array([float(np.mean(e[round(k / steps * n):])) for k in range(steps)])


def ause_ratio(
    score: np.ndarray, error: np.ndarray, steps: int = 20
) -> tuple[float, np.ndarray, np.ndarray]:
    """AUSE of ``score`` over random order's (area between each sparsification curve and the oracle's),
    with the curve and the oracle's curve."""
    curve = sparsification(score, error, steps)
    oracle = sparsification(error, error, steps)
    random_gap = float(np.mean(np.mean(error) - oracle))
    gap = float(np.mean(curve - oracle))
    return (gap / random_gap if random_gap > 0 else float("nan")), curve, oracle


def _signals(a: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    cov = a["cov"]
    return {"sigma": cov[:, 0] + cov[:, 2], "cost": a["cost"], "min_eigen": -a["min_eigen"],
            "fb_distance": a["fb"]}


def ranking(a: dict[str, np.ndarray]) -> dict[str, dict[str, float]]:
    """AUROC for errors > 1 px and AUSE ratio of every signal of :data:`SIGNALS`."""
    err = np.hypot(*a["error"].T)
    bad = err > BAD_PX
    out = {}
    for name, score in _signals(a).items():
        ratio, _, _ = ause_ratio(score, err)
        out[name] = {"auroc": auroc(score, bad), "ause_ratio": ratio}
    return out


# -- report ---------------------------------------------------------------------------------------------


def _pool(groups: dict[str, Samples], prefix: str) -> dict[str, np.ndarray]:
    parts = [g.arrays() for k, g in groups.items() if k.startswith(prefix)]
    return {key: np.concatenate([p[key] for p in parts]) for key in parts[0]} if parts else {}


def _pools(groups: dict[str, Samples]) -> dict[str, dict[str, np.ndarray]]:
    """The report's rows: each pair subset (all strengths), each sequence level, everything, and of
    everything what the tracker would publish (its track check passed)."""
    from nsflow_ros.evaluation.pairs import SUBSETS

    names = [*SUBSETS, *(f"sequence {lv}" for lv in LEVELS), ""]
    out = {}
    for name in names:
        pooled = _pool(groups, name)
        if pooled and len(pooled["error"]):
            out[name or "all"] = pooled
    if "all" in out and out["all"]["published"].any():
        keep = out["all"]["published"]
        out["published"] = {k: v[keep] for k, v in out["all"].items()}
    return out


def _fmt(v: Any, fmt: str = "{:.3f}") -> str:
    if isinstance(v, str):
        return v
    return "-" if v is None or (isinstance(v, float) and not np.isfinite(v)) else fmt.format(v)


def _tables(results: dict[str, dict[str, Any]]) -> str:
    head = ("| method | data | inliers | in 68 % | in 95 % | decile RMS/sigma | NLL gain (nat) | AUSE/random "
            "| AUROC sigma | AUROC cost | AUROC min-eig | AUROC FB |")
    lines = [head, "|" + "---|" * 12]
    for m, rows in results.items():
        for name, r in rows.items():
            c, k = r["calibration"], r["ranking"]
            lines.append(
                f"| {m} | {name} | {c['inliers']} | {_fmt(c.get('inside_68'), '{:.2f}')} | "
                f"{_fmt(c.get('inside_95'), '{:.2f}')} | {_fmt(c.get('decile_ratio_min'), '{:.2f}')}-"
                f"{_fmt(c.get('decile_ratio_max'), '{:.2f}')} | {_fmt(c.get('nll_gain'), '{:.2f}')} | "
                f"{_fmt(k['sigma']['ause_ratio'], '{:.2f}')} | "
                + " | ".join(_fmt(k[s]["auroc"], "{:.3f}") for s in SIGNALS) + " |"
            )
    return "\n".join(lines)


def _rotation_table(rot: dict[str, dict[str, list[tuple[float, float]]]]) -> str:
    lines = ["| method | perturbation | pairs | median error isotropic (deg) | weighted (deg) | change |",
             "|---|---|---|---|---|---|"]
    for m, per in rot.items():
        for level, vals in per.items():
            if not vals:
                continue
            v = np.asarray(vals)
            iso, wtd = float(np.median(v[:, 0])), float(np.median(v[:, 1]))
            change = (wtd - iso) / iso if iso > 0 else float("nan")
            lines.append(f"| {m} | {level} | {len(v)} | {iso:.4f} | {wtd:.4f} | {change:+.1%} |")
    return "\n".join(lines)


def _figure(results: dict[str, dict[str, Any]], curves: dict[str, np.ndarray], path: Path) -> Path:
    fig = new_figure(12, 4.5)
    ax1, ax2 = fig.subplots(1, 2)
    for m, rows in results.items():
        dec = rows.get("all", {}).get("calibration", {}).get("deciles")
        if dec:
            p, r = np.asarray(dec).T
            ax1.loglog(p, r, "o-", label=m)
    lim = ax1.get_xlim()
    xs = np.geomspace(*lim, 10)
    ax1.plot(xs, xs, "k--", lw=0.8, label="ideal")
    ax1.fill_between(xs, 0.8 * xs, 1.25 * xs, color="gray", alpha=0.15, label="0.8-1.25")
    from matplotlib.ticker import NullFormatter

    for axis in (ax1.xaxis, ax1.yaxis):
        axis.set_minor_formatter(NullFormatter())  # log axes: the decade labels alone stay readable
    ax1.set_xlabel("predicted sigma per axis (px, decile RMS)")
    ax1.set_ylabel("actual RMS error per axis (px)")
    ax1.set_title("Reliability per decile (inliers < 2 px, all data)")
    ax1.legend(fontsize=7)
    steps = None
    for name, curve in curves.items():
        steps = len(curve)
        style = "--" if name in ("oracle", "random") else "-"
        ax2.plot(np.arange(steps) / steps, curve, label=name, ls=style)
    ax2.set_xlabel("fraction of points removed (most uncertain first)")
    ax2.set_ylabel("mean endpoint error of the rest (px)")
    ax2.set_yscale("log")
    ax2.set_title(f"Sparsification, {next(iter(results), '')} (all data)")
    ax2.legend(fontsize=7)
    fig.tight_layout()
    return save_figure(fig, path)


def _verdict(results: dict[str, dict[str, Any]]) -> list[str]:
    t = TARGETS
    lines = ["**Against the targets** (all held-out data pooled, per method):", ""]
    for m, rows in results.items():
        r = rows.get("all")
        if r is None:
            continue
        c, k = r["calibration"], r["ranking"]
        if "inside_68" not in c:
            continue
        checks = [
            ("68 % ellipse share", c["inside_68"], t["inside_68"][0] <= c["inside_68"] <= t["inside_68"][1],
             "0.60-0.76"),
            ("95 % ellipse share", c["inside_95"], t["inside_95"][0] <= c["inside_95"] <= t["inside_95"][1],
             "0.90-0.98"),
            ("decile RMS/sigma", f"{c['decile_ratio_min']:.2f}-{c['decile_ratio_max']:.2f}",
             c["decile_ratio_min"] >= t["decile_ratio"][0] and c["decile_ratio_max"] <= t["decile_ratio"][1],
             "every decile 0.8-1.25"),
            ("NLL gain (nat)", c["nll_gain"], c["nll_gain"] >= t["nll_gain"], ">= 0.15"),
            ("AUSE / random", k["sigma"]["ause_ratio"], k["sigma"]["ause_ratio"] <= t["ause_ratio"],
             "<= 0.5"),
            ("AUROC > 1 px", k["sigma"]["auroc"], k["sigma"]["auroc"] >= t["auroc"], ">= 0.90"),
        ]
        best_other = max((k[s]["auroc"] for s in SIGNALS[1:] if np.isfinite(k[s]["auroc"])), default=np.nan)
        margin = k["sigma"]["auroc"] - best_other
        checks.append(("AUROC margin over the best tracker signal", margin, margin >= t["auroc_margin"],
                       ">= 0.02"))
        text = "; ".join(f"{name} {_fmt(v)} (target {tgt}: {'met' if ok else '**not met**'})"
                         for name, v, ok, tgt in checks)
        lines.append(f"- {m}: {text}.")
    return lines


def _results(data: dict[str, dict[str, Samples]]) -> tuple[dict, dict]:
    results: dict[str, dict[str, Any]] = {}
    rot: dict[str, dict[str, list]] = {}
    for m, groups in data.items():
        results[m] = {}
        for name, a in _pools(groups).items():
            results[m][name] = {"calibration": calibration(a["error"], a["cov"]), "ranking": ranking(a),
                                "points": len(a["error"])}
        rot[m] = {lv: groups[f"sequence {lv}"].rotation for lv in LEVELS if f"sequence {lv}" in groups}
    return results, rot


def _setup(ctx: EvalContext) -> CovarianceSetup:
    base = QUICK if ctx.quick else FULL
    opts = dict(ctx.extra.get(KEY, {}))
    setup = replace(base, photos=_heldout()[:1] if ctx.quick else _heldout(), seed=ctx.seed)
    for name in ("duration", "scale", "per_level", "max_points", "stride"):
        if name in opts:
            setup = replace(setup, **{name: type(getattr(setup, name))(opts[name])})
    return setup


def run(ctx: EvalContext) -> Section:
    """The ``covariance`` section: calibration, ranking and rotation tables, reliability + sparsification
    figure.

    ``ctx.extra["covariance"]`` may override ``duration``, ``scale``, ``per_level``, ``max_points`` and
    ``stride`` of the data.

    Raises:
        EvaluationError: no methods, or a method / the sample sequence fails.
    """
    if not ctx.methods:
        raise EvaluationError("the covariance analysis needs at least one method")
    setup = _setup(ctx)
    data = collect(ctx, setup)
    results, rot = _results(data)
    first = ctx.methods[0].name
    pooled = _pools(data[first]).get("all")
    curves: dict[str, np.ndarray] = {}
    if pooled is not None:
        err = np.hypot(*pooled["error"].T)
        for name, score in _signals(pooled).items():
            _, curves[name], oracle = ause_ratio(score, err)
        curves["oracle"] = oracle
        curves["random"] = np.full(len(oracle), float(np.mean(err)))
    fig = _figure(results, curves, ctx.out_dir / f"{KEY}.png")
    cals = {m.name: m.core.covariance_scale for m in ctx.methods}
    scales = {n: (c.scale, c.source, c.floor, c.knee, c.power) for n, c in cals.items()}
    scale_text = ", ".join(f"{n} {c.scale:.3g} / {c.floor:.2g}"
                           + (f" / {c.power:.2g} above {c.knee:g} px" if c.power > 0 else "")
                           + f" ({c.source})" for n, c in cals.items())
    w, h = setup.pair_size
    md = "\n\n".join([
        "Sigma = s sigma_hat^2 (J^T J)^-1 + f I per tracked feature (the LM methods: the solver's own final "
        "J^T J and cost; the OpenCV LK methods: the template's gradients over the 21x21 window at the "
        "rounded point and OpenCV's own err, the mean absolute window difference at the solution), times "
        "(sigma / k)^(2 p) above a knee k (the tail, as published; the track check reads Sigma without it). "
        f"Scale s / floor f (px^2) / tail p above k: {scale_text}. "
        "Data held out from the fit: homography pairs of the photos "
        f"{', '.join(setup.photos)} ({w}x{h}, {setup.pair_levels} strengths per subset) and every "
        f"{setup.stride}. frame pair of the sample sequence seed {setup.sequence_seed} "
        f"({setup.duration:g} s, "
        f"scale {setup.scale:g}) under each perturbation level; GFTT points (up to {setup.max_points}) "
        "tracked from zero flow by each method's forward solve, then back by its flow-back solve. "
        "Calibration on inliers (< 2 px); ranking on every tracked point (sigma = trace of Sigma; cost = "
        "final window cost; min-eig = minus the Shi-Tomasi minimum eigenvalue at the point; FB = "
        "forward-backward distance). Row published: of all the data, the points the tracker would publish "
        "(the method's track check passed: the covariance check for a method with one, else the 0.5 px "
        "flow-back check)." + quick_note(ctx.quick),
        _tables(results),
        "\n".join(_verdict(results)),
        "Relative rotation of each sample-sequence frame pair from the points the tracker would publish: "
        "5-point RANSAC, then Sampson refinement over its inliers with one variance for all points "
        "(isotropic) or with each point's Sigma (weighted), against the true rotation:",
        _rotation_table(rot),
        f"![reliability and sparsification]({fig.name})",
    ])
    headline = []
    for m, rows in results.items():
        r = rows.get("all")
        if r and "inside_68" in r["calibration"]:
            headline.append(HeadlineRow(f"covariance: AUROC of sigma for errors > 1 px ({m})",
                                        {m: _fmt(r["ranking"]["sigma"]["auroc"])}, ">= 0.90",
                                        r["ranking"]["sigma"]["auroc"] >= 0.90))
    out_data = {"setup": {k: (list(v) if isinstance(v, tuple) else v) for k, v in vars(setup).items()},
                "scales": scales, "results": _jsonable(results),
                "rotation": {m: {lv: [list(x) for x in v] for lv, v in per.items()}
                             for m, per in rot.items()}}
    return Section(KEY, "Per-feature covariance", md, [fig], headline, out_data)


def _jsonable(x: Any) -> Any:
    if isinstance(x, dict):
        return {k: _jsonable(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [_jsonable(v) for v in x]
    if isinstance(x, float) and not np.isfinite(x):
        return None
    return x


# -- the fit ------------------------------------------------------------------------------------------


def fit(ctx: EvalContext, setup: CovarianceSetup, keep_scale: bool = False) -> dict[str, CovarianceScale]:
    """Each method's maximum-likelihood scale and floor (:func:`fit_calibration`) on ``setup``'s data, all
    groups pooled, then its tail (:func:`fit_tail`) above its covariance check's ``max_sigma`` (none for
    a method without that check).

    Every method gets a floor: without one the default model's largest predicted sigmas are too large
    (top decile 0.69) and too many inliers fall inside the 68 % ellipse (docs/evaluation.md). It evens out
    the weights of the best-localised features, so weighting gains less than with a scale alone, but
    still meets its targets. The tail is fitted with the scale and floor held: the checks read those.

    Args:
        keep_scale: keep each method's current scale and floor (what its checks were tuned on) and fit
            the tail alone.

    Raises:
        EvaluationError: ``keep_scale`` with a method that has no fitted scale; no inlier to fit on.
    """
    if keep_scale:
        for m in ctx.methods:
            if not m.core.covariance_scale.calibrated:
                raise EvaluationError(f"--keep-scale: {m.name} has no fitted scale and floor to keep "
                                      f"({m.core.covariance_scale.source}); fit without --keep-scale")
    data = collect(ctx, setup, scaled=False)
    out = {}
    for m in ctx.methods:
        pooled = _pool(data[m.name], "")
        current = m.core.covariance_scale
        scale, floor = ((current.scale, current.floor) if keep_scale
                        else fit_calibration(pooled["error"], pooled["cov"]))
        base = CovarianceScale(scale, "fit", floor)
        check = m.core.spec.check
        if check is None:
            out[m.name] = base
            continue
        power = fit_tail(pooled["error"], base.apply(pooled["cov"]), check.max_sigma)
        out[m.name] = replace(base, knee=check.max_sigma, power=power)
    return out


def _entry_of(cal: CovarianceScale) -> dict[str, float]:
    """A sidecar entry: scale and floor, and the tail where there is one."""
    entry = {"scale": cal.scale, "floor": cal.floor}
    if cal.power > 0:
        entry |= {"knee": cal.knee, "power": cal.power}
    return entry


def main(args: Sequence[str] | None = None) -> int:
    """``python -m nsflow_ros.evaluation.covariance fit``: fit the scales, floors and tails on training
    data; the learned methods' go into the JSON beside the model, the others' are printed for their
    registry entries."""
    from nsflow_ros.core.encoder import model_file
    from nsflow_ros.evaluation.methods import VARIANTS, usable_methods

    parser = argparse.ArgumentParser(prog="python -m nsflow_ros.evaluation.covariance",
                                     description="Fit the per-feature covariance scales, floors and tails on "
                                                 "training data.")
    parser.add_argument("command", choices=["fit"])
    parser.add_argument("--model", default=None, help="ONNX encoder (file or shipped name; default: default)")
    parser.add_argument("--out", default="out/covariance_fit", help="folder for the sample-sequence cache")
    parser.add_argument("--keep-scale", action="store_true",
                        help="keep each method's current scale and floor (its checks read them) and fit the "
                             "tail alone")
    parser.add_argument("--quick", action="store_true", help="tiny data (tests)")
    parser.add_argument("--threads", type=int, default=None)
    parser.add_argument("--no-write", action="store_true", help="print the scales, write nothing")
    opts = parser.parse_args(args)
    try:
        # no --model: each learned method its registry's default model, as the tracker loads it
        model = model_file(opts.model) if opts.model is not None else None
        methods, _ = usable_methods(None if model is None else str(model), threads=opts.threads)
        methods = [m for m in methods if not m.equalize]  # one scale per registry method
        out = Path(opts.out)
        out.mkdir(parents=True, exist_ok=True)
        ctx = EvalContext(methods=methods, model=model, quick=opts.quick, out_dir=out, progress=False)
        setup = replace(QUICK if opts.quick else FIT, photos=_training()[:1] if opts.quick else _training(),
                        sequence_seed=1, seed=1)
        scales = fit(ctx, setup, keep_scale=opts.keep_scale)
    except (EvaluationError, CoreError, OSError) as err:
        print(f"covariance fit: {err}", file=sys.stderr)
        return 1
    by_method = {VARIANTS[label].method: _entry_of(c) for label, c in scales.items()}
    for label, c in scales.items():
        print(f"{VARIANTS[label].method}: scale {c.scale:.4g} floor {c.floor:.4g} px^2{c.tail_text}")
    # each learned method's calibration goes beside the model it was fitted with
    files: dict[Path, dict[str, dict[str, float]]] = {}
    for m in methods:
        name = VARIANTS[m.name].method
        if VARIANTS[m.name].spec.learned and name in by_method:
            files.setdefault(Path(m.encoder.path), {})[name] = by_method[name]
    for path, learned in ([] if opts.no_write else files.items()):
        side = sidecar_path(path)
        sha = hashlib.sha256(path.read_bytes()).hexdigest()
        kept = {}
        if side.is_file():  # another method's calibration fitted on this same file stays
            old = json.loads(side.read_text())
            if isinstance(old, dict) and old.get("model_sha256") == sha:
                kept = old.get("scales", {})
        doc = {"scales": {**kept, **learned}, "model_sha256": sha,
               "fitted_on": "training photos' homography pairs and sample sequence seed 1, every level",
               "command": "python -m nsflow_ros.evaluation.covariance fit"
               + (f" --model {path.name}" if model is not None else "")
               + (" --keep-scale" if opts.keep_scale else "")}
        side.write_text(json.dumps(doc, indent=2) + "\n")
        print(f"wrote {side}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
