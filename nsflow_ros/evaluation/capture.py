"""Capture from zero flow: how far can a method bring a point it starts on, at the deployed pyramid depth.

The tracker starts most solves with no knowledge of the motion (a point's first track, stereo left ->
right), so this measures the share of GFTT keypoints a method brings within 1 px of the truth from zero
flow, at the deployed depth and one level fewer, without and with a full-strength lighting change, on
two sources: held-out photos shifted by 5-30 px (:mod:`nsflow_ros.evaluation.pairs`), and left / right
pairs of the sample room rendered through EuRoC's two cameras (unrectified, as VINS tracks them) with
the exact disparity from the scene geometry.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from nsflow_ros.data.perturb import perturb_pair
from nsflow_ros.data.photos import HELDOUT_IMAGES, load_photo
from nsflow_ros.evaluation.context import (
    CONDITIONS,
    EvalContext,
    condition_label,
    level_reductions,
    levels_text,
    new_figure,
    sample_sequence,
    save_figure,
)
from nsflow_ros.evaluation.errors import EvaluationError
from nsflow_ros.evaluation.methods import KLT, KLT_CLAHE, NSFLOW, EvalMethod, prepare_pair
from nsflow_ros.evaluation.pairs import (
    endpoint_errors,
    keep_inside,
    keypoints,
    random_homography,
    render_pair,
    true_flow,
)
from nsflow_ros.evaluation.section import HeadlineRow, Section, config_data, quick_note
from nsflow_ros.evaluation.targets import Clause, Target, headline_row

__all__ = [
    "BIN_EDGES",
    "CONDITIONS",
    "KEY",
    "QUICK",
    "SOURCES",
    "TARGETS",
    "CaptureConfig",
    "CapturePair",
    "capture_errors",
    "load_stereo_sequence",
    "photo_pairs",
    "run",
    "shift_homography",
    "stereo_pairs",
    "stretch_target",
]

KEY = "capture"
SOURCES = ("photo shifts", "stereo")
BIN_EDGES = (2.5, 7.5, 12.5, 17.5, 22.5, 27.5, 32.5)
"""Displacement bins (px) of the per-displacement table and plot, centred on 5, 10, ..., 30."""
TARGETS: dict[str, Target] = {
    "none": Target("share_within_1px", (Clause(">=", (KLT,)),)),
    "light": Target("share_within_1px", (Clause(">=", (KLT,)), Clause(">", (KLT_CLAHE,), optional=True))),
}
"""Condition -> NSFlow's target on the share within 1 px of each source at the deployed levels."""


def stretch_target(depth: str, klt_share: float) -> Target:
    """The stretch goal: NSFlow at one level fewer captures at least what KLT does at the deployed levels.

    Args:
        depth: KLT's deployed levels in words.
        klt_share: KLT's pooled share within 1 px at its deployed levels (NaN: KLT not evaluated).

    Returns:
        the target, checked on ``{NSFLOW: share at one level fewer, KLT: share at the deployed levels}``.
    """
    label = f"{KLT} at {depth} ({100 * klt_share:.1f}%)"
    return Target("pooled_within_1px", (Clause(">=", (KLT,), label=label),), stretch=True,
                  subject_text="NSFlow here")  # fmt: skip


@dataclass(frozen=True)
class CaptureConfig:
    """Settings of the capture analysis.

    Attributes:
        width, height: size of the photo pairs in pixels.
        photos: held-out photos.
        displacements: nominal shifts of the photo pairs (px).
        per_displacement: photo pairs per photo and displacement.
        max_points: GFTT keypoints per photo pair (at most).
        min_distance: GFTT minimum distance (px).
        stereo_frames: stereo pairs, evenly spaced over the sample sequence.
        stereo_duration: seconds of sample sequence to draw them from.
        stereo_points: GFTT keypoints per left image (at most).
        sequence_seed: seed of the sample sequence (scene and flight).
    """

    width: int = 480
    height: int = 360
    photos: tuple[str, ...] = HELDOUT_IMAGES
    displacements: tuple[float, ...] = (5.0, 10.0, 15.0, 20.0, 25.0, 30.0)
    per_displacement: int = 1
    max_points: int = 500
    min_distance: float = 8.0
    stereo_frames: int = 8
    stereo_duration: float = 8.0
    stereo_points: int = 300
    sequence_seed: int = 0


