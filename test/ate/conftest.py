"""Synthetic trajectories shared by the ATE tests (fixtures only; no test data is downloaded)."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pytest

from nsflow_ros.ate import Trajectory


def axis_angle_quaternion(axis: np.ndarray | list[float], angle: np.ndarray | float) -> np.ndarray:
    """Quaternions (w, x, y, z) for rotations of ``angle`` (scalar or (N,)) about ``axis``."""
    axis = np.asarray(axis, dtype=float)
    axis = axis / np.linalg.norm(axis)
    angle = np.asarray(angle, dtype=float)
    half = angle[..., None] / 2.0
    return np.concatenate([np.cos(half), np.sin(half) * axis], axis=-1)


def rotation_matrix(axis: list[float], angle: float) -> np.ndarray:
    """Rodrigues' formula, written independently of nsflow_ros.ate.rotation."""
    k = np.asarray(axis, dtype=float)
    k = k / np.linalg.norm(k)
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(angle) * kx + (1 - np.cos(angle)) * kx @ kx


def _hamilton(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    w1, x1, y1, z1 = np.moveaxis(a, -1, 0)
    w2, x2, y2, z2 = np.moveaxis(b, -1, 0)
    return np.stack(
        [
            w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
            w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
            w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
            w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
        ],
        axis=-1,
    )


def make_trajectory(
    n: int = 600, rate: float = 20.0, t0: float = 1403636579.0, name: str = "gt", seed: int | None = None
) -> Trajectory:
    """A smooth 3-D Lissajous flight with turning orientation, sampled at ``rate`` Hz from ``t0``."""
    t = t0 + np.arange(n) / rate
    s = t - t0
    pos = np.stack([3.0 * np.sin(0.3 * s), 2.0 * np.sin(0.45 * s + 0.5), 1.0 + 0.5 * np.sin(0.2 * s)], axis=1)
    yaw = axis_angle_quaternion([0, 0, 1], 0.4 * s)
    tilt = axis_angle_quaternion([1, 0.2, 0], 0.1 * np.sin(s))
    quats = _hamilton(yaw, tilt)
    if seed is not None:
        pos = pos + np.random.default_rng(seed).normal(0.0, 0.03, pos.shape)
    return Trajectory(t, pos, quats, name)


@pytest.fixture
def make_traj() -> Callable[..., Trajectory]:
    """Factory of smooth synthetic trajectories (see :func:`make_trajectory`)."""
    return make_trajectory


@pytest.fixture
def gt() -> Trajectory:
    """600 poses at 20 Hz (30 s)."""
    return make_trajectory()


@pytest.fixture(scope="session")
def rot() -> Callable[[list[float], float], np.ndarray]:
    """Rotation matrix from axis and angle."""
    return rotation_matrix


@pytest.fixture(scope="session")
def aaq() -> Callable[..., np.ndarray]:
    """Quaternion (w, x, y, z) from axis and angle."""
    return axis_angle_quaternion
