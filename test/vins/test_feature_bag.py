"""The VINS feature bag: every image tracked, read back and decoded as VINS-Fusion's feature callback does."""

from __future__ import annotations

import itertools
import re

import numpy as np
import pytest
from rosbags.highlevel import AnyReader

from nsflow_ros.data.errors import DataError
from nsflow_ros.data.replay import ReplayOptions, replay_records
from nsflow_ros.data.sample import make_sample_sequence
from nsflow_ros.data.sources import SensorSource
from nsflow_ros.resources import DEFAULT_CONFIG, STEREO_CONFIG, share_file
from nsflow_ros.ros.replay_node import main as replay_main
from nsflow_ros.vins.config import load_vins_config
from nsflow_ros.vins.feature_bag import FEATURE_TOPIC, bag_format, feature_bag_topics
from nsflow_ros.vins.feature_bag import write_feature_bag as write_records
from nsflow_ros.vins.messages import decode_fusion
from nsflow_ros.vins.tracker import tracker_from_config


def write_feature_bag(opts: ReplayOptions, out, *, config=None, **kw):
    """The feature bag of a bag or ASL folder, read as ``nsflow-replay --features-bag`` reads it."""
    from dataclasses import replace

    cfg = load_vins_config(config or share_file(DEFAULT_CONFIG))
    return write_records(replay_records(replace(opts, topics=feature_bag_topics(cfg))), out, cfg, **kw)


@pytest.fixture(scope="module")
def seq(tmp_path_factory):
    root = tmp_path_factory.mktemp("feature_bag") / "seq"
    return make_sample_sequence(root, seed=4, duration=0.5, formats=("asl", "ros1"), progress=False)


def _read(bag):
    """(feature messages as (bag time, header stamp, decoded frame, channel count), IMU bag times)."""
    feats, imu = [], []
    with AnyReader([bag]) as reader:
        for conn, t, raw in reader.messages():
            msg = reader.deserialize(raw, conn.msgtype)
            if conn.topic == FEATURE_TOPIC:
                assert conn.msgtype == "sensor_msgs/msg/PointCloud"
                points = np.array([[p.x, p.y, p.z] for p in msg.points]).reshape(-1, 3)
                channels = np.array([np.asarray(c.values) for c in msg.channels])
                channels = channels.reshape(len(msg.channels), -1)
                stamp = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
                feats.append((t, stamp, decode_fusion(points, channels), len(msg.channels)))
            else:
                assert conn.msgtype == "sensor_msgs/msg/Imu"
                imu.append(t)
    return feats, imu


def test_mono_ros1_bag_holds_every_frame_as_vins_fusion_reads_it(seq, tmp_path):
    out = tmp_path / "features.bag"
    summary = write_feature_bag(ReplayOptions(seq.asl_dir), out, method="klt", progress=False)
    assert summary.format == "ros1" and summary.frames == len(seq) and summary.unpaired == 0
    feats, imu = _read(out)

    # one message per image, stamped (header and bag time) with the image's stamp
    assert [f[0] for f in feats] == [f[1] for f in feats] == [int(s) for s in seq.stamps_ns]
    # the estimator reads channels 6-8 whenever there are more than 5; klt adds no covariance unless asked
    assert all(f[3] == 9 for f in feats)
    source_imu = [r.stamp_ns for r in SensorSource(seq.asl_dir, topics=["/imu0"]).records()]
    assert imu == source_imu and summary.imu == len(imu) > 0

    # the same features the tracker makes from the same images, point for point
    tracker = tracker_from_config(load_vins_config(share_file(DEFAULT_CONFIG)), {"method": "klt"})
    previous: set[int] = set()
    carried = 0
    for (_, _, frame, _), rec in zip(feats, SensorSource(seq.asl_dir, topics=["/cam0/image_raw"]).records(),
                                     strict=True):
        cam = tracker.process(rec.stamp_ns * 1e-9, rec.gray()).cameras[0]
        assert sorted(frame) == sorted(int(i) for i in cam.ids)
        for k, fid in enumerate(cam.ids):
            ((camera_id, row),) = frame[int(fid)]  # one observation per id in mono
            assert camera_id == 0 and row[2] == 1.0
            np.testing.assert_allclose(row[:2], cam.undistorted[k], atol=1e-6)
            np.testing.assert_allclose(row[3:5], cam.pixels[k], atol=1e-3)
            np.testing.assert_allclose(row[5:7], cam.velocities[k], atol=1e-3)
        carried += len(previous & set(frame))
        previous = set(frame)
    assert carried > 100  # ids persist from frame to frame: tracks, not fresh detections