QUICK = CaptureConfig(
    width=240, height=180, photos=HELDOUT_IMAGES[:1], displacements=(5.0, 15.0, 30.0),
    max_points=80, stereo_frames=1, stereo_duration=0.6, stereo_points=80,
)  # fmt: skip
"""Tiny sizes for tests and CI."""


@dataclass(frozen=True)
class CapturePair:
    """Two frames, keypoints in the first and their exact displacement into the second.

    Attributes:
        source: one of :data:`SOURCES`.
        condition: "none" or "light".
        label: the pair in words ("coffee, 15 px", "stereo frame 40").
        image1, image2: (H, W) uint8 frames.
        points: (N, 2) keypoints in frame 1.
        flow: (N, 2) their exact displacement into frame 2.
    """

    source: str
    condition: str
    label: str
    image1: np.ndarray
    image2: np.ndarray
    points: np.ndarray
    flow: np.ndarray


def shift_homography(rng: np.random.Generator, width: int, height: int, shift: float) -> np.ndarray:
    """A translation by ``shift`` px in a random direction after a mild random homography (level 0.3).

    Returns:
        P, (3, 3) float64, frame-1 pixel -> frame-2 pixel.
    """
    ang = rng.uniform(0.0, 2.0 * np.pi)
    move = np.array([[1.0, 0.0, shift * np.cos(ang)], [0.0, 1.0, shift * np.sin(ang)], [0.0, 0.0, 1.0]])
    return move @ random_homography(rng, width, height, 0.3)


def photo_pairs(cfg: CaptureConfig, seed: int = 0) -> list[CapturePair]:
    """The ``2 * len(photos) * len(displacements) * per_displacement`` photo-shift pairs: each without and
    with a lighting change (same geometry and points)."""
    out = []
    for k, name in enumerate(cfg.photos):
        photo = load_photo(name)
        for di, shift in enumerate(cfg.displacements):
            for i in range(cfg.per_displacement):
                rng = np.random.default_rng([seed, 21, k, di, i])
                p = shift_homography(rng, cfg.width, cfg.height, shift)
                f1, f2 = render_pair(photo, rng, cfg.width, cfg.height, p)
                pts = keypoints(f1, cfg.max_points, cfg.min_distance)
                pts, gt = keep_inside(pts, true_flow(pts, p), cfg.width, cfg.height)
                label = f"{name}, {shift:g} px"
                out.append(CapturePair(SOURCES[0], "none", label, f1, f2, pts, gt))
                l1, l2 = perturb_pair(f1, f2, np.random.default_rng([seed, 22, k, di, i]), 1.0)
                out.append(CapturePair(SOURCES[0], "light", label, l1, l2, pts, gt))
    return out


def stereo_pairs(sequence: Any, cfg: CaptureConfig, seed: int = 0) -> list[CapturePair]:
    """``2 * cfg.stereo_frames`` left / right pairs (fewer when the sequence is shorter) of a stereo
    :class:`~nsflow_ros.data.sample.SampleSequence` with exact disparities, without and with light.

    Raises:
        EvaluationError: the sequence has no second camera.
    """
    if len(sequence.cameras) < 2:
        raise EvaluationError("the capture analysis needs a stereo sample sequence (two cameras)")
    n = len(sequence)
    frames = sorted({round(float(v)) for v in np.linspace(0, n - 1, max(1, min(cfg.stereo_frames, n)))})
    out = []
    for i in frames:
        left, right = sequence.image(i, 0), sequence.image(i, 1)
        h, w = left.shape[:2]
        pts = keypoints(left, cfg.stereo_points, cfg.min_distance)
        flow, visible = sequence.flow(i, i, pts, 0, 1)
        pts, flow = keep_inside(pts[visible], flow[visible], w, h)
        label = f"stereo frame {i}"
        out.append(CapturePair(SOURCES[1], "none", label, left, right, pts, flow))
        l1, l2 = perturb_pair(left, right, np.random.default_rng([seed, 23, i]), 1.0)
        out.append(CapturePair(SOURCES[1], "light", label, l1, l2, pts, flow))
    return out


