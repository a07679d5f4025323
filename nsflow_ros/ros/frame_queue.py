"""The frames waiting for the tracker: a bounded queue where a new frame supersedes the oldest waiting one.

Keeping at most ``size`` waiting frames bounds the latency of what is tracked when the tracker falls behind.
"""

from __future__ import annotations

import threading
from collections import deque
from dataclasses import dataclass
from typing import Any, Generic, TypeVar

import numpy as np

from nsflow_ros.ros.errors import ParameterError

__all__ = ["LatestFrames", "QueuedFrame"]

T = TypeVar("T")


@dataclass
class QueuedFrame:
    """A decoded frame (a mono image or a stereo pair) waiting for the tracker's worker."""

    header: Any
    image0: np.ndarray
    image1: np.ndarray | None
    t_recv: float  # perf_counter when its (first) image arrived
    t_queued: float = 0.0  # perf_counter when it joined the queue (decoded and paired)
    masks: tuple[np.ndarray | None, ...] = ()  # this frame's masks per camera, once the worker took them


class LatestFrames(Generic[T]):
    """At most ``size`` waiting frames, oldest first; a frame put into a full queue supersedes the oldest.

    Args:
        size: frames waiting at most (>= 1).

    Raises:
        ParameterError: ``size`` < 1.
    """

    def __init__(self, size: int) -> None:
        if size < 1:
            raise ParameterError(f"queue_size must be >= 1, got {size}")
        self.size = size
        self.superseded = 0
        """Frames given up for a newer one since the start."""
        self._items: deque[T] = deque()
        self._wake = threading.Condition()
        self._closed = False

    def __len__(self) -> int:
        with self._wake:
            return len(self._items)

    def put(self, item: T) -> int:
        """Queue a frame; returns how many waiting frames it superseded (0 or 1; 0 after :meth:`close`)."""
        with self._wake:
            if self._closed:
                return 0
            dropped = 0
            while len(self._items) >= self.size:  # the tracker is behind: the oldest frame is stale
                self._items.popleft()
                dropped += 1
            self.superseded += dropped
            self._items.append(item)
            self._wake.notify()
            return dropped

    def take(self, timeout: float | None = None) -> T | None:
        """The oldest waiting frame, waiting for one; None once closed (or after ``timeout`` seconds)."""
        with self._wake:
            if not self._wake.wait_for(lambda: self._items or self._closed, timeout) or self._closed:
                return None
            return self._items.popleft()

    def close(self) -> int:
        """Stop: wake the waiting :meth:`take`, refuse further frames; returns the frames left waiting."""
        with self._wake:
            left = 0 if self._closed else len(self._items)
            self._closed = True
            self._items.clear()
            self._wake.notify_all()
            return left
