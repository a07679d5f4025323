"""The Trajectory container: guards and transforms."""

from __future__ import annotations

import numpy as np
import pytest

from nsflow_ros.ate import ATEError, Trajectory


def test_normalises_and_freezes(gt):
    traj = Trajectory([0.0, 1.0], np.zeros((2, 3)), [[2.0, 0, 0, 0], [0, 0, 0, 3.0]], "t")
    np.testing.assert_allclose(traj.quaternions, [[1, 0, 0, 0], [0, 0, 0, 1]])
    with pytest.raises(ValueError):
        traj.positions[0, 0] = 1.0
    assert len(gt) == 600
    assert gt.duration == pytest.approx(599 / 20)
    assert "poses=600" in repr(gt)


@pytest.mark.parametrize(
    ("stamps", "positions", "quats", "match"),
    [
        (np.zeros((2, 1)), np.zeros((2, 3)), np.ones((2, 4)), r"stamps must have shape \(N,\), got \(2, 1\)"),
        (np.zeros(2), np.zeros((3, 3)), np.ones((2, 4)), r"positions must have shape \(2, 3\), got \(3, 3\)"),
        (np.zeros(2), np.zeros((2, 3)), np.ones((2, 3)), r"quaternions must have shape \(2, 4\), got"),
        (np.array([0.0, np.nan]), np.zeros((2, 3)), np.ones((2, 4)), r"stamps contain NaN .* index 1"),
        (np.zeros(2), np.array([[0, 0, 0], [0, np.inf, 0]]), np.ones((2, 4)), "positions contain NaN"),
        (np.zeros(2), np.zeros((2, 3)), np.array([[1, 0, 0, 0], [0, 0, 0, 0.0]]), "index 1 has zero norm"),
    ],
)
def test_guards(stamps, positions, quats, match):
    with pytest.raises(ATEError, match=match):
        Trajectory(stamps, positions, quats, "bad")


def test_nan_reason():
    with pytest.raises(ATEError) as info:
        Trajectory([0.0], [[np.nan, 0, 0]], [[1, 0, 0, 0]])
    assert info.value.reason == "nan"


def test_transformed_moves_positions_and_orientations(gt, rot):
    r = rot([1, 2, 3], 0.8)
    t = np.array([1.0, -2.0, 3.0])
    out = gt.transformed(r, t, 2.5)
    np.testing.assert_allclose(out.positions, 2.5 * gt.positions @ r.T + t, atol=1e-12)
    np.testing.assert_allclose(out.rotation_matrices(), r @ gt.rotation_matrices(), atol=1e-12)
    np.testing.assert_array_equal(out.stamps, gt.stamps)
    with pytest.raises(ATEError, match="scale must be a positive"):
        gt.transformed(r, t, 0.0)
    with pytest.raises(ATEError, match=r"rotation must have shape \(3, 3\)"):
        gt.transformed(np.eye(2), t)


def test_take_sort_shift_and_length():
    traj = Trajectory([2.0, 0.0, 1.0], [[2, 0, 0], [0, 0, 0], [1, 0, 0]], np.tile([1.0, 0, 0, 0], (3, 1)))
    ordered = traj.sorted_by_time()
    np.testing.assert_array_equal(ordered.stamps, [0, 1, 2])
    assert ordered.path_length() == pytest.approx(2.0)
    assert traj.shifted(0.5).stamps[0] == 2.5
    assert traj.renamed("x").name == "x"
    assert len(traj.take([0, 0])) == 2
    assert Trajectory(np.zeros(0), np.zeros((0, 3)), np.zeros((0, 4))).path_length() == 0.0