def capture_errors(
    methods: list[EvalMethod], pair: CapturePair, fewer_levels: int = 0
) -> dict[str, np.ndarray]:
    """Each method's (N,) endpoint errors (inf where lost) tracking the pair's keypoints from zero flow,
    ``fewer_levels`` below its own depth (a stereo pair's: the depth of the tracker's first stereo solve).

    Raises:
        EvaluationError: an object that is not an evaluation method, or too few levels to remove.
    """
    frames = prepare_pair(methods, pair.image1, pair.image2)
    out = {}
    stereo = pair.source == SOURCES[1]
    for m in methods:
        res = m.track(*frames[m.name], pair.points, None, m.levels_fewer(fewer_levels, stereo))
        out[m.name] = endpoint_errors(res, pair.flow)
    return out


def load_stereo_sequence(ctx: EvalContext, cfg: CaptureConfig) -> Any:
    """The stereo sample sequence (poses and scene only: frames are rendered when asked), made once
    (:func:`~nsflow_ros.evaluation.context.sample_sequence`)."""
    return sample_sequence(ctx, KEY, cfg.sequence_seed, cfg.stereo_duration, stereo=True, images=False,
                           progress=False)  # fmt: skip


def _share(errors: list[np.ndarray]) -> float:
    e = np.concatenate(errors) if errors else np.zeros(0)
    return float(np.mean(e < 1.0)) if e.size else float("nan")


def _bin_shares(errors: list[np.ndarray], displacement: list[np.ndarray]) -> list[float]:
    e = np.concatenate(errors) if errors else np.zeros(0)
    d = np.concatenate(displacement) if displacement else np.zeros(0)
    out = []
    for lo, hi in itertools.pairwise(BIN_EDGES):
        sel = (d >= lo) & (d < hi)
        out.append(float(np.mean(e[sel] < 1.0)) if sel.any() else float("nan"))
    return out


def _centres() -> list[float]:
    return [(lo + hi) / 2 for lo, hi in itertools.pairwise(BIN_EDGES)]


