"""The tracking state from what reaches the estimator: thresholds, hysteresis, causes, start-up masks."""

from __future__ import annotations

import numpy as np
import pytest

from nsflow_ros.vins.errors import ConfigError
from nsflow_ros.vins.health import (
    HealthMonitor,
    State,
    Thresholds,
    check_static_masks,
    is_uniform,
    usable_share,
)

RNG = np.random.default_rng(0)
TEXTURE = RNG.integers(0, 256, (240, 320), dtype=np.uint8)


def _frames(monitor: HealthMonitor, n: int, features: int, carried: int, *, image=TEXTURE, usable=None,
            start: int = 0) -> int:
    """Publish ``n`` frames of ``features`` ids, each carrying ``carried`` of the previous frame's."""
    next_id = start
    ids = np.arange(next_id, next_id + features)
    next_id += features
    for _ in range(n):
        monitor.add_frame(ids, image=image, usable=usable)
        fresh = np.arange(next_id, next_id + features - carried)
        next_id += features - carried
        ids = np.concatenate([ids[:carried], fresh])
    return next_id


def test_a_camera_tracked_well_is_ok():
    m = HealthMonitor()
    _frames(m, 20, 150, 135)
    r = m.assess(max_cnt=150)
    assert (r.state, r.cause, r.text) == (State.OK, "", "OK")
    assert r.features == 150 and r.carried == pytest.approx(0.9)


@pytest.mark.parametrize("value", [0, 255])
def test_uniform_images_are_lost_and_named(value):
    m = HealthMonitor()
    _frames(m, 10, 0, 0, image=np.full((240, 320), value, np.uint8))
    r = m.assess(max_cnt=150)
    assert r.state is State.LOST and r.cause.startswith("images uniform (10 of 10 frames")
    assert r.text.startswith("LOST: images uniform") and r.text.endswith("; 0 features/frame")
    assert is_uniform(np.full((8, 8, 3), 7, np.uint8)) and not is_uniform(TEXTURE)


def test_a_mask_that_blocks_the_image_is_named_with_its_share():
    m = HealthMonitor()
    _frames(m, 10, 0, 0, usable=0.0)
    r = m.assess(max_cnt=150)
    assert r.state is State.LOST and r.cause == "masks leave 0 % of the image usable"
    assert m.run_report(max_cnt=150).cause == "masks leave 0 % of the image usable"  # the run's too


def test_every_feature_gated_by_max_sigma_is_lost_though_150_features_are_published():
    m = HealthMonitor()
    _frames(m, 20, 150, 0)  # new corners every frame: none carries on
    r = m.assess(max_cnt=150, gated=20 * 150)
    assert r.state is State.LOST and r.carried == 0.0 and r.features == 150
    assert r.cause == "every tracked feature gated by max_sigma (150 per frame)"


def test_max_sigma_that_leaves_9_of_150_carried_is_lost():
    m = HealthMonitor()
    _frames(m, 20, 150, 9)
    r = m.assess(max_cnt=150, gated=20 * 141)
    assert r.state is State.LOST and r.cause == "max_sigma gated 141 tracked features per frame"
    assert "6 % of ids carried" in r.text


def test_few_features_are_degraded_and_recovery_needs_a_margin():
    m = HealthMonitor()
    _frames(m, 10, 40, 36)  # 40 of 150 = 0.27 < 0.3
    r = m.assess(max_cnt=150)
    assert r.state is State.DEGRADED and r.cause.startswith("few corners detected")
    _frames(m, 10, 50, 45, start=10_000)  # 0.33: above the threshold, not by 20 %
    assert m.assess(max_cnt=150).state is State.DEGRADED
    _frames(m, 10, 60, 54, start=20_000)  # 0.4 > 0.36
    r = m.assess(max_cnt=150)
    assert r.state is State.OK and r.recovered and r.text == "OK: recovered from DEGRADED"
    _frames(m, 10, 10, 9, start=30_000)  # worse at once
    assert m.assess(max_cnt=150).state is State.LOST
    assert m.periods == {"OK": 1, "DEGRADED": 2, "LOST": 1, "IDLE": 0}


def test_tracks_that_do_not_carry_over_without_a_gate_are_named_so():
    m = HealthMonitor()
    _frames(m, 10, 150, 45)  # 30 % carried
    r = m.assess(max_cnt=150)
    assert r.state is State.DEGRADED and r.cause.startswith("tracks do not carry over")


def test_no_images_is_idle_and_frames_all_held_back_keep_the_state():
    m = HealthMonitor()
    _frames(m, 5, 0, 0, image=None)
    assert m.assess(max_cnt=150).state is State.LOST
    assert m.assess(max_cnt=150, images=4, tracked=2).state is State.LOST  # all throttled: no news
    assert m.assess(max_cnt=150, images=4, tracked=0).cause == "no frame reached the estimator"
    r = m.assess(max_cnt=150, images=0)
    assert r.state is State.IDLE and r.text == "IDLE" and not r.recovered


def test_the_run_report_judges_the_whole_run_without_hysteresis():
    m = HealthMonitor()
    _frames(m, 30, 150, 0)
    m.assess(max_cnt=150)
    r = m.run_report(max_cnt=150, gated=30 * 150)
    assert r.state is State.LOST and r.frames == 30 and r.carried == 0.0
    m = HealthMonitor()
    _frames(m, 30, 150, 140)
    r = m.run_report(max_cnt=150)
    assert r.state is State.OK and r.carried == pytest.approx(0.93)
    assert HealthMonitor().run_report(max_cnt=150).cause == "no frame reached the estimator"


def test_thresholds_are_shares_and_lost_is_at_most_degraded():
    assert Thresholds.from_values({"lost_carried": 0.2, "max_cnt": 5}).lost_carried == 0.2
    with pytest.raises(ConfigError, match=r"lost_features \(0.5\) must be at most degraded_features"):
        Thresholds(lost_features=0.5)
    with pytest.raises(ConfigError, match=r"degraded_carried must be a share in \[0, 1\], got 2"):
        Thresholds(degraded_carried=2)


def test_static_masks_with_little_or_no_usable_pixel_are_warned_about_or_refused():
    small = np.zeros((240, 320), np.uint8)
    small[:40, :100] = 255  # 5.2 %
    assert check_static_masks({"mask0 a.png": np.full((240, 320), 255, np.uint8), "mask1": None}, 0.25) == []
    (warning,) = check_static_masks({"mask0 a.png": small}, 0.25)
    assert warning.startswith("mask0 a.png leaves 5.2 % of the image usable, less than mask_min_usable 0.25")
    with pytest.raises(ConfigError, match=r"mask0 b\.png leaves no usable pixel: nothing can be tracked"):
        check_static_masks({"mask0 b.png": np.zeros((240, 320), np.uint8)}, 0.25)


def test_usable_share_combines_masks_of_different_resolutions():
    full = np.zeros((240, 320), np.uint8)
    full[:, :160] = 255  # the left half
    half = np.zeros((120, 160), np.uint8)
    half[:60] = 255  # the top half, at half resolution
    assert usable_share(full) == pytest.approx(0.5)
    assert usable_share(full, half) == pytest.approx(0.25)
    assert usable_share(None) is None


def test_the_default_thresholds_are_the_settings_tables():
    from nsflow_ros.vins.settings import SETTINGS

    assert Thresholds() == Thresholds.from_values({s.name: s.default for s in SETTINGS})
