"""Unit quaternions (w, x, y, z: Hamilton, scalar first as in EuRoC and VINS files) and rotation
matrices, vectorised over leading axes."""

from __future__ import annotations

import numpy as np

__all__ = ["matrix_to_quaternion", "quaternion_multiply", "quaternion_to_matrix", "rotation_angle"]


def quaternion_to_matrix(quaternions: np.ndarray) -> np.ndarray:
    """Convert quaternions (w, x, y, z) to rotation matrices; they are normalised first.

    Shape:
        quaternions (..., 4) -> (..., 3, 3).

    Raises:
        ValueError: when the last axis is not 4 long.
    """
    q = np.asarray(quaternions, dtype=np.float64)
    if q.shape[-1:] != (4,):
        raise ValueError(f"quaternions must have shape (..., 4), got {q.shape}")
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    rot = np.empty((*q.shape[:-1], 3, 3))
    rot[..., 0, 0] = 1.0 - 2.0 * (y * y + z * z)
    rot[..., 0, 1] = 2.0 * (x * y - w * z)
    rot[..., 0, 2] = 2.0 * (x * z + w * y)
    rot[..., 1, 0] = 2.0 * (x * y + w * z)
    rot[..., 1, 1] = 1.0 - 2.0 * (x * x + z * z)
    rot[..., 1, 2] = 2.0 * (y * z - w * x)
    rot[..., 2, 0] = 2.0 * (x * z - w * y)
    rot[..., 2, 1] = 2.0 * (y * z + w * x)
    rot[..., 2, 2] = 1.0 - 2.0 * (x * x + y * y)
    return rot


def matrix_to_quaternion(rotations: np.ndarray) -> np.ndarray:
    """Convert rotation matrices to unit quaternions (w, x, y, z) with w >= 0.

    Each matrix is solved from the largest of its four diagonal combinations, for numerical stability.

    Shape:
        rotations (..., 3, 3) -> (..., 4).

    Raises:
        ValueError: when the last two axes are not 3 x 3.
    """
    r = np.asarray(rotations, dtype=np.float64)
    if r.shape[-2:] != (3, 3):
        raise ValueError(f"rotations must have shape (..., 3, 3), got {r.shape}")
    lead = r.shape[:-2]
    m = r.reshape(-1, 3, 3)
    trace = m[:, 0, 0] + m[:, 1, 1] + m[:, 2, 2]
    # Four candidate values of 4 * component^2; pick the largest per matrix.
    cand = np.stack(
        [
            1.0 + trace,
            1.0 + 2.0 * m[:, 0, 0] - trace,
            1.0 + 2.0 * m[:, 1, 1] - trace,
            1.0 + 2.0 * m[:, 2, 2] - trace,
        ],
        axis=1,
    )
    # 4 * (product of components j and k) for each pair j < k, from the off-diagonal entries
    pairs = {
        (0, 1): m[:, 2, 1] - m[:, 1, 2],
        (0, 2): m[:, 0, 2] - m[:, 2, 0],
        (0, 3): m[:, 1, 0] - m[:, 0, 1],
        (1, 2): m[:, 0, 1] + m[:, 1, 0],
        (1, 3): m[:, 0, 2] + m[:, 2, 0],
        (2, 3): m[:, 1, 2] + m[:, 2, 1],
    }
    best = np.argmax(cand, axis=1)
    q = np.empty((m.shape[0], 4))
    for k in range(4):
        sel = best == k
        if not np.any(sel):
            continue
        s = np.sqrt(np.maximum(cand[sel, k], 0.0)) * 2.0  # = 4 * |component k|
        q[sel] = np.stack(
            [s / 4.0 if c == k else pairs[min(c, k), max(c, k)][sel] / s for c in range(4)], axis=1
        )
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    q[q[:, 0] < 0] *= -1.0
    return q.reshape(*lead, 4)


def quaternion_multiply(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product a * b of quaternions (w, x, y, z): rotation b first, then a.

    Shape:
        a (..., 4), b (..., 4) -> (..., 4) (broadcast).
    """
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    aw, ax, ay, az = a[..., 0], a[..., 1], a[..., 2], a[..., 3]
    bw, bx, by, bz = b[..., 0], b[..., 1], b[..., 2], b[..., 3]
    return np.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        axis=-1,
    )


def rotation_angle(rotations: np.ndarray) -> np.ndarray:
    """Angle in radians of rotation matrices, in [0, pi].

    atan2(|sin|, cos) of the skew and trace parts stays accurate near 0, where an arccos of the trace
    loses half the digits.

    Shape:
        rotations (..., 3, 3) -> (...).
    """
    r = np.asarray(rotations, dtype=np.float64)
    cos = (np.trace(r, axis1=-2, axis2=-1) - 1.0) / 2.0
    skew = np.stack(
        [r[..., 2, 1] - r[..., 1, 2], r[..., 0, 2] - r[..., 2, 0], r[..., 1, 0] - r[..., 0, 1]], axis=-1
    )
    sin = 0.5 * np.linalg.norm(skew, axis=-1)
    return np.arctan2(sin, cos)
