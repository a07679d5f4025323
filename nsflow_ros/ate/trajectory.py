"""The :class:`Trajectory` container: stamped 3-D poses as plain NumPy arrays, what every reader returns
and every metric consumes."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from nsflow_ros.ate.errors import ATEError
from nsflow_ros.ate.rotation import matrix_to_quaternion, quaternion_multiply, quaternion_to_matrix

__all__ = ["Trajectory"]


def _frozen(array: np.ndarray) -> np.ndarray:
    array = np.array(array, dtype=np.float64, copy=True)
    array.setflags(write=False)
    return array


def _check_finite(name: str, what: str, array: np.ndarray) -> None:
    bad = ~np.isfinite(array)
    if np.any(bad):
        row = int(np.argwhere(bad)[0][0])
        raise ATEError(
            f"{name}: {what} contain NaN or inf (first at pose index {row}: {array[row]})", reason="nan"
        )


@dataclass(frozen=True, eq=False)
class Trajectory:
    """Stamped poses of one estimator run or one ground truth; immutable (operations return new ones).

    Attributes:
        stamps: time of each pose in seconds.
        positions: position of each pose in metres.
        quaternions: orientation of each pose, (w, x, y, z), normalised on construction.
        name: label used in error messages and plots (usually the file it came from).

    Shape:
        stamps (N,), positions (N, 3), quaternions (N, 4); N may be 0.

    Raises:
        ATEError: on construction, for disagreeing shapes, a NaN or infinite value, or a zero quaternion.
    """

    stamps: np.ndarray
    positions: np.ndarray
    quaternions: np.ndarray
    name: str = "trajectory"

    def __post_init__(self) -> None:
        stamps = np.asarray(self.stamps, dtype=np.float64)
        positions = np.asarray(self.positions, dtype=np.float64)
        quats = np.asarray(self.quaternions, dtype=np.float64)
        if stamps.ndim != 1:
            raise ATEError(f"{self.name}: stamps must have shape (N,), got {stamps.shape}")
        n = stamps.shape[0]
        if positions.shape != (n, 3):
            raise ATEError(f"{self.name}: positions must have shape ({n}, 3), got {positions.shape}")
        if quats.shape != (n, 4):
            raise ATEError(f"{self.name}: quaternions must have shape ({n}, 4), got {quats.shape}")
        _check_finite(self.name, "stamps", stamps[:, None])
        _check_finite(self.name, "positions", positions)
        _check_finite(self.name, "quaternions", quats)
        norms = np.linalg.norm(quats, axis=1)
        if n and np.min(norms) < 1e-9:
            row = int(np.argmin(norms))
            raise ATEError(f"{self.name}: quaternion at pose index {row} has zero norm: {quats[row]}")
        object.__setattr__(self, "stamps", _frozen(stamps))
        object.__setattr__(self, "positions", _frozen(positions))
        object.__setattr__(self, "quaternions", _frozen(quats / norms[:, None] if n else quats))

    def __len__(self) -> int:
        return int(self.stamps.shape[0])

    def __repr__(self) -> str:
        span = f"{self.stamps[0]:.3f}..{self.stamps[-1]:.3f} s" if len(self) else "empty"
        return f"Trajectory(name={self.name!r}, poses={len(self)}, {span})"

    @property
    def duration(self) -> float:
        """Time between the first and the last stamp in seconds (0 for fewer than two poses)."""
        if len(self) < 2:
            return 0.0
        return float(np.max(self.stamps) - np.min(self.stamps))

    def path_length(self) -> float:
        """Length of the polyline through the positions, in metres (0 for fewer than two poses)."""
        if len(self) < 2:
            return 0.0
        return float(np.sum(np.linalg.norm(np.diff(self.positions, axis=0), axis=1)))

    def take(self, indices: np.ndarray | list[int]) -> Trajectory:
        """The poses at the given (M,) indices, in that order (repeats allowed), under the same name."""
        idx = np.asarray(indices, dtype=np.int64)
        return Trajectory(self.stamps[idx], self.positions[idx], self.quaternions[idx], self.name)

    def sorted_by_time(self) -> Trajectory:
        """The poses ordered by stamp (equal stamps keep their file order)."""
        return self.take(np.argsort(self.stamps, kind="stable"))

    def renamed(self, name: str) -> Trajectory:
        """The same poses under another name."""
        return Trajectory(self.stamps, self.positions, self.quaternions, name)

    def shifted(self, offset: float) -> Trajectory:
        """The trajectory with ``offset`` seconds added to every stamp."""
        return Trajectory(self.stamps + float(offset), self.positions, self.quaternions, self.name)

    def rotation_matrices(self) -> np.ndarray:
        """Orientations as (N, 3, 3) body-to-world rotation matrices."""
        return quaternion_to_matrix(self.quaternions)

    def transformed(self, rotation: np.ndarray, translation: np.ndarray, scale: float = 1.0) -> Trajectory:
        """The similarity p' = scale * R p + t applied to the positions and R to the orientations.

        Shape:
            rotation (3, 3), translation (3,).

        Raises:
            ATEError: when the shapes are wrong or the scale is not a positive finite number.
        """
        rot = np.asarray(rotation, dtype=np.float64)
        trans = np.asarray(translation, dtype=np.float64)
        if rot.shape != (3, 3):
            raise ATEError(f"rotation must have shape (3, 3), got {rot.shape}")
        if trans.shape != (3,):
            raise ATEError(f"translation must have shape (3,), got {trans.shape}")
        if not (np.isfinite(scale) and scale > 0):
            raise ATEError(f"scale must be a positive finite number, got {scale}")
        positions = float(scale) * self.positions @ rot.T + trans
        quats = quaternion_multiply(matrix_to_quaternion(rot), self.quaternions)
        return Trajectory(self.stamps, positions, quats, self.name)
