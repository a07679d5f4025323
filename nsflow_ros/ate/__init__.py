"""Offline trajectory scoring: ATE/RPE against ground truth, UMA-VI drift, batch tables, plots.

Reads EuRoC / ASL, TUM and VINS trajectories, associates stamps, aligns by Umeyama and reports the
position error's statistics following evo's conventions; batch mode turns a directory of runs into the
paper's EuRoC table. Typical use::

    from nsflow_ros.ate import read_trajectory, evaluate_ape
    result = evaluate_ape(read_trajectory("MH_01"), read_trajectory("out/vio.csv"), align="se3")
    print(result.stats.rmse)
"""

from __future__ import annotations

from nsflow_ros.ate.align import ALIGN_METHODS, Alignment, align_trajectory, umeyama
from nsflow_ros.ate.associate import Association, associate, match_stamps
from nsflow_ros.ate.batch import (
    FAIL_POLICIES,
    BatchResult,
    Cell,
    FailureCriteria,
    RunResult,
    RunSpec,
    batch_csv,
    batch_markdown,
    discover_runs,
    find_ground_truth,
    runs_csv,
    score_batch,
    write_batch_tables,
)
from nsflow_ros.ate.drift import DriftResult, evaluate_drift, split_segments
from nsflow_ros.ate.errors import ATEError
from nsflow_ros.ate.formats import (
    FORMATS,
    detect_format,
    read_trajectory,
    resolve_trajectory_path,
    write_trajectory,
)
from nsflow_ros.ate.metrics import (
    STAT_KEYS,
    APEResult,
    ErrorStats,
    RPEResult,
    error_statistics,
    evaluate_ape,
    position_errors,
    relative_pose_error,
    rpe_errors,
)
from nsflow_ros.ate.plot import plot_top_view
from nsflow_ros.ate.trajectory import Trajectory

__all__ = [
    "ALIGN_METHODS",
    "FAIL_POLICIES",
    "FORMATS",
    "STAT_KEYS",
    "APEResult",
    "ATEError",
    "Alignment",
    "Association",
    "BatchResult",
    "Cell",
    "DriftResult",
    "ErrorStats",
    "FailureCriteria",
    "RPEResult",
    "RunResult",
    "RunSpec",
    "Trajectory",
    "align_trajectory",
    "associate",
    "batch_csv",
    "batch_markdown",
    "detect_format",
    "discover_runs",
    "error_statistics",
    "evaluate_ape",
    "evaluate_drift",
    "find_ground_truth",
    "match_stamps",
    "plot_top_view",
    "position_errors",
    "read_trajectory",
    "relative_pose_error",
    "resolve_trajectory_path",
    "rpe_errors",
    "runs_csv",
    "score_batch",
    "split_segments",
    "umeyama",
    "write_batch_tables",
    "write_trajectory",
]
