"""Trackable-region ratio (the paper's Table I and its heat-map figure).

As in the paper, every pixel (every ``stride``-th in quick mode) of a pair rendered from a held-out photo
is a keypoint whose initial flow is off by 15 px in a random direction, and the share recovered within
1 / 2 / 3 px is counted, without and with a full-strength lighting change, at the deployed depth and one
level fewer. A lighting change at full strength saturates parts of some photos and no descriptor keeps
what clipping erased, so the shares are also given among the keypoints whose solver window is not
clipped (:func:`clipped_windows`).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from nsflow_ros.core.methods import DEPLOYED_LM
from nsflow_ros.data.perturb import perturb_pair
from nsflow_ros.data.photos import HELDOUT_IMAGES, load_photo
from nsflow_ros.evaluation.context import (
    CONDITIONS,
    EvalContext,
    condition_label,
    level_reductions,
    levels_text,
    new_figure,
    save_figure,
)
from nsflow_ros.evaluation.errors import EvaluationError
from nsflow_ros.evaluation.methods import BASELINES, CLASSICAL, EvalMethod, PairResult, prepare_pair
from nsflow_ros.evaluation.pairs import (
    MARGIN,
    HomographyPair,
    endpoint_errors,
    inside,
    random_homography,
    render_pair,
    true_flow,
)
from nsflow_ros.evaluation.section import HeadlineRow, Section, config_data, quick_note
from nsflow_ros.evaluation.targets import Clause, Target, headline_row
from nsflow_ros.optional import require

__all__ = [
    "CLIP_SHARE",
    "QUICK",
    "TARGETS",
    "THRESHOLDS",
    "TrackableConfig",
    "TrackableMap",
    "clipped_windows",
    "make_trackable_pairs",
    "run",
    "trackable_map",
]

THRESHOLDS = (1.0, 2.0, 3.0)
CLIP_DARK, CLIP_BRIGHT = 5, 250  # gray values at or beyond which a pixel counts as clipped
CLIP_SHARE = 0.2
"""A window is clipped when more than this share of its pixels is (:func:`clipped_windows`)."""
TARGETS: dict[str, Target] = {
    "none": Target("ratio@1px", (Clause(">", (CLASSICAL,)), Clause(">=", bound=0.85, unit="%"))),
    "light": Target("ratio@1px", (Clause(">=", BASELINES, 1.5, label="the best baseline ({rivals})"),)),
}
"""Condition -> NSFlow's target on the median trackable-region ratio at 1 px (deployed levels)."""


@dataclass(frozen=True)
class TrackableConfig:
    """Settings of the trackable-region analysis.

    Attributes:
        width, height: frame size in pixels.
        stride: keypoint grid step (1 = every pixel, as the paper).
        photos: held-out photos, one pair per photo and condition.
        perturbation: length of the initial-flow error in pixels (the paper: 15).
        chunk: points per solver call (the result does not depend on it); it bounds memory, since the
            solver holds a (window + 2)^2 x d float32 patch per point.
    """

    width: int = 320
    height: int = 240
    stride: int = 1
    photos: tuple[str, ...] = HELDOUT_IMAGES
    perturbation: float = 15.0
    chunk: int = 2000


QUICK = TrackableConfig(width=160, height=120, stride=6, photos=HELDOUT_IMAGES[:1])
"""Tiny sizes for tests and CI."""


