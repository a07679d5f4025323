"""``nsflow-replay --offline / --features-bag`` as run_tracked runs them: checks first, then the outputs."""

from __future__ import annotations

import argparse

import pytest

from nsflow_ros.data.replay import ReplayOptions
from nsflow_ros.data.sample import make_sample_sequence
from nsflow_ros.errors import NSFlowError
from nsflow_ros.ros.replay_tracked import run_tracked


@pytest.fixture(scope="module")
def seq(tmp_path_factory):
    # the replay tests' shared sequence (test/vins/test_offline.py): make_sample_sequence reuses it
    root = tmp_path_factory.getbasetemp() / "replay_seq"
    return make_sample_sequence(
        root, seed=3, duration=1.0, stereo=False, formats=("asl", "ros2"), progress=False
    )


def _opts(**kw) -> argparse.Namespace:
    base = dict(path=None, topics=None, config=None, offline=None, features_bag=None, method="klt",
                features_bag_format=None, providers="cpu", model="", downsample=1, publish_rate=None,
                max_sigma=None, mask0=None, mask1=None, mask_convention="vins", no_progress=True)
    return argparse.Namespace(**{**base, **kw})


def test_offline_writes_its_outputs_and_exits_0(seq, tmp_path, capsys):
    opts = _opts(path=str(seq.asl_dir), offline=tmp_path / "out")
    assert run_tracked(opts, ReplayOptions(seq.asl_dir, duration=0.3), "nsflow-replay") == 0
    assert "features/frame" in capsys.readouterr().out and (tmp_path / "out" / "summary.json").exists()


def test_topics_that_leave_the_camera_out_are_refused_before_any_output(seq, tmp_path):
    opts = _opts(path=str(seq.asl_dir), offline=tmp_path / "out", topics=["/imu0"])
    with pytest.raises(NSFlowError, match=r"leaves out the camera topic\(s\) /cam0/image_raw"):
        run_tracked(opts, ReplayOptions(seq.asl_dir), "nsflow-replay")
    assert not (tmp_path / "out").exists()
