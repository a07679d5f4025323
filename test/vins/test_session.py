"""The front-end session: VINS frame policy and live setting changes, without any middleware."""

from __future__ import annotations

import itertools
from pathlib import Path

import numpy as np
import pytest
import synthetic_sequences as syn

from nsflow_ros.vins.config import load_vins_config
from nsflow_ros.vins.errors import ConfigError
from nsflow_ros.vins.session import FrontEndSession

T0 = 100.0


def _config(folder: Path, dialect: str = "fusion", freq: int = 10) -> Path:
    cam = syn.camera()
    common = (
        f"image_width: {cam.width}\nimage_height: {cam.height}\nmax_cnt: 120\nmin_dist: 20\nfreq: {freq}\n"
        "F_threshold: 1.0\nshow_track: 0\nflow_back: 1\nestimate_extrinsic: 2\n"
    )
    if dialect == "mono":
        text = (
            "%YAML:1.0\nimu_topic: \"/imu\"\nimage_topic: \"/cam0\"\nmodel_type: PINHOLE\ncamera_name: c\n"
            "distortion_parameters:\n   k1: 0.0\n   k2: 0.0\n   p1: 0.0\n   p2: 0.0\n"
            f"projection_parameters:\n   fx: {cam.fx}\n   fy: {cam.fy}\n   cx: {cam.cx}\n   cy: {cam.cy}\n"
            + common + "equalize: 0\n"
        )
    else:
        cam.save_yaml(folder / "cam0.yaml")
        text = (
            "%YAML:1.0\nimu: 0\nnum_of_cam: 1\nimage0_topic: \"/cam0\"\nimage1_topic: \"\"\n"
            "cam0_calib: \"cam0.yaml\"\n" + common
        )
    path = folder / f"{dialect}.yaml"
    path.write_text(text)
    return path


@pytest.fixture(scope="module")
def pan() -> syn.Sequence:
    return syn.translating(12)


def _session(tmp_path: Path, dialect: str = "fusion", **settings) -> FrontEndSession:
    return FrontEndSession(load_vins_config(_config(tmp_path, dialect)), {"method": "classical", **settings})


def test_fusion_layout_publishes_every_frame_and_skips_a_repeated_stamp(tmp_path, pan):
    s = _session(tmp_path)
    outs = [s.process(T0 + pan.stamps[k], pan.frames[k]) for k in range(4)]
    assert all(o.tracked and o.features is not None and not o.restart for o in outs)
    ids1 = set(outs[1].features.cameras[0].ids.tolist())
    assert len(ids1 & set(outs[2].features.cameras[0].ids.tolist())) > 0.7 * len(ids1)
    dup = s.process(T0 + pan.stamps[3], pan.frames[3])
    assert dup.skipped == "duplicate_stamp" and dup.features is None and "repeats" in dup.note
    back = s.process(T0 + pan.stamps[1], pan.frames[1])  # time going backwards: tracks restart
    assert back.tracked and "backwards" in back.note
    assert np.all(back.features.cameras[0].track_counts == 1)
    assert s.counters.tracked == 5 and s.counters.resets == 1
    assert s.counters.skipped["duplicate_stamp"] == 1


def test_mono_layout_first_frame_freq_and_restart(tmp_path, pan):
    s = _session(tmp_path, "mono")
    assert s.layout == "mono" and s.freq == 10 and s.tracker.settings.reject_with_f
    outs = [s.process(T0 + pan.stamps[k], pan.frames[k]) for k in range(len(pan.frames))]
    assert outs[0].skipped == "first_frame" and not outs[0].tracked
    assert all(o.tracked for o in outs[1:])
    published = [k for k, o in enumerate(outs) if o.features is not None]
    # 20 Hz in, freq 10: about every other frame, minus the first published one that VINS-Mono skips
    assert 4 <= len(published) <= 6 and s.counters.throttled >= 4
    gap = s.process(T0 + 5.0, pan.frames[0])  # a 4.4 s gap restarts the estimator
    assert gap.restart and gap.features is None and "discontinuity" in gap.note
    assert s.counters.restarts == 1
    again = s.process(T0 + 5.05, pan.frames[1])
    assert again.skipped == "first_frame"  # after a restart, VINS-Mono drops the first image again


