"""NSFlow vs classical on held-out pairs, with the project's NumPy solver (what runs on the robot).

Both modes solve the same pairs, points and initial flows and differ only in the descriptor maps (the
ONNX encoder, or intensities). Metrics are over ALL points, a lost point counting as an infinite error,
so a mode cannot look better by dropping hard points.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from nsflow_ros.core.encoder import Encoder
from nsflow_ros.core.methods import METHODS, LMMethod, make_method
from nsflow_ros.core.solver import LMConfig
from nsflow_ros.train.data import HELDOUT_IMAGES, Pair, PairConfig, load_image, make_pair

__all__ = ["Comparison", "ModeMetrics", "compare", "format_table", "heldout_pairs", "mode_metrics"]


@dataclass(frozen=True)
class ModeMetrics:
    """Accuracy of one mode on a pair set: median error (px), shares within 1 and 3 px, share tracked,
    median error of the tracked points, point count."""

    median_epe: float
    within_1px: float
    within_3px: float
    tracked: float
    median_epe_tracked: float
    points: int


@dataclass(frozen=True)
class Comparison:
    """NSFlow and classical metrics on one pair set, with every point's error (inf where lost)."""

    label: str
    nsflow: ModeMetrics
    classical: ModeMetrics
    config: LMConfig
    nsflow_errors: np.ndarray = field(default_factory=lambda: np.zeros(0), repr=False)
    classical_errors: np.ndarray = field(default_factory=lambda: np.zeros(0), repr=False)


def heldout_pairs(
    per_image: int = 20, strength: float = 1.0, init_error: float = 5.0, seed: int = 20240601
) -> list[Pair]:
    """``per_image`` fixed pairs of each held-out photo, starting exactly ``init_error`` px off (same
    geometry at every ``strength``: only the lighting differs)."""
    pairs = []
    for k, name in enumerate(HELDOUT_IMAGES):
        src = load_image(name)
        for i in range(per_image):
            rng = np.random.default_rng([seed, k, i])
            pairs.append(make_pair(src, rng, PairConfig(), strength=strength, init_error=init_error))
    return pairs


def mode_metrics(errors: np.ndarray, status: np.ndarray) -> ModeMetrics:
    """Summarise endpoint errors (inf for lost points) and statuses of all points."""
    e = np.where(status & np.isfinite(errors), errors, np.inf)
    if e.size == 0:
        return ModeMetrics(float("nan"), 0.0, 0.0, 0.0, float("nan"), 0)
    tracked = e[np.isfinite(e)]
    return ModeMetrics(
        median_epe=float(np.median(e)),
        within_1px=float(np.mean(e < 1.0)),
        within_3px=float(np.mean(e < 3.0)),
        tracked=float(np.mean(np.isfinite(e))),
        median_epe_tracked=float(np.median(tracked)) if tracked.size else float("nan"),
        points=int(e.size),
    )


def _run_mode(method: LMMethod, pairs: list[Pair]) -> tuple[ModeMetrics, np.ndarray]:
    errs, stats = [], []
    for p in pairs:
        if len(p.points) == 0:
            continue
        # the maps as the method prepares them (the encoder applies its own fine smoothing)
        f1, f2 = (method.pyramid(method.encoder(im)) for im in (p.image1, p.image2))
        res = method.track_pair_result(f1, f2, p.points, p.flow0)
        errs.append(np.linalg.norm(res.flow - p.flow_gt, axis=1))
        stats.append(res.status)
    if not errs:
        return mode_metrics(np.zeros(0), np.zeros(0, bool)), np.zeros(0)
    e, s = np.concatenate(errs), np.concatenate(stats)
    return mode_metrics(e, s), np.where(s & np.isfinite(e), e, np.inf)


def compare(
    encoder: Encoder, pairs: list[Pair], config: LMConfig | None = None, label: str = ""
) -> Comparison:
    """Run NSFlow (``encoder``) and the classical mode on the same pairs with the NumPy solver.

    Args:
        encoder: the learned encoder, e.g. ``nsflow_ros.load_encoder(path)``.
        pairs: evaluation pairs, e.g. :func:`heldout_pairs`.
        config: solver settings of both methods; None = the registry's deployed ``nsflow`` and
            ``classical``.
        label: name of the pair set for tables.
    """
    specs = {name: METHODS[name] if config is None else replace(METHODS[name], lm=config)
             for name in ("nsflow", "classical")}
    nsflow, intensity = make_method(specs["nsflow"], encoder=encoder), make_method(specs["classical"])
    cfg = nsflow.lm  # type: ignore[attr-defined]
    learned, learned_err = _run_mode(nsflow, pairs)  # type: ignore[arg-type]
    classical, classical_err = _run_mode(intensity, pairs)  # type: ignore[arg-type]
    return Comparison(label, learned, classical, cfg, learned_err, classical_err)


def format_table(comparisons: list[Comparison]) -> str:
    """A Markdown table of comparisons."""
    lines = [
        "| pairs | solver | mode | median EPE (px) | < 1 px | < 3 px | tracked "
        "| median EPE tracked (px) | points |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for c in comparisons:
        solver = f"levels={c.config.levels}"
        for name, m in (("NSFlow", c.nsflow), ("classical", c.classical)):
            lines.append(
                f"| {c.label} | {solver} | {name} | {m.median_epe:.3f} | {m.within_1px:.1%} "
                f"| {m.within_3px:.1%} | {m.tracked:.1%} | {m.median_epe_tracked:.3f} | {m.points} |"
            )
    return "\n".join(lines)
