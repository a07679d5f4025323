"""Convergence: mean tracking error against iteration from a 5 px initial error (the paper's figure).

On held-out photo pairs (a mild homography, without and with a full-strength lighting change), GFTT
keypoints start 5 px off their true flow on a single pyramid level, as in the paper. The LM methods'
per-iteration flow is read from the solver's recorded history; OpenCV's LK keeps none, so it is run
again with ``max_iterations = k`` for every k on the same prepared images. The curve is the mean of
min(error, 10 px) so that a few diverging points cannot hide it. A capture-range table repeats the
solve from several initial errors at that level, at each method's deployed depth and one level fewer.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from nsflow_ros.data.perturb import perturb_pair
from nsflow_ros.data.photos import HELDOUT_IMAGES, load_photo
from nsflow_ros.evaluation.context import (
    CONDITIONS,
    EvalContext,
    condition_label,
    new_figure,
    save_figure,
)
from nsflow_ros.evaluation.errors import EvaluationError
from nsflow_ros.evaluation.methods import CLASSICAL, KLT_CLAHE, EvalMethod, prepare_pair
from nsflow_ros.evaluation.pairs import (
    HomographyPair,
    endpoint_errors,
    keep_inside,
    keypoints,
    random_homography,
    render_pair,
    true_flow,
)
from nsflow_ros.evaluation.section import Section, config_data, quick_note
from nsflow_ros.evaluation.targets import Clause, Target, headline_row

__all__ = ["QUICK", "TARGETS", "ConvergenceConfig", "capture_range", "convergence_curves", "run"]

# the paper's claim: faster error reduction than LK on intensity; under changing light also faster than the
# baseline a VINS user picks then (KLT on CLAHE'd images)
TARGETS: dict[str, Target] = {
    "none": Target("mean_clipped", (Clause("<", (CLASSICAL,)),)),
    "light": Target("mean_clipped", (Clause("<", (CLASSICAL,)), Clause("<", (KLT_CLAHE,), optional=True))),
}
"""Condition -> NSFlow's target on the mean clipped error after 5 iterations at one level."""
REPORT_AT = (0, 1, 2, 3, 5, 10, 20, 30)

Frames = dict[str, tuple[Any, Any]]
"""Method name -> its representations of a pair's two frames
(:func:`~nsflow_ros.evaluation.methods.prepare_pair`)."""


@dataclass(frozen=True)
class ConvergenceConfig:
    """Settings of the convergence analysis.

    Attributes:
        width, height: frame size in pixels.
        photos: held-out photos.
        per_photo: pairs per photo and condition.
        max_points: GFTT keypoints per pair (at most).
        min_distance: GFTT minimum distance.
        init_error: initial flow error in pixels (the paper: 5).
        iterations: K, iterations per curve (LM's K_max for this analysis).
        levels: pyramid levels (the paper: 1).
        ceiling: errors are clipped here for the mean curve, pixels.
        basin_errors: initial errors (px) of the capture-range table, run at ``levels`` and at each
            method's deployed levels.
    """

    width: int = 480
    height: int = 360
    photos: tuple[str, ...] = HELDOUT_IMAGES
    per_photo: int = 2
    max_points: int = 1000
    min_distance: float = 6.0
    init_error: float = 5.0
    iterations: int = 30
    levels: int = 1
    ceiling: float = 10.0
    basin_errors: tuple[float, ...] = (1.0, 3.0, 5.0, 8.0)


QUICK = ConvergenceConfig(
    width=240, height=180, photos=HELDOUT_IMAGES[:1], per_photo=1, max_points=100, iterations=8,
    basin_errors=(1.0, 5.0),
)
"""Tiny sizes for tests and CI."""


def _clipped(flow: np.ndarray, gt: np.ndarray, ceiling: float) -> np.ndarray:
    with np.errstate(invalid="ignore"):
        e = np.linalg.norm(flow - gt, axis=1)
    return np.minimum(np.where(np.isfinite(e), e, ceiling), ceiling)


