"""Front-end metrics on the sample sequences, per perturbation (illumination, low light) and method.

Every method runs through the deployed :class:`~nsflow_ros.core.tracker.FeatureTracker` with its
deployed settings, offline (every frame processed), so the methods differ only in the flow. Per
perturbation (:data:`~nsflow_ros.data.perturb.PERTURBATIONS`: the paper's illumination levels and ``dark``,
low light with sensor noise; the same images for every
method) it measures track survival and lengths, the tracking error against the exact ground-truth flow,
the relative-rotation error of a 5-point RANSAC, the paper's Table III fundamental-matrix inlier rate and
epipolar error, and where tracks are lost (the report's text beside the table says how each is
computed). Two long-track figures are kept because they differ: a tracker that loses and re-detects
features makes more distinct tracks reaching 10 frames, but keeps fewer old tracks alive in any frame.

Quick mode renders a tiny version of the same scene and flight in memory; full mode generates (once,
cached) an 8 s 752x480 sample sequence.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from nsflow_ros.core.encoder import Encoder
from nsflow_ros.core.errors import CoreError
from nsflow_ros.core.methods import method_encoder
from nsflow_ros.core.tracker import FeatureTracker, TrackerSettings
from nsflow_ros.evaluation.context import EvalContext, new_figure, sample_sequence, save_figure
from nsflow_ros.evaluation.errors import EvaluationError
from nsflow_ros.evaluation.methods import CLASSICAL, KLT, NSFLOW, VARIANTS
from nsflow_ros.evaluation.section import HeadlineRow, Section
from nsflow_ros.evaluation.targets import Clause, Target, headline_row

__all__ = [
    "FULL",
    "F_THRESHOLD_PX",
    "LEVELS",
    "MIN_MATCHES",
    "NEAR_BORDER_PX",
    "QUICK",
    "TARGETS",
    "TRACKER_METHODS",
    "FrameSource",
    "MethodRun",
    "SequenceSetup",
    "epipolar_distances",
    "evaluate_sequences",
    "fundamental_inliers",
    "learned_encoder",
    "load_source",
    "method_encoders",
    "relative_rotation_error",
    "rotation_angle_deg",
    "run",
    "track_sequence",
]

KEY = "sequences"
LEVELS = ("none", "small", "large", "dark")
"""Perturbations of :data:`~nsflow_ros.data.perturb.PERTURBATIONS` the section runs by default: the paper's
illumination levels and low light with sensor noise."""
TRACKER_METHODS: dict[str, dict[str, Any]] = {label: v.tracker_overrides for label, v in VARIANTS.items()}
"""Report name of a method -> the :class:`TrackerSettings` fields that make the tracker run it (a view
over :data:`~nsflow_ros.evaluation.methods.VARIANTS`)."""
LEARNED = tuple(label for label, v in VARIANTS.items() if v.spec.learned)
"""Methods that use the run's ONNX encoder."""

F_THRESHOLD_PX = 1.0
"""RANSAC threshold (px) of the fundamental-matrix and essential-matrix steps."""
MIN_MATCHES = 8
"""Fewest matches a frame pair needs for the E / F estimation (fewer: the pair counts as failed)."""
LONG_TRACK = 10
"""Frames a track must reach to count as long (the issue's target)."""
NEAR_BORDER_PX = 40.0
"""A lost track counts as lost near the border when its last position is this close to the image edge:
the LM solver's window half-width (5 px) at the coarsest of the tracker's 4 levels (x 8)."""
TARGETS: dict[tuple[str, str], Target] = {
    ("large", "tracks_10_frames"): Target("tracks_10_frames", (Clause(">=", (KLT,), 2),)),
    ("large", "long_tracks_per_frame"): Target("long_tracks_per_frame", (Clause(">=", (KLT,), 2),)),
    ("large", "error_median_px"): Target("error_median_px", (Clause("<=", bound=0.5, unit="px"),)),
    ("none", "error_median_px"): Target("error_median_px", (Clause("<=", (KLT,), 1.1),)),
}
"""(perturbation level, figure) -> NSFlow's target on that figure of the sample-sequence runs."""
TARGET_ROWS: dict[tuple[str, str], tuple[str, str]] = {
    ("large", "tracks_10_frames"): (
        "tracks reaching 10 frames, large perturbation (sample sequence)", "{:d}"
    ),
    ("large", "long_tracks_per_frame"): (
        "features per frame on a track >= 10 frames old, large perturbation", "{:.1f}"
    ),
    ("large", "error_median_px"): ("median tracking error vs GT flow, large perturbation (px)", "{:.3f}"),
    ("none", "error_median_px"): ("median tracking error vs GT flow, no perturbation (px)", "{:.3f}"),
}
"""The headline row (metric, value format) of each target, in report order."""


