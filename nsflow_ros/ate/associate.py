"""Time association of two trajectories, evo's nearest-time convention.

Each pose of the shorter trajectory (the estimate on equal lengths) takes the other's pose of nearest
stamp within ``max_diff`` seconds after ``offset`` is added to the estimate's stamps; on a tie the earlier
pose wins, and a pose of the longer trajectory may serve several.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from nsflow_ros.ate.errors import ATEError
from nsflow_ros.ate.trajectory import Trajectory

__all__ = ["Association", "associate", "match_stamps"]


def match_stamps(
    stamps: np.ndarray, candidates: np.ndarray, max_diff: float = 0.01
) -> tuple[np.ndarray, np.ndarray]:
    """For each of ``stamps``, the nearest of ``candidates`` within ``max_diff`` (any order, >= 0).

    Returns:
        (indices into ``stamps``, indices into ``candidates``) of the matched pairs, ordered by the stamps
        (stable for equal stamps).

    Shape:
        stamps (N,), candidates (M,) -> two int64 arrays (K,), K <= N.

    Raises:
        ATEError: when an array is not 1-D or holds NaN, or ``max_diff`` is negative or not finite.
    """
    a = np.asarray(stamps, dtype=np.float64)
    b = np.asarray(candidates, dtype=np.float64)
    for what, arr in (("stamps", a), ("candidates", b)):
        if arr.ndim != 1:
            raise ATEError(f"{what} must have shape (N,), got {arr.shape}")
        if not np.all(np.isfinite(arr)):
            raise ATEError(f"{what} contain NaN or inf", reason="nan")
    if not (math.isfinite(max_diff) and max_diff >= 0):
        raise ATEError(f"max_diff must be a finite number >= 0, got {max_diff}")
    empty = np.empty(0, dtype=np.int64)
    if a.size == 0 or b.size == 0:
        return empty, empty
    order_a = np.argsort(a, kind="stable")
    order_b = np.argsort(b, kind="stable")
    sb = b[order_b]
    sa = a[order_a]
    # Insertion point after equal candidates: 'upper' is the first candidate strictly later.
    upper = np.searchsorted(sb, sa, side="right")
    lower = upper - 1
    upper_c = np.minimum(upper, sb.size - 1)
    lower_c = np.maximum(lower, 0)
    d_up = np.where(upper < sb.size, sb[upper_c] - sa, np.inf)
    d_low = np.where(lower >= 0, sa - sb[lower_c], np.inf)
    take_low = d_low <= d_up
    best = np.where(take_low, lower_c, upper_c)
    diff = np.where(take_low, d_low, d_up)
    ok = diff <= max_diff
    return order_a[ok].astype(np.int64), order_b[best[ok]].astype(np.int64)


@dataclass(frozen=True, eq=False)
class Association:
    """Two trajectories reduced to their matched poses, paired index by index (the estimate keeps its
    own stamps), with each pose's index in its original trajectory and the tolerance and offset used."""

    ref: Trajectory
    est: Trajectory
    ref_indices: np.ndarray
    est_indices: np.ndarray
    max_diff: float
    offset: float

    def __len__(self) -> int:
        return len(self.ref)


def associate(
    ref: Trajectory, est: Trajectory, *, max_diff: float = 0.01, offset: float = 0.0
) -> Association:
    """Pair the poses of an estimate with those of a reference by nearest stamp (at least one pair).

    Args:
        ref: reference (ground-truth) trajectory.
        est: estimated trajectory.
        max_diff: largest accepted stamp difference in seconds.
        offset: seconds added to the estimate's stamps before matching.

    Raises:
        ATEError: when a trajectory is empty, ``max_diff``/``offset`` are invalid, or no stamps overlap (the
            message gives both time ranges, so a missing offset or a seconds/nanoseconds mix-up shows).
    """
    for traj in (ref, est):
        if len(traj) == 0:
            raise ATEError(f"{traj.name}: trajectory is empty", reason="empty")
    if not math.isfinite(offset):
        raise ATEError(f"offset must be a finite number of seconds, got {offset}")
    if len(est) > len(ref):
        idx_ref, idx_est = match_stamps(ref.stamps, est.stamps + offset, max_diff)
    else:
        idx_est, idx_ref = match_stamps(est.stamps, ref.stamps - offset, max_diff)
    if idx_ref.size == 0:
        raise ATEError(
            f"no overlapping stamps between {ref.name} ({ref.stamps.min():.6f}..{ref.stamps.max():.6f} s) "
            f"and {est.name} ({est.stamps.min():.6f}..{est.stamps.max():.6f} s) with max_diff {max_diff} s "
            f"and offset {offset} s",
            reason="no_overlap",
        )
    return Association(ref.take(idx_ref), est.take(idx_est), idx_ref, idx_est, float(max_diff), float(offset))
