"""Does fine-tuning help on the user's footage? Models side by side on its held-out frames.

The held-out frames become fixed homography pairs with and without the training's lighting change,
scored as the held-out photo comparison (:mod:`~nsflow_ros.train.evaluate`) scores them.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from nsflow_ros.core.encoder import Encoder
from nsflow_ros.core.solver import LMConfig
from nsflow_ros.train.data import Pair, PairConfig, make_pair
from nsflow_ros.train.errors import TrainError
from nsflow_ros.train.evaluate import ModeMetrics, compare

__all__ = ["FootageRow", "evaluate_footage", "footage_pairs", "format_footage_table", "plot_footage"]


def footage_pairs(
    frames: list[np.ndarray], per_frame: int, strength: float, init_error: float = 5.0, seed: int = 20240601
) -> list[Pair]:
    """Fixed evaluation pairs of held-out frames (same geometry at every strength; only lighting differs).

    Raises:
        TrainError: no frame given.
    """
    if not frames:
        raise TrainError("no held-out footage frame to evaluate on (set a footage holdout > 0)")
    pairs = []
    for k, frame in enumerate(frames):
        for i in range(per_frame):
            rng = np.random.default_rng([seed, k, i])
            pairs.append(make_pair(frame, rng, PairConfig(), strength=strength, init_error=init_error))
    return pairs


@dataclass(frozen=True)
class FootageRow:
    """One line of the comparison: a mode (an encoder's label or "classical") on a pair set, with every
    point's error."""

    pairs: str
    mode: str
    metrics: ModeMetrics
    errors: np.ndarray = field(repr=False)


def evaluate_footage(
    encoders: dict[str, Encoder], frames: list[np.ndarray], per_frame: int = 4, config: LMConfig | None = None
) -> list[FootageRow]:
    """Each encoder and the classical mode on held-out footage pairs, with and without lighting change.

    Args:
        encoders: label -> encoder.
        frames: the held-out frames.
        per_frame: pairs per frame and condition.
        config: solver settings; None = as deployed.

    Returns:
        per condition, a row per encoder then the classical mode's.
    """
    rows = []
    for label, strength in (("lighting change", 1.0), ("same lighting", 0.0)):
        pairs = footage_pairs(frames, per_frame, strength)
        classical = None
        for name, enc in encoders.items():
            c = compare(enc, pairs, config, label)
            rows.append(FootageRow(label, name, c.nsflow, c.nsflow_errors))
            classical = c
        if classical is not None:
            rows.append(FootageRow(label, "classical", classical.classical, classical.classical_errors))
    return rows


def format_footage_table(rows: list[FootageRow]) -> str:
    """A Markdown table of the rows (errors over all points; a lost point counts as a failure)."""
    lines = [
        "| pairs | model | median EPE (px) | < 1 px | < 3 px | tracked | points |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        m = r.metrics
        lines.append(
            f"| {r.pairs} | {r.mode} | {m.median_epe:.3f} | {m.within_1px:.1%} | {m.within_3px:.1%} "
            f"| {m.tracked:.1%} | {m.points} |"
        )
    return "\n".join(lines)


def plot_footage(rows: list[FootageRow], path: str | Path) -> Path:
    """Cumulative error curves of every row (the training's validation figure)."""
    from nsflow_ros.train.figures import plot_validation

    curves = {f"{r.mode} ({r.pairs})": (r.errors, None) for r in rows}
    return plot_validation(curves, "held-out footage frames, NumPy solver, 5 px start", Path(path))
