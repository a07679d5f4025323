"""Nearest-stamp association with max_diff and offset."""

from __future__ import annotations

import numpy as np
import pytest

from nsflow_ros.ate import ATEError, Trajectory, associate, match_stamps


def _traj(stamps, name="t"):
    stamps = np.asarray(stamps, dtype=float)
    n = stamps.size
    return Trajectory(stamps, np.arange(n * 3.0).reshape(n, 3), np.tile([1.0, 0, 0, 0], (n, 1)), name)


def test_match_nearest_within_max_diff():
    ia, ib = match_stamps(np.array([0.0, 1.004, 2.02, 3.0]), np.array([0.001, 1.0, 1.01, 2.0, 3.01]), 0.01)
    assert ia.tolist() == [0, 1, 3]
    assert ib.tolist() == [0, 1, 4]  # 1.004 is nearer to 1.0 than to 1.01; 2.02 is 0.02 away


def test_boundary_is_inclusive_and_ties_pick_the_earlier():
    ia, ib = match_stamps(np.array([1.0]), np.array([0.5, 1.5]), 0.5)
    assert ia.tolist() == [0] and ib.tolist() == [0]
    ia, _ = match_stamps(np.array([1.0]), np.array([0.25, 1.75]), 0.5)
    assert ia.size == 0


def test_unsorted_inputs_give_time_ordered_pairs():
    ia, ib = match_stamps(np.array([2.0, 0.0, 1.0]), np.array([1.0, 2.0, 0.0]), 0.01)
    assert ia.tolist() == [1, 2, 0]
    assert ib.tolist() == [2, 0, 1]


def test_shorter_trajectory_drives_the_matching():
    ref = _traj(np.arange(0, 10, 0.005), "ref")  # 200 Hz
    est = _traj(np.arange(0, 10, 0.05) + 0.002, "est")  # 20 Hz, 2 ms late
    pairs = associate(ref, est)
    assert len(pairs) == len(est)
    np.testing.assert_allclose(pairs.ref.stamps, pairs.est.stamps - 0.002, atol=1e-9)
    assert pairs.est_indices.tolist() == list(range(len(est)))
    # Several estimate poses may share a reference pose when the reference is the sparse one.
    pairs = associate(_traj([0.0, 1.0, 2.0, 3.0]), _traj([0.0, 0.004, 1.0, 2.0, 3.0]))
    assert len(pairs) == 4


def test_offset_is_added_to_the_estimate():
    ref = _traj(np.arange(100) * 0.1)
    est = _traj(np.arange(100) * 0.1 - 50.0)  # estimator clock 50 s behind
    with pytest.raises(ATEError, match="no overlapping stamps") as info:
        associate(ref, est, max_diff=0.01, offset=0.5)
    assert info.value.reason == "no_overlap"
    assert "offset 0.5 s" in str(info.value)
    pairs = associate(ref, est, offset=50.0)
    assert len(pairs) == 100
    np.testing.assert_allclose(pairs.est.stamps + 50.0, pairs.ref.stamps, atol=1e-9)
    # A partial offset leaves a partial overlap.
    assert len(associate(ref, est, offset=45.0)) == 50
    # Same when the estimate is the longer one (the offset is applied with the right sign).
    dense = _traj(np.arange(1000) * 0.01 - 50.0)
    assert len(associate(ref, dense, offset=50.0)) == 100
    assert len(associate(ref, dense, offset=45.0)) == 51  # ref 5.0 meets the last estimate (4.99) within 0.01


def test_max_diff_controls_matches():
    ref = _traj(np.arange(10.0))
    est = _traj(np.arange(10.0) + 0.02)
    with pytest.raises(ATEError, match=r"max_diff 0\.01 s"):
        associate(ref, est)
    assert len(associate(ref, est, max_diff=0.03)) == 10


def test_guards():
    empty = Trajectory(np.zeros(0), np.zeros((0, 3)), np.zeros((0, 4)), "nothing")
    with pytest.raises(ATEError, match="nothing: trajectory is empty"):
        associate(empty, _traj([1.0]))
    with pytest.raises(ATEError, match="max_diff must be"):
        associate(_traj([1.0]), _traj([1.0]), max_diff=-1)
    with pytest.raises(ATEError, match="offset must be"):
        associate(_traj([1.0]), _traj([1.0]), offset=float("nan"))
    with pytest.raises(ATEError, match=r"must have shape \(N,\)"):
        match_stamps(np.zeros((2, 2)), np.zeros(2))
    assert match_stamps(np.zeros(0), np.zeros(3))[0].size == 0
