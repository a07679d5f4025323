"""Thread settings of a tracker process (a process-wide choice, made by the entry points, never on import).

OpenCV's pool of all the cores costs CPU time for little wall time on a machine the tracker shares with
the estimator (its workers wake for every call and spin before they sleep), so the tracker's node,
``nsflow-replay`` and ``nsflow-bench`` set OpenCV's threads from the ``opencv_threads`` setting.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

import cv2

from nsflow_ros.errors import NSFlowError

__all__ = ["opencv_threads", "set_opencv_threads"]


def set_opencv_threads(threads: int) -> int:
    """Set OpenCV's threads for the whole process: >= 1 that many (1: every call on the calling thread),
    0 OpenCV's default pool; returns the thread count before the call.

    Raises:
        NSFlowError: ``threads`` negative.
    """
    if threads < 0:
        raise NSFlowError(f"opencv_threads must be >= 0 (0 = OpenCV's default), got {threads}")
    before = cv2.getNumThreads()
    cv2.setNumThreads(threads if threads > 0 else -1)  # -1 restores OpenCV's default pool
    return before


@contextmanager
def opencv_threads(threads: int | None) -> Iterator[int]:
    """Run the block with OpenCV's threads set as :func:`set_opencv_threads` does (None: left alone), then
    restore them; yields OpenCV's thread count inside the block.

    Raises:
        NSFlowError: ``threads`` negative.
    """
    before = cv2.getNumThreads() if threads is None else set_opencv_threads(threads)
    try:
        yield cv2.getNumThreads()
    finally:
        cv2.setNumThreads(before)
