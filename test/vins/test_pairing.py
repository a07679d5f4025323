"""Stereo pairing within a stamp tolerance: nearest partner, either arrival order, stale images dropped."""

from __future__ import annotations

import pytest

from nsflow_ros.vins.pairing import MAX_PENDING, STEREO_SYNC_TOLERANCE, StereoPairer

MS = 1_000_000
PERIOD = 50 * MS  # a 20 Hz camera


def test_mono_passes_every_item_through():
    p: StereoPairer[str] = StereoPairer(1)
    assert p.add(0, 5, "a") == ("a", None) and p.unpaired == 0


def test_default_tolerance_is_vins_fusions_3_ms():
    assert STEREO_SYNC_TOLERANCE == 0.003 and StereoPairer(2).tolerance == pytest.approx(0.003)


@pytest.mark.parametrize("left_first", [True, False])
@pytest.mark.parametrize("jitter_ms", [0.0, 1.0, -2.0, 3.0, -3.0])
def test_pairs_within_the_tolerance_in_either_arrival_order(left_first, jitter_ms):
    p: StereoPairer[str] = StereoPairer(2)
    for k in range(5):
        t = k * PERIOD
        r = t + round(jitter_ms * MS)
        first = p.add(0, t, f"L{k}") if left_first else p.add(1, r, f"R{k}")
        assert first is None
        pair = p.add(1, r, f"R{k}") if left_first else p.add(0, t, f"L{k}")
        assert pair == (f"L{k}", f"R{k}")  # camera 0 first whatever came first
    assert p.unpaired == 0


def test_beyond_the_tolerance_nothing_pairs_and_every_image_is_counted():
    p: StereoPairer[str] = StereoPairer(2, tolerance=0.003)
    for k in range(30):
        t = k * PERIOD
        assert p.add(0, t, f"L{k}") is None
        assert p.add(1, t + 5 * MS, f"R{k}") is None
    assert p.unpaired == 60 - 2 * MAX_PENDING
    assert p.flush() == 2 * MAX_PENDING and p.unpaired == 60


def test_zero_tolerance_pairs_equal_stamps_only():
    p: StereoPairer[str] = StereoPairer(2, tolerance=0.0)
    assert p.add(0, 100, "L") is None and p.add(1, 101, "R") is None
    assert p.add(1, 100, "R2") == ("L", "R2")


def test_the_nearest_waiting_partner_wins():
    p: StereoPairer[str] = StereoPairer(2, tolerance=0.004)
    # two right images close to the left one (a fast right camera): the nearer one pairs
    assert p.add(1, 1000 * MS - 3 * MS, "far") is None
    assert p.add(1, 1000 * MS + 1 * MS, "near") is None
    assert p.add(0, 1000 * MS, "L") == ("L", "near")
    assert p.unpaired == 1  # "far" arrived before the pair's member: its partner can no longer come


def test_stale_images_are_dropped_when_a_later_pair_forms():
    p: StereoPairer[str] = StereoPairer(2)
    for k in range(3):
        assert p.add(0, k * PERIOD, f"L{k}") is None  # the right camera lags three frames
    assert p.add(1, 2 * PERIOD, "R2") == ("L2", "R2")  # R0 and R1 were lost
    assert p.unpaired == 2
    assert p.add(1, 3 * PERIOD, "R3") is None  # now the left one lags
    assert p.add(0, 3 * PERIOD + MS, "L3") == ("L3", "R3") and p.unpaired == 2
    assert p.flush() == 0


def test_memory_is_bounded_when_one_camera_stops():
    p: StereoPairer[int] = StereoPairer(2, max_pending=4)
    for k in range(1000):
        assert p.add(0, k * PERIOD, k) is None
    assert len(p._pending[0]) == 4 and p.unpaired == 996
    # the right camera comes back: the waiting left image of its stamp pairs, older ones are counted
    assert p.add(1, 998 * PERIOD, -1) == (998, -1)
    assert p.unpaired == 998 and len(p._pending[0]) == 1


def test_time_going_back_does_not_strand_images():
    p: StereoPairer[str] = StereoPairer(2)
    assert p.add(0, 10_000 * MS, "L_late") is None  # its partner is lost, then the stream restarts
    assert p.add(0, 0, "L0") is None and p.add(1, 0, "R0") == ("L0", "R0")
    assert p.unpaired == 1 and p.flush() == 0


def test_tolerance_can_change_and_is_checked():
    p: StereoPairer[str] = StereoPairer(2, tolerance=0.001)
    assert p.add(0, 0, "L") is None and p.add(1, 2 * MS, "R") is None
    p.tolerance = 0.0025
    assert p.add(1, 2 * MS, "R'") == ("L", "R'")
    with pytest.raises(ValueError, match="tolerance"):
        p.tolerance = -0.001
    with pytest.raises(ValueError, match="cameras"):
        StereoPairer(3)
    with pytest.raises(ValueError, match="max_pending"):
        StereoPairer(2, max_pending=0)