@dataclass(frozen=True)
class TrackableMap:
    """Per-pixel recovery errors of each method on one pair.

    Attributes:
        label: the pair ("coffee, light").
        image1: frame 1, (H, W) uint8.
        points: (N, 2) keypoints (integer pixel positions as float64).
        errors: method name -> (N,) endpoint errors, inf where lost.
        grid_shape: (rows, cols) of the keypoint grid; ``errors[m].reshape`` it after ``grid_index``.
        grid_index: (N, 2) int (row, col) of each keypoint in the grid.
        clipped: (N,) bool, the keypoint's solver window is clipped in either frame
            (:func:`clipped_windows`).
    """

    label: str
    image1: np.ndarray
    points: np.ndarray
    errors: dict[str, np.ndarray]
    grid_shape: tuple[int, int]
    grid_index: np.ndarray
    clipped: np.ndarray

    def ratios(self, unclipped: bool = False) -> dict[str, list[float]]:
        """Method name -> share of keypoints recovered within each of :data:`THRESHOLDS`.

        Args:
            unclipped: count only the keypoints whose windows are not clipped.
        """
        keep = ~self.clipped if unclipped else slice(None)
        return {
            n: [float(np.mean(e[keep] < t)) if e[keep].size else float("nan") for t in THRESHOLDS]
            for n, e in self.errors.items()
        }

    def grid(self, name: str) -> np.ndarray:
        """(rows, cols) float map of a method's errors; NaN where no keypoint was evaluated."""
        out = np.full(self.grid_shape, np.nan)
        out[self.grid_index[:, 0], self.grid_index[:, 1]] = self.errors[name]
        return out


def make_trackable_pairs(cfg: TrackableConfig, seed: int = 0) -> list[tuple[str, HomographyPair]]:
    """One mildly warped pair per photo and condition ("none", "light"), labelled; the same geometry for
    both conditions of a photo."""
    out = []
    for k, name in enumerate(cfg.photos):
        photo = load_photo(name)
        for cond in CONDITIONS:
            rng = np.random.default_rng([seed, 7, k])  # same geometry for both conditions
            p = random_homography(rng, cfg.width, cfg.height, 1.0)
            f1, f2 = render_pair(photo, rng, cfg.width, cfg.height, p)
            if cond == "light":
                f1, f2 = perturb_pair(f1, f2, np.random.default_rng([seed, 8, k]), 1.0)
            out.append((f"{name}, {cond}", HomographyPair(name, "trackable", 1, f1, f2, p)))
    return out


def clipped_windows(
    image1: np.ndarray, image2: np.ndarray, points1: np.ndarray, points2: np.ndarray, window: int,
    share: float = CLIP_SHARE,
) -> np.ndarray:
    """Which keypoints' ``window`` px windows are clipped: more than ``share`` of their pixels at or beyond
    :data:`CLIP_DARK` / :data:`CLIP_BRIGHT` gray, around the point in frame 1 or its true position in
    frame 2.

    Shape:
        image1, image2: (H, W) uint8. points1, points2: (N, 2). Returns (N,) bool.
    """

    def clipped_share(image: np.ndarray, pts: np.ndarray) -> np.ndarray:
        mask = ((image <= CLIP_DARK) | (image >= CLIP_BRIGHT)).astype(np.float32)
        frac = cv2.boxFilter(mask, -1, (window, window), borderType=cv2.BORDER_REPLICATE)
        h, w = image.shape
        x = np.clip(np.rint(pts[:, 0]).astype(int), 0, w - 1)
        y = np.clip(np.rint(pts[:, 1]).astype(int), 0, h - 1)
        return frac[y, x]

    return (clipped_share(image1, points1) > share) | (clipped_share(image2, points2) > share)


def _track_chunked(
    m: EvalMethod, frames: tuple, pts: np.ndarray, flow0: np.ndarray, chunk: int, levels: int
) -> PairResult:
    """The result for many points, ``chunk`` at a time."""
    flow = np.empty_like(pts)
    status = np.empty(len(pts), bool)
    for s in range(0, len(pts), chunk):
        sl = slice(s, s + chunk)
        res = m.track(*frames, pts[sl], flow0[sl], levels)
        flow[sl], status[sl] = res.flow, res.status
    return PairResult(flow, status)


