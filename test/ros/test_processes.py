"""The ROS tools as processes: --help, one-line start-up errors, clean exit 0 on SIGINT and SIGTERM."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
import uuid
from pathlib import Path

import pytest

from nsflow_ros.ros.tracker_node import main as tracker_main
from nsflow_ros.ros.tracker_params import PARAMETERS

NOISE = ("Traceback", "Failed to publish", "context is invalid", "RCLError")


def _env() -> dict[str, str]:
    return dict(os.environ, ROS_DOMAIN_ID=str(150 + os.getpid() % 50), PYTHONUNBUFFERED="1")


def _tracker(*ros_args: str) -> list[str]:
    return [sys.executable, "-m", "nsflow_ros.ros.tracker_node", *ros_args]


def _start_and_stop(
    cmd: list[str], ready: str, sig: int, tmp_path: Path, timeout: float = 60.0, settle: float = 0.0
):
    """Start a process, wait for ``ready`` in its output (then ``settle`` s), send ``sig``.

    Returns:
        (exit code, seconds from the signal to the exit, the output).
    """
    log = tmp_path / f"log_{uuid.uuid4().hex[:6]}.txt"
    with log.open("wb") as out:
        proc = subprocess.Popen(cmd, stdout=out, stderr=subprocess.STDOUT, env=_env())
    try:
        end = time.monotonic() + timeout
        while ready not in log.read_text(errors="replace"):
            assert proc.poll() is None, f"exited early:\n{log.read_text()}"
            assert time.monotonic() < end, f"never ready:\n{log.read_text()}"
            time.sleep(0.05)
        time.sleep(settle)
        assert proc.poll() is None, f"exited early:\n{log.read_text()}"
        t0 = time.monotonic()
        proc.send_signal(sig)
        code = proc.wait(15)
        return code, time.monotonic() - t0, log.read_text(errors="replace")
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def test_help_prints_usage_and_creates_no_node(capsys):
    for prog, flag in (("nsflow-tracker", "--help"), ("/opt/ros/lib/nsflow_ros/tracker", "-h")):
        assert tracker_main([prog, flag]) == 0
        out = capsys.readouterr().out
        for p in PARAMETERS:
            assert f"  {p.name} (" in out
    assert out.startswith("usage: ros2 run nsflow_ros tracker")
    assert tracker_main(["nsflow-tracker", "--bogus"]) == 2
    assert "unrecognized arguments: --bogus" in capsys.readouterr().err


def test_help_from_the_command_line():
    out = subprocess.run(_tracker("--help"), capture_output=True, text=True, env=_env(), timeout=60)
    assert out.returncode == 0 and "usage: " in out.stdout
    assert "F_threshold (number, px, default -1.0)" in out.stdout
    assert out.stderr == ""


@pytest.mark.parametrize(
    ("args", "expected"),
    [
        (["-p", "max_cnt:=abc"], "parameter max_cnt: got 'abc' (string), expected an integer"),
        (["-p", "use_imu_prediction:=2"], "use_imu_prediction: got 2 (integer), expected a boolean"),
        (["--params-file", "/missing.yaml"], "--params-file /missing.yaml: does not exist"),
        (["-p", "max_cnt"], "-p max_cnt: expected NAME:=VALUE"),
        (["--params-file", "BAD_YAML"], "bad.yaml: not valid YAML at line 3"),
        (["--params-file", "NOT_PARAMS"], "expected 'node_name: {ros__parameters: {...}}' entries"),
    ],
)
def test_type_slips_are_one_line_errors(args, expected, tmp_path):
    (tmp_path / "bad.yaml").write_text("a:\n  b: [1,\n")
    (tmp_path / "plain.yaml").write_text("max_cnt: 3\n")
    names = {"BAD_YAML": str(tmp_path / "bad.yaml"), "NOT_PARAMS": str(tmp_path / "plain.yaml")}
    args = [names.get(a, a) for a in args]
    cmd = _tracker("--ros-args", "-p", "method:=klt", *args)
    out = subprocess.run(cmd, capture_output=True, text=True, env=_env(), timeout=60)
    assert out.returncode == 1
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1 and expected in lines[0], out.stderr


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_tracker_stops_cleanly_and_names_resolved_topics(tmp_path, sig):
    prefix = f"/t{uuid.uuid4().hex[:8]}"
    cmd = _tracker(
        "--ros-args", "-p", "method:=klt", "-p", "F_threshold:=1",  # an integer for a number is fine
        "-r", f"/cam0/image_raw:={prefix}/left", "-p", f"summary_file:={tmp_path / 's.json'}",
    )
    code, seconds, log = _start_and_stop(cmd, "features on", sig, tmp_path)
    assert code == 0, log
    assert seconds < 3.0
    assert f"images on {prefix}/left;" in log  # the topic after remapping
    assert "shutting down: no images received" in log
    assert not any(n in log for n in NOISE), log
    assert (tmp_path / "s.json").is_file()


@pytest.mark.slow
def test_replay_and_demo_stop_cleanly(tmp_path):
    from nsflow_ros.data.sample import make_sample_sequence

    seq = make_sample_sequence(tmp_path / "seq", seed=3, duration=2.0, stereo=False, formats=("ros2",),
                               progress=False)
    replay = [sys.executable, "-m", "nsflow_ros.ros.replay_node", str(seq.ros2_dir), "--no-progress",
              "--rate", "0.2", "--wait-subscribers", "0"]
    # it prints nothing while it publishes: give it time to start before the signal
    code, seconds, log = _start_and_stop(replay, "", signal.SIGTERM, tmp_path, settle=3.0)
    assert code == 0 and seconds < 3 and not any(n in log for n in NOISE), log
    assert "replay stopped" in log
    demo = [sys.executable, "-m", "nsflow_ros.demo", "--out", str(tmp_path / "demo"), "--duration", "1"]
    code, seconds, log = _start_and_stop(demo, "replaying over ROS 2", signal.SIGINT, tmp_path, timeout=120)
    assert code == 0 and seconds < 15 and not any(n in log for n in NOISE), log