def test_freq_change_takes_effect(tmp_path, pan):
    s = _session(tmp_path, "mono")
    assert s.update(freq=0) == ["freq is now 100"]  # 0 = 100 Hz: every 20 Hz image
    outs = [s.process(T0 + pan.stamps[k], pan.frames[k]) for k in range(len(pan.frames))]
    assert sum(o.features is not None for o in outs) == len(pan.frames) - 2  # first frame, first published


def test_max_cnt_change_applies_to_the_next_frame_and_keeps_tracks(tmp_path, pan):
    s = _session(tmp_path)
    first = s.process(T0 + pan.stamps[0], pan.frames[0]).features
    assert len(first.cameras[0]) > 40
    notes = s.update(max_cnt=20, min_dist=10)
    assert "max_cnt is now 20" in notes and "min_dist is now 10" in notes
    nxt = s.process(T0 + pan.stamps[1], pan.frames[1]).features
    assert 0 < len(nxt.cameras[0]) <= 20
    assert np.all(nxt.cameras[0].track_counts == 2)  # the longest tracks were kept, not restarted
    cut = set(first.cameras[0].ids.tolist()) - set(nxt.cameras[0].ids.tolist())
    assert s.update(max_cnt=-1) == ["max_cnt is now 120"]  # back to the VINS config's value
    later = s.process(T0 + pan.stamps[2], pan.frames[2]).features
    assert len(later.cameras[0]) > 40
    # an id cut once never comes back (the estimator assumes contiguous observations), new ids fill up
    assert not cut & set(later.cameras[0].ids.tolist())
    assert later.cameras[0].ids.max() > first.cameras[0].ids.max()


def test_method_change_rebuilds_the_tracker_and_never_reuses_ids(tmp_path, pan):
    s = _session(tmp_path)
    for k in range(2):
        before = s.process(T0 + pan.stamps[k], pan.frames[k]).features
    highest = int(before.cameras[0].ids.max())
    old_tracker = s.tracker
    notes = s.update(method="klt")
    assert s.tracker is not old_tracker and s.tracker.settings.method == "klt"
    assert any("tracks restart" in n for n in notes) and s.counters.rebuilds == 1
    after = s.process(T0 + pan.stamps[2], pan.frames[2]).features
    assert after.cameras[0].ids.min() > highest
    assert np.all(after.cameras[0].track_counts == 1)
    nxt = s.process(T0 + pan.stamps[3], pan.frames[3]).features
    assert len(set(nxt.cameras[0].ids.tolist()) & set(after.cameras[0].ids.tolist())) > 30


def test_bad_updates_are_refused_and_change_nothing(tmp_path, pan):
    s = _session(tmp_path)
    settings, tracker = s.tracker.settings, s.tracker
    with pytest.raises(ConfigError, match="max_cnt"):
        s.update(max_cnt=0)
    with pytest.raises(ConfigError, match="F_threshold"):
        s.update(F_threshold="x")
    with pytest.raises(ConfigError, match="unknown front-end setting"):
        s.update(window=7)
    with pytest.raises(Exception, match="method"):
        s.update(method="nope")
    with pytest.raises(ConfigError, match="use_imu_prediction"):
        s.update(use_imu_prediction=True)
    with pytest.raises(Exception, match="unbounded descriptors"):  # OpenCV's LK and the fast model
        s.update(method="nsflow_lk", model_path="fast")
    assert s.tracker is tracker and s.tracker.settings == settings and s.settings == {"method": "classical"}
    assert s.update(F_threshold=2) == ["F_threshold is now 2.0"]  # an integer where a number is expected


def test_unknown_setting_or_layout_at_construction(tmp_path):
    cfg = load_vins_config(_config(tmp_path))
    with pytest.raises(ConfigError, match="unknown front-end setting"):
        FrontEndSession(cfg, {"maxcnt": 3})
    with pytest.raises(ConfigError, match="layout"):
        FrontEndSession(cfg, {"method": "classical"}, layout="ros1")


