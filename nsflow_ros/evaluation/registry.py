"""The registry of analyses the evaluation command runs, in report order.

To add one: write the module with its ``run(ctx) -> Section``, import it here and append it to
:data:`ANALYSES`.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

from nsflow_ros.evaluation import capture, convergence, covariance, efficiency, pairs, sequences, trackable
from nsflow_ros.evaluation.context import EvalContext
from nsflow_ros.evaluation.errors import EvaluationError
from nsflow_ros.evaluation.section import Section

__all__ = ["ANALYSES", "Analysis", "select"]


@dataclass(frozen=True)
class Analysis:
    """One analysis of the suite.

    Attributes:
        key: short identifier for ``--only`` / ``--skip`` (also the section key and file stem).
        title: one line saying what it measures (``--list``).
        run: ``run(ctx) -> Section``.
    """

    key: str
    title: str
    run: Callable[[EvalContext], Section]


ANALYSES: list[Analysis] = [
    Analysis(
        sequences.KEY,
        "front-end metrics per perturbation level on the sample sequence, F-matrix inliers (Table III)",
        sequences.run,
    ),
    Analysis("pairs", "tracking error on HPatches-style viewpoint / illumination pairs", pairs.run),
    Analysis("trackable", "trackable-region ratio from a 15 px initial error (paper Table I)", trackable.run),
    Analysis("convergence", "error against iteration from a 5 px initial error", convergence.run),
    Analysis(
        capture.KEY,
        "share within 1 px tracked from zero flow over 5-30 px: photo shifts, EuRoC-baseline stereo",
        capture.run,
    ),
    Analysis(
        covariance.KEY,
        "per-feature covariance: calibration, ranking of bad features, weighted relative rotation",
        covariance.run,
    ),
    Analysis(
        efficiency.KEY, "parameters, FLOPs, encoder and whole-tracker milliseconds (Table II)", efficiency.run
    ),
]


def select(only: Sequence[str] = (), skip: Sequence[str] = ()) -> list[Analysis]:
    """The analyses to run, in registry order: those in ``only`` (empty = all) that are not in ``skip``.

    Raises:
        EvaluationError: an unknown key, or nothing left to run.
    """
    keys = [a.key for a in ANALYSES]
    unknown = [k for k in (*only, *skip) if k not in keys]
    if unknown:
        raise EvaluationError(f"unknown analysis {', '.join(map(repr, unknown))}; known: {', '.join(keys)}")
    chosen = [a for a in ANALYSES if (not only or a.key in only) and a.key not in skip]
    if not chosen:
        raise EvaluationError("no analysis left to run after --only / --skip")
    return chosen
