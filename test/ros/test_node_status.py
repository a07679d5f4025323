"""The node's status formatting and bookkeeping, without a node: stamp gaps, lines and the summary."""

from __future__ import annotations

from nsflow_ros.ros.counters import NodeCounters
from nsflow_ros.ros.node_status import (
    ArrivalStamps,
    StampGaps,
    StatusWindow,
    covariance_line,
    period_line,
    status_level,
    summary_line,
)


def test_arrival_stamps_count_frames_no_camera_delivered_and_check_the_stereo_tolerance():
    arrivals = ArrivalStamps(2)
    for k in (0, 1, 2, 3, 4, 5, 8):  # frames 6 and 7 lost on both cameras
        for cam in (0, 1):
            missing = arrivals.add(cam, 0.05 * k)
    assert missing == 2 and abs(arrivals.period() - 0.05) < 1e-9
    assert arrivals.tolerance_problem(0.003) is None
    assert "expected less than half the frame period" in arrivals.tolerance_problem(0.03)
    assert ArrivalStamps(1).tolerance_problem(1.0) is None  # mono: nothing to pair


def test_a_period_with_refusals_and_nothing_tracked_is_an_error_named_by_cause():
    stats = NodeCounters()
    window = StatusWindow()
    stats.add("images_received", 3)
    stats.count("undecodable", 3, "truncated:png")
    level, message = status_level(window.take(stats), ["/cam0"])
    assert (int.from_bytes(level, "little") if isinstance(level, bytes) else level) == 2
    assert message == "nothing tracked: refused 3 images undecodable"


def test_period_line_and_summary_line_say_every_count():
    window = {"seconds": 5.0, "images_received": 10, "frames_received": 10, "frames_processed": 9,
              "frames_dropped": 1, "latency_p50": None}
    assert period_line("tracking [OK]", window) == (
        "tracking [OK] (last 5.0 s: 10 images, 10 frames received, 9 processed, 1 dropped)")
    c = {**NodeCounters().totals(), "images_received": 0}
    assert summary_line(c, masks=False) == "no images received"


def test_frames_lost_before_the_node_are_inferred_from_stamp_gaps():
    gaps = StampGaps()
    stamps = [0.05 * k for k in range(10)] + [0.05 * k for k in (12, 13, 17, 18)]  # 2, then 3 frames lost
    assert [gaps.add(t) for t in stamps] == [0] * 10 + [2, 0, 3, 0]
    assert gaps.add(0.1) == 0  # time going back is not a gap


def test_covariance_line_names_the_calibration_and_its_tail_where_there_is_one():
    from types import SimpleNamespace

    from nsflow_ros.core.covariance import CovarianceScale

    def line(scale: CovarianceScale) -> str:
        tracker = SimpleNamespace(settings=SimpleNamespace(max_sigma=0.0), method=SimpleNamespace(
            covariance_scale=scale))
        return covariance_line(tracker)

    plain = line(CovarianceScale(19.78, "registry", 1.5e-3))
    assert plain == "covariance scale 19.78, floor 0.0015 px^2 (registry), max_sigma 0 px (0 = off)"
    tail = line(CovarianceScale(6.48, "m.covariance.json", 5.8e-4, knee=0.15, power=0.434))
    assert "tail power 0.434 above 0.15 px (m.covariance.json)" in tail