def trackable_map(
    methods: list[EvalMethod],
    pair: HomographyPair,
    rng: np.random.Generator,
    *,
    stride: int = 1,
    perturbation: float = 15.0,
    chunk: int = 2000,
    label: str = "",
    fewer_levels: int = 0,
) -> TrackableMap:
    """Every (stride-th) pixel of frame 1 as a keypoint, recovered from a ``perturbation`` px offset.

    Args:
        rng: draws the direction of each keypoint's initial error (shared by all methods).
        stride: grid step in pixels (>= 1).
        perturbation: initial error length in pixels (>= 0).
        chunk: points per solver call.
        label: name of the pair in tables.
        fewer_levels: run each method on this many pyramid levels fewer than its own.

    Raises:
        EvaluationError: bad stride / perturbation / levels / methods, or frames of different shapes.

    Shape:
        pair.image1, pair.image2: (H, W) uint8.
    """
    if stride < 1:
        raise EvaluationError(f"stride must be >= 1, got {stride}")
    if not perturbation >= 0:
        raise EvaluationError(f"perturbation must be >= 0 px, got {perturbation}")
    if pair.image1.shape != pair.image2.shape or pair.image1.ndim != 2:
        raise EvaluationError(
            f"frames must be (H, W) of one shape, got {pair.image1.shape} and {pair.image2.shape}"
        )
    h, w = pair.image1.shape
    ys = np.arange(MARGIN, h - MARGIN, stride)
    xs = np.arange(MARGIN, w - MARGIN, stride)
    gy, gx = np.meshgrid(np.arange(len(ys)), np.arange(len(xs)), indexing="ij")
    index = np.stack([gy.ravel(), gx.ravel()], 1)
    pts = np.stack([xs[index[:, 1]], ys[index[:, 0]]], 1).astype(np.float64)
    gt = true_flow(pts, pair.homography)
    keep = inside(pts + gt, w, h)
    pts, gt, index = pts[keep], gt[keep], index[keep]
    ang = rng.uniform(0.0, 2.0 * np.pi, len(pts))
    flow0 = gt + perturbation * np.stack([np.cos(ang), np.sin(ang)], 1)
    frames = prepare_pair(methods, pair.image1, pair.image2)
    errors = {}
    for m in methods:
        res = _track_chunked(m, frames[m.name], pts, flow0, max(1, chunk), m.levels_fewer(fewer_levels))
        errors[m.name] = endpoint_errors(res, gt)
    clipped = clipped_windows(pair.image1, pair.image2, pts, pts + gt, DEPLOYED_LM.window)
    return TrackableMap(label, pair.image1, pts, errors, (len(ys), len(xs)), index, clipped)


def _heat_map(maps: list[TrackableMap], names: list[str], path: object) -> None:
    """Rows = pairs; columns = frame 1 and each method's recovery class per pixel."""
    colors = require("matplotlib.colors", "the trackable-regions figure")
    patch = require("matplotlib.patches", "the trackable-regions figure").Patch

    colours = ["#b2182b", "#ef8a62", "#fddbc7", "#2166ac"]  # <1, <2, <3, not recovered
    cmap = colors.ListedColormap(colours).with_extremes(bad="#d9d9d9")
    norm = colors.BoundaryNorm([0, 1, 2, 3, 4], cmap.N)
    cols = 1 + len(names)
    fig = new_figure(2.6 * cols, 2.1 * len(maps) + 0.6)
    axes = np.atleast_2d(fig.subplots(len(maps), cols))
    for r, tm in enumerate(maps):
        axes[r, 0].imshow(tm.image1, cmap="gray", vmin=0, vmax=255)
        axes[r, 0].set_title(f"{tm.label}: frame 1", fontsize=8)
        ratios = tm.ratios()
        for c, name in enumerate(names, start=1):
            err = tm.grid(name)
            cls = np.where(np.isnan(err), np.nan, np.digitize(np.nan_to_num(err, nan=0.0), THRESHOLDS) + 0.5)
            axes[r, c].imshow(cls, cmap=cmap, norm=norm, interpolation="nearest")
            axes[r, c].set_title(f"{name}\n@1 {ratios[name][0]:.0%} @3 {ratios[name][2]:.0%}", fontsize=8)
        for ax in axes[r]:
            ax.set_xticks([])
            ax.set_yticks([])
    labels = ["< 1 px", "1-2 px", "2-3 px", "not recovered"]
    fig.legend(
        [patch(color=c) for c in colours], labels, loc="lower center", ncol=4, fontsize=8, frameon=False
    )
    fig.suptitle("Trackable regions: recovery from a 15 px initial error, per pixel", fontsize=10)
    save_figure(fig, path)