def test_switches_reach_the_running_tracker(tmp_path, pan):
    s = _session(tmp_path)
    tracker = s.tracker
    assert s.tracker.settings.flow_back and not s.tracker.settings.reject_with_f
    notes = s.update(flow_back=0, reject_with_f=1, F_threshold=3.0, show_track=1)
    assert s.tracker is tracker  # applied in place: the tracks go on
    st = s.tracker.settings
    assert not st.flow_back and st.reject_with_f and st.F_threshold == 3.0 and s.show_track
    assert notes == ["F_threshold is now 3.0", "flow_back is now False", "reject_with_f is now True",
                     "show_track is now True"]
    assert s.update(flow_back=0) == []  # no change, nothing to say
    assert s.update(reject_with_f=-1) == ["reject_with_f is now False"]  # the layout's default again


def test_settings_apply_by_their_mode_through_one_path(tmp_path, pan):
    s = _session(tmp_path)
    s.process(T0 + pan.stamps[0], pan.frames[0])
    running = s.tracker
    # live: the running tracker's settings change (max_cnt also bounds what is published)
    assert s.update(max_cnt=30, reject_with_f=1) == ["max_cnt is now 30", "reject_with_f is now True"]
    assert s.tracker is running and running.settings.max_cnt == 30 and running.settings.reject_with_f
    out = s.process(T0 + pan.stamps[1], pan.frames[1]).features
    assert 0 < len(out.cameras[0]) <= 30
    # rebuild: a new tracker with every current setting
    notes = s.update(equalize=1)
    assert s.tracker is not running and s.tracker.settings.equalize and s.tracker.settings.max_cnt == 30
    assert "equalize changed: new tracker" in notes[0] and s.counters.rebuilds == 1
    # read-only: refused, nothing changes
    with pytest.raises(ConfigError, match="use_imu_prediction cannot change"):
        s.update(use_imu_prediction=True, max_cnt=10)
    assert s.tracker.settings.max_cnt == 30


def test_every_tracker_the_session_builds_is_warmed_up_before_its_first_frame(tmp_path, monkeypatch):
    from nsflow_ros.core.tracker import FeatureTracker

    warmed = []
    monkeypatch.setattr(FeatureTracker, "warm_up", lambda self: warmed.append(self))
    s = _session(tmp_path)
    assert warmed == [s.tracker]
    s.update(method="klt")  # a rebuild
    assert warmed == [warmed[0], s.tracker] and s.tracker is not warmed[0]


def test_publish_rate_tracks_every_frame_and_publishes_at_the_rate(tmp_path, pan):
    every = _session(tmp_path)
    ref = [every.process(T0 + pan.stamps[k], pan.frames[k]).features for k in range(len(pan.frames))]
    s = _session(tmp_path, publish_rate=10.0)
    assert s.publish_rate == 10.0
    outs = [s.process(T0 + pan.stamps[k], pan.frames[k]) for k in range(len(pan.frames))]
    assert all(o.tracked for o in outs)
    published = [k for k, o in enumerate(outs) if o.features is not None]
    assert published == list(range(0, len(pan.frames), 2))  # 20 Hz in, 10 Hz out: every 2nd frame
    assert s.counters.throttled == len(pan.frames) - len(published) and s.counters.tracked == len(pan.frames)
    for a, b in itertools.pairwise(published):
        cur, prev = outs[b].features.cameras[0], outs[a].features.cameras[0]
        same = ref[b].cameras[0]
        # the tracking is the same as when every frame is published: same ids, pixels, points
        assert np.array_equal(cur.ids, same.ids) and np.array_equal(cur.undistorted, same.undistorted)
        # velocities over the published interval (0.1 s), 0 for ids the previous published frame lacked
        rows = {int(i): n for n, i in enumerate(prev.ids)}
        old = np.array([int(i) in rows for i in cur.ids])
        expect = (cur.undistorted[old] - prev.undistorted[[rows[int(i)] for i in cur.ids[old]]]) / 0.1
        assert old.sum() > 20 and np.allclose(cur.velocities[old], expect, rtol=1e-6, atol=1e-9)
        assert np.all(cur.velocities[~old] == 0)
        assert not np.allclose(cur.velocities[old], same.velocities[old])  # not the per-frame rate
    # 0 = every frame (as by default), with the per-frame velocities of the default
    assert s.update(publish_rate=0) == ["publish_rate is now 0.0"]
    assert s.update(publish_rate=-1) == ["publish_rate is now None"]
    with pytest.raises(ConfigError, match="publish_rate' must be a finite number >= 0"):
        s.update(publish_rate=-3.0)


