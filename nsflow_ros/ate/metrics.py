"""Absolute and relative pose error (APE, RPE): per-pose errors, their statistics as evo reports them,
and the full APE pipeline."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from nsflow_ros.ate.align import Alignment, align_trajectory
from nsflow_ros.ate.associate import associate
from nsflow_ros.ate.errors import ATEError
from nsflow_ros.ate.rotation import rotation_angle
from nsflow_ros.ate.trajectory import Trajectory

__all__ = [
    "MIN_MATCHES",
    "STAT_KEYS",
    "APEResult",
    "ErrorStats",
    "RPEResult",
    "error_statistics",
    "evaluate_ape",
    "position_errors",
    "relative_pose_error",
    "rpe_errors",
]

STAT_KEYS: tuple[str, ...] = ("rmse", "mean", "median", "std", "min", "max", "n")
"""Keys of :meth:`ErrorStats.as_dict` (and of the CLI's ``--json`` object)."""

MIN_MATCHES = 3
"""Fewest matched poses an evaluation accepts (an alignment needs three)."""


@dataclass(frozen=True)
class ErrorStats:
    """Summary of a set of non-negative errors (``std`` is the population standard deviation)."""

    rmse: float
    mean: float
    median: float
    std: float
    min: float
    max: float
    n: int

    def as_dict(self) -> dict[str, float | int]:
        """The statistics keyed by :data:`STAT_KEYS`."""
        return {key: getattr(self, key) for key in STAT_KEYS}


def error_statistics(errors: np.ndarray) -> ErrorStats:
    """The :class:`ErrorStats` of one error per pose or pose pair.

    Shape:
        errors (N,), N >= 1.

    Raises:
        ATEError: when ``errors`` is not 1-D, is empty, or holds NaN/inf.
    """
    e = np.asarray(errors, dtype=np.float64)
    if e.ndim != 1:
        raise ATEError(f"errors must have shape (N,), got {e.shape}")
    if e.size == 0:
        raise ATEError("no errors to summarise (0 poses)", reason="empty")
    if not np.all(np.isfinite(e)):
        raise ATEError(
            f"errors contain NaN or inf (first at index {int(np.argmax(~np.isfinite(e)))})", reason="nan"
        )
    return ErrorStats(
        rmse=math.sqrt(float(np.mean(e * e))),
        mean=float(np.mean(e)),
        median=float(np.median(e)),
        std=float(np.std(e)),
        min=float(np.min(e)),
        max=float(np.max(e)),
        n=int(e.size),
    )


def _check_pair(ref: Trajectory, est: Trajectory) -> None:
    if len(ref) != len(est):
        raise ATEError(
            f"matched trajectories must have the same number of poses: {ref.name} has {len(ref)}, "
            f"{est.name} has {len(est)}"
        )


def position_errors(ref: Trajectory, est: Trajectory) -> np.ndarray:
    """``||p_ref_i - p_est_i||`` in metres of poses paired index by index (the estimate aligned).

    Shape:
        (N,) for N pairs.

    Raises:
        ATEError: when the lengths differ.
    """
    _check_pair(ref, est)
    return np.linalg.norm(ref.positions - est.positions, axis=1)


def _poses(traj: Trajectory) -> np.ndarray:
    out = np.zeros((len(traj), 4, 4))
    out[:, :3, :3] = traj.rotation_matrices()
    out[:, :3, 3] = traj.positions
    out[:, 3, 3] = 1.0
    return out


def _relative(first: np.ndarray, second: np.ndarray) -> np.ndarray:
    """first^-1 @ second for stacks of rigid transforms (N, 4, 4)."""
    rot_t = np.transpose(first[:, :3, :3], (0, 2, 1))
    inv = np.zeros_like(first)
    inv[:, :3, :3] = rot_t
    inv[:, :3, 3] = -np.einsum("nij,nj->ni", rot_t, first[:, :3, 3])
    inv[:, 3, 3] = 1.0
    return inv @ second


def rpe_errors(
    ref: Trajectory, est: Trajectory, delta: int = 1, all_pairs: bool = False
) -> tuple[np.ndarray, np.ndarray]:
    """Relative pose errors ``E = (Q_i^-1 Q_j)^-1 (P_i^-1 P_j)`` over j = i + ``delta`` matched poses.

    Args:
        ref: reference poses Q.
        est: estimate poses P, paired index by index with ``ref``.
        delta: pose-index distance of each pair (>= 1).
        all_pairs: use every start index i instead of i = 0, delta, 2 delta, ...

    Returns:
        (translation errors in metres, rotation errors in degrees), one per pair.

    Shape:
        (P,), (P,) with P = number of pairs.

    Raises:
        ATEError: when the lengths differ, ``delta`` < 1, or there is no pair (delta >= N).
    """
    _check_pair(ref, est)
    if int(delta) != delta or delta < 1:
        raise ATEError(f"RPE delta must be an integer >= 1 (poses), got {delta}")
    delta = int(delta)
    n = len(ref)
    starts = np.arange(0, n - delta) if all_pairs else np.arange(0, n - delta, delta)
    if starts.size == 0:
        raise ATEError(
            f"RPE with delta {delta} needs more than {delta} matched poses, got {n}", reason="too_few"
        )
    q = _poses(ref)
    p = _poses(est)
    q_rel = _relative(q[starts], q[starts + delta])
    p_rel = _relative(p[starts], p[starts + delta])
    err = _relative(q_rel, p_rel)
    return np.linalg.norm(err[:, :3, 3], axis=1), np.degrees(rotation_angle(err[:, :3, :3]))


@dataclass(frozen=True)
class RPEResult:
    """Relative pose error statistics of the translation (m) and rotation (degrees) errors."""

    delta: int
    all_pairs: bool
    translation: ErrorStats
    rotation_deg: ErrorStats

    def as_dict(self) -> dict[str, object]:
        """JSON-ready nested dictionaries."""
        return {
            "delta": self.delta,
            "all_pairs": self.all_pairs,
            "translation": self.translation.as_dict(),
            "rotation_deg": self.rotation_deg.as_dict(),
        }


def relative_pose_error(
    ref: Trajectory, est: Trajectory, delta: int = 1, all_pairs: bool = False
) -> RPEResult:
    """The statistics of :func:`rpe_errors` (which raises)."""
    trans, rot = rpe_errors(ref, est, delta, all_pairs)
    return RPEResult(int(delta), bool(all_pairs), error_statistics(trans), error_statistics(rot))


@dataclass(frozen=True, eq=False)
class APEResult:
    """Outcome of :func:`evaluate_ape`: the statistics and (n,) per-pose position errors (m), the
    alignment, the n matched reference and aligned estimate poses, and the RPE when requested."""

    stats: ErrorStats
    errors: np.ndarray
    alignment: Alignment
    ref: Trajectory
    est: Trajectory
    rpe: RPEResult | None = None


def evaluate_ape(
    ref: Trajectory,
    est: Trajectory,
    *,
    align: str = "se3",
    n_align: int | None = None,
    max_diff: float = 0.01,
    offset: float = 0.0,
    rpe_delta: int | None = None,
    rpe_all_pairs: bool = False,
    min_matches: int = MIN_MATCHES,
    skip: float = 0.0,
) -> APEResult:
    """Associate, align and score an estimate against a reference.

    Args:
        ref: ground truth.
        est: estimate.
        align: ``"se3"``, ``"sim3"`` or ``"none"``.
        n_align: fit the alignment on the first N matched poses only (``None``: all).
        max_diff: association tolerance in seconds.
        offset: seconds added to the estimate's stamps for the association.
        rpe_delta: also compute the relative pose error over this many matched poses (``None``: skip).
        rpe_all_pairs: use every start index for the RPE.
        min_matches: fewest matched poses accepted (at least 3).
        skip: leave out the estimate's first ``skip`` seconds (an estimator's start), before matching.

    Raises:
        ATEError: for empty trajectories, no overlapping stamps, fewer than ``min_matches`` matched poses,
            a degenerate alignment, or invalid options.
    """
    if not np.isfinite(skip) or skip < 0:
        raise ATEError(f"skip must be a finite number of seconds >= 0, got {skip}")
    if skip > 0 and len(est):
        est = est.take(np.flatnonzero(est.stamps >= est.stamps.min() + skip))
    pairs = associate(ref, est, max_diff=max_diff, offset=offset)
    need = max(int(min_matches), MIN_MATCHES)
    if len(pairs) < need:
        raise ATEError(
            f"only {len(pairs)} matched poses between {ref.name} and {est.name} (need at least {need}); "
            f"check max_diff ({max_diff} s) and offset ({offset} s)",
            reason="too_few",
        )
    est_aligned, fit = align_trajectory(pairs.est, pairs.ref, align, n_align)
    errors = position_errors(pairs.ref, est_aligned)
    rpe = None
    if rpe_delta is not None:
        rpe = relative_pose_error(pairs.ref, est_aligned, rpe_delta, rpe_all_pairs)
    return APEResult(error_statistics(errors), errors, fit, pairs.ref, est_aligned, rpe)