def convergence_curves(
    methods: list[EvalMethod],
    pair: HomographyPair,
    points: np.ndarray,
    flow0: np.ndarray,
    *,
    iterations: int = 30,
    levels: int = 1,
    ceiling: float = 10.0,
    frames: Frames | None = None,
) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    """Per-point error after each iteration k = 0..K, for every method.

    Args:
        points, flow0: (N, 2) keypoints in frame 1 and their initial flow.
        iterations: K.
        levels: pyramid levels every method uses here (at most each method's own).
        ceiling: clip errors (and non-finite flows) to this, pixels.
        frames: the methods' representations of the pair (:data:`Frames`); None = prepare here.

    Returns:
        (curves, final): ``curves[name]`` is (K + 1, N) clipped errors, row k after k iterations;
        ``final[name]`` is (N,) the final errors with lost points infinite.

    Raises:
        EvaluationError: bad shapes or settings, or an object that is not an evaluation method.
    """
    pts = np.asarray(points, np.float64)
    f0 = np.asarray(flow0, np.float64)
    if pts.ndim != 2 or pts.shape[1] != 2 or f0.shape != pts.shape:
        raise EvaluationError(f"points and flow0 must both be (N, 2), got {pts.shape} and {f0.shape}")
    if iterations < 1 or levels < 1:
        raise EvaluationError(f"iterations and levels must be >= 1, got {iterations} and {levels}")
    gt = true_flow(pts, pair.homography)
    if frames is None:
        frames = prepare_pair(methods, pair.image1, pair.image2)
    curves, final = {}, {}
    for m in methods:
        flows, result = m.iterate(*frames[m.name], pts, f0, levels, iterations)
        curves[m.name] = np.stack([_clipped(f, gt, ceiling) for f in (f0, *flows)])
        final[m.name] = endpoint_errors(result, gt)
    return curves, final


def capture_range(
    methods: list[EvalMethod], pair: HomographyPair, points: np.ndarray, direction: np.ndarray,
    errors: tuple[float, ...], levels: int, *, frames: Frames | None = None,
) -> dict[float, dict[str, np.ndarray]]:  # fmt: skip
    """Final errors (inf where lost) from initial errors of each length (px) along fixed unit directions.

    Args:
        points, direction: (N, 2) keypoints and the unit vectors of their initial errors.
        levels: pyramid levels every method uses (at most each method's own).
        frames: the methods' representations of the pair (:data:`Frames`); None = prepare here.

    Returns:
        ``{initial error: {method name: (N,) final errors}}``.
    """
    gt = true_flow(points, pair.homography)
    if frames is None:
        frames = prepare_pair(methods, pair.image1, pair.image2)
    out: dict[float, dict[str, np.ndarray]] = {}
    for err in errors:
        out[err] = {}
        flow0 = gt + err * direction
        for m in methods:
            out[err][m.name] = endpoint_errors(m.track(*frames[m.name], points, flow0, levels), gt)
    return out


def _basin_order(item: tuple[tuple[str, int, float], object]) -> tuple[int, int, float]:
    (cond, lev, err), _ = item
    return CONDITIONS.index(cond), lev, err


def _pairs(
    cfg: ConvergenceConfig, seed: int
) -> list[tuple[str, HomographyPair, np.ndarray, np.ndarray, np.ndarray]]:
    """(condition, pair, points, true flow, flow0) for every photo, pair index and condition."""
    out = []
    for k, name in enumerate(cfg.photos):
        photo = load_photo(name)
        for i in range(cfg.per_photo):
            for cond in CONDITIONS:
                rng = np.random.default_rng([seed, 11, k, i])  # same geometry and points for both
                p = random_homography(rng, cfg.width, cfg.height, 1.0)
                f1, f2 = render_pair(photo, rng, cfg.width, cfg.height, p)
                if cond == "light":
                    f1, f2 = perturb_pair(f1, f2, np.random.default_rng([seed, 12, k, i]), 1.0)
                pair = HomographyPair(name, "convergence", 1, f1, f2, p)
                pts = keypoints(f1, cfg.max_points, cfg.min_distance)
                pts, gt = keep_inside(pts, true_flow(pts, p), cfg.width, cfg.height)
                ang = np.random.default_rng([seed, 13, k, i]).uniform(0.0, 2.0 * np.pi, len(pts))
                flow0 = gt + cfg.init_error * np.stack([np.cos(ang), np.sin(ang)], 1)
                out.append((cond, pair, pts, gt, flow0))
    return out