def test_stereo_ros2_bag_orders_camera_0_before_camera_1(seq, tmp_path):
    out = tmp_path / "features"
    summary = write_feature_bag(
        ReplayOptions(seq.ros1_path), out, config=share_file(STEREO_CONFIG), method="klt", progress=False
    )
    assert summary.format == "ros2" and (out / "metadata.yaml").is_file()
    feats, imu = _read(out)
    assert [f[1] for f in feats] == [int(s) for s in seq.stamps_ns] and len(imu) == summary.imu
    right = 0
    for _, _, frame, _ in feats:
        for observations in frame.values():
            cams = [c for c, _ in observations]
            assert cams in ([0], [0, 1])  # no right-only id; left first (the estimator asserts it)
            right += len(cams) - 1
    assert right > 50 * len(feats)


def test_feature_bag_is_deterministic(seq, tmp_path):
    opts = ReplayOptions(seq.asl_dir, perturb="large", seed=3)
    a = write_feature_bag(opts, tmp_path / "a.bag", method="klt", progress=False)
    b = write_feature_bag(opts, tmp_path / "b.bag", method="klt", progress=False)
    assert a.frames == b.frames == len(seq)
    raw = []
    for bag in (tmp_path / "a.bag", tmp_path / "b.bag"):
        with AnyReader([bag]) as reader:
            raw.append([bytes(r) for c, _, r in reader.messages() if c.topic == FEATURE_TOPIC])
    assert raw[0] == raw[1]
    plain = write_feature_bag(ReplayOptions(seq.asl_dir), tmp_path / "c.bag", method="klt", progress=False)
    with AnyReader([tmp_path / "c.bag"]) as reader:
        unperturbed = [bytes(r) for c, _, r in reader.messages() if c.topic == FEATURE_TOPIC]
    assert plain.frames == a.frames and unperturbed != raw[0]  # the perturbation reaches the tracker