def _plot(bins: dict, names: list[str], fewer_set: tuple[int, ...], path: Path) -> None:
    fig = new_figure(11.0, 7.5)
    axes = fig.subplots(len(SOURCES), len(CONDITIONS), sharex=True, sharey=True)
    colours = ["#d62728", "#ff7f0e", "#1f77b4", "#2ca02c", "#9467bd", "#8c564b"]
    x = _centres()
    for r, source in enumerate(SOURCES):
        for c, cond in enumerate(CONDITIONS):
            ax = axes[r, c]
            for j, n in enumerate(names):
                for f in fewer_set:
                    ys = np.asarray(bins[(source, cond, f)][n])
                    have = np.isfinite(ys)  # bins without keypoints are skipped, not drawn as gaps
                    ax.plot(np.asarray(x)[have], 100 * ys[have], color=colours[j % len(colours)], marker="o",
                            ms=3,
                            ls="-" if f == 0 else "--", lw=1.6 if f == 0 else 1.0,
                            label=n if f == 0 else f"{n}, one level fewer")  # fmt: skip
            ax.set_title(f"{source}, {condition_label(cond)}", fontsize=9)
            ax.set_ylim(-3, 103)
            ax.grid(True, alpha=0.3)
    for ax in axes[-1]:
        ax.set_xlabel("true displacement (px, 5 px bins)")
    for ax in axes[:, 0]:
        ax.set_ylabel("share within 1 px (%)")
    handles, labels = axes[0, 0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower center", ncol=len(names), fontsize=7, frameon=False)
    fig.suptitle("Capture from zero flow: solid = deployed levels, dashed = one level fewer", fontsize=10)
    fig.tight_layout(rect=(0, 0.07, 1, 0.97))
    save_figure(fig, path)


@dataclass(frozen=True)
class _Shares:
    """Each method's share within 1 px per (source, condition, levels fewer), per bin, pooled over sources."""

    names: list[str]
    fewer_set: tuple[int, ...]
    share: dict[tuple[str, str, int], dict[str, float]]
    bins: dict[tuple[str, str, int], dict[str, list[float]]]
    pooled: dict[tuple[str, int], dict[str, float]]


def run(ctx: EvalContext, cfg: CaptureConfig | None = None) -> Section:
    """The ``capture`` section (``capture.png``, the tables, headline rows).

    ``cfg`` None: :data:`QUICK` in a quick run, else ``CaptureConfig()``.

    Raises:
        EvaluationError: no methods, or the sample sequence cannot be made.
    """
    cfg = cfg or (QUICK if ctx.quick else CaptureConfig())
    if not ctx.methods:
        raise EvaluationError("capture needs at least one method")
    pairs = photo_pairs(cfg, ctx.seed) + stereo_pairs(load_stereo_sequence(ctx, cfg), cfg, ctx.seed)
    shares, displacement = _measure(ctx, pairs)
    fig_path = ctx.out_dir / f"{KEY}.png"
    _plot(shares.bins, shares.names, shares.fewer_set, fig_path)
    clean = [p for p in pairs if p.condition == "none"]  # the lit copies share geometry and points
    points = {s: sum(len(p.points) for p in clean if p.source == s) for s in SOURCES}
    n_pairs = {s: sum(1 for p in clean if p.source == s) for s in SOURCES}
    stereo_d = np.concatenate([np.zeros(0), *displacement[(SOURCES[1], "none")]])
    stereo_d = stereo_d if stereo_d.size else np.full(1, np.nan)
    md = "\n".join([_method_text(ctx, cfg, n_pairs, points, stereo_d, shares.fewer_set),
                    *_tables(ctx, shares, fig_path.name)])  # fmt: skip
    data = {
        "config": config_data(cfg),
        "levels": {m.name: m.levels for m in ctx.methods},
        "stereo_levels": {m.name: m.stereo_levels for m in ctx.methods},
        "pairs": n_pairs,
        "points": points,
        "bin_edges_px": list(BIN_EDGES),
        **_share_data(shares),
        "stereo_disparity_px": {
            "min": float(np.min(stereo_d)), "median": float(np.median(stereo_d)),
            "max": float(np.max(stereo_d)),
        },
    }  # fmt: skip
    return Section(KEY, "Capture from zero flow (photo shifts and EuRoC-baseline stereo)", md,
                   [fig_path], _headline(ctx, shares), data)  # fmt: skip


def _measure(ctx: EvalContext, pairs: list[CapturePair]) -> tuple[_Shares, dict[tuple[str, str], list]]:
    """Every method on every pair at each depth: the shares, and the true displacements per source, light."""
    names = [m.name for m in ctx.methods]
    fewer_set = level_reductions(ctx.methods)
    errors: dict[tuple[str, str, int], dict[str, list[np.ndarray]]] = {}
    displacement: dict[tuple[str, str], list[np.ndarray]] = {}
    for pair in ctx.bar(pairs, desc=KEY, unit="pair"):
        displacement.setdefault((pair.source, pair.condition), []).append(np.linalg.norm(pair.flow, axis=1))
        for f in fewer_set:
            per = errors.setdefault((pair.source, pair.condition, f), {n: [] for n in names})
            for n, e in capture_errors(ctx.methods, pair, f).items():
                per[n].append(e)
    share = {key: {n: _share(v) for n, v in per.items()} for key, per in errors.items()}
    bins = {
        key: {n: _bin_shares(v, displacement[key[:2]]) for n, v in per.items()} for key, per in errors.items()
    }
    pooled = {
        (cond, f): {n: _share([e for s in SOURCES for e in errors[(s, cond, f)][n]]) for n in names}
        for cond in CONDITIONS
        for f in fewer_set
    }
    return _Shares(names, fewer_set, share, bins, pooled), displacement


def _method_text(ctx: EvalContext, cfg: CaptureConfig, n_pairs: dict[str, int], points: dict[str, int],
                 stereo_d: np.ndarray, fewer_set: tuple[int, ...]) -> str:  # fmt: skip
    """The paragraph saying what was run."""
    return (
        f"Tracked from zero flow. Photo shifts: {n_pairs[SOURCES[0]]} pairs of {cfg.width}x{cfg.height} px "
        f"from the held-out photos ({', '.join(cfg.photos)}) moved by "
        f"{', '.join(f'{d:g}' for d in cfg.displacements)} px in random directions, {points[SOURCES[0]]} "
        f"GFTT keypoints. Stereo: {n_pairs[SOURCES[1]]} left / right pairs of the sample sequence (seed "
        f"{cfg.sequence_seed}) through EuRoC's cameras, {points[SOURCES[1]]} keypoints seen by both, "
        f"disparities {np.min(stereo_d):.1f}-{np.max(stereo_d):.1f} px "
        f"(median {np.median(stereo_d):.1f}). Each pair once without and once with a full-strength "
        f"lighting change of both frames. Every method at {levels_text(ctx.methods)} (the tracker's deployed "
        f"depth; the stereo pairs at {levels_text(ctx.methods, stereo=True)}, the tracker's first stereo "
        "solve)" + (" and at one level fewer" if 1 in fewer_set else "")
        + ". Share of keypoints within 1 px of the truth (a lost point is not)." + quick_note(ctx.quick)
    )


def _tables(ctx: EvalContext, sh: _Shares, figure: str) -> list[str]:
    """The share tables (per source, condition and depth; then per displacement bin too) and the figure."""
    names = sh.names
    keys = [(s, cond, f) for s in SOURCES for cond in CONDITIONS for f in sh.fewer_set]
    lines = ["", "| source | condition | levels | " + " | ".join(names) + " |",
             "|---|---|---|" + "---|" * len(names)]  # fmt: skip
    for s, cond, f in keys:
        tag = _depth(ctx, s) if f == 0 else f"{_depth(ctx, s, 1)} (one fewer)"
        cells = " | ".join(f"{100 * sh.share[(s, cond, f)][n]:.1f} %" for n in names)
        lines.append(f"| {s} | {cond} | {tag} | {cells} |")
    lines += [
        "",
        "Share within 1 px per true displacement (5 px bins; `-`: no keypoint in the bin):",
        "",
        "| source | condition | levels | method | " + " | ".join(f"{c:g} px" for c in _centres()) + " |",
        "|---|---|---|---|" + "---|" * len(_centres()),
    ]
    for s, cond, f in keys:
        for n in names:
            cells = " | ".join("-" if np.isnan(v) else f"{100 * v:.0f} %" for v in sh.bins[(s, cond, f)][n])
            lines.append(f"| {s} | {cond} | {'deployed' if f == 0 else 'one fewer'} | {n} | {cells} |")
    return [*lines, "", f"![capture from zero flow]({figure})", ""]


def _depth(ctx: EvalContext, source: str, fewer: int = 0) -> str:
    """The methods' depth on ``source``'s pairs in words, ``fewer`` less."""
    return levels_text(ctx.methods, fewer, stereo=source == SOURCES[1])


def _headline(ctx: EvalContext, sh: _Shares) -> list[HeadlineRow]:
    """Each source's share at the deployed depth against :data:`TARGETS`, then the stretch goal per light."""
    pct = "{:.1%}".format
    rows = [
        headline_row(f"capture from zero flow, {s}, share < 1 px, {condition_label(cond)} ({_depth(ctx, s)})",
                     sh.share[(s, cond, 0)], pct, TARGETS[cond])
        for s in SOURCES for cond in CONDITIONS
    ]  # fmt: skip
    klt_depth = levels_text([m for m in ctx.methods if m.name == KLT] or ctx.methods)
    for cond in CONDITIONS if 1 in sh.fewer_set else ():
        deployed, fewer = sh.pooled[(cond, 0)], sh.pooled[(cond, 1)]
        rows.append(stretch_target(klt_depth, deployed.get(KLT, np.nan)).row(
            f"capture from zero flow, both sources, share < 1 px, {condition_label(cond)}, "
            "one level fewer",
            {n: pct(v) for n, v in fewer.items()}, {NSFLOW: fewer.get(NSFLOW), KLT: deployed.get(KLT)},
        ))  # fmt: skip
    return rows


def _share_data(sh: _Shares) -> dict[str, list[dict]]:
    """The shares as the section's JSON data."""
    keys = [(s, c, f) for s in SOURCES for c in CONDITIONS for f in sh.fewer_set]

    def rows(table: dict) -> list[dict]:
        return [{"source": s, "condition": c, "levels_fewer": f, **table[(s, c, f)]} for s, c, f in keys]

    return {"share_within_1px": rows(sh.share), "share_within_1px_by_displacement": rows(sh.bins),
            "pooled_within_1px": [{"condition": c, "levels_fewer": f, **sh.pooled[(c, f)]}
                                  for c in CONDITIONS for f in sh.fewer_set]}  # fmt: skip
