"""Per-frame masks of one camera waiting for their frames: a small stamp-keyed buffer that never blocks a
subscriber.

A mask (e.g. moving objects from a segmentation node) arrives on its own topic, before or after its frame.
One that arrives before waits here; the tracker's worker takes the one within the stamp tolerance of its
frame when the frame's turn comes, waiting for it at most as long as it is told (0 = not at all). A frame
whose mask is not there by then is tracked without it (counted as missing), and a mask that arrives after
its frame was tracked is of no use any more (counted as late). Masks whose frame never came to the tracker
(superseded while it was busy) are counted as unused when a later frame is taken, masks still waiting when
the node stops as left at the stop: every mask that reaches the buffer ends used, late, unused or left.

A wait that runs out marks the topic silent: later frames do not wait until a mask comes again, so a mask
publisher that stopped costs the tracker no time.
"""

from __future__ import annotations

import threading
import time
from collections import deque
from collections.abc import Callable

import numpy as np

__all__ = ["MAX_WAITING_MASKS", "FrameMasks"]

MAX_WAITING_MASKS = 10
"""Masks kept waiting for their frames at most; the oldest goes (counted as unused) when one more comes."""


class FrameMasks:
    """The waiting masks of one camera, matched to frames by stamp.

    Args:
        tolerance: largest stamp difference in seconds between a frame and its mask (0 = equal stamps).
        max_waiting: masks kept at most.

    Attributes:
        used: masks taken by their frame.
        missing: frames tracked without their mask (it had not come in time).
        late: masks that came after their frame (or a later one) was tracked.
        unused: masks dropped without a frame: it never reached the tracker, or too many were waiting.
        left_at_stop: masks still waiting for their frame when the buffer was closed.
        silent: a wait ran out and no mask came since: frames do not wait for this topic.
        silences: how many times the topic went silent.

    Raises:
        ValueError: a negative tolerance or max_waiting < 1.
    """

    def __init__(self, tolerance: float, max_waiting: int = MAX_WAITING_MASKS) -> None:
        if max_waiting < 1:
            raise ValueError(f"max_waiting must be >= 1, got {max_waiting}")
        self.max_waiting = max_waiting
        self.tolerance = tolerance
        self.used = 0
        self.missing = 0
        self.late = 0
        self.unused = 0
        self.left_at_stop = 0
        self.silent = False
        self.silences = 0
        self._waiting: deque[tuple[int, np.ndarray]] = deque()  # (stamp ns, mask), in arrival order
        self._taken_ns: int | None = None  # the stamp of the last frame taken
        self._wake = threading.Condition()
        self._closed = False

    @property
    def tolerance(self) -> float:
        """Largest stamp difference of a frame and its mask in seconds; may change at run time."""
        return self._tolerance_ns * 1e-9

    @tolerance.setter
    def tolerance(self, seconds: float) -> None:
        if not seconds >= 0:
            raise ValueError(f"mask stamp tolerance must be >= 0 seconds, got {seconds}")
        self._tolerance_ns = round(seconds * 1e9)

    def __len__(self) -> int:
        with self._wake:
            return len(self._waiting)

    def add(self, stamp_ns: int, mask: np.ndarray) -> bool:
        """Keep a mask for its frame; returns False (and counts it) when it comes too late to be used.

        Any mask, late or not, ends a silence: the publisher is there again."""
        with self._wake:
            self.silent = False
            if self._closed:  # the node stopped: nothing will take it
                self.left_at_stop += 1
                return False
            if self._taken_ns is not None and stamp_ns <= self._taken_ns + self._tolerance_ns:
                self.late += 1
                return False
            self._waiting.append((stamp_ns, mask))
            if len(self._waiting) > self.max_waiting:
                self._waiting.popleft()
                self.unused += 1
            self._wake.notify_all()
            return True

    def take(
        self, stamp_ns: int, wait: float = 0.0, until: Callable[[], bool] | None = None
    ) -> np.ndarray | None:
        """The mask of the frame stamped ``stamp_ns``, waiting for it up to ``wait`` seconds; None when it
        has not come (counted as missing). Masks older than the frame are dropped (counted as unused).

        Args:
            until: ends the wait early when true (checked at each :meth:`wake`), e.g. "a newer frame came".

        A wait that ends without the mask (not at the stop) makes the topic :attr:`silent`: later frames take
        what is there without waiting until a mask comes again.
        """
        wait = 0.0 if self.silent else max(wait, 0.0)
        deadline = time.monotonic() + wait
        with self._wake:
            while True:
                found = self._nearest(stamp_ns)
                remaining = deadline - time.monotonic()
                if found is not None or remaining <= 0 or self._closed or (until is not None and until()):
                    break
                self._wake.wait(remaining)
            mask = None
            if found is not None:
                mask = self._waiting[found][1]
                del self._waiting[found]
                self.used += 1
            else:
                self.missing += 1
                if wait > 0 and not self._closed and not self.silent:
                    self.silent = True
                    self.silences += 1
            self._taken_ns = stamp_ns if self._taken_ns is None else max(self._taken_ns, stamp_ns)
            limit = self._taken_ns + self._tolerance_ns
            stale = [k for k, (t, _) in enumerate(self._waiting) if t <= limit]
            for k in reversed(stale):  # their frames are gone: a later one was tracked
                del self._waiting[k]
            self.unused += len(stale)
            return mask

    def wake(self) -> None:
        """Make a waiting :meth:`take` check its ``until`` now (a newer frame came)."""
        with self._wake:
            self._wake.notify_all()

    def _nearest(self, stamp_ns: int) -> int | None:
        best, best_gap = None, self._tolerance_ns
        for k, (t, _) in enumerate(self._waiting):
            gap = abs(t - stamp_ns)
            if gap <= best_gap and (best is None or gap < best_gap):
                best, best_gap = k, gap
        return best

    def close(self) -> None:
        """Wake a waiting :meth:`take` (the node stops): it returns at once. The masks still waiting are
        counted as left at the stop."""
        with self._wake:
            if not self._closed:
                self.left_at_stop += len(self._waiting)
                self._waiting.clear()
            self._closed = True
            self._wake.notify_all()
