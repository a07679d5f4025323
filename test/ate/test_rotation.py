"""Quaternion / rotation-matrix helpers."""

from __future__ import annotations

import numpy as np
import pytest

from nsflow_ros.ate.rotation import (
    matrix_to_quaternion,
    quaternion_multiply,
    quaternion_to_matrix,
    rotation_angle,
)


def test_axis_angle_matches_rodrigues(rot, aaq):
    for axis, angle in (([0, 0, 1], 0.3), ([1, -2, 0.5], 2.9), ([1, 0, 0], np.pi - 1e-9)):
        np.testing.assert_allclose(quaternion_to_matrix(aaq(axis, angle)), rot(axis, angle), atol=1e-12)


def test_round_trip_all_branches(aaq):
    # Angles near 0 and near pi exercise every branch of the matrix -> quaternion conversion.
    axes = [[1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 1], [-1, 2, 0.1]]
    quats = np.stack([aaq(a, ang) for a in axes for ang in (0.0, 0.5, 3.0, np.pi)])
    back = matrix_to_quaternion(quaternion_to_matrix(quats))
    same = np.abs(np.sum(back * quats, axis=1))  # q and -q are the same rotation
    np.testing.assert_allclose(same, 1.0, atol=1e-12)
    assert np.all(back[:, 0] >= 0)


def test_product_composes_rotations(rot, aaq):
    a, b = aaq([0, 1, 1], 0.7), aaq([1, 0, 0], -1.2)
    expected = rot([0, 1, 1], 0.7) @ rot([1, 0, 0], -1.2)
    np.testing.assert_allclose(quaternion_to_matrix(quaternion_multiply(a, b)), expected, atol=1e-12)


def test_angle(rot):
    assert rotation_angle(rot([3, 1, 2], 1.25)) == pytest.approx(1.25)
    assert rotation_angle(np.eye(3)) == pytest.approx(0.0)
    assert rotation_angle(rot([1, 0, 0], 1e-9)) == pytest.approx(1e-9, rel=1e-6)
    assert rotation_angle(rot([0, 1, 1], np.pi)) == pytest.approx(np.pi)


def test_shape_guards():
    with pytest.raises(ValueError, match=r"\(\.\.\., 4\)"):
        quaternion_to_matrix(np.zeros(3))
    with pytest.raises(ValueError, match=r"\(\.\.\., 3, 3\)"):
        matrix_to_quaternion(np.zeros((2, 3)))
