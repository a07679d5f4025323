"""FeatureTracker: VINS-Fusion trackImage semantics on image sequences with known motion."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest
import synthetic_sequences as syn
from onnx_models import conv_encoder

from nsflow_ros.core.encoder import IntensityEncoder, load_encoder
from nsflow_ros.core.errors import CoreError
from nsflow_ros.core.methods import METHODS, EncoderSource, make_method
from nsflow_ros.core.pyramid import Smoothing
from nsflow_ros.core.tracker import (
    FeatureTracker,
    FrameFeatures,
    TrackerSettings,
    reject_with_fundamental,
)

ROOT = Path(__file__).resolve().parents[2]


def _classical(**kw) -> TrackerSettings:
    kw.setdefault("min_dist", 20)
    return TrackerSettings(method="classical", **kw)


def _run(tracker: FeatureTracker, seq: syn.Sequence, n: int | None = None) -> list[FrameFeatures]:
    out = []
    for k in range(n or len(seq.frames)):
        right = seq.right[k] if seq.right is not None else None
        out.append(tracker.process(float(seq.stamps[k]), seq.frames[k], right))
    return out


def _matches(prev, cur) -> tuple[np.ndarray, np.ndarray]:
    """Indices (in prev, in cur) of the ids both hold."""
    where = {int(i): j for j, i in enumerate(prev.ids)}
    cur_idx = np.array([j for j, i in enumerate(cur.ids) if int(i) in where], np.int64)
    prev_idx = np.array([where[int(cur.ids[j])] for j in cur_idx], np.int64)
    return prev_idx, cur_idx


@pytest.fixture(scope="module")
def pan() -> syn.Sequence:
    return syn.translating(12)


@pytest.fixture(scope="module")
def pan_result(pan):
    tracker = FeatureTracker([syn.camera()], _classical())
    return _run(tracker, pan)


def test_ids_persist_and_follow_the_true_motion(pan, pan_result):
    seen: set[int] = set()
    for k in range(1, len(pan_result)):
        prev, cur = pan_result[k - 1].cameras[0], pan_result[k].cameras[0]
        pi, ci = _matches(prev, cur)
        assert len(pi) >= 0.7 * len(prev), f"frame {k}: only {len(pi)} of {len(prev)} tracks survived"
        err = np.hypot(*(cur.pixels[ci] - pan.truth(k - 1, k, prev.pixels[pi])).T)
        # Within a window and a frame's motion of the edge where new content enters, half of a window is
        # replicated border and a few points go wrong (as with OpenCV's LK); inside, all but a few follow.
        h, w = pan.frames[0].shape
        p = prev.pixels[pi]
        inner = (p[:, 0] >= 8) & (p[:, 0] <= w - 9) & (p[:, 1] >= 8) & (p[:, 1] <= h - 9)
        assert np.median(err) < 0.15 and np.mean(err < 1.0) > 0.9, f"frame {k}: errors {np.sort(err)[-5:]}"
        assert np.mean(err[inner] < 1.0) > 0.97, f"frame {k}: inner errors {np.sort(err[inner])[-5:]}"
        np.testing.assert_array_equal(cur.track_counts[ci], prev.track_counts[pi] + 1)
        new = np.setdiff1d(cur.ids, prev.ids)
        assert np.all(cur.track_counts[np.isin(cur.ids, new)] == 1)
        # fresh ids are never reused: all larger than any id seen so far
        seen |= set(prev.ids.tolist())
        assert new.size == 0 or new.min() > max(seen)
        assert len(np.unique(cur.ids)) == len(cur.ids)
    long_lived = max(int(f.cameras[0].track_counts.max()) for f in pan_result)
    assert long_lived == len(pan_result)


def test_features_respect_min_dist_and_max_cnt(pan_result):
    for frame in pan_result:
        px = frame.cameras[0].pixels
        assert 0 < len(px) <= 150
        d = np.hypot(*(px[:, None] - px[None]).transpose(2, 0, 1))
        d[np.diag_indices_from(d)] = np.inf
        # the mask works on rounded pixels: allow the rounding
        assert d.min() >= 20 - 1.5, f"two features only {d.min():.2f} px apart"


def test_longest_tracks_win_the_mask():
    cam = syn.camera()
    tracker = FeatureTracker([cam], _classical(max_cnt=5, min_dist=40))
    pts = np.array([[100.0, 100.0], [110.0, 100.0], [200.0, 100.0]])
    keep, mask = tracker._set_mask(pts, np.array([1, 7, 3]), (cam.width, cam.height))
    assert keep.tolist() == [1, 2]  # id with count 7 blocks its neighbour with count 1
    assert mask[100, 110] == 0 and mask[100, 300] == 255


def test_velocities_are_undistorted_displacements_over_dt(pan, pan_result):
    cam = syn.camera()
    dt = float(pan.stamps[1] - pan.stamps[0])
    expected = np.array([-2.7 / cam.fx, -1.3 / cam.fy]) / dt
    assert np.all(pan_result[0].cameras[0].velocities == 0)
    for k in range(1, len(pan_result)):
        prev, cur = pan_result[k - 1].cameras[0], pan_result[k].cameras[0]
        pi, ci = _matches(prev, cur)
        np.testing.assert_allclose(cur.velocities[ci], (cur.undistorted[ci] - prev.undistorted[pi]) / dt)
        assert np.allclose(np.median(cur.velocities[ci], axis=0), expected, atol=0.01)
        fresh = np.ones(len(cur), bool)
        fresh[ci] = False
        assert np.all(cur.velocities[fresh] == 0)
        np.testing.assert_allclose(cur.undistorted, cam.lift(cur.pixels))
        assert np.all(np.isnan(cur.previous[fresh])) and np.allclose(cur.previous[ci], prev.pixels[pi])


def _occluded() -> syn.Sequence:
    """A patch of another photo appears in frame 3 (an occluder) of a pan."""
    seq = syn.translating(6)
    seq.frames[3] = seq.frames[3].copy()
    seq.frames[3][60:140, 100:190] = syn.base_texture("astronaut")[:80, :90]
    return seq


@pytest.mark.parametrize("check", ["reverse solves", "covariance"])
def test_occluded_points_are_rejected(check):
    # Points under the occluder must be dropped, not reported at wrong places: by the reverse solves, or by
    # the covariance check, whose departure test solves back the one that slid onto the occluder's edge.
    seq = _occluded()
    settings, method = _checked() if check == "covariance" else (_classical(), None)
    res = _run(FeatureTracker([syn.camera()], settings, method=method), seq)
    prev, cur = res[2].cameras[0], res[3].cameras[0]
    truth_all = seq.truth(2, 3, prev.pixels)
    x, y = truth_all.T
    under = (x > 96) & (x < 194) & (y > 56) & (y < 144)
    assert under.sum() >= 3, "the occluder should cover some tracked points"
    pi, ci = _matches(prev, cur)
    err = np.hypot(*(cur.pixels[ci] - truth_all[pi]).T)
    assert err.max() < 1.0, f"a wrong track survived: {err.max():.2f} px"
    survivors_under = np.isin(prev.ids[under], cur.ids).sum()
    assert survivors_under <= 0.2 * under.sum()


def test_fundamental_ransac_rejects_injected_outliers():
    rng = np.random.default_rng(3)
    pts3 = np.c_[rng.uniform(-2, 2, (120, 2)), rng.uniform(3, 9, 120)]
    rot = cv2.Rodrigues(np.array([0.02, -0.05, 0.01]))[0]
    t = np.array([0.3, 0.05, 0.1])
    a = pts3[:, :2] / pts3[:, 2:]
    q = pts3 @ rot.T + t
    b = q[:, :2] / q[:, 2:]
    bad = rng.choice(120, 12, replace=False)
    b_out = b.copy()
    b_out[bad] += rng.choice([-1, 1], (12, 2)) * rng.uniform(8, 20, (12, 2)) / 460.0
    inl = reject_with_fundamental(a, b_out, 1.0, (320, 240))
    assert not inl[bad].any()
    assert inl.sum() >= 0.95 * (120 - 12)
    assert reject_with_fundamental(a[:5], b[:5], 1.0, (320, 240)).all()  # too few points: keep all


def test_reject_with_f_runs_in_the_tracker(pan):
    res = _run(FeatureTracker([syn.camera()], _classical(reject_with_f=True)), pan, 5)
    assert all(len(f.cameras[0]) > 30 for f in res)


def test_stereo_ids_pair_with_the_left_ids():
    seq = syn.translating(8, stereo_disparity=-9.5)
    tracker = FeatureTracker([syn.camera(), syn.camera()], _classical(stereo=True))
    res = _run(tracker, seq)
    off = total = 0
    for k, frame in enumerate(res):
        left, right = frame.cameras
        assert (left.camera_id, right.camera_id) == (0, 1)
        assert np.isin(right.ids, left.ids).all() and len(np.unique(right.ids)) == len(right.ids)
        assert len(right) >= 0.7 * len(left)
        li, ri = _matches(left, right)
        err = np.hypot(*(right.pixels[ri] - (left.pixels[li] + [-9.5, 0.0])).T)
        # Near the image border the coarse levels see mostly replicated pixels, and now and then a point
        # there slides along the border in both directions (one of ~60 in one frame: 20 px off, passing
        # the flow-back check), as in VINS-Fusion's stereo matching, which has no further test. The
        # two-level back-check started at the answer lets one more such point through in 550.
        assert np.median(err) < 0.15 and (err < 1.0).mean() >= 0.97
        off += int((err >= 1.0).sum())
        total += err.size
        np.testing.assert_array_equal(right.track_counts[ri], left.track_counts[li])
        if k:
            prev_right = res[k - 1].cameras[1]
            pi, ci = _matches(prev_right, right)
            dt = float(seq.stamps[k] - seq.stamps[k - 1])
            np.testing.assert_allclose(
                right.velocities[ci], (right.undistorted[ci] - prev_right.undistorted[pi]) / dt
            )
    assert off <= 0.01 * total


def test_descriptor_maps_are_computed_once_per_image(pan):
    calls = []

    class Counting(IntensityEncoder):
        def __call__(self, image):
            calls.append(image.shape)
            return super().__call__(image)

    seq = syn.translating(5, stereo_disparity=-6)
    mono = FeatureTracker([syn.camera()], _classical(), encoder=Counting())
    for k in range(5):
        mono.process(float(seq.stamps[k]), seq.frames[k])
    assert len(calls) == 5
    calls.clear()
    _run(FeatureTracker([syn.camera(), syn.camera()], _classical(stereo=True), encoder=Counting()), seq)
    assert len(calls) == 10


def test_warm_up_encodes_one_frame_of_camera_0s_size_and_changes_no_track(pan):
    calls = []

    class Counting(IntensityEncoder):
        def __call__(self, image):
            calls.append(image.shape)
            return super().__call__(image)

    cold = FeatureTracker([syn.camera()], _classical(), encoder=Counting())
    warm = FeatureTracker([syn.camera()], _classical(), encoder=Counting())
    warm.warm_up()
    cam = syn.camera()
    assert calls == [(cam.height, cam.width)]
    assert warm.last_stamp is None and warm.next_id == 0
    for a, b in zip(_run(cold, pan, 4), _run(warm, pan, 4), strict=True):
        assert np.array_equal(a.cameras[0].ids, b.cameras[0].ids)
        assert np.array_equal(a.cameras[0].pixels, b.cameras[0].pixels)


def test_a_frame_without_checks_skips_only_its_own_reverse_solves(monkeypatch):
    from nsflow_ros.core.methods import SolveKind

    seq = syn.translating(4, stereo_disparity=-6)
    tracker = FeatureTracker([syn.camera(), syn.camera()], _classical(stereo=True))
    kinds: list[list[SolveKind]] = []
    solve = tracker.method.solve

    def counting(kind, *args, **kwargs):
        kinds[-1].append(kind)
        return solve(kind, *args, **kwargs)

    monkeypatch.setattr(tracker.method, "solve", counting)
    for k, checks in enumerate((True, True, False, True)):
        kinds.append([])
        tracker.process(float(seq.stamps[k]), seq.frames[k], seq.right[k], checks=checks)
    back = {SolveKind.FLOW_BACK, SolveKind.STEREO_BACK}
    assert back <= set(kinds[1]) and back <= set(kinds[3])
    assert not back & set(kinds[2]) and {SolveKind.FORWARD, SolveKind.STEREO} <= set(kinds[2])


def test_nsflow_method_loads_an_onnx_encoder(tmp_path, pan):
    model = conv_encoder(tmp_path / "tiny.onnx", c_in=1, d=3)
    settings = TrackerSettings(model_path=str(model), min_dist=20, num_threads=1)
    tracker = FeatureTracker([syn.camera()], settings)
    assert tracker.encoder.channels == 3
    res = _run(tracker, pan, 4)
    pi, ci = _matches(res[2].cameras[0], res[3].cameras[0])
    assert len(ci) > 20
    err = np.hypot(*(res[3].cameras[0].pixels[ci] - pan.truth(2, 3, res[2].cameras[0].pixels[pi])).T)
    assert np.median(err) < 0.3


def test_missing_model_is_a_clear_error(tmp_path):
    with pytest.raises(CoreError, match="not found"):
        FeatureTracker([syn.camera()], TrackerSettings(model_path=str(tmp_path / "none.onnx")))
    assert load_encoder  # the tracker goes through load_encoder's checks


def test_bad_input_raises_and_leaves_the_state_alone(pan):
    tracker = FeatureTracker([syn.camera()], _classical())
    first = tracker.process(1.0, pan.frames[0])
    with pytest.raises(CoreError, match="timestamps must increase"):
        tracker.process(0.5, pan.frames[1])
    with pytest.raises(CoreError, match="timestamps must increase"):
        tracker.process(1.0, pan.frames[1])
    with pytest.raises(CoreError, match="calibrated for 320x240"):
        tracker.process(1.1, np.zeros((100, 100), np.uint8))
    with pytest.raises(CoreError, match="uint8"):
        tracker.process(1.1, pan.frames[1].astype(np.float32))
    with pytest.raises(CoreError, match="mono"):
        tracker.process(1.1, pan.frames[1], pan.frames[1])
    with pytest.raises(CoreError, match="finite"):
        tracker.process(float("nan"), pan.frames[1])
    assert tracker.last_stamp == 1.0
    second = tracker.process(1.05, pan.frames[1])
    assert np.isin(first.cameras[0].ids, second.cameras[0].ids).mean() > 0.7
    stereo = FeatureTracker([syn.camera(), syn.camera()], _classical(stereo=True))
    with pytest.raises(CoreError, match="needs image1"):
        stereo.process(0.0, pan.frames[0])
    with pytest.raises(CoreError, match="needs 2 camera"):
        FeatureTracker([syn.camera()], _classical(stereo=True))


def test_reset_forgets_tracks_but_never_reuses_ids(pan):
    tracker = FeatureTracker([syn.camera()], _classical())
    a = tracker.process(5.0, pan.frames[0])
    tracker.reset()
    b = tracker.process(1.0, pan.frames[1])  # time may restart after a reset
    assert b.cameras[0].ids.min() > a.cameras[0].ids.max()
    assert np.all(b.cameras[0].track_counts == 1) and np.all(b.cameras[0].velocities == 0)


def test_detect_false_only_tracks(pan):
    tracker = FeatureTracker([syn.camera()], _classical())
    a = tracker.process(0.0, pan.frames[0])
    b = tracker.process(0.05, pan.frames[1], detect=False)
    assert np.isin(b.cameras[0].ids, a.cameras[0].ids).all()


def test_settings_validation_and_overrides():
    with pytest.raises(CoreError, match="method"):
        TrackerSettings(method="orb")
    s = TrackerSettings().with_overrides({"max_cnt": 80, "equalize": True})
    assert (s.max_cnt, s.equalize) == (80, True)
    with pytest.raises(CoreError, match="unknown tracker setting"):
        TrackerSettings().with_overrides({"maxcnt": 3})
    with pytest.raises(CoreError, match="unknown tracker setting"):  # the method's spec owns the solver
        TrackerSettings().with_overrides({"levels": 2})


def test_klt_method_tracks_a_known_shift_through_the_same_pipeline(pan):
    tracker = FeatureTracker([syn.camera()], TrackerSettings(method="klt", min_dist=20))
    assert tracker.encoder is None
    res = _run(tracker, pan, 6)
    for k in range(1, len(res)):
        prev, cur = res[k - 1].cameras[0], res[k].cameras[0]
        pi, ci = _matches(prev, cur)
        assert len(pi) >= 0.7 * len(prev), f"frame {k}: only {len(pi)} of {len(prev)} tracks survived"
        err = np.hypot(*(cur.pixels[ci] - pan.truth(k - 1, k, prev.pixels[pi])).T)
        assert np.median(err) < 0.15 and err.max() < 1.0, f"frame {k}: errors {np.sort(err)[-5:]}"
        np.testing.assert_array_equal(cur.track_counts[ci], prev.track_counts[pi] + 1)
    # min_dist and max_cnt come from the shared detection step
    assert max(len(f.cameras[0]) for f in res) <= 150


def test_klt_flow_back_rejects_occluded_points_and_stereo_works():
    seq = syn.translating(6)
    seq.frames[3] = seq.frames[3].copy()
    seq.frames[3][60:140, 100:190] = syn.base_texture("astronaut")[:80, :90]
    mono = _run(FeatureTracker([syn.camera()], TrackerSettings(method="klt", min_dist=20)), seq)
    prev, cur = mono[2].cameras[0], mono[3].cameras[0]
    pi, ci = _matches(prev, cur)
    err = np.hypot(*(cur.pixels[ci] - seq.truth(2, 3, prev.pixels[pi])).T)
    assert err.max() < 1.0, f"a wrong track survived the KLT flow-back: {err.max():.2f} px"
    seq = syn.translating(4, stereo_disparity=-9.5)
    settings = TrackerSettings(method="klt", stereo=True, min_dist=20)
    stereo = FeatureTracker([syn.camera(), syn.camera()], settings)
    left, right = _run(stereo, seq)[-1].cameras
    li, ri = _matches(left, right)
    assert len(ri) >= 0.7 * len(left)
    assert np.median(np.hypot(*(right.pixels[ri] - (left.pixels[li] + [-9.5, 0.0])).T)) < 0.15


def test_klt_method_refuses_an_encoder():
    with pytest.raises(CoreError, match="klt"):
        FeatureTracker([syn.camera()], TrackerSettings(method="klt"), encoder=IntensityEncoder())


def _circle_mask(cam, radius):
    mask = np.zeros((cam.height, cam.width), np.uint8)
    cv2.circle(mask, (cam.width // 2, cam.height // 2), radius, 255, -1)
    return mask


def test_fisheye_mask_keeps_tracks_and_new_corners_inside(pan):
    cam = syn.camera()
    mask = _circle_mask(cam, 90)
    plain = _run(FeatureTracker([cam], _classical()), pan, 6)
    masked = _run(FeatureTracker([cam], _classical(), mask=mask), pan, 6)

    def inside(frame):
        px = np.rint(frame.cameras[0].pixels).astype(int)
        return mask[px[:, 1], px[:, 0]] == 255

    assert not all(inside(f).all() for f in plain), "without the mask some features lie outside the circle"
    for frame in masked:
        assert len(frame.cameras[0]) > 10 and inside(frame).all()
    # tracks survive from frame to frame inside the mask
    pi, _ = _matches(masked[-2].cameras[0], masked[-1].cameras[0])
    assert len(pi) >= 0.5 * len(masked[-2].cameras[0])


def _band_mask(cam, x0, x1):
    """Usable everywhere but the columns x0 .. x1 - 1."""
    mask = np.full((cam.height, cam.width), 255, np.uint8)
    mask[:, x0:x1] = 0
    return mask


def _on_zero(mask, pixels):
    px = np.rint(pixels).astype(int)
    return mask[px[:, 1], px[:, 0]] == 0


def test_an_all_usable_mask_changes_nothing(pan, pan_result):
    cam = syn.camera()
    full = np.full((cam.height, cam.width), 255, np.uint8)
    out = _run(FeatureTracker([cam], _classical(), mask=full), pan, 4)
    framed = FeatureTracker([cam], _classical())
    masked = [framed.process(float(pan.stamps[k]), pan.frames[k], frame_masks=[full]) for k in range(4)]
    for a, b, c in zip(pan_result[:4], out, masked, strict=True):
        for other in (b, c):
            np.testing.assert_array_equal(a.cameras[0].ids, other.cameras[0].ids)
            np.testing.assert_array_equal(a.cameras[0].pixels, other.cameras[0].pixels)


def test_a_track_moving_into_the_static_mask_is_dropped(pan):
    # the content moves 2.7 px left per frame: tracks right of the band walk into it
    cam = syn.camera()
    mask = _band_mask(cam, 120, 160)
    frames = _run(FeatureTracker([cam], _classical()), pan, 8)
    masked = _run(FeatureTracker([cam], _classical(), mask=mask), pan, 8)
    assert any(_on_zero(mask, f.cameras[0].pixels).any() for f in frames), "no features in the band"
    entered = 0
    for k, frame in enumerate(masked):
        c = frame.cameras[0]
        assert len(c) > 20 and not _on_zero(mask, c.pixels).any(), f"frame {k}: a feature on the mask"
        if k:
            prev = masked[k - 1].cameras[0]
            moved_in = _on_zero(mask, pan.truth(k - 1, k, prev.pixels))
            entered += int(moved_in.sum())
            assert not np.isin(prev.ids[moved_in], c.ids).any(), f"frame {k}: a track inside the mask kept"
    assert entered > 0, "no track walked into the band: the test shows nothing"


def test_frame_masks_move_with_the_objects_and_mask_the_right_camera():
    seq = syn.translating(6, stereo_disparity=-9.5)
    cam = syn.camera()
    mask1 = _band_mask(cam, 200, 240)  # the right camera's own static mask
    tracker = FeatureTracker([cam, cam], _classical(stereo=True), mask1=mask1)
    plain = _run(FeatureTracker([cam, cam], _classical(stereo=True)), seq)
    for k in range(len(seq.frames)):
        box = np.full((cam.height, cam.width), 255, np.uint8)
        box[60:160, 40 + 20 * k : 140 + 20 * k] = 0  # a moving object in the left image
        box1 = np.roll(box, -10, axis=1)  # the same object seen by the right camera
        out = tracker.process(float(seq.stamps[k]), seq.frames[k], seq.right[k], frame_masks=[box, box1])
        left, right = out.cameras
        assert len(left) > 20 and len(right) > 10
        assert not _on_zero(box, left.pixels).any()
        assert not _on_zero(box1, right.pixels).any() and not _on_zero(mask1, right.pixels).any()
        assert set(right.ids.tolist()) <= set(left.ids.tolist())
    assert any(_on_zero(mask1, f.cameras[1].pixels).any() for f in plain), "mask1's band holds right points"


def test_a_frame_mask_of_the_wrong_size_is_refused_and_the_state_kept(pan):
    cam = syn.camera()
    tracker = FeatureTracker([cam], _classical())
    tracker.process(float(pan.stamps[0]), pan.frames[0])
    before = tracker.next_id
    with pytest.raises(CoreError, match=r"frame mask 0 is 10x20 but camera 0 \(.*\) is 320x240"):
        tracker.process(float(pan.stamps[1]), pan.frames[1], frame_masks=[np.zeros((20, 10), np.uint8)])
    with pytest.raises(CoreError, match=r"2 frame masks for a tracker of 1 camera"):
        tracker.process(float(pan.stamps[1]), pan.frames[1], frame_masks=[None, None])
    assert tracker.next_id == before and tracker.last_stamp == pan.stamps[0]
    with pytest.raises(CoreError, match="mask1 given but the tracker is mono"):
        FeatureTracker([cam], _classical(), mask1=np.zeros((cam.height, cam.width), np.uint8))
    with pytest.raises(CoreError, match=r"mask1 is 10x20 but camera 1"):
        FeatureTracker([cam, cam], _classical(stereo=True), mask1=np.zeros((20, 10), np.uint8))


def test_mask_must_match_camera_0():
    cam = syn.camera()
    with pytest.raises(CoreError, match=r"mask is 10x20 but camera 0"):
        FeatureTracker([cam], _classical(), mask=np.zeros((20, 10), np.uint8))
    with pytest.raises(CoreError, match="uint8"):
        FeatureTracker([cam], _classical(), mask=np.zeros((cam.height, cam.width), np.float32))
    with pytest.raises(CoreError, match="2-D"):
        FeatureTracker([cam], _classical(), mask=np.zeros((cam.height, cam.width, 3), np.uint8))


def test_a_bad_right_image_leaves_the_state_as_it_was():
    seq = syn.translating(2, stereo_disparity=-6)
    tracker = FeatureTracker([syn.camera(), syn.camera()], _classical(stereo=True))
    tracker.process(float(seq.stamps[0]), seq.frames[0], seq.right[0])
    before = tracker.next_id
    four = np.dstack([seq.right[1]] * 4)
    with pytest.raises(CoreError, match=r"image1 must be a uint8 \(H, W\) or \(H, W, 3\) array"):
        tracker.process(float(seq.stamps[1]), seq.frames[1], four)
    assert tracker.next_id == before and tracker.last_stamp == float(seq.stamps[0])


def test_deployed_settings_keep_tracks_through_a_brightness_step():
    # Auto-exposure: from frame 3 on the image is 20 gray levels brighter. The deployed zero-mean residual
    # compares windows up to that offset; the plain SSD loses most tracks at the step (and lets some
    # through at wrong places).
    seq = syn.translating(6)
    for k in range(3, 6):
        seq.frames[k] = cv2.add(seq.frames[k], 20)
    spec = METHODS["classical"]
    assert spec.lm.zero_mean
    kept = {}
    for zero_mean in (True, False):
        method = make_method(replace(spec, lm=replace(spec.lm, zero_mean=zero_mean)))
        res = _run(FeatureTracker([syn.camera()], _classical(), method=method), seq)
        prev, cur = res[2].cameras[0], res[3].cameras[0]
        pi, ci = _matches(prev, cur)
        kept[zero_mean] = len(ci) / len(prev)
        if zero_mean:
            assert np.hypot(*(cur.pixels[ci] - seq.truth(2, 3, prev.pixels[pi])).T).max() < 1.0
    assert kept[True] > 0.85 and kept[False] < 0.5 * kept[True], kept


def test_make_method_is_exactly_what_the_tracker_runs(tmp_path):
    model = conv_encoder(tmp_path / "m.onnx", c_in=1, d=3)
    smoothed, plain = load_encoder(model, smoothing=Smoothing(1.0, 0.5)), load_encoder(model)
    for name, spec in METHODS.items():
        given = None if spec.encoder is EncoderSource.NONE else smoothed if spec.smoothed else plain
        tracker = FeatureTracker([syn.camera()], TrackerSettings(method=name, equalize=True), encoder=given)
        built = make_method(name, encoder=given)
        # every setting: the spec (LM settings, solve policy, OpenCV LK arguments, encoder source and
        # smoothing, CLAHE) and what the objects hold
        assert tracker.method.spec == built.spec == METHODS[name]
        assert type(tracker.method) is type(built)
        assert vars(tracker.method).keys() == vars(built).keys()
        for key, value in vars(built).items():
            if key != "encoder":
                assert vars(tracker.method)[key] == value, (name, key)
        if built.spec.is_lm:
            assert tracker.method.pyramid_smoothing == built.pyramid_smoothing == Smoothing(coarse=0.5)
        assert tracker._clahe.getClipLimit() == METHODS[name].clahe.clip == 3.0
        assert tuple(tracker._clahe.getTilesGridSize()) == METHODS[name].clahe.tiles == (8, 8)
    shipped = FeatureTracker([syn.camera()], TrackerSettings())
    assert shipped.method.spec == make_method("nsflow").spec
    assert shipped.encoder.smoothing == make_method("nsflow").encoder.smoothing


def test_a_tracker_given_a_built_method_tracks_as_one_built_from_its_settings():
    seq = syn.translating(4)
    own = _run(FeatureTracker([syn.camera()], _classical()), seq)
    given = _run(FeatureTracker([syn.camera()], _classical(), method=make_method("classical")), seq)
    for a, b in zip(own, given, strict=True):
        np.testing.assert_array_equal(a.cameras[0].ids, b.cameras[0].ids)
        np.testing.assert_array_equal(a.cameras[0].pixels, b.cameras[0].pixels)
    with pytest.raises(CoreError, match=r"must be settings\.method"):
        FeatureTracker([syn.camera()], _classical(), method=make_method("klt"))
    with pytest.raises(CoreError, match="own encoder"):
        FeatureTracker([syn.camera()], _classical(), method=make_method("classical"),
                       encoder=IntensityEncoder())


def test_update_settings_changes_a_running_tracker_and_keeps_its_tracks(pan):
    tracker = FeatureTracker([syn.camera()], _classical(max_cnt=80))
    first = tracker.process(0.0, pan.frames[0])
    tracker.update_settings({"max_cnt": 40, "min_dist": 20.0})
    assert tracker.settings.max_cnt == 40 and tracker.settings.min_dist == 20.0
    second = tracker.process(0.05, pan.frames[1])
    carried = np.isin(second.cameras[0].ids, first.cameras[0].ids)
    assert carried.sum() > 20  # the tracks went on
    assert len(second.cameras[0]) <= 80  # carried tracks are kept; only the top-up obeys the new max_cnt


@pytest.mark.parametrize("field, value", [("method", "klt"), ("equalize", True), ("num_threads", 2)])
def test_update_settings_refuses_what_needs_a_new_tracker(pan, field, value):
    tracker = FeatureTracker([syn.camera()], _classical())
    before = tracker.settings
    with pytest.raises(CoreError, match=f"{field} cannot change on a running tracker"):
        tracker.update_settings({field: value})
    assert tracker.settings is before


def test_update_settings_refuses_unknown_and_invalid_values(pan):
    tracker = FeatureTracker([syn.camera()], _classical())
    with pytest.raises(CoreError, match="unknown tracker setting"):
        tracker.update_settings({"max_count": 10})
    with pytest.raises(CoreError, match="max_cnt"):
        tracker.update_settings({"max_cnt": 0})


def test_covariance_is_carried_without_changing_a_track(pan, pan_result):
    plain = pan_result
    with_cov = _run(FeatureTracker([syn.camera()], _classical(publish_covariance=True)), pan)
    for a, b in zip(plain, with_cov, strict=True):
        ca, cb = a.cameras[0], b.cameras[0]
        np.testing.assert_array_equal(ca.ids, cb.ids)
        np.testing.assert_array_equal(ca.pixels, cb.pixels)  # bit-identical tracks
        assert ca.covariance is None and cb.covariance.shape == (len(cb), 3) and b.gated == 0
        new = cb.track_counts == 1
        np.testing.assert_allclose(cb.covariance[new], [[1 / 12, 0, 1 / 12]] * int(new.sum()))
        tracked = cb.covariance[~new]
        assert np.all(tracked[:, 0] > 0) and np.all(tracked[:, 0] * tracked[:, 2] > tracked[:, 1] ** 2)


def test_max_sigma_drops_and_counts_wide_points(pan):
    loose = _run(FeatureTracker([syn.camera()], _classical(max_sigma=100.0)), pan, 4)
    assert all(f.gated == 0 for f in loose) and loose[-1].cameras[0].covariance is None
    tracker = FeatureTracker([syn.camera()], _classical(max_sigma=1e-6))  # tighter than any point
    frames = _run(tracker, pan, 4)
    # the same state up to frame 0: what the loose run carried into frame 1 is what the gate dropped
    assert frames[1].gated == int((loose[1].cameras[0].track_counts > 1).sum()) > 0
    for cur in frames[1:]:
        assert cur.gated > 0 and np.all(cur.cameras[0].track_counts == 1)  # nothing carried over
    tracker.update_settings({"max_sigma": 0.0})
    assert tracker.settings.covariance is False
    with pytest.raises(CoreError, match="max_sigma"):
        _classical(max_sigma=-1.0)


def _checked(stereo: bool = False, check: object = None, **kw) -> tuple[TrackerSettings, object]:
    """The classical method with the covariance check (as ``nsflow`` has it; None: the default one), and
    its settings."""
    from nsflow_ros.core.checks import CovarianceCheck

    settings = _classical(stereo=stereo, **kw)
    return settings, make_method(replace(METHODS["classical"], check=check or CovarianceCheck()))


@pytest.mark.parametrize(("max_sigma", "per_frame", "overall"), [(0.3, 0.85, 0.92), (None, 0.7, 0.75)])
def test_the_covariance_check_keeps_most_tracks_the_reverse_solves_keep(max_sigma, per_frame, overall):
    from nsflow_ros.core.checks import CovarianceCheck

    seq = _occluded()
    # at 0.3 px about as many; the default bound (0.15 px) also ends the widest-sigma tracks, here about a
    # fifth more than the reverse solves do
    settings, method = _checked(check=None if max_sigma is None else CovarianceCheck(max_sigma=max_sigma))
    res = _run(FeatureTracker([syn.camera()], settings, method=method), seq)
    reverse = _run(FeatureTracker([syn.camera()], _classical()), seq)
    # frames away from the occluder; the first one's tracks are all new corners
    kept, kept_reverse = (np.array([np.isin(r[k - 1].cameras[0].ids, r[k].cameras[0].ids).sum()
                                    for k in (1, 2, 4, 5)]) for r in (res, reverse))
    assert (kept >= per_frame * kept_reverse).all(), (kept, kept_reverse)
    assert kept.sum() >= overall * kept_reverse.sum(), (kept, kept_reverse)


def test_the_published_covariance_has_the_tail_the_check_does_not_read():
    from nsflow_ros.core.checks import CovarianceCheck
    from nsflow_ros.core.covariance import max_sigma

    seq = _occluded()
    base = METHODS["classical"].covariance_scale
    # a knee low enough that many tracks lie above it: the check still reads the calibration without it
    tail = replace(base, knee=0.02, power=0.5)
    runs = []
    for cal in (base, tail):
        method = make_method(replace(METHODS["classical"], check=CovarianceCheck(), covariance_scale=cal))
        runs.append(_run(FeatureTracker([syn.camera()], _classical(publish_covariance=True), method=method),
                         seq))
    above = 0
    for a, b in zip(*runs, strict=True):
        ca, cb = a.cameras[0], b.cameras[0]
        np.testing.assert_array_equal(ca.ids, cb.ids)
        np.testing.assert_array_equal(ca.pixels, cb.pixels)  # the same tracks
        tracked = ca.track_counts > 1
        np.testing.assert_allclose(cb.covariance[tracked], tail.expected(ca.covariance[tracked]))
        np.testing.assert_array_equal(cb.covariance[~tracked], ca.covariance[~tracked])  # 1/12: detected
        above += int((max_sigma(ca.covariance[tracked]) > tail.knee).sum())
    assert above > 20  # the tail was live


def test_the_covariance_check_solves_in_reverse_only_unsure_points_unless_reverse_checks(monkeypatch):
    from nsflow_ros.core.methods import SolveKind

    seq = syn.translating(5, stereo_disparity=-6)
    counts = {}
    for reverse in (False, True):
        settings, method = _checked(stereo=True, reverse_checks=reverse)
        tracker = FeatureTracker([syn.camera(), syn.camera()], settings, method=method)
        points = dict.fromkeys(SolveKind, 0)
        for name in ("solve", "solve_with_covariance"):
            solve = getattr(tracker.method, name)

            def counting(kind, frame1, frame2, pts, *a, _s=solve, _n=points, **k):
                _n[kind] += len(pts)
                return _s(kind, frame1, frame2, pts, *a, **k)

            monkeypatch.setattr(tracker.method, name, counting)
        _run(tracker, seq)
        counts[reverse] = points
    # VINS's checks track every live point back; the covariance check only those far from their prior
    full, unsure = counts[True], counts[False]
    assert full[SolveKind.FLOW_BACK] >= 0.9 * full[SolveKind.FORWARD]
    assert full[SolveKind.STEREO_BACK] >= 0.8 * full[SolveKind.STEREO]
    assert unsure[SolveKind.FLOW_BACK] <= 0.05 * unsure[SolveKind.FORWARD]
    assert unsure[SolveKind.STEREO_BACK] <= 0.05 * unsure[SolveKind.STEREO]


def test_the_epipolar_test_drops_right_points_off_their_row():
    pose = np.eye(4)
    pose[0, 3] = -0.11  # camera 1 to the right of camera 0: matches lie on the same row
    for dy, kept in ((0.0, True), (4.0, False)):
        seq = syn.translating(3, stereo_disparity=-6)
        seq.right = [syn.render(syn.base_texture("coffee"), syn.translation(-6, dy) @ m)
                     for m in seq.homographies]
        settings, method = _checked(stereo=True)
        tracker = FeatureTracker([syn.camera(), syn.camera()], settings, method=method, cam1_T_cam0=pose)
        res = _run(tracker, seq)
        left, right = res[-1].cameras
        if kept:
            assert len(right) >= 0.7 * len(left)
        else:  # every match is 4 px off its epipolar line
            assert len(right) == 0, f"{len(right)} of {len(left)} right points off their row survived"
        # without the pair's pose the same matches all pass
        settings, method = _checked(stereo=True)
        free = _run(FeatureTracker([syn.camera(), syn.camera()], settings, method=method), seq)
        assert len(free[-1].cameras[1]) >= 0.7 * len(free[-1].cameras[0])


def test_the_epipolar_test_lifts_each_point_once_with_the_published_points(monkeypatch):
    pose = np.eye(4)
    pose[0, 3] = -0.11
    seq = syn.translating(3, stereo_disparity=-6)
    settings, method = _checked(stereo=True)
    cams = [syn.camera(), syn.camera()]
    plain = _run(FeatureTracker(cams, settings, method=method), seq)
    lifted: list[int] = []
    original = type(cams[0]).lift_rays

    def counting(self, px):
        lifted.append(len(px))
        return original(self, px)

    monkeypatch.setattr(type(cams[0]), "lift_rays", counting)
    settings, method = _checked(stereo=True)
    res = _run(FeatureTracker(cams, settings, method=method, cam1_T_cam0=pose), seq)
    # Two lifts a frame, camera 0's and camera 1's points, as without the test; the same points published.
    assert len(lifted) == 2 * len(res)
    for a, b in zip(plain, res, strict=True):
        for ca, cb in zip(a.cameras, b.cameras, strict=True):
            np.testing.assert_array_equal(ca.undistorted, cb.undistorted)
