"""Thread settings of a tracker process: OpenCV's pool set and restored."""

from __future__ import annotations

import cv2
import pytest

from nsflow_ros.errors import NSFlowError
from nsflow_ros.threads import opencv_threads, set_opencv_threads


def test_opencv_threads_are_set_inside_and_restored_after():
    before = cv2.getNumThreads()
    with opencv_threads(1) as n:
        assert n == 1 == cv2.getNumThreads()
    assert cv2.getNumThreads() == before
    with opencv_threads(None) as n:
        assert n == before


def test_zero_is_opencvs_default_pool_and_negative_is_refused():
    before = cv2.getNumThreads()
    try:
        cv2.setNumThreads(-1)
        default = cv2.getNumThreads()
        cv2.setNumThreads(1)
        assert set_opencv_threads(0) == 1 and cv2.getNumThreads() == default
    finally:
        cv2.setNumThreads(before)
    with pytest.raises(NSFlowError, match="opencv_threads must be >= 0"):
        set_opencv_threads(-2)
