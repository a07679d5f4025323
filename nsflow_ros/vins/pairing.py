"""Stereo pairing by exact stamp, as VINS-Fusion pairs its image topics: one pairer for node and feature bag.

Images of the two cameras arrive one at a time; an image waits until the other camera's image of the same
stamp arrives, then the pair is a frame. An image whose partner never comes is dropped and counted once,
when more than ``max_pending`` images of its camera wait, or at :meth:`StereoPairer.flush`.
"""

from __future__ import annotations

from typing import Generic, TypeVar

__all__ = ["MAX_PENDING", "StereoPairer"]

T = TypeVar("T")

MAX_PENDING = 10
"""Unpaired images kept per camera before the oldest is dropped."""


class StereoPairer(Generic[T]):
    """Pairs camera-0 and camera-1 items (decoded images, records) of the same stamp.

    Args:
        cameras: 1 (every item is a frame at once) or 2.
        max_pending: unpaired items kept per camera.

    Attributes:
        unpaired: items dropped because their partner never came.
    """

    def __init__(self, cameras: int, max_pending: int = MAX_PENDING) -> None:
        if cameras not in (1, 2):
            raise ValueError(f"cameras must be 1 or 2, got {cameras}")
        self.cameras = cameras
        self.max_pending = max_pending
        self.unpaired = 0
        self._pending: tuple[dict[int, T], dict[int, T]] = ({}, {})

    def add(self, camera: int, stamp_ns: int, item: T) -> tuple[T, T | None] | None:
        """Add one camera's item.

        Args:
            camera: 0 or 1.
            stamp_ns: the image's stamp in nanoseconds (pairs match exactly).
            item: what to pair.

        Returns:
            ``(camera-0 item, camera-1 item or None for mono)`` when a frame is complete, else None.
        """
        if self.cameras == 1:
            return item, None
        other = self._pending[1 - camera].pop(stamp_ns, None)
        if other is None:
            pending = self._pending[camera]
            pending[stamp_ns] = item
            while len(pending) > self.max_pending:  # the partner never came
                pending.pop(min(pending))
                self.unpaired += 1
            return None
        return (item, other) if camera == 0 else (other, item)

    def flush(self) -> int:
        """Drop every waiting item (counted in :attr:`unpaired`); returns how many were dropped."""
        dropped = sum(len(p) for p in self._pending)
        for p in self._pending:
            p.clear()
        self.unpaired += dropped
        return dropped
