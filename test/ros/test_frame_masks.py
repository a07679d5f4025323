"""Per-frame masks waiting for their frames: matched by stamp, never blocking, every loss counted."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from nsflow_ros.ros.frame_masks import FrameMasks

MS = 1_000_000


def _mask(value: int) -> np.ndarray:
    return np.full((2, 3), value, np.uint8)


def test_a_mask_that_came_first_waits_for_its_frame_within_the_tolerance():
    b = FrameMasks(0.003)
    assert b.add(100 * MS, _mask(1)) and b.add(150 * MS, _mask(2))
    got = b.take(102 * MS)  # 2 ms off: its mask
    assert got is not None and got[0, 0] == 1
    assert b.take(140 * MS) is None and b.missing == 1  # 10 ms off: none; the frame goes on without
    assert b.take(150 * MS)[0, 0] == 2
    assert (b.missing, b.late, b.unused, len(b)) == (1, 0, 0, 0)


def test_a_mask_after_its_frame_is_late_and_masks_of_skipped_frames_unused():
    b = FrameMasks(0.003)
    assert b.take(100 * MS) is None  # tracked before its mask came
    assert not b.add(100 * MS, _mask(1)) and b.late == 1
    assert not b.add(90 * MS, _mask(1)) and b.late == 2  # a later frame was tracked already
    b.add(150 * MS, _mask(1))  # its frame is superseded and never tracked ...
    b.add(200 * MS, _mask(2))
    assert b.take(200 * MS)[0, 0] == 2
    assert b.unused == 1 and len(b) == 0  # ... so its mask is dropped when a later frame is taken


def test_the_buffer_is_small_and_counts_what_it_drops():
    b = FrameMasks(0.0, max_waiting=2)
    for k in range(4):
        b.add((k + 1) * 10 * MS, _mask(k))
    assert len(b) == 2 and b.unused == 2
    assert b.take(40 * MS)[0, 0] == 3 and b.unused == 3  # the one at 30 ms is older than the frame
    with pytest.raises(ValueError, match="tolerance must be >= 0"):
        FrameMasks(-1.0)
    with pytest.raises(ValueError, match="max_waiting"):
        FrameMasks(0.0, max_waiting=0)


def test_take_waits_at_most_as_told_and_wakes_when_the_mask_comes():
    b = FrameMasks(0.003)
    t0 = time.monotonic()
    assert b.take(100 * MS, wait=0.05) is None
    assert 0.04 <= time.monotonic() - t0 < 1.0 and b.missing == 1
    assert b.silent and b.silences == 1
    b.add(150 * MS, _mask(0))  # a mask again: the topic is back, frames wait for theirs again
    assert not b.silent
    timer = threading.Timer(0.05, lambda: b.add(200 * MS, _mask(7)))
    timer.start()
    t0 = time.monotonic()
    got = b.take(200 * MS, wait=5.0)
    assert got is not None and got[0, 0] == 7 and time.monotonic() - t0 < 2.0
    timer.join()
    closer = threading.Timer(0.05, b.close)
    closer.start()
    t0 = time.monotonic()
    assert b.take(300 * MS, wait=5.0) is None and time.monotonic() - t0 < 2.0  # a stop ends the wait
    closer.join()


def test_a_silent_topic_costs_one_wait_until_a_mask_comes_again():
    b = FrameMasks(0.003)
    t0 = time.monotonic()
    assert b.take(100 * MS, wait=0.05) is None and b.silent
    for k in range(1, 20):  # the publisher stopped: no frame waits any more
        assert b.take((100 + 50 * k) * MS, wait=0.05) is None
    assert time.monotonic() - t0 < 0.05 + 0.5 and b.missing == 20 and b.silences == 1
    b.add(2000 * MS, _mask(3))
    assert not b.silent and b.take(2000 * MS, wait=0.05)[0, 0] == 3


def test_a_newer_frame_ends_the_wait():
    b = FrameMasks(0.003)
    newer = threading.Event()
    timer = threading.Timer(0.05, lambda: (newer.set(), b.wake()))
    timer.start()
    t0 = time.monotonic()
    assert b.take(100 * MS, wait=5.0, until=newer.is_set) is None
    assert time.monotonic() - t0 < 2.0 and b.missing == 1
    timer.join()


def test_every_mask_ends_used_late_unused_or_left_at_the_stop():
    b = FrameMasks(0.003, max_waiting=2)
    received = 0
    for stamp in (100, 150, 200, 250):  # 100 and 150 are pushed out: unused
        b.add(stamp * MS, _mask(0))
        received += 1
    assert b.take(200 * MS) is not None  # used
    b.add(190 * MS, _mask(0))  # its frame is gone: late
    b.add(300 * MS, _mask(0))  # never taken: left at the stop, with the one at 250
    received += 2
    b.close()
    b.add(350 * MS, _mask(0))  # after the stop
    received += 1
    assert (b.used, b.late, b.unused, b.left_at_stop) == (1, 1, 2, 3)
    assert b.used + b.late + b.unused + b.left_at_stop == received