@dataclass(frozen=True)
class SequenceSetup:
    """Which sequence and tracker settings an evaluation uses.

    Attributes:
        duration: seconds of sequence (20 Hz).
        scale: image scale (1 = 752x480); below 1 the frames are rendered at the smaller size.
        seed: seed of the sample sequence (scene, flight, image noise); 0 = the demo's sequence.
        max_cnt: tracker ``max_cnt``.
        min_dist: tracker ``min_dist`` (px).
    """

    duration: float
    scale: float = 1.0
    seed: int = 0
    max_cnt: int = 150
    min_dist: float = 30.0

    def __post_init__(self) -> None:
        if not self.duration > 0:
            raise EvaluationError(f"duration must be > 0 s, got {self.duration}")
        if not 0 < self.scale <= 1:
            raise EvaluationError(f"scale must be in (0, 1], got {self.scale}")

    def tracker_settings(self, ctx: EvalContext) -> TrackerSettings:
        """The tracker's settings for this setup, with the run's threads and providers."""
        return TrackerSettings(max_cnt=self.max_cnt, min_dist=self.min_dist, num_threads=ctx.threads,
                               providers=ctx.providers)  # fmt: skip


QUICK = SequenceSetup(duration=0.6, scale=0.4, max_cnt=60, min_dist=12.0)
FULL = SequenceSetup(duration=8.0)


