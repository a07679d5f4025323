"""Trajectory kinematics and the synthetic IMU."""

from __future__ import annotations

import numpy as np
import pytest

from nsflow_ros.data.camera import EUROC_CAM0
from nsflow_ros.data.errors import DataError
from nsflow_ros.data.motion import (
    EUROC_IMU_NOISE,
    GRAVITY,
    NO_IMU_NOISE,
    RAMP_S,
    Trajectory,
    quaternion_to_rotation,
    rotation_to_quaternion,
    synthesize_imu,
)
from nsflow_ros.data.scene import Scene

T0 = 1_700_000_000_000_000_000


def _exp(w: np.ndarray) -> np.ndarray:
    th = np.linalg.norm(w)
    K = np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]])
    if th < 1e-12:
        return np.eye(3) + K
    return np.eye(3) + np.sin(th) / th * K + (1 - np.cos(th)) / th**2 * K @ K


def _angle(R: np.ndarray) -> float:
    return float(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1)))


@pytest.mark.parametrize(("rest", "t"), [(0.0, [0.7, 5.3]), (1.5, [1.2, 1.9, 2.5, 3.4, 6.0])])
def test_derivatives_match_finite_differences(rest, t):
    # With a rest: at rest, in the speed-up (its time warp's chain rule) and after it.
    traj = Trajectory.from_seed(4, rest=rest)
    t, h = np.array(t), 1e-5
    dp = (traj.position(t + h) - traj.position(t - h)) / (2 * h)
    dv = (traj.velocity(t + h) - traj.velocity(t - h)) / (2 * h)
    assert np.allclose(dp, traj.velocity(t), atol=1e-7)
    assert np.allclose(dv, traj.acceleration(t), atol=1e-6)
    R0, R1 = traj.rotation(t - h), traj.rotation(t + h)
    for k in range(len(t)):
        W = (R0[k].T @ R1[k] - R1[k].T @ R0[k]) / (4 * h)  # body-frame skew of the angular velocity
        assert np.allclose([W[2, 1], W[0, 2], W[1, 0]], traj.angular_velocity(t)[k], atol=1e-7)


@pytest.mark.parametrize("rest", [0.0, 1.5])
def test_integrating_the_noiseless_imu_reproduces_rotation_and_velocity(rest):
    traj = Trajectory.from_seed(2, rest=rest)  # with a rest, 2-3 s is the speed-up
    stamps = T0 + np.arange(0, 201) * 5_000_000  # 1 s at 200 Hz
    imu = synthesize_imu(traj, stamps, T0 - 2_000_000_000, noise=NO_IMU_NOISE)  # span starts at t = 2 s
    t = (stamps - (T0 - 2_000_000_000)) * 1e-9
    R, v = traj.rotation(t[0])[0], traj.velocity(t[0])[0]
    for k in range(len(t) - 1):
        dt = t[k + 1] - t[k]
        R_next = R @ _exp(0.5 * (imu.gyro[k] + imu.gyro[k + 1]) * dt)
        v = v + 0.5 * (R @ imu.accel[k] + R_next @ imu.accel[k + 1]) * dt + GRAVITY * dt
        R = R_next
    assert _angle(R.T @ traj.rotation(t[-1])[0]) < 1e-4
    assert np.linalg.norm(v - traj.velocity(t[-1])[0]) < 1e-3
    # At hover-like attitudes the accelerometer's x axis (up) carries about +g.
    assert 8.0 < np.mean(imu.accel[:, 0]) < 11.5


def test_imu_noise_is_seeded_with_euroc_like_levels():
    traj = Trajectory.from_seed(0)
    stamps = T0 + np.arange(2000) * 5_000_000
    a = synthesize_imu(traj, stamps, T0, seed=1)
    b = synthesize_imu(traj, stamps, T0, seed=1)
    c = synthesize_imu(traj, stamps, T0, seed=2)
    exact = synthesize_imu(traj, stamps, T0, noise=NO_IMU_NOISE)
    assert np.array_equal(a.gyro, b.gyro) and not np.array_equal(a.gyro, c.gyro)
    white = a.gyro - exact.gyro - a.gyro_bias
    expected = EUROC_IMU_NOISE.gyro_noise * np.sqrt(200.0)
    assert 0.9 * expected < white.std() < 1.1 * expected
    white_a = a.accel - exact.accel - a.accel_bias
    assert 0.9 < white_a.std() / (EUROC_IMU_NOISE.accel_noise * np.sqrt(200.0)) < 1.1
    assert np.all(np.abs(a.gyro_bias) < 0.05) and np.all(np.abs(a.accel_bias) < 0.5)