def _plot(mean: dict, median: dict, names: list[str], cfg: ConvergenceConfig, path: object) -> None:
    fig = new_figure(11.0, 4.2)
    axes = fig.subplots(1, len(CONDITIONS), sharey=True)
    colours = ["#d62728", "#1f77b4", "#2ca02c", "#9467bd", "#8c564b"]
    for ax, cond in zip(axes, CONDITIONS, strict=True):
        for j, n in enumerate(names):
            k = np.arange(len(mean[cond][n]))
            c = colours[j % len(colours)]
            ax.plot(k, mean[cond][n], color=c, lw=1.8, label=f"{n} mean")
            ax.plot(k, median[cond][n], color=c, lw=1.0, ls="--", label=f"{n} median")
        ax.set_yscale("log")
        ax.set_xlabel("iteration")
        ax.set_title("no lighting change" if cond == "none" else "illumination change (strength 1)")
        ax.grid(True, which="both", alpha=0.3)
    axes[0].set_ylabel(f"error (px, clipped at {cfg.ceiling:g})")
    axes[-1].legend(fontsize=7)
    fig.suptitle(
        f"Convergence from a {cfg.init_error:g} px initial error, {cfg.levels} pyramid level(s)", fontsize=10
    )
    save_figure(fig, path)


def run(ctx: EvalContext, cfg: ConvergenceConfig | None = None) -> Section:
    """The ``convergence`` section (``convergence.png``, the tables, headline rows).

    ``cfg`` None: :data:`QUICK` in a quick run, else ``ConvergenceConfig()``.
    """
    cfg = cfg or (QUICK if ctx.quick else ConvergenceConfig())
    names = [m.name for m in ctx.methods]
    items = _pairs(cfg, ctx.seed)
    curves, finals, basin = _measure(ctx, cfg, items, names)
    mean = {c: {n: np.hstack(curves[c][n]).mean(axis=1) for n in names} for c in CONDITIONS}
    median = {c: {n: np.median(np.hstack(curves[c][n]), axis=1) for n in names} for c in CONDITIONS}
    final = {c: {n: np.concatenate(finals[c][n]) for n in names} for c in CONDITIONS}
    npts = {c: len(final[c][names[0]]) if names else 0 for c in CONDITIONS}
    within1 = {key: {n: float(np.mean(np.concatenate(v) < 1.0)) for n, v in per.items()}
               for key, per in sorted(basin.items(), key=_basin_order)}  # fmt: skip
    fig_path = ctx.out_dir / "convergence.png"
    _plot(mean, median, names, cfg, fig_path)
    md = _markdown(ctx, cfg, len(items), npts, mean, final, within1, fig_path.name)
    k5 = min(5, cfg.iterations)
    headline = [
        headline_row(f"convergence: mean error after {k5} iterations, one level, {condition_label(c)} (px)",
                     {n: mean[c][n][k5] for n in names}, "{:.3f}".format, target)
        for c, target in TARGETS.items()
    ]  # fmt: skip
    data = {
        "config": config_data(cfg),
        "mean_clipped": {c: {n: mean[c][n].tolist() for n in names} for c in CONDITIONS},
        "median": {c: {n: median[c][n].tolist() for n in names} for c in CONDITIONS},
        "final_tracked": {c: {n: float(np.mean(np.isfinite(e))) for n, e in per.items()}
                          for c, per in final.items()},
        "points": npts,
        "capture_within_1px": [{"condition": c, "levels": lev, "initial_error_px": err, **per}
                               for (c, lev, err), per in within1.items()],
    }  # fmt: skip
    return Section("convergence", "Convergence from a 5 px initial error", md, [fig_path], headline, data)


