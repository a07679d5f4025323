"""The command-line tools fail politely: one line on stderr naming what is wrong, exit 1 (2 for a bad
argument, from argparse), no traceback, and no output left behind for an input that does not exist."""

from __future__ import annotations

import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import pytest

from nsflow_ros.data.sample import make_sample_sequence


@pytest.fixture(scope="module")
def seq(tmp_path_factory):
    root = tmp_path_factory.mktemp("cli_errors") / "seq"
    return make_sample_sequence(
        root, seed=2, duration=0.3, stereo=False, formats=("asl", "ros1"), progress=False
    )


def _main(name: str) -> Callable[[list[str]], int]:
    if name == "nsflow-replay":
        from nsflow_ros.ros.replay_node import main
    elif name == "nsflow-make-sample":
        from nsflow_ros.data.cli import main
    elif name == "nsflow-ate":
        from nsflow_ros.ate.cli import main
    elif name == "nsflow-demo":
        from nsflow_ros.demo import main
    else:
        from nsflow_ros.bench import main
    return main


def _run(name: str, args: list[str], capsys) -> tuple[int, list[str]]:
    try:
        code = _main(name)(args)
    except SystemExit as exc:  # argparse
        code = exc.code
    err = capsys.readouterr().err
    assert "Traceback" not in err
    return code, err.strip().splitlines()


def _not_a_dir(tmp_path: Path) -> Path:
    """A path no one can create, even root: its parent is a regular file."""
    blocker = tmp_path / "file"
    blocker.write_text("x")
    return blocker / "out"


def _random_bytes(path: Path) -> Path:
    path.write_bytes(bytes(range(256)) * 3 + b"\x00\xff\xfe" * 100)
    return path


# (tool, arguments from (sample, tmp_path), exit code, text the error line holds)
CASES = {
    "bench negative frames": ("nsflow-bench", lambda s, t: ["--frames", "-5"], 2, "argument --frames"),
    "make-sample negative rate": ("nsflow-make-sample", lambda s, t: ["--rate", "-5"], 2, "argument --rate"),
    "demo negative rate": ("nsflow-demo", lambda s, t: ["--rate", "-1", "--out", str(t / "demo")], 2,
                           "argument --rate"),
    "replay negative rate": ("nsflow-replay", lambda s, t: [str(s.asl_dir), "--rate", "-1"], 2,
                             "argument --rate"),
    "replay offline to an unwritable folder": (
        "nsflow-replay",
        lambda s, t: [str(s.asl_dir), "--offline", str(_not_a_dir(t)), "--method", "klt", "--no-progress"],
        1, "cannot create output folder",
    ),
    "replay feature bag to an unwritable folder": (
        "nsflow-replay",
        lambda s, t: [str(s.asl_dir), "--features-bag", str(_not_a_dir(t) / "f.bag"), "--method", "klt",
                      "--no-progress"],
        1, "cannot create",
    ),
    "make-sample to an unwritable folder": (
        "nsflow-make-sample", lambda s, t: ["--out", str(_not_a_dir(t)), "--duration", "0.1"], 1,
        "cannot create",
    ),
    "ate on random bytes": (
        "nsflow-ate", lambda s, t: [str(_random_bytes(t / "gt.csv")), str(_random_bytes(t / "est.csv"))], 1,
        "cannot parse it as a trajectory",
    ),
    "replay random bytes named .bag": (
        "nsflow-replay", lambda s, t: [str(_random_bytes(t / "x.bag")), "--write-bag", str(t / "o")], 1,
        "not a ROS 1 bag",
    ),
    "replay offline from random bytes named .bag": (
        "nsflow-replay",
        lambda s, t: [str(_random_bytes(t / "x.bag")), "--offline", str(t / "o"), "--no-progress"], 1,
        "not a ROS 1 bag",
    ),
    "replay topics that match nothing": (
        "nsflow-replay", lambda s, t: [str(s.ros1_path), "--topics", "/nothing", "--write-bag", str(t / "o")],
        1, "/nothing not found",
    ),
    "replay offline with topics that leave the camera out": (
        "nsflow-replay",
        lambda s, t: [str(s.asl_dir), "--topics", "/imu0", "--offline", str(t / "o"), "--no-progress"],
        1, "leaves out the camera topic(s) /cam0/image_raw",
    ),
    "replay offline from a missing path": (
        "nsflow-replay", lambda s, t: [str(t / "missing"), "--offline", str(t / "o"), "--no-progress"], 1,
        "data set not found",
    ),
    "replay feature bag from a missing path": (
        "nsflow-replay", lambda s, t: [str(t / "missing"), "--features-bag", str(t / "o.bag")], 1,
        "data set not found",
    ),
}


@pytest.mark.parametrize("case", list(CASES))
def test_known_errors_are_one_line(case, seq, tmp_path, capsys):
    tool, make_args, want_code, text = CASES[case]
    before = {p.name for p in tmp_path.iterdir()}
    code, lines = _run(tool, make_args(seq, tmp_path), capsys)
    assert code == want_code, lines
    assert lines, "no error message"
    if want_code == 1:
        assert len(lines) == 1, lines
    assert lines[-1].startswith(f"{tool}: ") and text in lines[-1], lines
    # nothing is written for a bad argument, a missing input or an unwritable output
    made = {p.name for p in tmp_path.iterdir()} - before - {"file", "gt.csv", "est.csv", "x.bag"}
    assert made == set(), made


def test_console_script_prints_no_traceback(seq, tmp_path):
    exe = Path(sys.executable).parent / "nsflow-replay"
    proc = subprocess.run(
        [str(exe), str(_random_bytes(tmp_path / "x.bag")), "--write-bag", str(tmp_path / "o")],
        capture_output=True, text=True, timeout=120,
    )
    assert proc.returncode == 1
    assert proc.stderr.strip().count("\n") == 0 and "Traceback" not in proc.stderr, proc.stderr


def test_an_asl_image_missing_from_its_folder_is_one_line_without_a_decoder_warning(seq, tmp_path, capfd):
    import shutil

    asl = tmp_path / "asl"
    shutil.copytree(seq.asl_dir, asl)
    images = sorted((asl / "mav0" / "cam0" / "data").iterdir())
    images[2].unlink()  # data.csv still names it
    from nsflow_ros.ros.replay_node import main

    code = main([str(asl), "--write-bag", str(tmp_path / "o"), "--no-progress"])
    err = capfd.readouterr().err.strip().splitlines()
    assert code == 1 and len(err) == 1, err  # OpenCV's imread would have written "can't open/read file"
    assert err[0].startswith("nsflow-replay: image ") and f"{images[2].name} named in" in err[0]
    assert err[0].endswith("cam0/data.csv does not exist")