@pytest.mark.parametrize("seed", range(4))
def test_flight_is_euroc_like_and_stays_in_free_space(seed):
    traj, scene = Trajectory.from_seed(seed), Scene.from_seed(seed)
    t = np.arange(0.0, 60.0, 0.05)
    speed = np.linalg.norm(traj.velocity(t), axis=1)
    rate = np.linalg.norm(traj.angular_velocity(t), axis=1)
    assert 0.35 < speed.mean() < 1.0 and speed.max() < 1.5
    assert rate.mean() > 0.2 and rate.max() < 1.3
    cams = traj.camera_pose(t, EUROC_CAM0)
    assert all(scene.contains(p, margin=0.5) for p in cams[::10, :3, 3])
    # The camera looks roughly horizontally (at walls and boxes), never straight up or down.
    assert np.abs(cams[:, 2, 2]).max() < 0.45


def test_a_rest_holds_the_first_pose_then_flies_the_same_path():
    moving, resting = Trajectory.from_seed(5), Trajectory.from_seed(5, rest=2.0)
    still = np.linspace(0.0, 2.0, 41)
    assert np.array_equal(resting.pose(still), np.repeat(moving.pose(0.0), 41, axis=0))
    assert not resting.velocity(still).any() and not resting.angular_velocity(still).any()
    # At rest the accelerometer reads gravity alone: what the estimator's initialisation assumes.
    imu = synthesize_imu(resting, T0 + np.arange(300) * 5_000_000, T0, noise=NO_IMU_NOISE)
    assert np.allclose(np.linalg.norm(imu.accel[:300], axis=1), 9.81, atol=1e-9)
    # After the speed-up it is the same flight, half the speed-up later.
    t = np.linspace(2.0 + RAMP_S, 15.0, 50)
    assert np.allclose(resting.pose(t), moving.pose(t - 2.0 - RAMP_S / 2), atol=1e-12)
    assert np.allclose(resting.velocity(t), moving.velocity(t - 2.0 - RAMP_S / 2), atol=1e-12)
    speed = np.linalg.norm(resting.velocity(np.linspace(2.0, 2.0 + RAMP_S, 200)), axis=1)
    assert speed[0] == 0 and np.all(np.isfinite(speed))
    with pytest.raises(DataError, match="rest: expected a finite number of seconds >= 0, got -1"):
        Trajectory.from_seed(5, rest=-1.0)


def test_quaternions_round_trip_with_continuous_sign():
    R = Trajectory.from_seed(1).rotation(np.linspace(0, 20, 400))
    q = rotation_to_quaternion(R)
    assert np.allclose(quaternion_to_rotation(q), R, atol=1e-12)
    assert np.all(np.sum(q[1:] * q[:-1], axis=1) > 0)
    assert np.allclose(np.linalg.norm(q, axis=1), 1.0)


def test_description_round_trip_and_guards():
    traj = Trajectory.from_seed(3)
    again = Trajectory.from_dict(traj.to_dict())
    assert np.array_equal(again.pose([0.5, 1.5]), traj.pose([0.5, 1.5]))
    assert "rest" not in traj.to_dict()  # a description written before rests existed reads the same
    resting = Trajectory.from_seed(3, rest=1.0)
    assert Trajectory.from_dict(resting.to_dict()).rest == 1.0
    with pytest.raises(DataError, match="increasing"):
        synthesize_imu(traj, [3, 2, 1], 0)
    bad = {**traj.to_dict(), "center": [0.0, 0.0]}
    with pytest.raises(DataError, match=r"center: expected shape \(3,\), got \(2,\)"):
        Trajectory.from_dict(bad)
