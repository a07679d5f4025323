"""Downsampled tracking: cameras, images, masks and pixels at both scales, and a tracker on a large camera."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import synthetic_sequences as syn

from nsflow_ros.core.camera import KannalaBrandtCamera, MeiCamera, PinholeCamera
from nsflow_ros.core.downsample import (
    check_downsample,
    downsample_camera,
    downsample_image,
    downsample_mask,
    to_full_resolution,
    to_tracking_resolution,
)
from nsflow_ros.core.errors import CoreError
from nsflow_ros.core.tracker import FeatureTracker, TrackerSettings

CAMERAS = [
    PinholeCamera(width=1280, height=800, fx=640.0, fy=642.0, cx=641.3, cy=398.2, k1=-0.28, k2=0.07,
                  p1=2e-4, p2=-1e-4),
    KannalaBrandtCamera(width=1280, height=800, mu=400.0, mv=401.0, u0=640.2, v0=400.9, k2=-0.01, k3=0.02),
    MeiCamera(width=1280, height=800, xi=0.9, gamma1=800.0, gamma2=801.0, u0=639.0, v0=401.0, k1=-0.1),
]


@pytest.mark.parametrize("camera", CAMERAS, ids=lambda c: c.model_type)
@pytest.mark.parametrize("factor", [2, 4])
def test_a_point_lifts_to_the_same_ray_at_both_resolutions(camera, factor):
    small = downsample_camera(camera, factor)
    assert (small.width, small.height) == (1280 // factor, 800 // factor)
    full = np.random.default_rng(0).uniform([100, 80], [1180, 720], (50, 2))
    px = to_tracking_resolution(full, factor)
    assert np.allclose(small.lift(px), camera.lift(full), atol=1e-12)
    ray = camera.lift_rays(full)
    assert np.allclose(small.project(ray), to_tracking_resolution(camera.project(ray), factor), atol=1e-9)
    assert np.allclose(to_full_resolution(px, factor), full)
    assert downsample_camera(camera, 1) is camera


def test_image_decimation_is_the_block_mean_and_keeps_cv2_resize_pixel_centres():
    rng = np.random.default_rng(1)
    img = rng.integers(0, 256, (80, 120), dtype=np.uint8)
    small = downsample_image(img, 4)
    blocks = img.reshape(20, 4, 30, 4).astype(float).mean(axis=(1, 3))
    assert small.shape == (20, 30) and np.abs(small - blocks).max() <= 0.5 + 1e-9
    color = np.dstack([img] * 3)
    assert downsample_image(color, 2).shape == (40, 60, 3) and downsample_image(img, 1) is img
    # a ramp up-sampled by cv2.resize and decimated comes back in place (cv2.pyrDown's would move by half
    # a pixel): the two conventions agree
    ramp = np.tile(np.arange(120, dtype=np.float32) * 2, (80, 1))
    big = cv2.resize(ramp, (240, 160), interpolation=cv2.INTER_LINEAR)
    assert np.abs(downsample_image(big, 2) - ramp)[:, 1:-1].max() < 1e-4
    assert np.abs(cv2.pyrDown(big) - ramp)[:, 2:-2].max() > 0.4


def test_mask_keeps_a_small_pixel_only_where_all_it_covers_is_usable():
    mask = np.full((8, 12), 255, np.uint8)
    mask[3, 5] = 0  # one masked full-resolution pixel
    small = downsample_mask(mask, 2)
    assert small.shape == (4, 6) and small.dtype == np.uint8
    assert small[1, 2] == 0 and (small == 0).sum() == 1 and set(np.unique(small)) == {0, 255}
    assert downsample_mask(mask, 1) is mask


def test_bad_factors_and_sizes_are_one_clear_error():
    with pytest.raises(CoreError, match="downsample must be one of 1, 2, 4, got 3"):
        check_downsample(3)
    with pytest.raises(CoreError, match="downsample must be one of 1, 2, 4, got True"):
        check_downsample(True)
    with pytest.raises(CoreError, match="downsample must be one of"):
        TrackerSettings(downsample=3)
    odd = PinholeCamera(width=1282, height=800, fx=600.0, fy=600.0, cx=640.0, cy=400.0)
    with pytest.raises(CoreError, match=r"downsample 4 needs camera \(camera\) sizes divisible by 4, got 12"):
        downsample_camera(odd, 4)
    with pytest.raises(CoreError, match="mask must be a 2-D uint8 array"):
        downsample_mask(np.zeros((4, 4), np.float32), 2)


def _large(seq: syn.Sequence) -> tuple[list[np.ndarray], PinholeCamera]:
    """The sequence up-sampled 2x (cv2.resize's pixel centres) and its camera."""
    frames = [cv2.resize(f, (2 * syn.W, 2 * syn.H), interpolation=cv2.INTER_LINEAR) for f in seq.frames]
    cam = syn.camera()
    big = PinholeCamera(width=2 * syn.W, height=2 * syn.H, fx=2 * cam.fx, fy=2 * cam.fy,
                        cx=(cam.cx + 0.5) * 2 - 0.5, cy=(cam.cy + 0.5) * 2 - 0.5)
    return frames, big


def test_tracker_on_a_large_camera_publishes_full_resolution_pixels_that_follow_the_truth():
    seq = syn.translating(8)
    frames, big = _large(seq)
    settings = TrackerSettings(method="classical", min_dist=40, max_cnt=80)
    down = FeatureTracker([big], settings.with_overrides({"downsample": 2}))
    ref = FeatureTracker([syn.camera()], settings.with_overrides({"min_dist": 20}))
    assert (down.cameras[0].width, down.cameras[0].height) == (syn.W, syn.H)
    prev = None
    for k in range(len(frames)):
        out = down.process(float(seq.stamps[k]), frames[k])
        small = ref.process(float(seq.stamps[k]), seq.frames[k])
        c, r = out.cameras[0], small.cameras[0]
        assert out.image_size == (2 * syn.W, 2 * syn.H) and len(c) > 40
        # about the features of the tracker at the small size (min_dist scaled: the same layout; each
        # tracker detects and loses its own, 74-85 % within 4.5 px per frame) ...
        near = np.hypot(*(c.pixels[:, None] - to_full_resolution(r.pixels, 2)[None]).transpose(2, 0, 1))
        assert abs(len(c) - len(r)) <= 0.15 * len(r) and np.mean(near.min(axis=1) < 4.5) > 0.7
        # ... published in the full-resolution calibration
        assert np.allclose(c.undistorted, big.lift(c.pixels), atol=1e-12)
        if prev is not None:
            old = np.isfinite(c.previous[:, 0])
            truth = to_full_resolution(seq.truth(k - 1, k, to_tracking_resolution(c.previous[old], 2)), 2)
            assert np.median(np.hypot(*(c.pixels[old] - truth).T)) < 0.3
            rows = {int(i): n for n, i in enumerate(prev.ids)}
            keep = [n for n in np.flatnonzero(old)]
            before = prev.undistorted[[rows[int(i)] for i in c.ids[keep]]]
            assert np.allclose(c.velocities[keep], (c.undistorted[keep] - before) / 0.05)
        prev = c
    with pytest.raises(CoreError, match="image0 is 320x240 but camera 0"):
        down.process(10.0, seq.frames[0])


def test_the_full_resolution_mask_follows_the_downsample():
    seq = syn.translating(2)
    frames, big = _large(seq)
    mask = np.full((big.height, big.width), 255, np.uint8)
    mask[:, : big.width // 2] = 0  # the left half is the robot's body
    t = FeatureTracker([big], TrackerSettings(method="classical", min_dist=40, downsample=2), mask=mask)
    assert t.mask.shape == (syn.H, syn.W)
    out = t.process(0.0, frames[0]).cameras[0]
    assert len(out) > 10 and out.pixels[:, 0].min() >= big.width // 2 - 1


def test_covariances_and_max_sigma_are_in_full_resolution_pixels():
    seq = syn.translating(3)
    frames, big = _large(seq)
    settings = TrackerSettings(method="classical", min_dist=40, downsample=2, publish_covariance=True)
    same = FeatureTracker([big], settings)
    widest = 0.0  # the largest sigma of a tracked point over the run (full-resolution px)
    for k in range(3):
        a = same.process(float(seq.stamps[k]), frames[k]).cameras[0]
        old = np.isfinite(a.previous[:, 0])
        widest = max(widest, float(np.sqrt(a.covariance[old, 0].max(initial=0.0))))
    assert a.covariance is not None and a.covariance.shape == (len(a), 3)
    tracked = np.isfinite(a.previous[:, 0])
    # a 2x2 px^2 block per point, positive definite
    det = a.covariance[:, 0] * a.covariance[:, 2] - a.covariance[:, 1] ** 2
    assert np.all(a.covariance[:, 0] > 0) and np.all(det > 0)
    # new corners: whole-pixel rounding of the tracking image, 1/12 px^2 there, 4/12 at full resolution
    assert np.allclose(a.covariance[~tracked, 0], 4 / 12)
    # the gate reads full-resolution sigma: at 0.75x the widest, that point goes (its sigma in tracking
    # pixels, half of it, would pass)
    gate = FeatureTracker([big], settings.with_overrides({"max_sigma": 0.75 * widest}))
    gated = sum(gate.process(float(seq.stamps[k]), frames[k]).gated for k in range(3))
    assert gated > 0
