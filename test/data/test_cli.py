"""nsflow-make-sample: exit codes and messages."""

from __future__ import annotations

import pytest

from nsflow_ros.data.cli import main
from nsflow_ros.data.sample import SampleSequence


def test_makes_then_reuses_a_sample(tmp_path, capsys):
    out = tmp_path / "seq"
    args = ["--out", str(out), "--seed", "4", "--duration", "0.1", "--mono", "--formats", "asl,ros1",
            "--no-progress"]
    assert main(args) == 0
    text = capsys.readouterr().out
    assert "2 frames x 1 camera(s), formats asl, ros1" in text and str(out / "sample.bag") in text
    seq = SampleSequence.load(out)
    assert seq.params["seed"] == 4 and seq.formats == ("asl", "ros1") and len(seq.cameras) == 1
    assert main(args) == 0
    assert main([*args, "--rest", "1.5"]) == 0
    assert SampleSequence.load(out).trajectory.rest == 1.5


def test_known_errors_exit_1_with_a_message(tmp_path, capsys):
    (tmp_path / "keep.txt").write_text("x")
    assert main(["--out", str(tmp_path), "--duration", "0.1", "--no-progress"]) == 1
    err = capsys.readouterr().err
    assert err.startswith("nsflow-make-sample: error: ") and str(tmp_path) in err
    assert main(["--out", str(tmp_path / "y"), "--duration", "0.001", "--no-progress"]) == 1
    assert "gives no frame" in capsys.readouterr().err


def test_bad_arguments_exit_2(tmp_path, capsys):
    with pytest.raises(SystemExit) as info:
        main(["--out", str(tmp_path / "z"), "--formats", "asl,tiff"])
    assert info.value.code == 2
    assert "subset of asl,ros2,ros1" in capsys.readouterr().err
    with pytest.raises(SystemExit) as info:
        main(["--out", str(tmp_path / "z"), "--rest", "-1"])
    assert info.value.code == 2
