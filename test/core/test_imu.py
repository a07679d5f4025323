"""Gyro integration and rotation-only prediction; the prediction's effect under fast rotation."""

from __future__ import annotations

from dataclasses import replace

import cv2
import numpy as np
import pytest
import synthetic_sequences as syn

from nsflow_ros.core.errors import CoreError
from nsflow_ros.core.imu import (
    GyroBuffer,
    body_to_camera_rotation,
    integrate_gyro,
    predict_pixels,
    so3_exp,
)
from nsflow_ros.core.methods import METHODS, make_method
from nsflow_ros.core.tracker import FeatureTracker, TrackerSettings


@pytest.mark.parametrize("w", [[0.0, 0.0, 0.0], [1e-9, 0, 0], [0.3, -1.2, 0.7], [3.0, 0.1, -2.0]])
def test_so3_exp_matches_rodrigues(w):
    np.testing.assert_allclose(so3_exp(np.array(w)), cv2.Rodrigues(np.array(w, float))[0], atol=1e-12)


def test_constant_rate_integrates_exactly_with_interpolated_ends():
    rate = np.array([0.4, -1.1, 0.25])
    ts = np.arange(0.0, 1.0, 0.005)
    samples = np.c_[ts, np.tile(rate, (ts.size, 1))]
    np.testing.assert_allclose(integrate_gyro(samples, 0.1234, 0.1734), so3_exp(rate * 0.05), atol=1e-12)
    # a linearly growing rate: midpoint integration of a linear function is exact per axis
    lin = np.c_[ts, np.outer(ts, [0.0, 0.0, 2.0])]
    r = integrate_gyro(lin, 0.2, 0.6)
    np.testing.assert_allclose(r, so3_exp([0, 0, 0.6**2 - 0.2**2]), atol=1e-12)
    # samples that end before t1 hold the last rate
    np.testing.assert_allclose(integrate_gyro(samples[:10], 0.0, 0.1), so3_exp(rate * 0.1), atol=1e-12)


def test_bad_samples_are_clear_errors():
    with pytest.raises(CoreError, match=r"\(M, 4\)"):
        integrate_gyro(np.zeros((3, 3)), 0, 1)
    with pytest.raises(CoreError, match="empty"):
        integrate_gyro(np.zeros((0, 4)), 0, 1)
    with pytest.raises(CoreError, match="sorted"):
        integrate_gyro(np.array([[1.0, 0, 0, 0], [0.5, 0, 0, 0]]), 0, 1)
    with pytest.raises(CoreError, match="backwards"):
        integrate_gyro(np.array([[0.0, 0, 0, 0]]), 1, 0)


def test_body_rotation_is_conjugated_into_the_camera_frame():
    r_bc = so3_exp([0.1, 1.4, -0.3])
    w_cam = np.array([0.2, -0.5, 0.9])
    body = so3_exp(r_bc @ w_cam * 0.05)  # the same rotation seen by a gyro in the body frame
    np.testing.assert_allclose(body_to_camera_rotation(body, r_bc), so3_exp(w_cam * 0.05), atol=1e-12)
    np.testing.assert_allclose(body_to_camera_rotation(body, None), body)


def test_prediction_matches_the_rotation_homography():
    cam = syn.camera()
    rot = so3_exp([0.05, -0.1, 0.02])
    px = np.array([[50.0, 40.0], [160.0, 120.0], [300.0, 200.0]])
    expected = syn.apply_h(syn.k_matrix() @ rot.T @ np.linalg.inv(syn.k_matrix()), px)
    np.testing.assert_allclose(predict_pixels(cam, cam.lift(px), rot), expected, atol=1e-9)
    behind = predict_pixels(cam, cam.lift(px[:1]), so3_exp([0, np.pi, 0]))
    assert np.isnan(behind).all()


def test_gyro_buffer_windows_and_prunes():
    buf = GyroBuffer(max_samples=100)
    for t in np.arange(0, 1.0, 0.01):
        buf.add(t, (0.0, 0.0, t))
    buf.add(0.5, (9, 9, 9))  # out of order: ignored
    w = buf.window(0.205, 0.305)
    assert w[0, 0] <= 0.205 and w[-1, 0] >= 0.305 and len(w) == 12
    assert buf.window(2.0, 3.0) is None  # IMU stale: no prediction
    buf.prune(0.5)
    assert len(buf) == 50


def _run(seq: syn.Sequence, prediction: bool, prior: bool = False) -> tuple[float, float]:
    spec = METHODS["classical"]
    if not prior:  # no constant-velocity start either: the blind tracker
        spec = replace(spec, policy=replace(spec.policy, prior_levels=0))
    settings = TrackerSettings(method="classical", min_dist=20, use_imu_prediction=prediction)
    tracker = FeatureTracker([syn.camera()], settings, method=make_method(spec))
    prev = None
    survival, wrong = [], []
    for k in range(len(seq.frames)):
        cur = tracker.process(float(seq.stamps[k]), seq.frames[k], gyro=seq.gyro).cameras[0]
        if prev is not None:
            where = {int(i): j for j, i in enumerate(prev.ids)}
            ci = [j for j, i in enumerate(cur.ids) if int(i) in where]
            truth = seq.truth(k - 1, k, prev.pixels[[where[int(cur.ids[j])] for j in ci]])
            err = np.hypot(*(cur.pixels[ci] - truth).T)
            survival.append(len(ci) / len(prev))
            wrong.append(np.mean(err > 1.0))
        prev = cur
    return float(np.mean(survival)), float(np.mean(wrong))


def test_gyro_prediction_helps_under_fast_rotation():
    # 120 deg/s yaw with some pitch and roll, 20 Hz: about 28 px of flow per frame at 250 px focal length,
    # plus 0.5 px/frame of motion the gyro does not see (parallax).
    seq = syn.rotating(15, np.deg2rad([36.0, 120.0, 24.0]), translation_px=0.5)
    base_survival, base_wrong = _run(seq, prediction=False)
    pred_survival, pred_wrong = _run(seq, prediction=True)
    # the blind solve captures most of it on the full pyramid (survival 0.65), but a twentieth of what it
    # keeps is wrong; from the gyro's start 0.70 survive and nearly none is wrong
    assert pred_survival > base_survival + 0.03
    assert pred_wrong < base_wrong / 4
    # The constant-velocity start (the default without IMU) does no better than the blind solve here.
    cv_survival, cv_wrong = _run(seq, prediction=False, prior=True)
    assert cv_survival < pred_survival and pred_wrong < cv_wrong / 4
