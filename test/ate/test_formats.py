"""Reading, writing and detecting EuRoC, TUM and VINS trajectory files."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from nsflow_ros.ate import (
    FORMATS,
    ATEError,
    detect_format,
    read_trajectory,
    resolve_trajectory_path,
    write_trajectory,
)

EUROC_HEAD = (
    "#timestamp, p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], q_RS_w [], q_RS_x [], q_RS_y [], q_RS_z [], "
    "v_RS_R_x [m s^-1], v_RS_R_y [m s^-1], v_RS_R_z [m s^-1], b_w_RS_S_x [rad s^-1], b_w_RS_S_y [rad s^-1], "
    "b_w_RS_S_z [rad s^-1], b_a_RS_S_x [m s^-2], b_a_RS_S_y [m s^-2], b_a_RS_S_z [m s^-2]\n"
)


def _write(path: Path, text: str) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
    return path


def test_read_euroc_ground_truth_as_published(tmp_path):
    path = _write(
        tmp_path / "data.csv",
        EUROC_HEAD + "1403636580838555648,4.688319,-1.786938,0.783338,0.534108,-0.153029,-0.827383,-0.082152,"
        "-0.027876,0.033207,0.800006,-0.003172,0.021267,0.078502,-0.025266,0.136696,0.075593\n"
        "1403636580843555584,4.688177,-1.786770,0.787350,0.534640,-0.152990,-0.826976,-0.082863,"
        "-0.029272,0.033992,0.804870,-0.003172,0.021267,0.078502,-0.025266,0.136696,0.075593\n",
    )
    assert detect_format(path) == "euroc"
    traj = read_trajectory(path)
    assert len(traj) == 2
    assert traj.stamps[0] == 1403636580838555648 / 1e9
    assert traj.stamps[1] - traj.stamps[0] == pytest.approx(0.005, abs=1e-6)
    np.testing.assert_allclose(traj.positions[0], [4.688319, -1.786938, 0.783338])
    q = np.array([0.534108, -0.153029, -0.827383, -0.082152])
    np.testing.assert_allclose(traj.quaternions[0], q / np.linalg.norm(q))
    assert traj.name == str(path)


def test_read_vins_fusion_vio_csv(tmp_path):
    path = _write(
        tmp_path / "vio.csv",
        "1403636624013555456,0.000000,0.000000,0.000000,1.000000,0.000000,0.000000,0.000000,0.0,0.0,0.0,\n"
        "1403636624063555584,0.01234,-0.00123,0.00456,0.99998,0.00123,-0.00456,0.00012,0.01,0.02,0.03,\n",
    )
    assert detect_format(path) == "vins"
    traj = read_trajectory(path)
    assert traj.stamps[1] == pytest.approx(1403636624.063555584)
    np.testing.assert_allclose(traj.positions[1], [0.01234, -0.00123, 0.00456])


def test_read_vins_mono_and_loop_files(tmp_path):
    # vio_loop.csv has only the pose columns; VINS-Mono writes the same rows as VINS-Fusion.
    loop = _write(tmp_path / "vio_loop.csv", "1000000000,1,2,3,1,0,0,0,\n2000000000,1,2,4,1,0,0,0,\n")
    assert detect_format(loop) == "vins"
    assert read_trajectory(loop).stamps.tolist() == [1.0, 2.0]
    _write(tmp_path / "run" / "vins_result_no_loop.csv", "5000000000,1,2,3,0,0,0,1,0,0,0,\n")
    assert read_trajectory(tmp_path / "run").positions.tolist() == [[1.0, 2.0, 3.0]]


def test_read_tum_with_comments(tmp_path):
    text = "# timestamp tx ty tz qx qy qz qw\n\n1.5 1 2 3 0 0 0 1\n2.5\t1 2 3 0 0 1 0\n"
    path = _write(tmp_path / "traj.txt", text)
    assert detect_format(path) == "tum"
    traj = read_trajectory(path)
    np.testing.assert_array_equal(traj.stamps, [1.5, 2.5])
    np.testing.assert_allclose(traj.quaternions, [[1, 0, 0, 0], [0, 0, 0, 1]])


@pytest.mark.parametrize("fmt", FORMATS)
def test_write_read_round_trip(tmp_path, gt, fmt):
    path = write_trajectory(gt, tmp_path / "sub" / f"traj.{fmt}", fmt)
    assert detect_format(path) == fmt
    back = read_trajectory(path)
    np.testing.assert_allclose(back.stamps, gt.stamps, rtol=0, atol=1e-6)
    np.testing.assert_allclose(back.positions, gt.positions, atol=1e-9)
    np.testing.assert_allclose(back.quaternions, gt.quaternions, atol=1e-8)
    # A named format reads the same.
    np.testing.assert_array_equal(read_trajectory(path, fmt).positions, back.positions)


def test_euroc_writer_has_17_columns_and_vins_writer_trailing_comma(tmp_path, gt):
    lines = write_trajectory(gt, tmp_path / "gt.csv", "euroc").read_text().splitlines()
    assert lines[0].startswith("#timestamp")
    assert len(lines[1].split(",")) == 17
    assert int(lines[1].split(",")[0]) == round(gt.stamps[0] * 1e9)
    row = write_trajectory(gt, tmp_path / "vio.csv", "vins").read_text().splitlines()[0]
    assert row.endswith(",") and len(row.split(",")) == 12


def test_asl_sequence_folder_is_ground_truth(tmp_path, gt):
    write_trajectory(gt, tmp_path / "MH_01" / "mav0" / "state_groundtruth_estimate0" / "data.csv", "euroc")
    assert resolve_trajectory_path(tmp_path / "MH_01").name == "data.csv"
    assert detect_format(tmp_path / "MH_01") == "euroc"
    assert len(read_trajectory(tmp_path / "MH_01" / "mav0")) == len(gt)


def test_header_without_hash_and_detection_of_euroc_without_header(tmp_path):
    path = _write(tmp_path / "a.csv", "timestamp,x,y,z,qw,qx,qy,qz\n1000000000,1,2,3,1,0,0,0\n")
    assert detect_format(path) == "euroc"
    assert len(read_trajectory(path)) == 1
    row = "1000000000,1,2,3,1,0,0,0" + ",0" * 9 + "\n"
    assert detect_format(_write(tmp_path / "b.csv", row)) == "euroc"
    assert detect_format(_write(tmp_path / "c.csv", "1000000000,1,2,3,1,0,0,0\n")) == "vins"


@pytest.mark.parametrize(
    ("text", "match", "reason"),
    [
        ("", "empty trajectory file", "empty"),
        ("\n\n", "empty trajectory file", "empty"),
        (EUROC_HEAD, "empty trajectory file", "empty"),
        ("1000000000,1,2,3,1,0,0,0,\n2000000000,nan,2,3,1,0,0,0,\n", r"line 2: field px is nan", "nan"),
        ("1000000000,1,2,3,1,0,0,0,\n2000000000,1,2,3,1,0,0\n", r"line 2: expected at least 8", "malformed"),
        ("1000000000,1,2,3,1,0,0,0,\n2000000000,1,2,x,1,0,0,0,\n", r"line 2: field pz is not a", "malformed"),
        ("1000000000,1,2,3,1,0,,0,\n", r"line 1: expected at least 8", "malformed"),
        ("1000000000,1,2,3,0,0,0,0,\n", r"line 1: zero quaternion", "malformed"),
        ("1 2 3 4 5\n", r"line 1: cannot detect the trajectory format", "malformed"),
    ],
)
def test_read_errors_name_file_and_line(tmp_path, text, match, reason):
    path = _write(tmp_path / "bad.csv", text)
    with pytest.raises(ATEError, match=match) as info:
        read_trajectory(path)
    assert str(path) in str(info.value)
    assert info.value.reason == reason


def test_tum_row_errors(tmp_path):
    path = _write(tmp_path / "t.txt", "1 0 0 0 0 0 0 1\n2 0 0 0 0 0 1\n")
    with pytest.raises(ATEError, match=r"t.txt, line 2: expected 8 space-separated fields"):
        read_trajectory(path)
    path = _write(tmp_path / "u.txt", "1 0 0 0 0 0 0 1\n2 0 inf 0 0 0 0 1\n")
    with pytest.raises(ATEError, match=r"line 2: field y is inf"):
        read_trajectory(path, "tum")


def test_named_format_that_does_not_fit(tmp_path):
    path = _write(tmp_path / "t.txt", "1 0 0 0 0 0 0 1\n")
    with pytest.raises(ATEError, match="line 1: expected at least 8 comma-separated fields"):
        read_trajectory(path, "vins")
    with pytest.raises(ATEError, match="unknown trajectory format 'kitti'"):
        read_trajectory(path, "kitti")


def test_path_errors(tmp_path):
    with pytest.raises(ATEError, match="no such file") as info:
        read_trajectory(tmp_path / "missing.csv")
    assert info.value.reason == "missing"
    (tmp_path / "emptydir").mkdir()
    with pytest.raises(ATEError, match="emptydir: directory holds no trajectory file"):
        read_trajectory(tmp_path / "emptydir")
    _write(tmp_path / "two" / "vins_result_loop.csv", "1,0,0,0,1,0,0,0,\n")
    _write(tmp_path / "two" / "vins_result_other.csv", "1,0,0,0,1,0,0,0,\n")
    with pytest.raises(ATEError, match="several VINS result files"):
        read_trajectory(tmp_path / "two")
    (tmp_path / "bin.csv").write_bytes(b"\xff\xfe\x00\x81")
    with pytest.raises(ATEError, match="cannot parse it as a trajectory: not a text file"):
        read_trajectory(tmp_path / "bin.csv")
    # bytes that happen to be valid UTF-8 are still not a trajectory, and not an "empty" one
    (tmp_path / "nul.csv").write_bytes(b"ab\x00cd\x01\n\x02\x03\n")
    with pytest.raises(ATEError, match=r"cannot parse it as a trajectory: not a text file .*'\\x00'") as info:
        read_trajectory(tmp_path / "nul.csv")
    assert info.value.reason == "malformed"
    # only one header line may go without '#': two lines of words are a bad row, not an empty file
    _write(tmp_path / "words.txt", "hello world\nfoo bar baz\n")
    with pytest.raises(ATEError, match="line 2"):
        read_trajectory(tmp_path / "words.txt")
    with pytest.raises(ATEError, match="explicit format"):
        write_trajectory(read_trajectory(tmp_path / "two" / "vins_result_loop.csv"), tmp_path / "x", "auto")


# evo (GPL-3.0) is a test-time cross-check only: a user can check any figure of nsflow-ate with evo.
@pytest.mark.parametrize("fmt", ["tum", "euroc"])
def test_evo_reads_what_we_write(tmp_path, gt, fmt):
    from evo.tools import file_interface  # the test extra: a missing evo fails, never skips

    path = write_trajectory(gt, tmp_path / f"traj.{fmt}", fmt)
    fi = file_interface
    read = fi.read_tum_trajectory_file if fmt == "tum" else fi.read_euroc_csv_trajectory
    theirs = read(str(path))
    np.testing.assert_allclose(theirs.timestamps, gt.stamps, rtol=0, atol=1e-6)
    np.testing.assert_allclose(theirs.positions_xyz, gt.positions, atol=1e-9)
    np.testing.assert_allclose(theirs.orientations_quat_wxyz, gt.quaternions, atol=1e-8)


def test_we_read_what_evo_writes(tmp_path, gt):
    from evo.core.trajectory import PoseTrajectory3D
    from evo.tools import file_interface

    theirs = PoseTrajectory3D(gt.positions, gt.quaternions, gt.stamps)
    path = tmp_path / "evo.tum"
    file_interface.write_tum_trajectory_file(str(path), theirs)
    back = read_trajectory(path)  # the format detected, as a user runs nsflow-ate on it
    np.testing.assert_allclose(back.stamps, gt.stamps, rtol=0, atol=1e-6)
    np.testing.assert_allclose(back.positions, gt.positions, atol=1e-6)
    np.testing.assert_allclose(back.quaternions, gt.quaternions, atol=1e-6)
