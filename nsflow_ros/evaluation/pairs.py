"""HPatches-style homography pairs from the held-out real photos: tracking error per method.

HPatches cannot be downloaded here, so the pairs are rendered from the photos held out of training
(:data:`~nsflow_ros.data.photos.HELDOUT_IMAGES`) with an exact homography: a **viewpoint** subset of
growing geometric strength and an **illumination** subset (mild geometry, both frames perturbed by
:func:`~nsflow_ros.data.perturb.perturb_pair` at growing strength). Up to 1000 GFTT keypoints (the paper's
NMS 6) whose true position stays inside frame 2 are tracked from zero flow at the deployed depth, so the
pairs measure the capture range as well as the accuracy; a lost point counts as an infinite error, so a
method cannot look better by dropping hard points.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from nsflow_ros.core.detector import detect_corners
from nsflow_ros.core.errors import CoreError
from nsflow_ros.data.errors import DataError
from nsflow_ros.data.perturb import perturb_pair
from nsflow_ros.data.photos import HELDOUT_IMAGES, load_photo
from nsflow_ros.evaluation.context import EvalContext, axis_label, levels_text, new_figure, save_figure
from nsflow_ros.evaluation.errors import EvaluationError
from nsflow_ros.evaluation.methods import CLASSICAL, KLT, KLT_CLAHE, EvalMethod, PairResult, prepare_pair
from nsflow_ros.evaluation.section import HeadlineRow, Section, config_data, quick_note
from nsflow_ros.evaluation.targets import Clause, Target, headline_row

__all__ = [
    "MARGIN",
    "QUICK",
    "SUBSETS",
    "TARGETS",
    "HomographyPair",
    "PairSetConfig",
    "endpoint_errors",
    "error_summary",
    "inside",
    "keep_inside",
    "keypoints",
    "make_pairs",
    "random_homography",
    "render_pair",
    "run",
    "true_flow",
]

SUBSETS = ("viewpoint", "illumination")
MARGIN = 10  # px; half of KLT's 21 px window, so every method's window fits at the true position
PLOT_CEILING = 50.0  # px; lost points are drawn at this error in the box plots
TARGETS: dict[tuple[str, str], Target] = {
    ("viewpoint", "median"): Target("median", (Clause("<=", (KLT,), 1.2, label="KLT"),)),
    ("viewpoint", "within_1px"): Target("within_1px", (Clause(">=", (CLASSICAL,)),)),
    ("illumination", "median"): Target("median", (Clause("<", (KLT,), label="KLT"),)),
    # under changing light: a high floor, and better than KLT on CLAHE'd images
    ("illumination", "within_1px"): Target(
        "within_1px", (Clause(">=", bound=0.97, unit="%"), Clause(">", (KLT_CLAHE,), optional=True))
    ),
}
"""(subset, figure) -> NSFlow's target on it, against the other methods' figures of the same subset."""


@dataclass(frozen=True)
class HomographyPair:
    """Two views of a photo related by an exact homography.

    Attributes:
        photo: name of the source photo.
        subset: "viewpoint" or "illumination".
        level: strength level (1 = mildest).
        image1, image2: the frames, (H, W) uint8.
        homography: (3, 3) float64 P, frame-1 pixel -> frame-2 pixel.
    """

    photo: str
    subset: str
    level: int
    image1: np.ndarray
    image2: np.ndarray
    homography: np.ndarray


@dataclass(frozen=True)
class PairSetConfig:
    """How many pairs, how big.

    Attributes:
        width, height: frame size in pixels.
        photos: source photos (held out of training).
        levels: strength levels 1..levels per subset.
        per_level: pairs per photo and level.
        max_points: GFTT keypoints per pair (at most).
        min_distance: GFTT minimum distance (the paper's NMS 6).
    """

    width: int = 480
    height: int = 360
    photos: tuple[str, ...] = HELDOUT_IMAGES
    levels: int = 5
    per_level: int = 3
    max_points: int = 1000
    min_distance: float = 6.0


QUICK = PairSetConfig(width=240, height=180, photos=HELDOUT_IMAGES[:1], levels=2, per_level=1, max_points=150)
"""Tiny sizes for tests and CI."""


def random_homography(rng: np.random.Generator, width: int, height: int, level: float) -> np.ndarray:
    """A random homography moving the frame corners by up to about ``6 * level`` pixels (0: identity).

    Rotation about the centre (up to 1 degree per level), scale (1 +- 1 % per level), translation and
    independent corner jitter (each up to 2 px per level), composed.

    Returns:
        P, (3, 3) float64, frame-1 pixel -> frame-2 pixel.
    """
    corners = np.float32([[0, 0], [width - 1, 0], [width - 1, height - 1], [0, height - 1]])
    centre = np.array([(width - 1) / 2, (height - 1) / 2])
    theta = np.deg2rad(rng.uniform(-1, 1) * level)
    scale = 1.0 + 0.01 * level * rng.uniform(-1, 1)
    rot = scale * np.array([[np.cos(theta), -np.sin(theta)], [np.sin(theta), np.cos(theta)]])
    moved = (corners - centre) @ rot.T + centre
    moved += 2.0 * level * rng.uniform(-1, 1, 2)
    moved += 2.0 * level * rng.uniform(-1, 1, (4, 2))
    return cv2.getPerspectiveTransform(corners, moved.astype(np.float32)).astype(np.float64)


def render_pair(
    photo: np.ndarray, rng: np.random.Generator, width: int, height: int, homography: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Render frame 1 (a random crop of the photo) and frame 2 (the crop seen through ``homography``).

    Args:
        photo: (H, W) uint8 source photo.
        rng: random generator (crop position and size).
        width, height: frame size.
        homography: (3, 3) P, frame-1 pixel -> frame-2 pixel.

    Returns:
        (frame1, frame2), each (height, width) uint8.

    Raises:
        EvaluationError: a photo that is not (H, W) uint8, or a homography that is not (3, 3).
    """
    if photo.ndim != 2 or photo.dtype != np.uint8:
        raise EvaluationError(f"photo must be (H, W) uint8, got {photo.shape} {photo.dtype}")
    if np.shape(homography) != (3, 3):
        raise EvaluationError(f"homography must be (3, 3), got {np.shape(homography)}")
    sh, sw = photo.shape
    # photo pixels per frame pixel: most of the photo, so little upsampling blurs the texture away
    scale = min(sw / width, sh / height) * rng.uniform(0.8, 0.95)
    x0 = rng.uniform(0, sw - scale * width)
    y0 = rng.uniform(0, sh - scale * height)
    m1 = np.array([[scale, 0, x0], [0, scale, y0], [0, 0, 1]])  # frame-1 pixel -> photo pixel
    if scale > 1.0:
        # anti-aliasing before the bilinear downsampling: otherwise aliasing differs between the two
        # views and puts a floor under every method's error
        photo = cv2.GaussianBlur(photo, (0, 0), 0.5 * np.sqrt(scale**2 - 1.0))
    flags = cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP
    f1 = cv2.warpPerspective(photo, m1, (width, height), flags=flags, borderMode=cv2.BORDER_REFLECT_101)
    f2 = cv2.warpPerspective(
        photo, m1 @ np.linalg.inv(homography), (width, height), flags=flags, borderMode=cv2.BORDER_REFLECT_101
    )
    return f1, f2


def make_pairs(subset: str, cfg: PairSetConfig, seed: int = 0) -> list[HomographyPair]:
    """The ``len(cfg.photos) * cfg.levels * cfg.per_level`` pairs of one subset, mildest first.

    Raises:
        EvaluationError: unknown subset or photo.
    """
    if subset not in SUBSETS:
        raise EvaluationError(f"subset must be one of {SUBSETS}, got {subset!r}")
    pairs = []
    for level in range(1, cfg.levels + 1):
        for k, name in enumerate(cfg.photos):
            try:
                photo = load_photo(name)
            except DataError as err:
                raise EvaluationError(str(err)) from err
            for i in range(cfg.per_level):
                rng = np.random.default_rng([seed, SUBSETS.index(subset), level, k, i])
                geo = level if subset == "viewpoint" else 1
                p = random_homography(rng, cfg.width, cfg.height, geo)
                f1, f2 = render_pair(photo, rng, cfg.width, cfg.height, p)
                if subset == "illumination":
                    f1, f2 = perturb_pair(f1, f2, rng, level / cfg.levels)  # top level: full strength
                pairs.append(HomographyPair(name, subset, level, f1, f2, p))
    return pairs


def keypoints(image: np.ndarray, max_points: int = 1000, min_distance: float = 6.0) -> np.ndarray:
    """GFTT keypoints as the paper's evaluation takes them (1000, NMS 6), strongest first.

    Shape:
        image: (H, W) uint8. Returns (N, 2) float64 (x, y).

    Raises:
        EvaluationError: a bad image.
    """
    try:
        return detect_corners(image, max_points, min_distance=min_distance)
    except CoreError as err:
        raise EvaluationError(str(err)) from err


def true_flow(points: np.ndarray, homography: np.ndarray) -> np.ndarray:
    """Exact flow P(x) - x of frame-1 points under the homography P.

    Shape:
        points: (N, 2). homography: (3, 3). Returns (N, 2) float64.

    Raises:
        EvaluationError: points that are not (N, 2).
    """
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 2:
        raise EvaluationError(f"points must be (N, 2), got {pts.shape}")
    if len(pts) == 0:
        return np.zeros((0, 2))
    return cv2.perspectiveTransform(pts[None], np.asarray(homography, np.float64))[0] - pts


def inside(points: np.ndarray, width: int, height: int, margin: float = MARGIN) -> np.ndarray:
    """(N,) bool: the points lie at least ``margin`` px inside a width x height frame."""
    return (
        (points[:, 0] >= margin)
        & (points[:, 0] <= width - 1 - margin)
        & (points[:, 1] >= margin)
        & (points[:, 1] <= height - 1 - margin)
    )


def keep_inside(
    points: np.ndarray, flow: np.ndarray, width: int, height: int
) -> tuple[np.ndarray, np.ndarray]:
    """The points, and their flow, whose true position ``points + flow`` lies :data:`MARGIN` px inside."""
    keep = inside(points + flow, width, height)
    return points[keep], flow[keep]


def endpoint_errors(result: PairResult, flow_gt: np.ndarray) -> np.ndarray:
    """Endpoint error (px) of every point, infinite where the method lost it or its flow is not finite.

    Shape:
        result: N points. flow_gt: (N, 2). Returns (N,) float64.

    Raises:
        EvaluationError: the shapes differ.
    """
    if result.flow.shape != flow_gt.shape:
        raise EvaluationError(f"flow has shape {result.flow.shape}, ground truth {flow_gt.shape}")
    with np.errstate(invalid="ignore"):
        err = np.linalg.norm(result.flow - flow_gt, axis=1)
    return np.where(result.status & np.isfinite(err), err, np.inf)


def error_summary(errors: np.ndarray) -> dict[str, float]:
    """``median`` (lost = inf), ``within_1px`` / ``2px`` / ``3px``, ``tracked``, ``median_tracked``,
    ``mean_tracked`` and ``points`` of (N,) errors (inf where lost; nan statistics for no points)."""
    e = np.asarray(errors, dtype=np.float64).reshape(-1)
    if e.size == 0:
        nan = float("nan")
        return dict(median=nan, within_1px=nan, within_2px=nan, within_3px=nan, tracked=nan,
                    median_tracked=nan, mean_tracked=nan, points=0)  # fmt: skip
    fin = e[np.isfinite(e)]
    return {
        "median": float(np.median(e)),
        "within_1px": float(np.mean(e < 1.0)),
        "within_2px": float(np.mean(e < 2.0)),
        "within_3px": float(np.mean(e < 3.0)),
        "tracked": float(fin.size / e.size),
        "median_tracked": float(np.median(fin)) if fin.size else float("nan"),
        "mean_tracked": float(np.mean(fin)) if fin.size else float("nan"),
        "points": int(e.size),
    }


def _track_pair(
    pair: HomographyPair, methods: list[EvalMethod], cfg: PairSetConfig
) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """The true displacement of one pair's keypoints, and each method's errors."""
    pts = keypoints(pair.image1, cfg.max_points, cfg.min_distance)
    pts, gt = keep_inside(pts, true_flow(pts, pair.homography), cfg.width, cfg.height)
    frames = prepare_pair(methods, pair.image1, pair.image2)
    errs = {m.name: endpoint_errors(m.track(*frames[m.name], pts), gt) for m in methods}
    return np.linalg.norm(gt, axis=1), errs


def _fmt(v: float, digits: int = 3) -> str:
    return "nan" if np.isnan(v) else ("inf" if np.isinf(v) else f"{v:.{digits}f}")


def _box_plot(errors: dict[str, dict[str, np.ndarray]], names: list[str], path: object) -> None:
    """Box plots per method for each subset and for all pairs (lost points drawn at the ceiling)."""
    panels = [*SUBSETS, "all"]
    fig = new_figure(max(4.0, 1.1 * len(names)) * len(panels), 4.2)
    axes = fig.subplots(1, len(panels), sharey=True)
    for ax, panel in zip(axes, panels, strict=True):
        data, labels = [], []
        for name in names:
            e = np.concatenate([errors[s][name] for s in SUBSETS]) if panel == "all" else errors[panel][name]
            tracked = float(np.mean(np.isfinite(e))) if e.size else float("nan")
            data.append(np.clip(np.nan_to_num(e, posinf=PLOT_CEILING), 1e-3, PLOT_CEILING))
            labels.append(f"{axis_label(name)}\ntracked {tracked:.0%}")
        ax.boxplot(data, whis=(5, 95), showfliers=False, medianprops={"color": "crimson"})
        ax.set_xticks(range(1, len(labels) + 1), labels, fontsize=7)
        ax.set_yscale("log")
        ax.axhline(1.0, color="gray", lw=0.6, ls=":")
        ax.set_title(f"{panel} pairs")
        ax.grid(True, axis="y", which="both", alpha=0.3)
    axes[0].set_ylabel(f"endpoint error (px, log; lost drawn at {PLOT_CEILING:.0f})")
    fig.suptitle("Tracking error on homography pairs of held-out photos (boxes 25-75 %, whiskers 5-95 %)")
    save_figure(fig, path)


@dataclass(frozen=True)
class _Subset:
    """One subset's tracking: pairs, each method's errors over all of them and per strength level."""

    count: int
    errors: dict[str, np.ndarray]
    per_level: dict[int, dict[str, dict[str, float]]]
    displacement: dict[int, float]


def run(ctx: EvalContext, cfg: PairSetConfig | None = None) -> Section:
    """The ``pairs`` section: every method on both subsets (``pairs_boxplot.png``, tables, headline rows).

    ``cfg`` None: :data:`QUICK` in a quick run, else ``PairSetConfig()``.
    """
    cfg = cfg or (QUICK if ctx.quick else PairSetConfig())
    names = [m.name for m in ctx.methods]
    subsets = {s: _track_subset(ctx, cfg, s, names) for s in SUBSETS}
    summary = {s: {n: error_summary(subsets[s].errors[n]) for n in names} for s in SUBSETS}
    fig_path = ctx.out_dir / "pairs_boxplot.png"
    _box_plot({s: r.errors for s, r in subsets.items()}, names, fig_path)
    md = _markdown(ctx, cfg, names, subsets, summary, fig_path.name)
    return Section("pairs", "Tracking error on homography pairs (HPatches-style)", md, [fig_path],
                   _headline(summary, names), _data(cfg, subsets, summary))  # fmt: skip


def _track_subset(ctx: EvalContext, cfg: PairSetConfig, subset: str, names: list[str]) -> _Subset:
    """Every method on every pair of one subset, pooled and per strength level."""
    pairs = make_pairs(subset, cfg, ctx.seed)
    collected: dict[int, list[tuple[np.ndarray, dict[str, np.ndarray]]]] = {}
    for pair in ctx.bar(pairs, desc=f"pairs {subset}", unit="pair"):
        collected.setdefault(pair.level, []).append(_track_pair(pair, ctx.methods, cfg))
    errors = {n: np.concatenate([e[n] for lv in collected.values() for _, e in lv]) for n in names}
    per_level = {
        lv: {n: error_summary(np.concatenate([e[n] for _, e in items])) for n in names}
        for lv, items in collected.items()
    }
    displacement = {
        lv: float(np.median(np.concatenate([d for d, _ in items]))) for lv, items in collected.items()
    }
    return _Subset(len(pairs), errors, per_level, displacement)


def _markdown(ctx: EvalContext, cfg: PairSetConfig, names: list[str], subsets: dict[str, _Subset],
              summary: dict[str, dict[str, dict[str, float]]], figure: str) -> str:  # fmt: skip
    """The section's text: what was run, the per-subset table, the per-level table, the figure."""
    counts = {s: r.count for s, r in subsets.items()}
    lines = [
        f"{sum(counts.values())} pairs ({counts['viewpoint']} viewpoint, {counts['illumination']} "
        f"illumination) of {cfg.width}x{cfg.height} px rendered from the held-out photos "
        f"{', '.join(cfg.photos)} with exact homographies; up to {cfg.max_points} GFTT keypoints "
        f"(minimum distance {cfg.min_distance:g} px) on frame 1, tracked from zero initial flow at "
        f"{levels_text(ctx.methods)} by every method (the tracker's deployed depth). A lost point counts as "
        "an infinite error." + quick_note(ctx.quick),
        "",
        "| subset | method | points | median error (px) | < 1 px | < 3 px | tracked "
        "| median of tracked (px) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for s in SUBSETS:
        for n in names:
            m = summary[s][n]
            lines.append(
                f"| {s} | {n} | {m['points']} | {_fmt(m['median'])} | {m['within_1px']:.1%} "
                f"| {m['within_3px']:.1%} | {m['tracked']:.1%} | {_fmt(m['median_tracked'])} |"
            )
    lines += [
        "",
        "Median error (px) / share < 1 px per strength level (viewpoint: corners moved by up to ~6k px; "
        f"illumination: perturbation strength k/{cfg.levels} on both frames):",
        "",
        "| subset | level | median true displacement (px) | " + " | ".join(names) + " |",
        "|---|---|---|" + "---|" * len(names),
    ]
    for s in SUBSETS:
        per_level = subsets[s].per_level
        for lv in sorted(per_level):
            cells = [f"{_fmt(per_level[lv][n]['median'])} / {per_level[lv][n]['within_1px']:.0%}"
                     for n in names]  # fmt: skip
            lines.append(f"| {s} | {lv} | {subsets[s].displacement[lv]:.1f} | " + " | ".join(cells) + " |")
    return "\n".join([*lines, "", f"![tracking error box plots]({figure})", ""])


def _headline(summary: dict[str, dict[str, dict[str, float]]], names: list[str]) -> list[HeadlineRow]:
    """The median error and share within 1 px of each subset against their :data:`TARGETS`."""
    metrics = {"median": ("median error (px)", _fmt), "within_1px": ("share < 1 px", "{:.1%}".format)}
    return [
        headline_row(f"pairs {s}: {metrics[key][0]}", {n: summary[s][n][key] for n in names}, metrics[key][1],
                     target)
        for (s, key), target in TARGETS.items()
    ]  # fmt: skip


def _data(cfg: PairSetConfig, subsets: dict[str, _Subset], summary: dict) -> dict:
    """The section's JSON data."""
    def by_level(field: str) -> dict[str, dict[str, object]]:
        return {s: {str(lv): v for lv, v in getattr(r, field).items()} for s, r in subsets.items()}

    return {"config": config_data(cfg), "pairs": {s: r.count for s, r in subsets.items()}, "summary": summary,
            "per_level": by_level("per_level"), "median_displacement": by_level("displacement")}  # fmt: skip