class FrameSource:
    """Frames of a sample sequence at some scale, with exact ground-truth flow and poses.

    Args:
        sequence: a :class:`~nsflow_ros.data.sample.SampleSequence`.
        scale: image scale; 1 uses the stored images, below 1 renders the same scene and flight through
            the scaled camera.

    Attributes:
        camera: the (scaled) camera as the tracker's camera model.
        size: (width, height).
        stamps_ns: (N,) int64 frame stamps.
    """

    def __init__(self, sequence: Any, scale: float = 1.0) -> None:
        if not 0 < scale <= 1:
            raise EvaluationError(f"scale must be in (0, 1], got {scale}")
        self.sequence = sequence
        self.scale = float(scale)
        src = sequence.cameras[0]
        self._cam = src if scale == 1 else src.scaled(scale)
        self.camera = self._cam.camera_model()
        self.size = (self._cam.width, self._cam.height)
        self.stamps_ns = np.asarray(sequence.stamps_ns, dtype=np.int64)
        self._renderer: Any = None
        self._images: dict[int, np.ndarray] = {}

    def __len__(self) -> int:
        return int(self.stamps_ns.size)

    def time(self, i: int) -> float:
        """Seconds since the first frame."""
        return float(self.stamps_ns[i] - self.stamps_ns[0]) * 1e-9

    def image(self, i: int) -> np.ndarray:
        """Frame ``i`` (unperturbed), uint8 (H, W); rendered once and kept."""
        if i not in self._images:
            if self.scale == 1:
                self._images[i] = self.sequence.image(i)
            else:
                from nsflow_ros.data.scene import Renderer

                if self._renderer is None:
                    self._renderer = Renderer(self.sequence.scene, self._cam)
                noise = float(self.sequence.params["image_noise"])
                noise_seed = int(self.sequence.params["seed"]) * 7919 + i  # fixed per frame: reproducible
                self._images[i] = self._renderer.render(
                    self.sequence.pose(i), noise_sigma=noise, noise_seed=noise_seed
                ).image
        return self._images[i]

    def flow(self, i: int, j: int, pixels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Exact flow of ``pixels`` from frame i to j and its visibility. Shape: (N, 2) -> (N, 2), (N,)."""
        from nsflow_ros.data.scene import flow_between

        seq = self.sequence
        return flow_between(seq.scene, self._cam, seq.pose(i), self._cam, seq.pose(j), pixels)

    def relative_rotation(self, i: int, j: int) -> np.ndarray:
        """Ground-truth rotation taking camera-i coordinates to camera-j coordinates. Shape: (3, 3)."""
        ri, rj = self.sequence.pose(i)[:3, :3], self.sequence.pose(j)[:3, :3]
        return rj.T @ ri


def rotation_angle_deg(r: np.ndarray) -> float:
    """Angle of a rotation matrix in degrees (clipped against round-off)."""
    c = (float(np.trace(r)) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def relative_rotation_error(
    x1: np.ndarray,
    x2: np.ndarray,
    r_true: np.ndarray,
    threshold: float,
    seed: int = 0,
) -> float | None:
    """Rotation error (degrees) of a 5-point RANSAC essential matrix + ``recoverPose``.

    Args:
        x1: undistorted normalised points in view 1.
        x2: the same points in view 2.
        r_true: ground-truth rotation from view-1 to view-2 coordinates (``X2 = R X1 + t``).
        threshold: RANSAC threshold in normalised units (pixels / focal length).
        seed: OpenCV RNG seed, so the RANSAC is reproducible.

    Returns:
        the angle of ``R_est R_true^T`` in degrees, or None when fewer than :data:`MIN_MATCHES` points or
        no essential matrix / pose was found.

    Shape:
        x1, x2: (N, 2). r_true: (3, 3).
    """
    a = np.asarray(x1, dtype=np.float64)
    b = np.asarray(x2, dtype=np.float64)
    if a.shape != b.shape or a.ndim != 2 or a.shape[1] != 2:
        raise EvaluationError(f"point sets must both be (N, 2), got {a.shape} and {b.shape}")
    if np.asarray(r_true).shape != (3, 3):
        raise EvaluationError(f"r_true must be (3, 3), got {np.asarray(r_true).shape}")
    if not threshold > 0:
        raise EvaluationError(f"threshold must be > 0, got {threshold}")
    if a.shape[0] < MIN_MATCHES:
        return None
    cv2.setRNGSeed(int(seed))
    eye = np.eye(3)
    e, mask = cv2.findEssentialMat(a, b, eye, method=cv2.RANSAC, prob=0.999, threshold=float(threshold))
    if e is None or e.shape[0] < 3:
        return None
    # Several solutions may come stacked (3k x 3); the first is the one with the most inliers. The
    # cheirality test's default distanceThresh (50 baselines) drops every point of a 20 Hz frame pair
    # (depth / baseline ~ 100), leaving the choice between the two rotations to chance: no depth limit.
    n_good, r, _, _, _ = cv2.recoverPose(e[:3], a, b, eye, distanceThresh=1e9, mask=mask.copy())
    if n_good == 0:
        return None
    return rotation_angle_deg(r @ np.asarray(r_true, dtype=np.float64).T)


def epipolar_distances(f: np.ndarray, p1: np.ndarray, p2: np.ndarray) -> np.ndarray:
    """Point-to-line distance (px) of ``p2`` to its epipolar line ``F p1`` in image 2.

    Shape:
        f: (3, 3). p1, p2: (N, 2). Returns (N,).
    """
    h1 = np.c_[p1, np.ones(len(p1))]
    h2 = np.c_[p2, np.ones(len(p2))]
    lines = h1 @ np.asarray(f, dtype=np.float64).T  # (a, b, c) per point
    norm = np.hypot(lines[:, 0], lines[:, 1])
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.abs((lines * h2).sum(axis=1)) / norm


def fundamental_inliers(
    p1: np.ndarray, p2: np.ndarray, n_first: int, threshold: float = F_THRESHOLD_PX, seed: int = 0
) -> tuple[float, float] | None:
    """The paper's Table III figures for one frame pair: RANSAC F inlier rate and mean epipolar error.

    Args:
        p1: undistorted pixel positions in frame 1 of the tracked features.
        p2: their tracked positions in frame 2.
        n_first: features in frame 1 (the inlier rate's denominator: lost tracks count as outliers).
        threshold: ``cv2.findFundamentalMat`` RANSAC threshold (px).
        seed: OpenCV RNG seed.

    Returns:
        (inlier rate in [0, 1], mean point-to-line distance of the inliers in px), or None when fewer than
        :data:`MIN_MATCHES` matches or no F was found.

    Shape:
        p1, p2: (N, 2).
    """
    a = np.asarray(p1, dtype=np.float64)
    b = np.asarray(p2, dtype=np.float64)
    if a.shape != b.shape or a.ndim != 2 or a.shape[1] != 2:
        raise EvaluationError(f"point sets must both be (N, 2), got {a.shape} and {b.shape}")
    if n_first < a.shape[0]:
        raise EvaluationError(f"n_first ({n_first}) must be at least the number of matches ({a.shape[0]})")
    if a.shape[0] < MIN_MATCHES:
        return None
    cv2.setRNGSeed(int(seed))
    f, mask = cv2.findFundamentalMat(a, b, cv2.FM_RANSAC, float(threshold), 0.99)
    if f is None or mask is None or f.shape != (3, 3):
        return None
    inl = mask.reshape(-1).astype(bool)
    if not inl.any():
        return 0.0, float("nan")
    d = epipolar_distances(f, a[inl], b[inl])
    return float(inl.sum()) / float(n_first), float(np.nanmean(d))


@dataclass
class MethodRun:
    """What one method did on one perturbation level.

    Attributes:
        method: report name of the method.
        level: perturbation level.
        figures: the summary numbers (:meth:`summary`).
        lengths: final length (frames) of every track.
        errors: GT tracking error (px) of every carried-over, visible feature.
        rotation_errors: per consecutive frame pair, degrees (NaN where the 5-point step failed).
        inlier_rates, epipolar_errors: per frame pair, Table III figures (NaN where F failed).
        frame_ms: per-frame tracker time (ms).
        long_per_frame: per frame from the 10th on, features whose track is at least 10 frames old.
        lost_border_distance: per track lost between two frames, its last position's distance to the
            nearest image edge (px).
    """

    method: str
    level: str
    figures: dict[str, Any] = field(default_factory=dict)
    lengths: list[int] = field(default_factory=list)
    errors: list[float] = field(default_factory=list)
    rotation_errors: list[float] = field(default_factory=list)
    inlier_rates: list[float] = field(default_factory=list)
    epipolar_errors: list[float] = field(default_factory=list)
    frame_ms: list[float] = field(default_factory=list)
    long_per_frame: list[int] = field(default_factory=list)
    lost_border_distance: list[float] = field(default_factory=list)

    def summary(self, stats: dict[str, Any]) -> dict[str, Any]:
        """Combine :class:`~nsflow_ros.data.scoring.TrackStats` figures with the geometry figures."""
        err = np.asarray(self.errors)
        rot = np.asarray(self.rotation_errors)
        inl = np.asarray(self.inlier_rates)
        epi = np.asarray(self.epipolar_errors)

        def stat(x: np.ndarray, q: float) -> float | None:
            x = x[np.isfinite(x)]
            return float(np.percentile(x, q)) if x.size else None

        self.figures = {
            "frames": stats["frames"],
            "features_per_frame": stats["features_per_frame"],
            "tracked_share": stats["tracked_share"],
            "mean_track_length": stats["mean_track_length"],
            "tracks_10_frames": stats["tracks_10_frames"],
            "long_tracks_per_frame": float(np.mean(self.long_per_frame)) if self.long_per_frame else None,
            "error_median_px": stat(err, 50),
            "error_p90_px": stat(err, 90),
            "error_count": int(err.size),
            "rotation_error_median_deg": stat(rot, 50),
            "rotation_error_mean_deg": float(np.nanmean(rot)) if np.isfinite(rot).any() else None,
            "rotation_failures": int((~np.isfinite(rot)).sum()),
            "f_inlier_rate": float(np.nanmean(inl)) if np.isfinite(inl).any() else None,
            "f_epipolar_error_px": float(np.nanmean(epi)) if np.isfinite(epi).any() else None,
            "frame_ms_median": stat(np.asarray(self.frame_ms), 50),
            "lost_per_frame": len(self.lost_border_distance) / max(stats["frames"] - 1, 1),
            "lost_near_border_share": (
                float((np.asarray(self.lost_border_distance) < NEAR_BORDER_PX).mean())
                if self.lost_border_distance else None
            ),
        }
        return self.figures


def track_sequence(
    source: FrameSource,
    method: str,
    level: str,
    *,
    settings: TrackerSettings,
    encoder: Encoder | None = None,
    seed: int = 0,
    tick: Callable[[], None] | None = None,
) -> MethodRun:
    """Run one method over every frame of ``source`` under one perturbation level and measure it.

    Args:
        source: the frames and their ground truth.
        method: report name (a key of :data:`TRACKER_METHODS`).
        level: a perturbation of :data:`~nsflow_ros.data.perturb.PERTURBATIONS` (``none``, ``small``,
            ``large``, ``dark``).
        settings: tracker settings; the method's :data:`TRACKER_METHODS` fields replace theirs.
        encoder: encoder of a method that has one (None: the tracker loads its own).
        seed: perturbation and RANSAC seed.
        tick: called after every frame (progress bar).

    Raises:
        EvaluationError: unknown method or level, or the tracker / model fails.
    """
    from nsflow_ros.data.errors import DataError
    from nsflow_ros.data.perturb import make_perturber
    from nsflow_ros.data.scoring import TrackStats

    if method not in TRACKER_METHODS:
        raise EvaluationError(f"unknown method {method!r}; expected one of {list(TRACKER_METHODS)}")
    try:
        perturb = make_perturber(level, seed)
    except DataError as err:
        raise EvaluationError(str(err)) from err
    overrides = TRACKER_METHODS[method]
    try:
        tracker = FeatureTracker(
            [source.camera], settings.with_overrides(overrides), encoder=encoder
        )
    except CoreError as err:
        raise EvaluationError(f"{method}: {err}") from err
    cam = source.camera
    k_mat = np.array([cam.fx, cam.fy])
    c_vec = np.array([cam.cx, cam.cy])
    threshold_norm = F_THRESHOLD_PX / float(np.mean(k_mat))
    stats = TrackStats(source)
    run_ = MethodRun(method, level)
    prev = None
    for i in range(len(source)):
        img = perturb(source.image(i), source.time(i))
        try:
            feats = tracker.process(source.stamps_ns[i] * 1e-9, img)
        except CoreError as err:
            raise EvaluationError(f"{method}, level {level}, frame {i}: {err}") from err
        run_.frame_ms.append(feats.timings["total"])
        cur = feats.cameras[0]
        if i >= LONG_TRACK - 1:  # before that no track can be 10 frames old
            run_.long_per_frame.append(int((cur.track_counts >= LONG_TRACK).sum()))
        stats.add_frame(int(source.stamps_ns[i]), dict(zip(cur.ids.tolist(), cur.pixels, strict=True)))
        if prev is not None:
            where = {int(j): n for n, j in enumerate(prev.ids)}
            ci = np.array([n for n, j in enumerate(cur.ids) if int(j) in where], np.int64)
            pi = np.array([where[int(cur.ids[n])] for n in ci], np.int64)
            x1, x2 = prev.undistorted[pi], cur.undistorted[ci]
            lost = np.ones(len(prev), bool)
            lost[pi] = False
            u, v = prev.pixels[lost].T
            w, h = source.size
            run_.lost_border_distance.extend(np.minimum.reduce([u, v, w - 1 - u, h - 1 - v]).tolist())
            r_true = source.relative_rotation(i - 1, i)
            rot = relative_rotation_error(x1, x2, r_true, threshold_norm, seed + i)
            run_.rotation_errors.append(np.nan if rot is None else rot)
            fi = fundamental_inliers(x1 * k_mat + c_vec, x2 * k_mat + c_vec, len(prev), seed=seed + i)
            run_.inlier_rates.append(np.nan if fi is None else fi[0])
            run_.epipolar_errors.append(np.nan if fi is None else fi[1])
        prev = cur
        if tick is not None:
            tick()
    run_.lengths = [int(v) for v in stats.lengths.values()]
    run_.errors = [float(e) for e in stats.errors]
    run_.summary(stats.figures())
    return run_


def evaluate_sequences(
    source: FrameSource,
    methods: Sequence[str],
    levels: Sequence[str] = LEVELS,
    *,
    settings: TrackerSettings,
    encoders: dict[str, Encoder] | None = None,
    seed: int = 0,
    progress: bool = False,
) -> dict[str, dict[str, MethodRun]]:
    """Every method (keys of :data:`TRACKER_METHODS`) on every level, as :func:`track_sequence` runs
    them (``encoders`` by method name; progress over all frames); returns ``{level: {method: run}}``.

    Raises:
        EvaluationError: no or unknown methods, or a run that fails.
    """
    from nsflow_ros.progress import progress_bar

    if not methods:
        raise EvaluationError("no methods to evaluate")
    bad = [m for m in methods if m not in TRACKER_METHODS]
    if bad:
        raise EvaluationError(f"unknown method(s) {bad}; expected some of {list(TRACKER_METHODS)}")
    out: dict[str, dict[str, MethodRun]] = {}
    total = len(levels) * len(methods) * len(source)
    with progress_bar(total=total, desc="sequences", unit="frame", enabled=progress, leave=False) as bar:
        for level in levels:
            out[level] = {}
            for m in methods:
                bar.set_postfix_str(f"{level}/{m}")
                out[level][m] = track_sequence(
                    source, m, level, settings=settings, encoder=(encoders or {}).get(m), seed=seed,
                    tick=lambda: bar.update(1),
                )
    return out


# -- report ----------------------------------------------------------------------------------------------

_COLUMNS = (
    ("tracked_share", "tracked share", "{:.1%}"),
    ("mean_track_length", "mean track len", "{:.2f}"),
    ("tracks_10_frames", "tracks >= 10 fr", "{:d}"),
    ("long_tracks_per_frame", ">= 10 fr per frame", "{:.1f}"),
    ("error_median_px", "err median px", "{:.3f}"),
    ("error_p90_px", "err p90 px", "{:.3f}"),
    ("rotation_error_median_deg", "rot err median deg", "{:.3f}"),
    ("f_inlier_rate", "F inlier rate", "{:.1%}"),
    ("f_epipolar_error_px", "epipolar err px", "{:.3f}"),
)
_MEASURES = (
    "Tracked share: features carried over from the previous frame over all features of frames 2..N. "
    "Track length: frames an id was seen (tracks alive at the end count as they are); `tracks >= 10 fr`: "
    "distinct tracks that reached 10 frames; `>= 10 fr per frame`: features per frame (frames 10..N) "
    "whose track is at least 10 frames old. Errors: each "
    "carried-over feature against the exact ground-truth flow of its previous position (occluded points "
    "left out). Rotation: 5-point RANSAC (`findEssentialMat`, 1 px threshold, + `recoverPose`) on the "
    "undistorted normalised points of consecutive frames, against the ground-truth relative rotation. "
    f"F (the paper's Table III method): `findFundamentalMat` RANSAC at {F_THRESHOLD_PX:g} px on "
    "undistorted pixels of consecutive frames; inlier rate over all features of the first frame, "
    "epipolar error = mean point-to-line distance of the inliers (px)."
)
"""What the table's figures are, in words."""


def _fmt(value: Any, fmt: str) -> str:
    if value is None or (isinstance(value, float) and not np.isfinite(value)):
        return "-"
    return fmt.format(value)


def _table(runs: dict[str, dict[str, MethodRun]]) -> str:
    head = "| level | method | " + " | ".join(c[1] for c in _COLUMNS) + " | ms/frame |"
    lines = [head, "|" + "---|" * (len(_COLUMNS) + 3)]
    for level, per in runs.items():
        for m, r in per.items():
            f = r.figures
            cells = [_fmt(f[k], fmt) for k, _, fmt in _COLUMNS]
            cells.append(_fmt(f["frame_ms_median"], "{:.1f}"))
            lines.append(f"| {level} | {m} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def _bar_figure(runs: dict[str, dict[str, MethodRun]], path: Path) -> Path:
    levels = list(runs)
    methods = list(next(iter(runs.values())))
    fig = new_figure(13, 9)
    axes = fig.subplots(3, 3).ravel()
    width = 0.8 / len(methods)
    x = np.arange(len(levels))
    for ax, (key, label, _) in zip(axes, _COLUMNS, strict=True):
        for k, m in enumerate(methods):
            vals = [runs[lv][m].figures.get(key) for lv in levels]
            ys = [np.nan if v is None else float(v) for v in vals]
            ax.bar(x + (k - (len(methods) - 1) / 2) * width, ys, width, label=m)
        ax.set_xticks(x, levels)
        ax.set_title(label, fontsize=10)
        ax.grid(axis="y", alpha=0.3)
    handles, labels = axes[0].get_legend_handles_labels()
    fig.suptitle("Front-end metrics per perturbation level (sample sequence, every frame tracked)")
    fig.tight_layout(rect=(0, 0, 1, 0.94))
    fig.legend(handles, labels, loc="upper center", ncol=len(methods), bbox_to_anchor=(0.5, 0.965))
    return save_figure(fig, path)


def _hist_figure(runs: dict[str, dict[str, MethodRun]], path: Path) -> Path:
    levels = list(runs)
    fig = new_figure(4.5 * len(levels), 3.6)
    axes = np.atleast_1d(fig.subplots(1, len(levels)))
    longest = max((max(r.lengths, default=1) for per in runs.values() for r in per.values()), default=1)
    bins = np.arange(1, longest + 2) - 0.5
    for ax, level in zip(axes, levels, strict=True):
        for m, r in runs[level].items():
            ax.hist(r.lengths, bins=bins, histtype="step", linewidth=1.5, label=m)
        ax.axvline(LONG_TRACK - 0.5, color="gray", linestyle="--", linewidth=1)
        ax.set_yscale("log")
        ax.set_xlabel("track length (frames)")
        ax.set_title(f"perturbation {level}")
    axes[0].set_ylabel("tracks")
    axes[0].legend(fontsize=8)
    fig.tight_layout()
    return save_figure(fig, path)


def _headline(runs: dict[str, dict[str, MethodRun]]) -> list[HeadlineRow]:
    """The figures of :data:`TARGET_ROWS` against :data:`TARGETS`, then the rotation error per level."""

    def row(level: str, key: str, metric: str, fmt: str, target: Target | None = None) -> HeadlineRow:
        figures = {m: r.figures.get(key) for m, r in runs[level].items()}
        return headline_row(metric, figures, lambda v: _fmt(v, fmt), target)

    rows = [row(level, key, metric, fmt, TARGETS[(level, key)])
            for (level, key), (metric, fmt) in TARGET_ROWS.items() if level in runs]  # fmt: skip
    return rows + [row(level, "rotation_error_median_deg",
                       f"5-point relative-rotation error, median, perturbation {level} (deg)", "{:.3f}")
                   for level in ("none", "large", "dark") if level in runs]  # fmt: skip


def _verdict(runs: dict[str, dict[str, MethodRun]]) -> str:
    """The issue's targets in words, with the figures that decide them and where tracks are lost."""
    lines = ["**Against the issue's targets** (computed from the table above):", ""]
    for row in _headline(runs):
        if row.met is None:
            continue
        ns, klt = row.values.get(NSFLOW, "-"), row.values.get(KLT, "-")
        lines.append(f"- {row.metric}: NSFlow {ns}, OpenCV KLT {klt}; target {row.target}: "
                     f"{'met' if row.met else '**not met**'}.")
    level = "none" if "none" in runs else next(iter(runs))
    parts = []
    for m, r in runs[level].items():
        f = r.figures
        if f.get("lost_near_border_share") is not None:
            share = f["lost_near_border_share"]
            parts.append(f"{m} {f['lost_per_frame']:.1f} per frame, {share:.0%} of them "
                         f"within {NEAR_BORDER_PX:g} px of the border")
    if parts:
        lines += ["", f"Tracks lost between frames (perturbation {level}): " + "; ".join(parts) + "."]
    return "\n".join(lines)


def learned_encoder(
    name: str, model: str | Path | None, threads: int | None, providers: str = "cpu"
) -> Encoder | None:
    """The encoder of a method of :data:`LEARNED`, as the method registry loads it for that method.

    Raises:
        EvaluationError: the model cannot be loaded.
    """
    try:
        return method_encoder(TRACKER_METHODS[name]["method"], model, threads, providers)
    except CoreError as err:
        raise EvaluationError(str(err)) from err


def load_source(ctx: EvalContext, setup: SequenceSetup) -> FrameSource:
    """The sample sequence of ``setup`` as a :class:`FrameSource`, made once
    (:func:`~nsflow_ros.evaluation.context.sample_sequence`); a scaled one keeps only the poses and
    scene on disk, since its frames are rendered in memory.

    Raises:
        EvaluationError: the sequence cannot be made.
    """
    seq = sample_sequence(ctx, KEY, setup.seed, setup.duration, stereo=False, images=setup.scale == 1,
                          progress=ctx.progress and not ctx.quick)  # fmt: skip
    return FrameSource(seq, setup.scale)


def run(ctx: EvalContext) -> Section:
    """The ``sequences`` section: bar chart, track-length histogram, table and headline rows.

    ``ctx.extra["sequences"]`` may hold ``duration`` (s), ``scale``, ``sequence_seed``, ``levels`` and
    ``cache_dir`` to override the quick / full setups.

    Raises:
        EvaluationError: no usable method, a model or sequence that cannot be loaded.
    """
    setup, levels = _setup(ctx)
    methods = [m.name for m in ctx.methods if m.name in TRACKER_METHODS]
    if not methods:
        have = [m.name for m in ctx.methods]
        raise EvaluationError(f"none of the run's methods {have} is one of {list(TRACKER_METHODS)}")
    encoders = method_encoders(ctx, methods)
    source = load_source(ctx, setup)
    runs = evaluate_sequences(
        source, methods, levels, settings=setup.tracker_settings(ctx), encoders=encoders, seed=ctx.seed,
        progress=ctx.progress,
    )
    out = Path(ctx.out_dir)
    figs = [
        _bar_figure(runs, out / f"{KEY}_metrics.png"),
        _hist_figure(runs, out / f"{KEY}_track_lengths.png"),
    ]
    md = "\n\n".join([
        _method_text(ctx, setup, source), _table(runs), _MEASURES, _verdict(runs),
        f"![front-end metrics]({figs[0].name})\n\n![track lengths]({figs[1].name})",
    ])
    data = {
        "setup": {
            "frames": len(source), "size": list(source.size), "sequence_seed": setup.seed,
            "perturb_seed": ctx.seed, "max_cnt": setup.max_cnt, "min_dist": setup.min_dist,
            "quick": ctx.quick, "f_threshold_px": F_THRESHOLD_PX,
        },
        "results": {lv: {m: r.figures for m, r in per.items()} for lv, per in runs.items()},
        # histogram counts: index = track length in frames
        "track_lengths": {
            lv: {m: np.bincount(r.lengths).tolist() if r.lengths else [] for m, r in per.items()}
            for lv, per in runs.items()
        },
    }  # fmt: skip
    return Section(KEY, "Front-end metrics on the sample sequences", md, figs, _headline(runs), data)


def _setup(ctx: EvalContext) -> tuple[SequenceSetup, tuple[str, ...]]:
    """The quick / full setup with ``ctx.extra["sequences"]``'s overrides, and the perturbation levels."""
    opts = dict(ctx.extra.get(KEY, {}))
    base = QUICK if ctx.quick else FULL
    setup = replace(
        base,
        duration=float(opts.get("duration", base.duration)),
        scale=float(opts.get("scale", base.scale)),
        seed=int(opts.get("sequence_seed", base.seed)),
    )
    return setup, tuple(opts.get("levels", LEVELS))


def method_encoders(ctx: EvalContext, methods: list[str]) -> dict[str, Encoder]:
    """The encoders of the methods that have one: the run's loaded models, the missing learned ones loaded.

    Raises:
        EvaluationError: a model cannot be loaded.
    """
    encoders: dict[str, Encoder] = {}
    for m in ctx.methods:
        if m.name in (*LEARNED, CLASSICAL) and m.encoder is not None:
            encoders[m.name] = m.encoder  # reuse the run's loaded model instead of opening it again
    for name in (n for n in LEARNED if n in methods and n not in encoders):
        encoders[name] = learned_encoder(name, ctx.model, ctx.threads, ctx.providers)
    return encoders


def _dark_text() -> str:
    """The dark perturbation's sensor model in words."""
    from nsflow_ros.data.perturb import DARK_SENSOR

    s = DARK_SENSOR
    return (f"{s.stops:g} stops under-exposed, Poisson shot noise on a {s.full_well_e:,.0f} e- full well, "
            f"{s.read_noise_e:g} e- read noise, gain x{s.total_gain:g}, 8-bit quantisation")


def _method_text(ctx: EvalContext, setup: SequenceSetup, source: FrameSource) -> str:
    """The paragraph saying what was run."""
    w, h = source.size
    mode = "quick mode (tiny sequence: numbers are not meaningful)" if ctx.quick else "full mode"
    return (
        f"Sample sequence seed {setup.seed}, {len(source)} frames at 20 Hz, {w}x{h} ({mode}); "
        f"perturbation seed {ctx.seed} (dark: {_dark_text()}). Every method runs through the VINS-style "
        "`FeatureTracker` "
        f"(max_cnt {setup.max_cnt}, min_dist {setup.min_dist:g}, flow-back 0.5 px), offline with every frame "
        "processed; the LM methods use the tracker's 6 levels, the OpenCV LK methods (KLT, KLT on CLAHE'd "
        "images, LK on the uint8 NSFlow descriptors) are called exactly as VINS-Fusion calls KLT (21x21, "
        "maxLevel 3, 30 iterations / eps 0.01)."
    )