def _measure(
    ctx: EvalContext, cfg: ConvergenceConfig, items: list, names: list[str]
) -> tuple[dict, dict, dict[tuple[str, int, float], dict[str, list[np.ndarray]]]]:
    """Every method's curves and final errors per condition, and the capture range per depth and error."""
    curves: dict[str, dict[str, list[np.ndarray]]] = {c: {n: [] for n in names} for c in CONDITIONS}
    finals: dict[str, dict[str, list[np.ndarray]]] = {c: {n: [] for n in names} for c in CONDITIONS}
    # the curves' single level, each method's deployed depth and one level fewer (the basin per level)
    depths = {cfg.levels, *(m.levels for m in ctx.methods), *(m.levels - 1 for m in ctx.methods)}
    level_set = sorted(depths - {0})
    basin: dict[tuple[str, int, float], dict[str, list[np.ndarray]]] = {}
    for cond, pair, pts, gt, flow0 in ctx.bar(items, desc="convergence", unit="pair"):
        frames = prepare_pair(ctx.methods, pair.image1, pair.image2)
        cv, fin = convergence_curves(
            ctx.methods, pair, pts, flow0, iterations=cfg.iterations, levels=cfg.levels, ceiling=cfg.ceiling,
            frames=frames,
        )  # fmt: skip
        for n in names:
            curves[cond][n].append(cv[n])
            finals[cond][n].append(fin[n])
        off = flow0 - gt
        direction = off / np.maximum(np.linalg.norm(off, axis=1, keepdims=True), 1e-12)
        for lev in level_set:
            at = [m for m in ctx.methods if m.levels >= lev]
            basins = capture_range(at, pair, pts, direction, cfg.basin_errors, lev, frames=frames)
            for err, per in basins.items():
                for n, e in per.items():
                    basin.setdefault((cond, lev, err), {}).setdefault(n, []).append(e)
    return curves, finals, basin


def _markdown(ctx: EvalContext, cfg: ConvergenceConfig, n_pairs: int, npts: dict[str, int], mean: dict,
              final: dict, within1: dict[tuple, dict[str, float]], figure: str) -> str:  # fmt: skip
    """The section's text: what was run, the curves' table, the figure, the capture-range table."""
    names = [m.name for m in ctx.methods]
    at = [k for k in REPORT_AT if k <= cfg.iterations]
    lines = [
        f"{n_pairs} pairs of {cfg.width}x{cfg.height} px from the held-out photos "
        f"({', '.join(cfg.photos)}, a mild homography, without / with illumination perturbation), "
        f"up to {cfg.max_points} GFTT keypoints "
        f"({npts['none']} / {npts['light']} in all), initial flow off by {cfg.init_error:g} px, "
        f"{cfg.levels} pyramid level(s), {cfg.iterations} iterations. LM methods: the solver's recorded "
        "history; OpenCV LK methods: re-run with max_iterations = k. Mean of min(error, "
        f"{cfg.ceiling:g} px) after k iterations:" + quick_note(ctx.quick),
        "",
        f"| condition | method | {' | '.join(f'k={k}' for k in at)} | final median (px) | final tracked |",
        "|---|---|" + "---|" * (len(at) + 2),
    ]
    for c in CONDITIONS:
        for n in names:
            e = final[c][n]
            med = float(np.median(e)) if e.size else float("nan")
            tracked = float(np.mean(np.isfinite(e))) if e.size else float("nan")
            ks = " | ".join(f"{mean[c][n][k]:.3f}" for k in at)
            lines.append(f"| {c} | {n} | {ks} | {med:.3f} | {tracked:.1%} |")
    lines += [
        "", f"![convergence]({figure})", "",
        "Capture range: share of keypoints ending within 1 px of the truth (lost = not), from initial "
        "errors of several lengths (same directions), at the single level of the curves, at the deployed "
        "levels and at one level fewer:",
        "",
        "| condition | levels | initial error (px) | " + " | ".join(names) + " |",
        "|---|---|---|" + "---|" * len(names),
    ]  # fmt: skip
    for (c, lev, err), per in within1.items():
        cells = [f"{per[n]:.1%}" if n in per else "-" for n in names]
        lines.append(f"| {c} | {lev} | {err:g} | " + " | ".join(cells) + " |")
    return "\n".join([*lines, ""])