def _median(ratios: dict[str, dict[str, list[float]]], names: list[str]) -> dict[str, dict[str, list[float]]]:
    """Condition -> method -> median over the condition's pairs of each threshold's share."""
    return {
        cond: {
            n: [float(np.median([r[n][i] for label, r in ratios.items() if label.endswith(cond)]))
                for i in range(len(THRESHOLDS))]
            for n in names
        }
        for cond in CONDITIONS
    }  # fmt: skip


def run(ctx: EvalContext, cfg: TrackableConfig | None = None) -> Section:
    """The ``trackable`` section (``trackable_heatmap.png``, the tables, headline rows).

    ``cfg`` None: :data:`QUICK` in a quick run, else ``TrackableConfig()``.
    """
    cfg = cfg or (QUICK if ctx.quick else TrackableConfig())
    names = [m.name for m in ctx.methods]
    fewer_set = level_reductions(ctx.methods)
    maps = _measure(ctx, cfg, make_trackable_pairs(cfg, ctx.seed), fewer_set)
    fig_path = ctx.out_dir / "trackable_heatmap.png"
    _heat_map(maps[0], names, fig_path)
    ratios = {f: {tm.label: tm.ratios() for tm in maps[f]} for f in fewer_set}
    median = {f: _median(ratios[f], names) for f in fewer_set}
    unclipped = {tm.label: tm.ratios(unclipped=True) for tm in maps[0]}
    median_unclipped = _median(unclipped, names)
    clipped_share = {tm.label: float(np.mean(tm.clipped)) if tm.clipped.size else 0.0 for tm in maps[0]}
    md = "\n".join([
        _method_text(ctx, cfg, maps), *_ratio_table(names, maps, ratios, median),
        *_clipped_table(ctx, names, maps[0], clipped_share, unclipped, median_unclipped), "",
        "(percent of keypoints)", "", f"![trackable regions]({fig_path.name})", "",
        "(heat map: the deployed levels)", "",
    ])  # fmt: skip
    data = {
        "config": config_data(cfg),
        "thresholds_px": list(THRESHOLDS),
        "levels": {m.name: m.levels for m in ctx.methods},
        "ratios": ratios[0],
        "median": median[0],
        "points": {tm.label: len(tm.points) for tm in maps[0]},
        "clipped_share": clipped_share,
        "ratios_unclipped": unclipped,
        "median_unclipped": median_unclipped,
    }
    if 1 in fewer_set:
        data["ratios_one_level_fewer"] = ratios[1]
        data["median_one_level_fewer"] = median[1]
    return Section("trackable", "Trackable-region ratio (paper Table I)", md, [fig_path],
                   _headline(ctx, median, median_unclipped), data)  # fmt: skip


def _measure(ctx: EvalContext, cfg: TrackableConfig, pairs: list[tuple[str, HomographyPair]],
             fewer_set: tuple[int, ...]) -> dict[int, list[TrackableMap]]:  # fmt: skip
    """Every method on every pair at each depth (levels fewer -> the pairs' maps)."""
    maps: dict[int, list[TrackableMap]] = {f: [] for f in fewer_set}
    jobs = [(f, k, label, pair) for f in fewer_set for k, (label, pair) in enumerate(pairs)]
    for f, k, label, pair in ctx.bar(jobs, desc="trackable", total=len(jobs), unit="pair"):
        rng = np.random.default_rng([ctx.seed, 9, k])  # the same offsets at either depth
        maps[f].append(
            trackable_map(
                ctx.methods, pair, rng, stride=cfg.stride, perturbation=cfg.perturbation, chunk=cfg.chunk,
                label=label, fewer_levels=f,
            )
        )  # fmt: skip
    return maps


