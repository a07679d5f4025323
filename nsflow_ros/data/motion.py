"""A smooth 6-DoF trajectory for a MAV-like body and the IMU readings it produces.

The body frame is the IMU frame (EuRoC's ``S`` of imu0): x up when level, cameras looking along z, as on the
EuRoC MAV. Position and yaw / pitch / roll are seeded sums of sinusoids, so velocity, acceleration, angular
velocity and hence the synthetic IMU (before its deliberate noise) are exact. World frame: z up, gravity
``(0, 0, -9.81)`` m/s^2; times are seconds since the trajectory's start.

A flight may start at rest (``Trajectory.rest``), as EuRoC's do: the body holds its first pose, then speeds
up along the same path over :data:`RAMP_S` seconds, a smooth time warp whose derivatives keep the kinematics
exact.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from nsflow_ros.ate.rotation import quaternion_to_matrix
from nsflow_ros.data.camera import PinholeRadtan
from nsflow_ros.data.errors import DataError

__all__ = [
    "EUROC_IMU_NOISE",
    "GRAVITY",
    "NO_IMU_NOISE",
    "RAMP_S",
    "ImuNoise",
    "ImuSamples",
    "Trajectory",
    "quaternion_to_rotation",
    "rotation_to_quaternion",
    "synthesize_imu",
]

GRAVITY = np.array([0.0, 0.0, -9.81])

RAMP_S = 2.0
"""Seconds a flight that starts at rest takes to reach its path's own speed (a raised-cosine speed-up)."""

# Body axes in the world at zero yaw / pitch / roll: body x up, body z (the cameras' view) along world x.
_R0 = np.array([[0.0, 0.0, 1.0], [0.0, -1.0, 0.0], [1.0, 0.0, 0.0]])


def _sines(t: np.ndarray, amp: np.ndarray, freq: np.ndarray, phase: np.ndarray, order: int) -> np.ndarray:
    """Sum over k of the ``order``-th derivative of ``amp_k sin(freq_k t + phase_k)``; (N, D)."""
    arg = t[:, None, None] * freq[None] + phase[None]
    # d^n/dt^n sin(w t + p) = w^n sin(w t + p + n pi / 2)
    return (amp[None] * freq[None] ** order * np.sin(arg + order * np.pi / 2)).sum(axis=2)


def _rz(a: np.ndarray) -> np.ndarray:
    c, s, z, o = np.cos(a), np.sin(a), np.zeros_like(a), np.ones_like(a)
    return np.stack([np.stack([c, -s, z], -1), np.stack([s, c, z], -1), np.stack([z, z, o], -1)], -2)


def _ry(a: np.ndarray) -> np.ndarray:
    c, s, z, o = np.cos(a), np.sin(a), np.zeros_like(a), np.ones_like(a)
    return np.stack([np.stack([c, z, s], -1), np.stack([z, o, z], -1), np.stack([-s, z, c], -1)], -2)


def _rx(a: np.ndarray) -> np.ndarray:
    c, s, z, o = np.cos(a), np.sin(a), np.zeros_like(a), np.ones_like(a)
    return np.stack([np.stack([o, z, z], -1), np.stack([z, c, -s], -1), np.stack([z, s, c], -1)], -2)


def _times(t: Any) -> np.ndarray:
    arr = np.atleast_1d(np.asarray(t, dtype=np.float64))
    if arr.ndim != 1:
        raise DataError(f"times: expected a scalar or shape (N,), got {arr.shape}")
    return arr


