"""nsflow-replay: its command line and the rclpy publisher that paces the stream."""

from __future__ import annotations

import os
import random
import re
import threading
import time

import numpy as np
import pytest

from nsflow_ros.data.replay import ReplayOptions, replay_stream
from nsflow_ros.data.sample import make_sample_sequence
from nsflow_ros.ros.replay_node import main as replay_main
from nsflow_ros.ros.replay_node import publish_stream


@pytest.fixture(scope="module")
def seq(tmp_path_factory):
    # one sequence for the replay tests of data/, ros/ and vins/: make_sample_sequence reuses it
    root = tmp_path_factory.getbasetemp() / "replay_seq"
    return make_sample_sequence(
        root, seed=3, duration=1.0, stereo=False, formats=("asl", "ros2"), progress=False
    )


def test_cli_compress_is_for_publishing_only(seq, tmp_path, capsys):
    with pytest.raises(SystemExit) as info:
        replay_main([str(seq.asl_dir), "--compress", "png", "--write-bag", str(tmp_path / "x")])
    assert info.value.code == 2 and "--compress applies to publishing" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        replay_main([str(seq.asl_dir), "--compress", "jpeg", "--jpeg-quality", "101"])
    assert "--jpeg-quality: expected 1..100, got 101" in capsys.readouterr().err


def test_cli_reports_a_missing_path(tmp_path, capsys):
    assert replay_main([str(tmp_path / "nope"), "--no-progress"]) == 1
    assert "nope" in capsys.readouterr().err


def test_publish_stream_reaches_a_subscriber(seq):
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import qos_profile_sensor_data
    from sensor_msgs.msg import Image, Imu

    os.environ.setdefault("ROS_DOMAIN_ID", str(random.randint(100, 200)))
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    got: dict[str, list] = {"img": [], "imu": []}
    try:
        sub = rclpy.create_node("replay_sink", context=ctx)
        pub = rclpy.create_node("replay_source", context=ctx)
        sub.create_subscription(Image, "/cam0/image_raw", got["img"].append, qos_profile_sensor_data)
        sub.create_subscription(Imu, "/imu0", got["imu"].append, 1000)
        ex = SingleThreadedExecutor(context=ctx)
        ex.add_node(sub)
        spin = threading.Thread(target=ex.spin, daemon=True)
        spin.start()
        opts = ReplayOptions(seq.asl_dir, ["/cam0/image_raw", "/imu0"], perturb="small", rate=0)
        msgs = list(replay_stream(opts))
        first_img = next(m for m in msgs if m.topic == "/cam0/image_raw")
        first_imu = next(m for m in msgs if m.topic == "/imu0")
        pubs: dict = {}
        # announce both publishers, then wait until the subscriber has matched them
        publish_stream(pub, [first_img, first_imu], rate=0, progress=False, publishers=pubs)
        deadline = time.monotonic() + 10
        while pub.count_subscribers("/imu0") + pub.count_subscribers("/cam0/image_raw") < 2:
            assert time.monotonic() < deadline, "subscriber never matched"
            time.sleep(0.05)
        got["img"].clear()
        got["imu"].clear()
        rest = [m for m in msgs if m is not first_img and m is not first_imu]
        sent = publish_stream(pub, rest, rate=4.0, progress=False, publishers=pubs, clock=False)
        time.sleep(1.0)
        ex.shutdown()
    finally:
        rclpy.shutdown(context=ctx)
    imu_sent = sum(m.topic == "/imu0" for m in rest)
    assert sent == len(rest)
    assert len(got["imu"]) >= 0.95 * imu_sent
    assert len(got["img"]) >= 0.8 * sum(m.topic == "/cam0/image_raw" for m in rest)
    img = got["img"][0]
    assert (img.width, img.height, img.encoding) == (752, 480, "mono8")
    assert np.frombuffer(bytes(img.data), np.uint8).size == 752 * 480


def test_replay_waits_for_a_subscriber_started_late(seq, capsys):
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import qos_profile_sensor_data
    from sensor_msgs.msg import Image

    os.environ.setdefault("ROS_DOMAIN_ID", str(random.randint(100, 200)))
    msgs = list(replay_stream(ReplayOptions(seq.asl_dir, ["/cam0/image_raw", "/imu0"], duration=0.5)))
    first = next(m for m in msgs if m.topic == "/cam0/image_raw")
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    got: list = []
    sent: list[int] = []
    ex = SingleThreadedExecutor(context=ctx)
    try:
        pub = rclpy.create_node("late_source", context=ctx)
        worker = threading.Thread(
            target=lambda: sent.append(
                publish_stream(pub, msgs, rate=1.0, clock=False, progress=True, total_s=0.5,
                               wait_subscribers=1, wait_timeout=30.0)
            )
        )
        worker.start()
        time.sleep(1.5)  # the tracker starts well after the replay
        assert not sent, "published before anyone subscribed"
        sub = rclpy.create_node("late_sink", context=ctx)
        sub.create_subscription(Image, "/cam0/image_raw", got.append, qos_profile_sensor_data)
        ex.add_node(sub)
        spin = threading.Thread(target=ex.spin, daemon=True)
        spin.start()
        worker.join(30)
        time.sleep(0.5)
    finally:
        ex.shutdown()
        rclpy.shutdown(context=ctx)
    assert sent == [len(msgs)]
    stamps = [m.header.stamp.sec * 1_000_000_000 + m.header.stamp.nanosec for m in got]
    assert stamps and stamps[0] == first.stamp_ns  # frame 0 reached the late subscriber
    bar = capsys.readouterr().err
    assert "0.4/0.5 s" in bar and not re.search(r"\d\.\d{4,}", bar), bar[-300:]