def test_a_damaged_source_keeps_the_frames_before_the_damage(seq, tmp_path):
    from nsflow_ros.errors import NSFlowError

    damaged = tmp_path / "damaged.bag"
    data = seq.ros1_path.read_bytes()
    damaged.write_bytes(data[: len(data) // 2])
    with pytest.raises(NSFlowError, match=r"the \d+ frames before it were tracked and written"):
        write_feature_bag(ReplayOptions(damaged), tmp_path / "f.bag", method="klt", progress=False)
    feats, _ = _read(tmp_path / "f.bag")
    assert 0 < len(feats) < len(seq)


def test_format_follows_the_name_unless_asked(tmp_path):
    assert bag_format(tmp_path / "x.bag") == "ros1"
    assert bag_format(tmp_path / "x") == "ros2"
    assert bag_format(tmp_path / "x.bag", "ros2") == "ros2"
    with pytest.raises(DataError, match=r"ROS 1 bag is a file ending in \.bag"):
        bag_format(tmp_path / "x", "ros1")


def test_cli_writes_the_bag_and_refuses_to_overwrite(seq, tmp_path, capsys):
    args = [str(seq.asl_dir), "--features-bag", str(tmp_path / "f.bag"), "--method", "klt", "--no-progress"]
    assert replay_main(args) == 0
    assert f"{len(seq)} feature messages on {FEATURE_TOPIC}" in capsys.readouterr().out
    assert replay_main(args) == 1
    assert "exists already" in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["f.bag"]  # no temporary left behind


def test_feature_bag_and_offline_run_give_the_same_features(seq, tmp_path):
    # both go through the session's frame policy (VINS-Fusion layout for the shipped config)
    from nsflow_ros.vins.offline import run_offline

    run_offline(ReplayOptions(seq.asl_dir), tmp_path / "offline", method="klt", progress=False)
    write_feature_bag(ReplayOptions(seq.asl_dir), tmp_path / "f.bag", method="klt", progress=False)
    feats, _ = _read(tmp_path / "f.bag")
    rows = np.loadtxt(tmp_path / "offline" / "features.csv", delimiter=",", skiprows=1)
    assert len(feats) == len(np.unique(rows[:, 0])) == len(seq)
    for _, stamp, frame, _ in feats:
        mine = rows[rows[:, 0] == stamp]
        assert sorted(frame) == sorted(int(i) for i in mine[:, 2])
        for fid, u, v in mine[:, 2:5]:
            ((_, row),) = frame[int(fid)]
            np.testing.assert_allclose(row[3:5], (u, v), atol=1e-3)


def _upsampled(seq, folder):
    """The sample up-sampled 2x (cv2.resize's pixel centres) as a ROS 2 bag, and a VINS config for it."""
    from dataclasses import replace

    import cv2

    from nsflow_ros.core.camera import PinholeCamera
    from nsflow_ros.data.writers import write_ros2_bag

    def big(rec):
        if not hasattr(rec, "image"):
            return rec
        h, w = rec.image.shape[:2]
        return replace(rec, image=cv2.resize(rec.image, (2 * w, 2 * h), interpolation=cv2.INTER_LINEAR))

    bag = folder / "large"
    records = SensorSource(seq.asl_dir, topics=["/cam0/image_raw", "/imu0"]).records()
    write_ros2_bag(bag, (big(r) for r in records))
    cfg = load_vins_config(share_file(DEFAULT_CONFIG))
    cam = cfg.cameras[0]
    PinholeCamera(width=2 * cam.width, height=2 * cam.height, fx=2 * cam.fx, fy=2 * cam.fy,
                  cx=(cam.cx + 0.5) * 2 - 0.5, cy=(cam.cy + 0.5) * 2 - 0.5, k1=cam.k1, k2=cam.k2,
                  p1=cam.p1, p2=cam.p2).save_yaml(folder / "cam0_large.yaml")
    text = cfg.path.read_text().replace("cam0_pinhole.yaml", "cam0_large.yaml")
    for key, size in (("image_width", 752), ("image_height", 480)):
        text = text.replace(f"{key}: {size}", f"{key}: {2 * size}")
    (folder / "large.yaml").write_text(text)
    return bag, folder / "large.yaml"


def test_cli_downsample_writes_features_in_the_full_resolution_calibration(seq, tmp_path, capsys):
    bag, config = _upsampled(seq, tmp_path)
    base = ["--method", "klt", "--no-progress"]
    assert replay_main([str(seq.asl_dir), "--features-bag", str(tmp_path / "small.bag"), *base]) == 0
    args = [str(bag), "--features-bag", str(tmp_path / "large.bag"), "--config", str(config), *base]
    assert replay_main([*args, "--downsample", "3"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["nsflow-replay: downsample must be one of 1, 2, 4, got 3"]
    assert replay_main([*args, "--downsample", "2"]) == 0
    assert f"{len(seq)} feature messages" in capsys.readouterr().out
    small, _ = _read(tmp_path / "small.bag")
    large, _ = _read(tmp_path / "large.bag")
    assert len(small) == len(large) == len(seq)
    camera = load_vins_config(config).cameras[0]
    offsets, total = [], 0
    for (_, _, a, _), (_, _, b, _) in zip(small, large, strict=True):
        ua = np.array([obs[0][1] for obs in a.values()])
        ub = np.array([obs[0][1] for obs in b.values()])
        assert ub[:, 3].max() > 1000  # pixels of the 1504 px wide image ...
        np.testing.assert_allclose(ub[:, :2], camera.lift(ub[:, 3:5]), atol=1e-5)  # ... and its calibration
        # many features are the 752 px tracker's, at (x + 0.5) 2 - 0.5 (GFTT's choice among the many
        # corners of the sample differs for the rest); no offset: the pixel-centre convention holds
        mapped = 2 * (ua[:, 3:5] + 0.5) - 0.5
        d = np.hypot(*(ub[:, None, 3:5] - mapped[None]).transpose(2, 0, 1))
        same = d.min(axis=1) < 1.0
        offsets.append(ub[same, 3:5] - mapped[d.argmin(axis=1)[same]])
        total += len(ub)
    offsets = np.concatenate(offsets)
    assert len(offsets) > 0.3 * total and np.all(np.abs(np.median(offsets, axis=0)) < 0.02)


def test_cli_publish_rate_writes_fewer_messages_with_velocities_over_their_interval(seq, tmp_path, capsys):
    out = tmp_path / "rate.bag"
    args = [str(seq.asl_dir), "--features-bag", str(out), "--method", "klt", "--no-progress"]
    assert replay_main([*args, "--publish-rate", "10"]) == 0
    text = capsys.readouterr().out
    half = (len(seq) + 1) // 2
    assert f"{half} feature messages" in text and f"{len(seq)} frames tracked, {half} published" in text
    feats, imu = _read(out)
    assert [f[1] for f in feats] == [int(s) for s in seq.stamps_ns[::2]]  # every 2nd 20 Hz frame
    assert len(imu) == len([r for r in SensorSource(seq.asl_dir, topics=["/imu0"]).records()])
    for (_, t0, a, _), (_, t1, b, _) in itertools.pairwise(feats):
        for fid, ((_, row),) in b.items():
            if fid in a:
                expected = (row[:2] - a[fid][0][1][:2]) / ((t1 - t0) * 1e-9)
                np.testing.assert_allclose(row[5:7], expected, rtol=1e-3, atol=1e-4)
    with pytest.raises(SystemExit):  # only with --features-bag
        replay_main([str(seq.asl_dir), "--publish-rate", "10"])
    assert "--publish-rate applies to --features-bag" in capsys.readouterr().err


def test_cli_max_sigma_leaves_out_the_features_predicted_wide(seq, tmp_path, capsys):
    args = [str(seq.asl_dir), "--method", "classical", "--no-progress"]
    tracks = []
    for name, extra in (("all", []), ("gated", ["--max-sigma", "0.02"])):
        assert replay_main([*args, "--features-bag", str(tmp_path / f"{name}.bag"), *extra]) == 0
        feats, _ = _read(tmp_path / f"{name}.bag")
        tracks.append(len({fid for f in feats for fid in f[2]}))
    capsys.readouterr()
    # a gated feature's track ends and a new corner takes its place: more, shorter tracks
    assert tracks[1] > tracks[0]
    with pytest.raises(SystemExit):  # only with --features-bag
        replay_main([str(seq.asl_dir), "--max-sigma", "1"])
    assert "--max-sigma applies to --features-bag" in capsys.readouterr().err


def test_cli_masks_keep_each_camera_off_its_masked_pixels(seq, tmp_path, capsys):
    import cv2

    left_half = np.zeros((480, 752), np.uint8)
    left_half[:, :376] = 255
    cv2.imwrite(str(tmp_path / "m0.png"), left_half)
    cv2.imwrite(str(tmp_path / "m1.png"), 255 - left_half)  # the right camera: its right half only
    out = tmp_path / "f"
    args = [str(seq.ros1_path), "--features-bag", str(out), "--config", str(share_file(STEREO_CONFIG)),
            "--method", "klt", "--no-progress", "--mask0", str(tmp_path / "m0.png"),
            "--mask1", str(tmp_path / "m1.png")]
    assert replay_main(args) == 0
    feats, _ = _read(out)
    rights = 0
    for _, _, frame, _ in feats:
        for entries in frame.values():
            for cam, row in entries:
                assert (row[3] < 376) if cam == 0 else (row[3] >= 375.5)
                rights += cam == 1
    assert len(feats) == len(seq) and rights > 0
    # bad input: one line, exit 1, no bag
    capsys.readouterr()
    for mask, said in ((tmp_path / "none.png", r"mask image not found: .*none\.png"),
                       (tmp_path / "small.png", r"mask0 .*small\.png is 10x20 but the image size of")):
        cv2.imwrite(str(tmp_path / "small.png"), np.zeros((20, 10), np.uint8))
        bad = [str(seq.asl_dir), "--features-bag", str(tmp_path / "g.bag"), "--method", "klt",
               "--no-progress", "--mask0", str(mask)]
        assert replay_main(bad) == 1
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and re.search(said, err), err
        assert not (tmp_path / "g.bag").exists()


def _black_copy(seq, tmp_path, value: int = 0):
    """The sample's ASL folder with every camera image uniform."""
    import shutil

    import cv2

    asl = tmp_path / "black"
    shutil.copytree(seq.asl_dir, asl)
    for png in asl.glob("mav0/cam*/data/*.png"):
        cv2.imwrite(str(png), np.full((480, 752), value, np.uint8))
    return asl


def test_cli_feature_bag_says_the_tracking_state_and_fails_when_nothing_was_tracked(seq, tmp_path, capsys):
    # uniform images: a bag of empty clouds is written, the tool says why and exits 1
    out = tmp_path / "black.bag"
    code = replay_main([str(_black_copy(seq, tmp_path)), "--features-bag", str(out), "--method", "klt",
                        "--no-progress"])
    std = capsys.readouterr()
    assert code == 1 and out.exists() and "0.0 features/frame" in std.out
    assert "tracking LOST: images uniform" in std.out
    (line,) = std.err.strip().splitlines()
    assert line.startswith(f"nsflow-replay: no feature was tracked in {len(seq)} frames: images uniform")
    # max_sigma far below the covariance floor: every track gated, features published, ids never carried
    out = tmp_path / "gated.bag"
    code = replay_main([str(seq.asl_dir), "--features-bag", str(out), "--method", "classical",
                        "--no-progress", "--max-sigma", "1e-9"])
    std = capsys.readouterr()
    assert code == 0 and "tracking LOST: every tracked feature gated by max_sigma" in std.out, std
    out = tmp_path / "plain.bag"
    args = [str(seq.asl_dir), "--features-bag", str(out), "--method", "klt", "--no-progress"]
    assert replay_main(args) == 0
    assert "tracking" not in capsys.readouterr().out  # OK: nothing to say


def test_cli_feature_bag_checks_static_masks_as_the_node_does(seq, tmp_path, capsys):
    import cv2

    corner = np.zeros((480, 752), np.uint8)
    corner[:100, :100] = 255
    cv2.imwrite(str(tmp_path / "corner.png"), corner)
    cv2.imwrite(str(tmp_path / "zeros.png"), np.zeros((480, 752), np.uint8))
    out = tmp_path / "corner.bag"
    code = replay_main([str(seq.asl_dir), "--features-bag", str(out), "--method", "klt", "--no-progress",
                        "--mask0", str(tmp_path / "corner.png")])
    err = capsys.readouterr().err
    assert code == 0 and out.exists()
    assert "nsflow-replay: warning: mask0 " in err and "corner.png leaves 2.8 % of the image usable" in err
    code = replay_main([str(seq.asl_dir), "--features-bag", str(tmp_path / "z.bag"), "--method", "klt",
                        "--no-progress", "--mask0", str(tmp_path / "zeros.png")])
    (line,) = capsys.readouterr().err.strip().splitlines()
    assert code == 1 and "zeros.png leaves no usable pixel" in line and not (tmp_path / "z.bag").exists()