def _warp(t: np.ndarray, rest: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The path's time s(t) of a flight at rest for ``rest`` s, and ds/dt, d2s/dt2.

    After the rest the speed factor ds/dt rises as (1 - cos(pi tau / RAMP_S)) / 2 over :data:`RAMP_S` s (tau:
    time since the rest), so velocity and acceleration are continuous; then s = t - rest - RAMP_S / 2.
    """
    tau = np.clip(t - rest, 0.0, RAMP_S)
    arg = np.pi * tau / RAMP_S
    s = tau / 2 - RAMP_S / (2 * np.pi) * np.sin(arg) + np.maximum(t - rest - RAMP_S, 0.0)
    ds = np.where(t >= rest + RAMP_S, 1.0, np.where(t > rest, (1 - np.cos(arg)) / 2, 0.0))
    dds = np.where((t > rest) & (t < rest + RAMP_S), np.pi / (2 * RAMP_S) * np.sin(arg), 0.0)
    return s, ds, dds


@dataclass(frozen=True, eq=False)
class Trajectory:
    """Position and yaw / pitch / roll as constants plus sums of sinusoids.

    Attributes:
        center: (3,) mean position (m).
        pos_amp, pos_freq, pos_phase: (3, K) amplitudes (m), angular frequencies (rad/s), phases (rad).
        ang_center: (3,) mean yaw, pitch, roll (rad).
        ang_amp, ang_freq, ang_phase: (3, K) the same for yaw, pitch, roll.
        rest: seconds the body holds its first pose before it speeds up along the path (0: it flies from the
            start, at the path's speed).

    Orientation: ``R_wb = Rz(yaw) Ry(pitch) Rx(roll) R0`` with ``R0`` the level pose (body x up, body z
    along world x).
    """

    center: np.ndarray
    pos_amp: np.ndarray
    pos_freq: np.ndarray
    pos_phase: np.ndarray
    ang_center: np.ndarray
    ang_amp: np.ndarray
    ang_freq: np.ndarray
    ang_phase: np.ndarray
    rest: float = 0.0

    def __post_init__(self) -> None:
        if not (math.isfinite(self.rest) and self.rest >= 0):
            raise DataError(f"trajectory rest: expected a finite number of seconds >= 0, got {self.rest}")
        object.__setattr__(self, "rest", float(self.rest))
        for name in ("center", "ang_center"):
            arr = np.asarray(getattr(self, name), dtype=np.float64)
            if arr.shape != (3,):
                raise DataError(f"trajectory {name}: expected shape (3,), got {arr.shape}")
            object.__setattr__(self, name, arr)
        shape = np.asarray(self.pos_amp).shape
        for name in ("pos_amp", "pos_freq", "pos_phase", "ang_amp", "ang_freq", "ang_phase"):
            arr = np.asarray(getattr(self, name), dtype=np.float64)
            if arr.ndim != 2 or arr.shape[0] != 3 or arr.shape != shape:
                raise DataError(f"trajectory {name}: expected shape (3, K) = {shape}, got {arr.shape}")
            object.__setattr__(self, name, arr)

    @classmethod
    def from_seed(cls, seed: int = 0, *, speed: float = 1.0, rest: float = 0.0) -> Trajectory:
        """Draw an EuRoC-like flight around the room's centre, deterministically from ``seed``.

        ``rest``: seconds at the first pose before the flight (the path is the same for every ``rest``).

        Bounds at ``speed`` 1 (a factor on every frequency): ``|x| <= 1.4 m``, ``|y| <= 1.0 m``, ``z`` in
        ``1.45 +- 0.35 m``, 0.5 - 1 m/s, yaw rate up to about 1 rad/s, pitch within +-0.25 rad, roll within
        +-0.15 rad; the full yaw range is swept, so the cameras see every wall and box.
        """
        rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0x7A7]))

        def split(total: float, k: int = 2) -> np.ndarray:
            w = rng.uniform(0.5, 1.0, k)
            return total * w / w.sum()

        pos_amp = np.stack([split(1.4), split(1.0), split(0.35)])
        pos_freq = rng.uniform([[0.35, 0.7]] * 3, [[0.55, 1.0]] * 3) * speed
        pos_phase = rng.uniform(0, 2 * np.pi, (3, 2))
        ang_amp = np.stack([
            np.array([rng.uniform(1.2, 1.6), rng.uniform(0.15, 0.3)]),
            split(0.25),
            split(0.15),
        ])
        ang_freq = np.stack([
            np.array([rng.uniform(0.35, 0.5), rng.uniform(0.9, 1.3)]),
            rng.uniform(0.5, 1.2, 2),
            rng.uniform(0.6, 1.4, 2),
        ]) * speed
        ang_phase = rng.uniform(0, 2 * np.pi, (3, 2))
        ang_center = np.array([rng.uniform(-np.pi, np.pi), 0.0, 0.0])
        return cls(np.array([0.0, 0.0, 1.45]), pos_amp, pos_freq, pos_phase, ang_center, ang_amp, ang_freq,
                   ang_phase, rest)

    def to_dict(self) -> dict[str, Any]:
        """Plain-JSON description that :meth:`from_dict` reads back (``rest`` only when there is one)."""
        out: dict[str, Any] = {k: getattr(self, k).tolist() for k in self.__dataclass_fields__ if k != "rest"}
        return out | ({"rest": self.rest} if self.rest else {})

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> Trajectory:
        """Rebuild a trajectory from :meth:`to_dict` output.

        Raises:
            DataError: when a key is missing or malformed.
        """
        try:
            arrays = {k: np.asarray(d[k], dtype=np.float64) for k in cls.__dataclass_fields__ if k != "rest"}
            return cls(**arrays, rest=float(d.get("rest", 0.0)))
        except (KeyError, TypeError, ValueError) as err:
            raise DataError(f"invalid trajectory description: {type(err).__name__}: {err}") from None

    # -- kinematics --------------------------------------------------------------------------------------

    def _path_time(self, t: Any) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
        """(s, ds/dt, d2s/dt2) of the path's time; the derivatives None for a flight without rest (s = t)."""
        tt = _times(t)
        return (tt, None, None) if self.rest == 0 else _warp(tt, self.rest)

    def position(self, t: Any) -> np.ndarray:
        """Body position in the world (m). Shape: (N,) -> (N, 3)."""
        s, _, _ = self._path_time(t)
        return self.center + _sines(s, self.pos_amp, self.pos_freq, self.pos_phase, 0)

    def velocity(self, t: Any) -> np.ndarray:
        """Body velocity in the world frame (m/s). Shape: (N,) -> (N, 3)."""
        s, ds, _ = self._path_time(t)
        v = _sines(s, self.pos_amp, self.pos_freq, self.pos_phase, 1)
        return v if ds is None else v * ds[:, None]

    def acceleration(self, t: Any) -> np.ndarray:
        """Body acceleration in the world frame (m/s^2). Shape: (N,) -> (N, 3)."""
        s, ds, dds = self._path_time(t)
        a = _sines(s, self.pos_amp, self.pos_freq, self.pos_phase, 2)
        if ds is None or dds is None:
            return a
        # d2/dt2 p(s(t)) = p''(s) s'^2 + p'(s) s''
        return a * ds[:, None] ** 2 + _sines(s, self.pos_amp, self.pos_freq, self.pos_phase, 1) * dds[:, None]

    def angles(self, t: Any) -> np.ndarray:
        """Yaw, pitch, roll (rad). Shape: (N,) -> (N, 3)."""
        s, _, _ = self._path_time(t)
        return self.ang_center + _sines(s, self.ang_amp, self.ang_freq, self.ang_phase, 0)

    def rotation(self, t: Any) -> np.ndarray:
        """Body-to-world rotation ``R_wb``. Shape: (N,) -> (N, 3, 3)."""
        a = self.angles(t)
        return _rz(a[:, 0]) @ _ry(a[:, 1]) @ _rx(a[:, 2]) @ _R0

    def angular_velocity(self, t: Any) -> np.ndarray:
        """Angular velocity in the body frame (rad/s), as a gyroscope measures it. Shape: (N,) -> (N, 3)."""
        tt = _times(t)
        a = self.angles(tt)
        s, ds, _ = self._path_time(tt)
        rate = _sines(s, self.ang_amp, self.ang_freq, self.ang_phase, 1)
        if ds is not None:
            rate = rate * ds[:, None]
        Rz, Ry = _rz(a[:, 0]), _ry(a[:, 1])
        ez, ey, ex = np.eye(3)[2], np.eye(3)[1], np.eye(3)[0]
        # World-frame rate of R = Rz Ry Rx R0: each Euler rate about its own (rotated) axis.
        w_world = (rate[:, 0:1] * ez + rate[:, 1:2] * (Rz @ ey) + rate[:, 2:3] * (Rz @ Ry @ ex))
        R = Rz @ Ry @ _rx(a[:, 2]) @ _R0
        return np.einsum("nji,nj->ni", R, w_world)

    def pose(self, t: Any) -> np.ndarray:
        """Body-to-world transform ``T_wb``. Shape: (N,) -> (N, 4, 4)."""
        tt = _times(t)
        T = np.tile(np.eye(4), (tt.size, 1, 1))
        T[:, :3, :3] = self.rotation(tt)
        T[:, :3, 3] = self.position(tt)
        return T

    def camera_pose(self, t: Any, camera: PinholeRadtan) -> np.ndarray:
        """Camera-to-world transform ``T_wc = T_wb T_BS``. Shape: (N,) -> (N, 4, 4)."""
        return self.pose(t) @ camera.T_BS


@dataclass(frozen=True)
class ImuNoise:
    """Continuous-time IMU noise model (Kalibr / EuRoC sensor.yaml conventions).

    Attributes:
        gyro_noise: gyroscope white-noise density (rad/s/sqrt(Hz)).
        gyro_walk: gyroscope bias random-walk density (rad/s^2/sqrt(Hz)).
        accel_noise: accelerometer white-noise density (m/s^2/sqrt(Hz)).
        accel_walk: accelerometer bias random-walk density (m/s^3/sqrt(Hz)).
        gyro_bias0: standard deviation of the initial gyroscope bias per axis (rad/s).
        accel_bias0: standard deviation of the initial accelerometer bias per axis (m/s^2).
    """

    gyro_noise: float = 1.6968e-4
    gyro_walk: float = 1.9393e-5
    accel_noise: float = 2.0e-3
    accel_walk: float = 3.0e-3
    gyro_bias0: float = 5e-3
    accel_bias0: float = 5e-2


EUROC_IMU_NOISE = ImuNoise()
NO_IMU_NOISE = ImuNoise(0.0, 0.0, 0.0, 0.0, 0.0, 0.0)


@dataclass(frozen=True)
class ImuSamples:
    """IMU readings and the biases inside them.

    Shapes: ``stamps_ns`` (N,) int64; ``gyro``, ``accel``, ``gyro_bias``, ``accel_bias`` (N, 3) float64.
    """

    stamps_ns: np.ndarray
    gyro: np.ndarray
    accel: np.ndarray
    gyro_bias: np.ndarray = field(repr=False)
    accel_bias: np.ndarray = field(repr=False)


def synthesize_imu(trajectory: Trajectory, stamps_ns: Any, t0_ns: int, *, noise: ImuNoise = EUROC_IMU_NOISE,
                   seed: int = 0) -> ImuSamples:
    """IMU readings along a trajectory: ``gyro = w_b + b_g + n_g``, ``accel = R^T (a - g) + b_a + n_a``.

    The white noise is drawn per sample with standard deviation ``density / sqrt(dt)`` and the biases
    follow a random walk with per-step deviation ``walk * sqrt(dt)``, ``dt`` being the mean sample period.

    Args:
        stamps_ns: (N,) increasing sample stamps in nanoseconds.
        t0_ns: stamp of the trajectory's time zero.
        noise: noise model; :data:`NO_IMU_NOISE` gives the exact kinematics.
        seed: random seed of the noise and biases.

    Raises:
        DataError: when the stamps are not a 1-D increasing sequence.
    """
    stamps = np.asarray(stamps_ns, dtype=np.int64)
    if stamps.ndim != 1 or stamps.size == 0 or np.any(np.diff(stamps) <= 0):
        raise DataError(f"IMU stamps: expected a non-empty increasing (N,) array, got shape {stamps.shape}")
    t = (stamps - np.int64(t0_ns)) * 1e-9
    R = trajectory.rotation(t)
    gyro = trajectory.angular_velocity(t)
    accel = np.einsum("nji,nj->ni", R, trajectory.acceleration(t) - GRAVITY)
    n = t.size
    dt = float(np.mean(np.diff(t))) if n > 1 else 0.005
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0x1A0]))
    bg0 = rng.standard_normal(3) * noise.gyro_bias0
    ba0 = rng.standard_normal(3) * noise.accel_bias0
    steps = rng.standard_normal((2, n, 3))
    steps[:, 0] = 0.0
    gyro_bias = bg0 + np.cumsum(steps[0] * noise.gyro_walk * np.sqrt(dt), axis=0)
    accel_bias = ba0 + np.cumsum(steps[1] * noise.accel_walk * np.sqrt(dt), axis=0)
    white = rng.standard_normal((2, n, 3))
    gyro = gyro + gyro_bias + white[0] * noise.gyro_noise / np.sqrt(dt)
    accel = accel + accel_bias + white[1] * noise.accel_noise / np.sqrt(dt)
    return ImuSamples(stamps, gyro, accel, gyro_bias, accel_bias)


