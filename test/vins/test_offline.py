"""Offline tracking of a recorded source: features, contact sheet and summary, and a damaged bag."""

from __future__ import annotations

import json

import pytest

from nsflow_ros.data.replay import ReplayOptions
from nsflow_ros.data.sample import make_sample_sequence
from nsflow_ros.errors import NSFlowError
from nsflow_ros.vins.offline import run_offline


@pytest.fixture(scope="module")
def seq(tmp_path_factory):
    # one sequence for the replay tests of data/, ros/ and vins/: make_sample_sequence reuses it
    root = tmp_path_factory.getbasetemp() / "replay_seq"
    return make_sample_sequence(
        root, seed=3, duration=1.0, stereo=False, formats=("asl", "ros2"), progress=False
    )


def test_offline_run_writes_features_sheet_and_summary(seq, tmp_path):
    summary = run_offline(ReplayOptions(seq.asl_dir), tmp_path, method="classical", progress=False)
    f = summary.figures
    assert f["frames"] == len(seq)
    assert f["features_per_frame"] > 50
    assert f["error_count"] > 100 and f["error_median_px"] < 0.3
    rows = (tmp_path / "features.csv").read_text().splitlines()
    assert rows[0].startswith("stamp_ns,camera_id,feature_id,u,v")
    assert len(rows) - 1 == round(f["features_per_frame"] * f["frames"])
    assert (tmp_path / "tracks.png").stat().st_size > 10_000
    assert json.loads((tmp_path / "summary.json").read_text())["figures"]["frames"] == len(seq)
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no partial files left


def test_truncated_bag_keeps_what_was_processed(seq, tmp_path):
    import shutil

    bag = tmp_path / "bag"
    shutil.copytree(seq.ros2_dir, bag)
    mcap = next(bag.glob("*.mcap"))
    data = mcap.read_bytes()
    mcap.write_bytes(data[: len(data) // 2])
    with pytest.raises(NSFlowError, match=r"frames before it were processed"):
        run_offline(ReplayOptions(bag), tmp_path / "out", method="classical", progress=False)
    rows = (tmp_path / "out" / "features.csv").read_text().splitlines()
    assert len(rows) > 1


def test_cli_offline_run_takes_a_static_mask(seq, tmp_path, capsys):
    import cv2
    import numpy as np

    from nsflow_ros.ros.replay_node import main as replay_main

    top = np.zeros((480, 752), np.uint8)
    top[240:] = 255  # OpenVINS convention: the bottom half is masked out
    cv2.imwrite(str(tmp_path / "top.png"), top)
    args = [str(seq.asl_dir), "--offline", str(tmp_path / "out"), "--method", "klt", "--no-progress",
            "--duration", "0.3", "--mask0", str(tmp_path / "top.png"), "--mask-convention", "openvins"]
    assert replay_main(args) == 0
    rows = np.loadtxt(tmp_path / "out" / "features.csv", delimiter=",", skiprows=1)
    assert len(rows) > 50 and np.all(np.rint(rows[:, 4]) < 240)
    with pytest.raises(SystemExit):  # publishing over ROS: masks are the tracker's
        replay_main([str(seq.asl_dir), "--mask0", str(tmp_path / "top.png")])
    assert "--mask0 / --mask1 apply to --offline / --features-bag" in capsys.readouterr().err


def test_cli_offline_run_fails_in_one_line_when_nothing_was_tracked(seq, tmp_path, capsys):
    import shutil

    import cv2
    import numpy as np

    from nsflow_ros.ros.replay_node import main as replay_main

    asl = tmp_path / "white"
    shutil.copytree(seq.asl_dir, asl)
    for png in asl.glob("mav0/cam0/data/*.png"):
        cv2.imwrite(str(png), np.full((480, 752), 255, np.uint8))
    args = [str(asl), "--offline", str(tmp_path / "out"), "--method", "klt", "--no-progress",
            "--duration", "0.3"]
    assert replay_main(args) == 1
    std = capsys.readouterr()
    assert "0.0 features/frame" in std.out and "tracking LOST: images uniform" in std.out
    (line,) = std.err.strip().splitlines()
    assert line.startswith("nsflow-replay: no feature was tracked in ") and ": images uniform (" in line
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert summary["tracking_state"] == "LOST" and summary["tracking_cause"].startswith("images uniform")
