"""The node's frame queue: the tracker gets the newest frames, and what it gives up is counted."""

from __future__ import annotations

import threading

import pytest

from nsflow_ros.ros.errors import ParameterError
from nsflow_ros.ros.frame_queue import LatestFrames


def test_a_queue_of_one_hands_over_the_newest_frame_and_counts_the_superseded():
    q: LatestFrames[int] = LatestFrames(1)
    assert [q.put(k) for k in range(5)] == [0, 1, 1, 1, 1]
    assert q.superseded == 4 and len(q) == 1
    assert q.take() == 4  # the newest, not the oldest
    assert q.take(timeout=0.01) is None and q.superseded == 4


def test_a_longer_queue_keeps_the_newest_in_order():
    q: LatestFrames[str] = LatestFrames(3)
    for item in "abcde":
        q.put(item)
    assert q.superseded == 2
    assert [q.take(), q.take(), q.take()] == ["c", "d", "e"]


def test_close_wakes_the_worker_and_reports_what_was_left():
    q: LatestFrames[int] = LatestFrames(2)
    got: list[int | None] = []
    worker = threading.Thread(target=lambda: got.append(q.take()))
    worker.start()
    assert q.close() == 0
    worker.join(2.0)
    assert not worker.is_alive() and got == [None]
    q2: LatestFrames[int] = LatestFrames(2)
    q2.put(1)
    q2.put(2)
    assert q2.close() == 2 and q2.close() == 0  # counted once
    assert q2.put(3) == 0 and len(q2) == 0 and q2.take() is None  # closed: refused, not counted


def test_a_waiting_worker_gets_a_frame_put_later():
    q: LatestFrames[int] = LatestFrames(1)
    got: list[int | None] = []
    worker = threading.Thread(target=lambda: got.append(q.take(timeout=5.0)))
    worker.start()
    q.put(7)
    worker.join(5.0)
    assert got == [7]


def test_size_below_one_is_refused():
    with pytest.raises(ParameterError, match="queue_size must be >= 1, got 0"):
        LatestFrames(0)