def rotation_to_quaternion(R: Any) -> np.ndarray:
    """Rotation matrices to unit quaternions ``(w, x, y, z)``, sign kept continuous along the sequence.

    Shape: (N, 3, 3) or (3, 3) -> (N, 4).
    """
    M = np.asarray(R, dtype=np.float64).reshape(-1, 3, 3)
    # Shepperd's method: pick the largest of the four squared components for stability.
    tr = np.trace(M, axis1=1, axis2=2)
    sq = np.stack([1 + tr, 1 + 2 * M[:, 0, 0] - tr, 1 + 2 * M[:, 1, 1] - tr, 1 + 2 * M[:, 2, 2] - tr], axis=1)
    best = np.argmax(sq, axis=1)
    q = np.empty((M.shape[0], 4))
    for i in range(M.shape[0]):
        m, k = M[i], best[i]
        s = 2.0 * np.sqrt(max(sq[i, k], 1e-300))
        if k == 0:
            q[i] = [s / 4, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s]
        elif k == 1:
            q[i] = [(m[2, 1] - m[1, 2]) / s, s / 4, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s]
        elif k == 2:
            q[i] = [(m[0, 2] - m[2, 0]) / s, (m[0, 1] + m[1, 0]) / s, s / 4, (m[1, 2] + m[2, 1]) / s]
        else:
            q[i] = [(m[1, 0] - m[0, 1]) / s, (m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, s / 4]
    if q[0, 0] < 0:
        q[0] = -q[0]
    for i in range(1, len(q)):
        if np.dot(q[i], q[i - 1]) < 0:
            q[i] = -q[i]
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def quaternion_to_rotation(q: Any) -> np.ndarray:
    """Unit quaternions ``(w, x, y, z)`` to rotation matrices. Shape: (N, 4) or (4,) -> (N, 3, 3)."""
    return quaternion_to_matrix(np.asarray(q, dtype=np.float64).reshape(-1, 4))
