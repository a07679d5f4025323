"""The covariance check and the stereo pair's epipolar distance."""

from __future__ import annotations

import numpy as np
import pytest
import synthetic_sequences as syn

from nsflow_ros.core.camera import KannalaBrandtCamera
from nsflow_ros.core.checks import CovarianceCheck, StereoGeometry
from nsflow_ros.core.errors import CoreError


def _pose(rot_vec=(0.0, 0.0, 0.0), t=(-0.11, 0.0, 0.0)) -> np.ndarray:
    import cv2

    out = np.eye(4)
    out[:3, :3] = cv2.Rodrigues(np.asarray(rot_vec, np.float64))[0]
    out[:3, 3] = t
    return out


@pytest.mark.parametrize("field", [
    "max_sigma", "stereo_max_sigma", "relative", "max_epipolar", "max_departure"])
@pytest.mark.parametrize("value", [0.0, -1.0, float("nan"), float("inf")])
def test_check_bounds_must_be_finite_and_positive(field, value):
    with pytest.raises(CoreError, match=f"CovarianceCheck.{field}"):
        CovarianceCheck(**{field: value})


def test_keep_follows_the_major_axis_and_drops_undefined_covariances():
    check = CovarianceCheck(max_sigma=0.3, relative=1.0)
    cov = np.array([
        [0.04, 0.0, 0.04],  # sigma 0.2 both ways: kept
        [0.04, 0.0, 0.16],  # 0.4 along v: dropped
        [0.05, 0.045, 0.05],  # round-ish terms, but a 0.31 px major axis along the diagonal: dropped
        [np.nan, np.nan, np.nan],  # no covariance: dropped
        [np.inf, 0.0, np.inf],  # a singular J^T J: dropped
    ])
    live = np.array([True, False, False, False, False])  # the solve's median: 0.2, under the floor
    np.testing.assert_array_equal(check.keep(cov, live), [True, False, False, False, False])


def test_the_bound_rises_with_the_solves_median_sigma():
    sigma = np.array([0.2, 0.22, 0.25, 0.3, 0.45, 0.6, 2.0])  # a noisy (dark) solve: median 0.3
    cov = np.c_[sigma**2, np.zeros(7), sigma**2 / 4]
    live = np.ones(7, bool)
    # 2x the median (0.6) bounds it, not the 0.3 px floor; a dead point's sigma does not count
    np.testing.assert_array_equal(CovarianceCheck().keep(cov, live), [True] * 6 + [False])
    np.testing.assert_array_equal(CovarianceCheck(relative=1.0).keep(cov, live), [True] * 4 + [False] * 3)
    few = np.zeros(7, bool)
    few[:3] = True  # the live points' median is 0.22: the floor holds
    np.testing.assert_array_equal(CovarianceCheck(max_sigma=0.3, relative=1.0).keep(cov, few),
                                  [True] * 4 + [False] * 3)


def test_a_stereo_match_has_its_own_floor():
    sigma = np.array([0.04, 0.05, 0.05, 0.06, 0.14, 0.18, 0.29])
    cov = np.c_[sigma**2, np.zeros(7), sigma**2]
    live = np.ones(7, bool)
    check = CovarianceCheck(max_sigma=0.15, stereo_max_sigma=0.2)
    np.testing.assert_array_equal(check.keep(cov, live), [True] * 5 + [False] * 2)
    np.testing.assert_array_equal(check.keep(cov, live, stereo=True), [True] * 6 + [False])


def test_the_default_floor_drops_a_clean_solves_widest_tracks():
    # a clean solve: median sigma 0.05, so the 0.15 px floor bounds (2x the median is 0.1)
    sigma = np.array([0.04, 0.05, 0.05, 0.06, 0.14, 0.16, 0.29])
    cov = np.c_[sigma**2, np.zeros(7), sigma**2]
    np.testing.assert_array_equal(CovarianceCheck().keep(cov, np.ones(7, bool)), [True] * 5 + [False] * 2)


def test_a_match_on_its_epipolar_line_is_at_zero_and_a_row_off_at_its_offset():
    cam = syn.camera()
    pose = _pose(rot_vec=(0.01, -0.02, 0.005))
    geo = StereoGeometry(cam, cam, pose)
    rng = np.random.default_rng(0)
    pts3 = np.c_[rng.uniform(-1, 1, (50, 2)), rng.uniform(2, 8, 50)]
    left = cam.project(pts3)
    right = cam.project(pts3 @ pose[:3, :3].T + pose[:3, 3])
    np.testing.assert_allclose(geo.distance(left, right), 0.0, atol=1e-6)
    # The baseline is along x and the rotation small: a shift along y leaves the line by about itself,
    # measured as an angle, so a little less towards the corners (the wide test camera's: down to 0.75).
    off = geo.distance(left, right + np.array([0.0, 3.0]))
    assert off.max() <= 3.0 * 1.01 and off.min() >= 3.0 * 0.75 and np.median(off) > 2.8
    assert geo.distance(np.zeros((0, 2)), np.zeros((0, 2))).shape == (0,)


def test_the_distance_is_in_pixels_of_any_camera_model():
    fisheye = KannalaBrandtCamera(width=752, height=480, k2=0.01, k3=-0.005, k4=0.0, k5=0.0,
                                  mu=300.0, mv=300.0, u0=376.0, v0=240.0)
    pose = _pose()
    geo = StereoGeometry(fisheye, fisheye, pose)
    assert geo.focal == pytest.approx(300.0, rel=1e-3)
    left = fisheye.project(np.array([[0.0, 0.0, 4.0]]))
    right = fisheye.project(np.array([[0.0, 0.0, 4.0]]) + pose[:3, 3])
    np.testing.assert_allclose(geo.distance(left, right + np.array([0.0, 2.0])), 2.0, rtol=0.02)


@pytest.mark.parametrize("pose, match", [
    (np.eye(3), "finite"),
    (np.full((4, 4), np.nan), "finite"),
    (np.eye(4), "baseline"),
    (np.diag([2.0, 1.0, 1.0, 1.0]) + _pose() - np.eye(4), "rigid"),
])
def test_a_stereo_pose_that_is_no_rigid_motion_with_a_baseline_is_refused(pose, match):
    with pytest.raises(CoreError, match=match):
        StereoGeometry(syn.camera(), syn.camera(), pose)


def test_unsure_points_are_those_far_from_their_prior():
    check = CovarianceCheck(max_departure=3.0)
    positions = np.array([[10.0, 10.0], [10.0, 10.0], [10.0, 10.0], [10.0, 10.0]])
    prior = np.array([[11.0, 12.0], [14.0, 10.0], [12.0, 12.5], [np.nan, np.nan]])
    np.testing.assert_array_equal(check.unsure(positions, prior), [False, True, True, False])
    assert not check.unsure(positions, None).any()  # no prior at all: nothing to depart from
