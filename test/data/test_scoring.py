"""The two ground-truth scorers on a hand-computed case: each keeps the definition of its figures."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest

from nsflow_ros.data.scoring import FrameQuality, TrackStats


class FakeSample:
    """Ground truth by hand: flow (1, 0.5) px between frames, (-10, 0) px left to right; u > 100 is hidden."""

    stamps_ns = np.array([10, 20, 30], dtype=np.int64)

    def flow(self, i: int, j: int, pixels: np.ndarray, cam: int = 0, cam_j: int | None = None
             ) -> tuple[np.ndarray, np.ndarray]:
        p = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
        step = np.array([-10.0, 0.0]) if i == j else np.array([1.0, 0.5]) * (j - i)
        return np.broadcast_to(step, p.shape).copy(), p[:, 0] <= 100


def test_track_stats_scores_a_published_stream_by_id_and_stamp():
    stats = TrackStats(FakeSample())
    stats.add_frame(10, {1: np.array([10.0, 10.0]), 2: np.array([20.0, 20.0])})
    stats.add_frame(20, {1: np.array([11.2, 10.5]), 3: np.array([5.0, 5.0])})
    stats.add_frame(30, {1: np.array([13.5, 11.0]), 3: np.array([6.0, 5.5]), 4: np.array([0.0, 0.0])})
    stats.add_frame(99, {1: np.array([14.0, 12.0])})  # not a sample frame: counted, no error
    assert stats.errors == pytest.approx([0.2, 1.3, 0.0])
    f = stats.figures()
    assert f["frames"] == 4
    assert f["features_per_frame"] == pytest.approx(8 / 4)
    assert f["tracked_share"] == pytest.approx(4 / 6)  # ratio of sums over the frames after the first
    assert f["mean_track_length"] == pytest.approx((4 + 1 + 2 + 1) / 4)
    assert f["tracks_10_frames"] == 0
    assert f["error_median_px"] == pytest.approx(0.2)
    assert f["error_within_1px"] == pytest.approx(2 / 3)
    assert f["error_count"] == 3


def test_track_stats_without_a_sample_measures_no_error():
    stats = TrackStats()
    stats.add_frame(10, {1: np.array([1.0, 1.0])})
    stats.add_frame(20, {1: np.array([2.0, 1.0])})
    f = stats.figures()
    assert f["tracked_share"] == 1.0
    assert f["error_median_px"] is None and f["error_within_1px"] is None and f["error_count"] == 0


@dataclass
class Cam:
    ids: np.ndarray
    pixels: np.ndarray
    previous: np.ndarray

    def __len__(self) -> int:
        return len(self.ids)


@dataclass
class Frame:
    cameras: list[Cam]


def _cam(ids: list[int], pixels: list[list[float]], previous: list[list[float]] | None = None) -> Cam:
    px = np.array(pixels, dtype=np.float64).reshape(-1, 2)
    prev = px if previous is None else np.array(previous, dtype=np.float64).reshape(-1, 2)
    return Cam(np.array(ids, dtype=np.int64), px, prev)


def test_frame_quality_scores_tracker_frames_by_their_previous_positions():
    q = FrameQuality()
    nan = float("nan")
    f1 = Frame([
        _cam([1, 2, 3], [[11.0, 10.5], [22.5, 20.5], [300.0, 0.0]], [[10.0, 10.0], [20.0, 20.0], [nan, nan]]),
        _cam([1, 3], [[1.0, 10.5], [290.0, 0.0]]),
    ])
    q.add_frame(FakeSample(), 1, f1, had=4, stereo=True)
    f2 = Frame([_cam([1], [[12.25, 11.0]], [[11.0, 10.5]]), _cam([], [])])
    q.add_frame(FakeSample(), 2, f2, had=3, stereo=True)
    f = q.figures()
    assert f["carried_share"] == pytest.approx((2 / 4 + 1 / 3) / 2)  # mean of per-frame ratios
    assert f["error_median_px"] == pytest.approx(0.25)
    assert f["error_over_1px_share"] == pytest.approx(1 / 3)
    assert f["stereo_matched_share"] == pytest.approx((2 / 3 + 0) / 2)
    assert f["stereo_error_median_px"] == 0.0  # the hidden right-image point is left out
    assert f["stereo_error_over_1px_share"] == 0.0


def test_frame_quality_mono_has_no_stereo_figures_and_empty_is_nan():
    q = FrameQuality()
    f = q.figures()
    assert np.isnan(f["carried_share"]) and np.isnan(f["error_median_px"])
    assert "stereo_matched_share" not in f