def test_replay_gives_up_waiting_after_the_timeout(seq):
    import rclpy

    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    try:
        node = rclpy.create_node("lonely_source", context=ctx)
        msgs = list(replay_stream(ReplayOptions(seq.asl_dir, ["/imu0"], duration=0.1)))
        t0 = time.monotonic()
        sent = publish_stream(node, msgs, rate=0, clock=False, progress=False, wait_subscribers=1,
                              wait_timeout=0.5)
        waited = time.monotonic() - t0
    finally:
        rclpy.shutdown(context=ctx)
    assert sent == len(msgs)
    assert 0.5 <= waited < 5.0


def test_cli_remaps_repeat_and_the_old_form_still_works(seq, tmp_path, capsys):
    from rosbags.highlevel import AnyReader

    def topics(bag):
        with AnyReader([bag]) as reader:
            return sorted(c.topic for c in reader.connections)

    new = ["--remap", "/cam0/image_raw:=/left", "--remap", "/imu0:=/imu"]
    assert replay_main([str(seq.asl_dir), *new, "--write-bag", str(tmp_path / "a")]) == 0
    assert "deprecated" not in capsys.readouterr().err
    assert topics(tmp_path / "a") == ["/imu", "/left"]
    old = ["--remap", "/cam0/image_raw:=/left", "/imu0:=/imu"]
    assert replay_main([str(seq.asl_dir), *old, "--write-bag", str(tmp_path / "b")]) == 0
    assert "repeat --remap FROM:=TO" in capsys.readouterr().err
    assert topics(tmp_path / "b") == ["/imu", "/left"]


def test_console_replay_applies_ros_args_remaps_and_waits(seq):
    import subprocess
    import sys
    from pathlib import Path

    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import Image

    env = dict(os.environ, ROS_DOMAIN_ID=str(random.randint(100, 200)))
    exe = Path(sys.executable).parent / "nsflow-replay"
    cmd = [str(exe), str(seq.asl_dir), "--topics", "/cam0/image_raw", "--duration", "0.3", "--rate", "0",
           "--no-progress", "--wait-timeout", "60", "--ros-args", "-r", "/cam0/image_raw:=/left"]
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    os.environ["ROS_DOMAIN_ID"] = env["ROS_DOMAIN_ID"]
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    got: list = []
    ex = SingleThreadedExecutor(context=ctx)
    try:
        sub = rclpy.create_node("remap_sink", context=ctx)
        # best effort like the tracker, with room for the whole burst (rate 0 sends all 6 at once)
        qos = QoSProfile(depth=20, reliability=ReliabilityPolicy.BEST_EFFORT)
        sub.create_subscription(Image, "/left", got.append, qos)
        ex.add_node(sub)
        spin = threading.Thread(target=ex.spin, daemon=True)
        spin.start()
        _, err = proc.communicate(timeout=120)
        time.sleep(0.3)
    finally:
        if proc.poll() is None:
            proc.kill()
        ex.shutdown()
        rclpy.shutdown(context=ctx)
    assert proc.returncode == 0, err
    stamps = [m.header.stamp.sec * 1_000_000_000 + m.header.stamp.nanosec for m in got]
    assert stamps == [int(s) for s in seq.stamps_ns[:6]]  # from frame 0, on the remapped topic


def test_cli_dark_perturbation_from_the_registry(seq, tmp_path, capsys):
    from nsflow_ros.data.perturb import make_perturber
    from nsflow_ros.data.sources import SensorSource

    out = tmp_path / "dark"
    args = [str(seq.asl_dir), "--topics", "/cam0/image_raw", "--perturb", "dark", "--seed", "4"]
    assert replay_main([*args, "--write-bag", str(out)]) == 0
    dark = make_perturber("dark", 4)
    plain = list(SensorSource(seq.asl_dir, topics=["/cam0/image_raw"]).records())
    written = list(SensorSource(out).records())
    assert len(written) == len(plain) > 0
    for a, b in zip(plain, written, strict=True):
        assert np.array_equal(b.image, dark(a.image, a.stamp_ns * 1e-9))
    with pytest.raises(SystemExit):
        replay_main([str(seq.asl_dir), "--perturb", "night"])
    assert re.search(r"invalid choice: 'night' \(choose from '?none'?, '?small'?, '?large'?, '?dark'?\)",
                     capsys.readouterr().err)


def test_a_truncated_bag_is_published_up_to_the_cut_and_says_where_it_ends(seq, tmp_path):
    import shutil

    import rclpy

    from nsflow_ros.data.errors import DataError

    cut = tmp_path / "cut"
    cut.mkdir()
    shutil.copy(seq.ros2_dir / "metadata.yaml", cut / "metadata.yaml")
    (mcap,) = seq.ros2_dir.glob("*.mcap")
    data = mcap.read_bytes()
    (cut / mcap.name).write_bytes(data[: int(len(data) * 0.55)])  # cut within the first second
    readable = []
    with pytest.raises(DataError):
        readable.extend(replay_stream(ReplayOptions(cut)))
    assert readable
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    try:
        node = rclpy.create_node("cut_source", context=ctx)
        # the wait for a subscriber reads ahead: what it read before the cut is still published
        with pytest.raises(DataError, match=rf"truncated.* \(the {len(readable)} messages before it were "
                                            "published\\)"):
            publish_stream(node, replay_stream(ReplayOptions(cut)), rate=0, clock=False, progress=False,
                           wait_subscribers=1, wait_timeout=0.1)
    finally:
        rclpy.shutdown(context=ctx)