def _method_text(ctx: EvalContext, cfg: TrackableConfig, maps: dict[int, list[TrackableMap]]) -> str:
    """The paragraph saying what was run."""
    grid = "every pixel" if cfg.stride == 1 else f"every {cfg.stride}th pixel in x and y"
    return (
        f"{len(maps[0])} pairs of {cfg.width}x{cfg.height} px (held-out photos {', '.join(cfg.photos)}, a "
        "mild homography, without and with full-strength illumination perturbation of both frames); "
        f"{grid} at least {MARGIN} px inside is a keypoint ({sum(len(tm.points) for tm in maps[0])} in "
        f"all), its initial flow off by {cfg.perturbation:g} px in a random direction; "
        f"{levels_text(ctx.methods)} for every method (what the tracker deploys)"
        + (f", and {levels_text(ctx.methods, 1)} (one fewer)" if 1 in maps else "")
        + ". Share of keypoints recovered within 1 / 2 / 3 px (a lost point is not recovered)."
        + quick_note(ctx.quick)
    )


def _cells(names: list[str], r: dict[str, list[float]]) -> str:
    """Each method's shares at 1 / 2 / 3 px in percent, as table cells."""
    return " | ".join("/".join(f"{100 * v:.1f}" for v in r[n]) for n in names)


def _ratio_table(names: list[str], maps: dict[int, list[TrackableMap]], ratios: dict,
                 median: dict) -> list[str]:  # fmt: skip
    """Each pair's shares and their median per condition, at each depth."""
    lines = ["", "| levels | pair | points | " + " | ".join(f"{n} @1/@2/@3" for n in names) + " |",
             "|---|---|---|" + "---|" * len(names)]  # fmt: skip
    for f, per in maps.items():
        tag = "deployed" if f == 0 else "one fewer"
        for tm in per:
            lines.append(f"| {tag} | {tm.label} | {len(tm.points)} | {_cells(names, ratios[f][tm.label])} |")
        for cond in CONDITIONS:
            lines.append(f"| {tag} | **median, {cond}** | | {_cells(names, median[f][cond])} |")
    return lines


def _clipped_table(ctx: EvalContext, names: list[str], maps: list[TrackableMap], clipped_share: dict,
                   unclipped: dict, median_unclipped: dict) -> list[str]:  # fmt: skip
    """The shares among the keypoints whose windows are not clipped, per pair and their median."""
    lines = [
        "", "(percent of keypoints)", "",
        f"Keypoints whose {DEPLOYED_LM.window} px window is clipped (more than {CLIP_SHARE:.0%} of its "
        f"pixels at <= {CLIP_DARK} or >= {CLIP_BRIGHT} gray around the keypoint in frame 1 or its true "
        "position in frame 2) carry little of the photo; the same shares among the others "
        f"({levels_text(ctx.methods)}):",
        "",
        "| pair | clipped windows | points not clipped | "
        + " | ".join(f"{n} @1/@2/@3" for n in names) + " |",
        "|---|---|---|" + "---|" * len(names),
    ]  # fmt: skip
    for tm in maps:
        lines.append(f"| {tm.label} | {100 * clipped_share[tm.label]:.1f} | {int(np.sum(~tm.clipped))} "
                     f"| {_cells(names, unclipped[tm.label])} |")  # fmt: skip
    for cond in CONDITIONS:
        lines.append(f"| **median, {cond}** | | | {_cells(names, median_unclipped[cond])} |")
    return lines


def _headline(ctx: EvalContext, median: dict[int, dict], median_unclipped: dict) -> list[HeadlineRow]:
    """The share at 1 px per condition against :data:`TARGETS`, among unclipped windows, one level fewer."""
    depth, pct = levels_text(ctx.methods), "{:.1%}".format
    rows = [headline_row(f"trackable region @1 px, {condition_label(cond)} ({depth})",
                         {n: v[0] for n, v in median[0][cond].items()}, pct, target)
            for cond, target in TARGETS.items()]  # fmt: skip
    rows.append(headline_row(f"trackable region @1 px, lighting change, windows not clipped ({depth})",
                             {n: v[0] for n, v in median_unclipped["light"].items()}, pct))  # fmt: skip
    fewer = f" ({levels_text(ctx.methods, 1)}: one fewer)"
    rows += [headline_row(f"trackable region @1 px, {condition_label(cond)}{fewer}",
                          {n: v[0] for n, v in median[1][cond].items()}, pct)
             for cond in CONDITIONS if 1 in median]  # fmt: skip
    return rows