def test_publish_rate_replaces_freq_in_the_mono_layout(tmp_path, pan):
    s = _session(tmp_path, "mono", publish_rate=5.0)
    outs = [s.process(T0 + pan.stamps[k], pan.frames[k]) for k in range(len(pan.frames))]
    published = [k for k, o in enumerate(outs) if o.features is not None]
    # freq 10 in the config would publish every 2nd frame; 5 Hz lets every 4th through (frames 4 and 8 of
    # 0.05 s; VINS-Mono skips the first one that passes)
    assert published == [8] and s.counters.throttled == len(pan.frames) - 1 - 2


def test_publish_covariance_follows_the_layout_unless_set_and_max_sigma_is_live(tmp_path, pan):
    from nsflow_ros.vins.messages import encode

    cases = (("fusion", -1, "classical", 12), ("fusion", 0, "classical", 9), ("fusion", -1, "klt", 9),
             ("fusion", 1, "klt", 12), ("mono", -1, "classical", 5), ("mono", 1, "classical", 8))
    for dialect, setting, method, channels in cases:  # -1: on for the LM methods in the fusion layout
        s = _session(tmp_path, dialect, publish_covariance=setting, method=method)
        outs = [s.process(T0 + pan.stamps[k], pan.frames[k]) for k in range(6)]
        frame = [o.features for o in outs if o.features is not None][-1]  # mono: throttled to freq
        assert encode(frame, s.layout).channels.shape[0] == channels, (dialect, setting, method)
    s = _session(tmp_path)
    for k in range(3):
        s.process(T0 + pan.stamps[k], pan.frames[k])
    assert s.update(max_sigma=1e-6) == ["max_sigma is now 1e-06"]
    out = s.process(T0 + pan.stamps[3], pan.frames[3])
    assert out.features.gated > 0 and s.counters.gated == out.features.gated
    with pytest.raises(ConfigError, match="max_sigma"):
        s.update(max_sigma=-2.0)


def test_frame_masks_keep_features_off_moving_objects_frame_by_frame(tmp_path, pan):
    s = _session(tmp_path)
    cam = syn.camera()
    for k in range(5):
        box = np.full((cam.height, cam.width), 255, np.uint8)
        box[40:200, 30 + 30 * k : 130 + 30 * k] = 0  # an object crossing the view
        out = s.process(T0 + pan.stamps[k], pan.frames[k], frame_masks=[box])
        px = np.rint(out.features.cameras[0].pixels).astype(int)
        assert len(px) > 20 and np.all(box[px[:, 1], px[:, 0]] == 255)
    bad = s.process(T0 + pan.stamps[5], pan.frames[5], frame_masks=[np.zeros((10, 10), np.uint8)])
    assert bad.skipped == "tracker" and "frame mask 0 is 10x10 but the images' size is 320x240" in bad.note
    assert s.process(T0 + pan.stamps[6], pan.frames[6]).tracked  # the next frame goes on


def test_static_masks_come_from_the_config_keys_and_survive_a_rebuild(tmp_path, pan):
    import cv2

    cam = syn.camera()
    half = np.zeros((cam.height, cam.width), np.uint8)
    half[:, : cam.width // 2] = 255
    cv2.imwrite(str(tmp_path / "half.png"), half)
    path = _config(tmp_path)
    path.write_text(path.read_text() + 'mask0: "half.png"\n')
    s = FrontEndSession(load_vins_config(path), {"method": "classical"})
    for k in range(3):
        if k == 2:
            s.update(method="klt")  # a new tracker keeps the masks
        px = s.process(T0 + pan.stamps[k], pan.frames[k]).features.cameras[0].pixels
        assert len(px) > 10 and np.all(np.rint(px[:, 0]) < cam.width // 2)
