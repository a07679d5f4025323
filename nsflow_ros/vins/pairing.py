"""Stereo pairing within a stamp tolerance, as VINS-Fusion pairs its image topics (node and feature bag).

An image waits for the nearest image of the other camera within the tolerance (cameras that stamp left and
right separately differ by a few milliseconds). Each camera's images come in stamp order, so images older
than a pair's members can no longer pair: they are dropped and counted in :attr:`StereoPairer.unpaired`.
"""

from __future__ import annotations

from collections import deque
from typing import Generic, TypeVar

__all__ = ["MAX_PENDING", "STEREO_SYNC_TOLERANCE", "StereoPairer"]

T = TypeVar("T")

MAX_PENDING = 10
"""Unpaired images kept per camera before the oldest is dropped."""

STEREO_SYNC_TOLERANCE = 0.003
"""Largest stamp difference in seconds between the two images of a pair, VINS-Fusion's."""


class StereoPairer(Generic[T]):
    """Pairs camera-0 and camera-1 items (decoded images, records) whose stamps are within a tolerance.

    Args:
        cameras: 1 (every item is a frame at once) or 2.
        tolerance: largest stamp difference of a pair in seconds (0 = equal stamps only).
        max_pending: unpaired items kept per camera (>= 1).

    Attributes:
        unpaired: items dropped because their partner never came.

    Raises:
        ValueError: cameras not 1 or 2, a negative tolerance or max_pending < 1.
    """

    def __init__(self, cameras: int, tolerance: float = STEREO_SYNC_TOLERANCE,
                 max_pending: int = MAX_PENDING) -> None:
        if cameras not in (1, 2):
            raise ValueError(f"cameras must be 1 or 2, got {cameras}")
        if max_pending < 1:
            raise ValueError(f"max_pending must be >= 1, got {max_pending}")
        self.cameras = cameras
        self.max_pending = max_pending
        self.tolerance = tolerance
        self.unpaired = 0
        self._pending: tuple[deque[tuple[int, T]], deque[tuple[int, T]]] = (deque(), deque())

    @property
    def tolerance(self) -> float:
        """Largest stamp difference of a pair in seconds; may change between items."""
        return self._tolerance_ns * 1e-9

    @tolerance.setter
    def tolerance(self, seconds: float) -> None:
        if not seconds >= 0:
            raise ValueError(f"stereo sync tolerance must be >= 0 seconds, got {seconds}")
        self._tolerance_ns = round(seconds * 1e9)

    def add(self, camera: int, stamp_ns: int, item: T) -> tuple[T, T | None] | None:
        """Add a camera's item; returns (camera-0 item, camera-1 item or None) once a frame is whole."""
        if self.cameras == 1:
            return item, None
        mine, others = self._pending[camera], self._pending[1 - camera]
        best, best_gap = -1, self._tolerance_ns
        for k, (stamp, _) in enumerate(others):
            gap = abs(stamp - stamp_ns)
            if gap <= best_gap and (best < 0 or gap < best_gap):
                best, best_gap = k, gap
        if best < 0:
            mine.append((stamp_ns, item))
            if len(mine) > self.max_pending:  # the partner never came
                mine.popleft()
                self.unpaired += 1
            return None
        # what arrived before the pair's members is older than both: its partner can no longer come
        self.unpaired += best + len(mine)
        for _ in range(best):
            others.popleft()
        other = others.popleft()[1]
        mine.clear()
        return (item, other) if camera == 0 else (other, item)

    def flush(self) -> int:
        """Drop every waiting item (counted in :attr:`unpaired`); returns how many were dropped."""
        dropped = sum(len(p) for p in self._pending)
        for p in self._pending:
            p.clear()
        self.unpaired += dropped
        return dropped
