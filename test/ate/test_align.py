"""Umeyama SE(3) / Sim(3) alignment: exact recovery, reflection fix, first-N, guards."""

from __future__ import annotations

import numpy as np
import pytest

from nsflow_ros.ate import ATEError, align_trajectory, umeyama


@pytest.mark.parametrize("scale", [1.0, 0.37, 4.2])
def test_sim3_recovers_known_transform_exactly(gt, rot, scale):
    r = rot([0.3, -0.5, 1.0], 2.1)
    t = np.array([10.0, -3.0, 0.25])
    target = scale * gt.positions @ r.T + t
    fit = umeyama(gt.positions, target, with_scale=True)
    np.testing.assert_allclose(fit.rotation, r, atol=1e-12)
    np.testing.assert_allclose(fit.translation, t, atol=1e-10)
    assert fit.scale == pytest.approx(scale, rel=1e-12)
    assert fit.method == "sim3" and fit.n_points == len(gt)
    np.testing.assert_allclose(fit.apply(gt.positions), target, atol=1e-10)
    np.testing.assert_allclose(fit.matrix()[:3, :3], scale * r, atol=1e-12)


def test_se3_recovers_known_rigid_transform_exactly(gt, rot):
    r = rot([1, 1, 0], -0.9)
    t = np.array([-1.0, 2.0, 3.0])
    fit = umeyama(gt.positions, gt.positions @ r.T + t)
    np.testing.assert_allclose(fit.rotation, r, atol=1e-12)
    np.testing.assert_allclose(fit.translation, t, atol=1e-10)
    assert fit.scale == 1.0 and fit.method == "se3"


def test_reflection_is_never_returned(gt):
    # The target is a mirror image: the best orthogonal map is a reflection; Umeyama's sign fix must
    # return a proper rotation instead.
    mirror = np.diag([1.0, 1.0, -1.0])
    for with_scale in (False, True):
        fit = umeyama(gt.positions, gt.positions @ mirror.T, with_scale=with_scale)
        assert np.linalg.det(fit.rotation) == pytest.approx(1.0)
        np.testing.assert_allclose(fit.rotation @ fit.rotation.T, np.eye(3), atol=1e-12)


def test_first_n_alignment(gt, rot):
    # The first 100 poses are an exact rigid copy; later poses drift away. Fitting on the first 100
    # recovers the transform exactly; fitting on all poses does not.
    r = rot([0, 0, 1], 0.5)
    t = np.array([1.0, 1.0, 0.0])
    ref = gt.transformed(r, t)
    drift = np.zeros((len(gt), 3))
    drift[100:, 0] = np.linspace(0, 2.0, len(gt) - 100)
    est = gt.__class__(gt.stamps, gt.positions + drift, gt.quaternions, "est")
    aligned, fit = align_trajectory(est, ref, "se3", n_first=100)
    np.testing.assert_allclose(fit.rotation, r, atol=1e-12)
    np.testing.assert_allclose(aligned.positions[:100], ref.positions[:100], atol=1e-10)
    _, fit_all = align_trajectory(est, ref, "se3")
    assert not np.allclose(fit_all.rotation, r, atol=1e-6)


def test_align_none_is_identity(gt):
    aligned, fit = align_trajectory(gt, gt, "none")
    assert aligned is gt and fit.method == "none" and fit.scale == 1.0
    np.testing.assert_array_equal(fit.matrix(), np.eye(4))
    assert fit.as_dict()["method"] == "none"


def test_guards(gt):
    with pytest.raises(ATEError, match="at least 3 point pairs, got 2") as info:
        umeyama(gt.positions[:2], gt.positions[:2])
    assert info.value.reason == "too_few"
    with pytest.raises(ATEError, match="collinear") as info:
        line = np.outer(np.arange(5.0), [1.0, 2.0, 3.0])
        umeyama(line, line)
    assert info.value.reason == "degenerate"
    with pytest.raises(ATEError, match="all equal or collinear"):
        umeyama(np.ones((4, 3)), np.zeros((4, 3)), with_scale=True)
    with pytest.raises(ATEError, match=r"same shape, got \(5, 3\) and \(4, 3\)"):
        umeyama(gt.positions[:5], gt.positions[:4])
    with pytest.raises(ATEError, match=r"source points must have shape \(N, 3\), got \(5, 2\)"):
        umeyama(gt.positions[:5, :2], gt.positions[:5, :2])
    bad = gt.positions[:5].copy()
    bad[2, 1] = np.nan
    with pytest.raises(ATEError, match=r"target points contain NaN .* row 2"):
        umeyama(gt.positions[:5], bad)
    with pytest.raises(ATEError, match="unknown alignment 'affine'"):
        align_trajectory(gt, gt, "affine")
    with pytest.raises(ATEError, match="n_first must be between 3 and the 600"):
        align_trajectory(gt, gt, "se3", n_first=601)
    with pytest.raises(ATEError, match="same length, got 600 and 5"):
        align_trajectory(gt, gt.take(range(5)), "se3")
    with pytest.raises(ATEError, match=r"points must have shape \(N, 3\)"):
        umeyama(gt.positions, gt.positions).apply(np.zeros(3))
