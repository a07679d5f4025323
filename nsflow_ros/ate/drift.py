"""UMA-VI style drift for sequences whose ground truth covers only the start and the end.

UMA-VI (like TUM-VI) has ground truth only inside the motion-capture area, so a full-trajectory ATE is
meaningless; instead the estimate is aligned separately to the first and the last ground-truth segment
(split at gaps longer than ``min_gap``) and the two alignments are compared (:class:`DriftResult`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from nsflow_ros.ate.align import Alignment, umeyama
from nsflow_ros.ate.associate import associate
from nsflow_ros.ate.errors import ATEError
from nsflow_ros.ate.metrics import MIN_MATCHES, ErrorStats, error_statistics
from nsflow_ros.ate.rotation import rotation_angle
from nsflow_ros.ate.trajectory import Trajectory

__all__ = ["DRIFT_KEYS", "DriftResult", "evaluate_drift", "split_segments"]

DRIFT_KEYS: tuple[str, ...] = (
    "alignment_error",
    "end_drift",
    "rotation_drift_deg",
    "path_length",
    "drift_percent",
    "n_start",
    "n_end",
)
"""Scalar keys of :meth:`DriftResult.as_dict`."""


def split_segments(stamps: np.ndarray, min_gap: float = 1.0) -> list[np.ndarray]:
    """The indices of each run of ``stamps`` (seconds, any order) between gaps longer than ``min_gap``,
    segments and indices in time order.

    Shape:
        stamps (N,) -> list of int64 arrays.

    Raises:
        ATEError: when ``stamps`` is not 1-D or ``min_gap`` is not positive.
    """
    t = np.asarray(stamps, dtype=np.float64)
    if t.ndim != 1:
        raise ATEError(f"stamps must have shape (N,), got {t.shape}")
    if not (math.isfinite(min_gap) and min_gap > 0):
        raise ATEError(f"min_gap must be a positive number of seconds, got {min_gap}")
    if t.size == 0:
        return []
    order = np.argsort(t, kind="stable")
    cuts = np.flatnonzero(np.diff(t[order]) > min_gap) + 1
    return [seg.astype(np.int64) for seg in np.split(order, cuts)]


@dataclass(frozen=True)
class DriftResult:
    """Start/end segment alignment drift.

    Attributes:
        alignment_error: RMS distance between the estimate under the two alignments (m), the alignment
            error of TUM-VI / UMA-VI.
        end_drift: RMSE over the end segment with the start alignment (m).
        rotation_drift_deg: angle between the two alignment rotations (degrees).
        path_length: length of the estimate's path after the start alignment (m).
        drift_percent: ``alignment_error`` / ``path_length`` * 100.
        n_start: matched poses in the start segment.
        n_end: matched poses in the end segment.
        start: the start-segment alignment.
        end: the end-segment alignment.
        start_fit: residual statistics of the start alignment on the start segment (m).
        end_fit: residual statistics of the end alignment on the end segment (m).
    """

    alignment_error: float
    end_drift: float
    rotation_drift_deg: float
    path_length: float
    drift_percent: float
    n_start: int
    n_end: int
    start: Alignment
    end: Alignment
    start_fit: ErrorStats
    end_fit: ErrorStats

    def as_dict(self) -> dict[str, object]:
        """The scalar results (:data:`DRIFT_KEYS`) plus the two fits, JSON-ready."""
        out: dict[str, object] = {key: getattr(self, key) for key in DRIFT_KEYS}
        out["start_fit"] = self.start_fit.as_dict()
        out["end_fit"] = self.end_fit.as_dict()
        return out


def evaluate_drift(
    ref: Trajectory,
    est: Trajectory,
    *,
    align: str = "se3",
    max_diff: float = 0.01,
    offset: float = 0.0,
    min_gap: float = 1.0,
) -> DriftResult:
    """Align the estimate to the start and to the end ground-truth segments and measure the drift.

    Args:
        ref: ground truth covering (at least) a start and an end segment.
        est: estimate covering the whole run.
        align: ``"se3"`` or ``"sim3"``.
        max_diff: association tolerance in seconds.
        offset: seconds added to the estimate's stamps for the association.
        min_gap: ground-truth gap (seconds) that separates segments.

    Raises:
        ATEError: for an alignment other than se3/sim3, ground truth without a gap longer than
            ``min_gap`` (it then covers the whole run: use the ATE), a segment with fewer than 3 matched
            poses, or any association/alignment error.
    """
    if align not in ("se3", "sim3"):
        raise ATEError(f"drift needs a se3 or sim3 alignment per segment, got {align!r}")
    segments = split_segments(ref.stamps, min_gap)
    if len(segments) < 2:
        raise ATEError(
            f"{ref.name}: ground truth has no gap longer than {min_gap} s, so no separate start and end "
            f"segments; it covers the whole run: score it with the ATE instead",
            reason="no_overlap",
        )
    fits: list[tuple[Alignment, ErrorStats, Trajectory, Trajectory]] = []
    for label, seg in (("start", segments[0]), ("end", segments[-1])):
        part = ref.take(seg).renamed(f"{ref.name} [{label} segment]")
        pairs = associate(part, est, max_diff=max_diff, offset=offset)
        if len(pairs) < MIN_MATCHES:
            raise ATEError(
                f"only {len(pairs)} estimate poses match the {label} segment of {ref.name} "
                f"({part.stamps[0]:.3f}..{part.stamps[-1]:.3f} s); need at least {MIN_MATCHES}",
                reason="too_few",
            )
        fit = umeyama(pairs.est.positions, pairs.ref.positions, with_scale=align == "sim3")
        residual = np.linalg.norm(fit.apply(pairs.est.positions) - pairs.ref.positions, axis=1)
        fits.append((fit, error_statistics(residual), pairs.ref, pairs.est))
    (t_start, start_fit, _, _), (t_end, end_fit, end_ref, end_est) = fits
    under_start = t_start.apply(est.positions)
    under_end = t_end.apply(est.positions)
    alignment_error = math.sqrt(float(np.mean(np.sum((under_start - under_end) ** 2, axis=1))))
    end_drift = error_statistics(
        np.linalg.norm(t_start.apply(end_est.positions) - end_ref.positions, axis=1)
    ).rmse
    rot_drift = float(np.degrees(rotation_angle(t_start.rotation.T @ t_end.rotation)))
    ordered = under_start[np.argsort(est.stamps, kind="stable")]
    path = float(np.sum(np.linalg.norm(np.diff(ordered, axis=0), axis=1)))
    percent = 100.0 * alignment_error / path if path > 0 else math.inf
    return DriftResult(
        alignment_error=alignment_error,
        end_drift=end_drift,
        rotation_drift_deg=rot_drift,
        path_length=path,
        drift_percent=percent,
        n_start=start_fit.n,
        n_end=end_fit.n,
        start=t_start,
        end=t_end,
        start_fit=start_fit,
        end_fit=end_fit,
    )
