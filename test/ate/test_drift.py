"""UMA-VI start/end segment drift."""

from __future__ import annotations

import json

import numpy as np
import pytest

from nsflow_ros.ate import ATEError, Trajectory, evaluate_drift, split_segments


def _segments_only(gt: Trajectory, seconds: float = 5.0) -> Trajectory:
    """Keep only the first and last ``seconds`` of the ground truth, as UMA-VI records it."""
    keep = (gt.stamps <= gt.stamps[0] + seconds) | (gt.stamps >= gt.stamps[-1] - seconds)
    return gt.take(np.flatnonzero(keep)).renamed("gt_segments")


def test_split_segments():
    segs = split_segments(np.array([5.0, 0.0, 0.1, 5.1, 0.2, 9.0]), min_gap=1.0)
    assert [s.tolist() for s in segs] == [[1, 2, 4], [0, 3], [5]]
    assert split_segments(np.zeros(0)) == []
    with pytest.raises(ATEError, match="min_gap must be a positive"):
        split_segments(np.zeros(3), min_gap=0.0)


def test_perfect_estimate_has_no_drift(gt, rot):
    est = gt.transformed(rot([0, 0, 1], 1.0), np.array([2.0, 0.0, 0.0])).renamed("est")
    result = evaluate_drift(_segments_only(gt), est)
    assert result.alignment_error < 1e-9 and result.end_drift < 1e-9
    assert result.rotation_drift_deg < 1e-6
    assert result.n_start == result.n_end == 101
    assert result.path_length == pytest.approx(gt.path_length())


def test_known_jump_is_the_drift(gt):
    # The estimate jumps by d in the middle of the unobserved part: each segment alignment is exact, and
    # the two alignments differ by the translation d for every pose.
    d = np.array([0.3, -0.4, 1.2])
    pos = gt.positions.copy()
    pos[300:] += d
    est = Trajectory(gt.stamps, pos, gt.quaternions, "est")
    result = evaluate_drift(_segments_only(gt), est)
    assert result.alignment_error == pytest.approx(np.linalg.norm(d), abs=1e-9)
    assert result.end_drift == pytest.approx(np.linalg.norm(d), abs=1e-9)
    assert result.rotation_drift_deg == pytest.approx(0.0, abs=1e-6)
    assert result.start_fit.rmse < 1e-9 and result.end_fit.rmse < 1e-9
    np.testing.assert_allclose(result.end.translation, -d, atol=1e-9)
    assert result.drift_percent == pytest.approx(100 * np.linalg.norm(d) / result.path_length)
    json.dumps(result.as_dict())


def test_known_yaw_drift(gt, rot):
    # After the start segment the estimate is rotated by 5 degrees about z (around the origin).
    r = rot([0, 0, 1], np.radians(5.0))
    est = gt.take(range(len(gt)))
    late = est.stamps > est.stamps[0] + 10.0
    pos = est.positions.copy()
    pos[late] = pos[late] @ r.T
    result = evaluate_drift(_segments_only(gt), Trajectory(est.stamps, pos, est.quaternions, "est"))
    assert result.rotation_drift_deg == pytest.approx(5.0, abs=1e-6)
    np.testing.assert_allclose(result.end.rotation, r.T, atol=1e-9)


def test_sim3_segments(gt, rot):
    est = gt.transformed(rot([1, 0, 0], 0.3), np.zeros(3), 2.0)
    result = evaluate_drift(_segments_only(gt), est, align="sim3")
    assert result.start.scale == pytest.approx(0.5) and result.alignment_error < 1e-9


def test_errors(gt):
    with pytest.raises(ATEError, match=r"no gap longer than 1\.0 s") as info:
        evaluate_drift(gt, gt)
    assert info.value.reason == "no_overlap"
    with pytest.raises(ATEError, match="se3 or sim3"):
        evaluate_drift(_segments_only(gt), gt, align="none")
    # The estimate stops before the end segment, or two poses into it.
    with pytest.raises(ATEError, match=r"no overlapping stamps between gt_segments \[end segment\]"):
        evaluate_drift(_segments_only(gt), gt.take(range(200)))
    with pytest.raises(ATEError, match="only 2 estimate poses match the end segment") as info:
        evaluate_drift(_segments_only(gt), gt.take(range(501)))
    assert info.value.reason == "too_few"
