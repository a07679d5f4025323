"""The ate CLI, called in-process: --json output, exit codes, subcommands."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from nsflow_ros.ate import STAT_KEYS, Trajectory, write_trajectory
from nsflow_ros.ate.cli import build_parser, main


@pytest.fixture
def pair(tmp_path, gt, rot):
    """Ground truth as an ASL folder and a noisy, rigidly moved estimate as vio.csv."""
    write_trajectory(gt, tmp_path / "MH_01" / "mav0" / "state_groundtruth_estimate0" / "data.csv", "euroc")
    noise = np.random.default_rng(0).normal(0, 0.05, (len(gt), 3))
    est = Trajectory(gt.stamps, gt.positions + noise, gt.quaternions, "est")
    est = est.transformed(rot([0, 0, 1], 0.4), np.array([1.0, 0.0, 0.0]))
    vio = write_trajectory(est, tmp_path / "run" / "vio.csv", "vins")
    return tmp_path / "MH_01", vio


def test_json_has_exactly_the_statistics(pair, capsys):
    gt, vio = pair
    assert main([str(gt), str(vio), "--json"]) == 0
    obj = json.loads(capsys.readouterr().out)
    assert tuple(obj) == STAT_KEYS
    assert obj["n"] == 600 and 0.05 < obj["rmse"] < 0.12
    assert obj["min"] <= obj["median"] <= obj["max"]


def test_explicit_subcommand_formats_and_rpe(pair, capsys):
    gt, vio = pair
    args = [
        "ape",
        str(gt),
        str(vio.parent),
        "--align",
        "sim3",
        "--gt-format",
        "euroc",
        "--est-format",
        "vins",
    ]
    assert main([*args, "--rpe-delta", "10", "--json"]) == 0
    obj = json.loads(capsys.readouterr().out)
    assert set(obj) == {*STAT_KEYS, "rpe"}
    assert obj["rpe"]["delta"] == 10 and obj["rpe"]["translation"]["n"] == 59


def test_skip_scores_fewer_poses(pair, capsys):
    gt, vio = pair
    assert main([str(gt), str(vio), "--json"]) == 0
    whole = json.loads(capsys.readouterr().out)
    assert main([str(gt), str(vio), "--skip", "5", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["n"] == whole["n"] - 100  # 20 Hz
    assert main([str(gt), str(vio), "--skip", "-1"]) == 2
    assert "--skip" in capsys.readouterr().err


def test_text_output_and_plot(pair, capsys, tmp_path):
    gt, vio = pair
    png = tmp_path / "top.png"
    code = main(
        [str(gt), str(vio), "--plot", str(png), "--n-align", "50", "--rpe-delta", "5", "--rpe-all-pairs"]
    )
    assert code == 0
    out = capsys.readouterr().out
    assert "rmse" in out and "600 matched poses" in out and "RPE over 5 poses (595 all pairs)" in out
    assert png.read_bytes()[:4] == b"\x89PNG"


def _bad(tmp_path: Path, name: str, text: str) -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


@pytest.mark.parametrize(
    ("case", "message"),
    [
        ("empty", "empty trajectory file"),
        ("nan", "line 3: field py is nan"),
        ("malformed", "line 2: expected at least 8 comma-separated fields"),
        ("no_overlap", "no overlapping stamps"),
        ("two_matches", "only 2 matched poses"),
        ("missing", "no such file or directory"),
    ],
)
def test_known_errors_exit_1_with_a_message(pair, tmp_path, capsys, case, message):
    gt, vio = pair
    rows = vio.read_text().splitlines()
    texts = {
        "empty": "",
        "nan": "\n".join([*rows[:2], rows[2].split(",")[0] + ",0,nan,0,1,0,0,0,"]) + "\n",
        "malformed": rows[0] + "\n" + rows[1][:20] + "\n",
        "no_overlap": "1,0,0,0,1,0,0,0,\n2,0,0,1,1,0,0,0,\n3,1,0,0,1,0,0,0,\n",
        "two_matches": "\n".join(rows[:2]) + "\n",
    }
    est = tmp_path / "missing.csv" if case == "missing" else _bad(tmp_path, f"{case}.csv", texts[case])
    assert main([str(gt), str(est), "--json"]) == 1
    captured = capsys.readouterr()
    assert captured.out == ""
    assert captured.err.startswith("nsflow-ate: error: ") and message in captured.err
    assert str(est) in captured.err


def test_drift_subcommand(tmp_path, gt, capsys):
    keep = np.flatnonzero((gt.stamps < gt.stamps[0] + 5) | (gt.stamps > gt.stamps[-1] - 5))
    gt_file = write_trajectory(gt.take(keep), tmp_path / "gt.txt", "tum")
    est_file = write_trajectory(gt, tmp_path / "est.csv", "vins")
    assert main(["drift", str(gt_file), str(est_file), "--json"]) == 0
    obj = json.loads(capsys.readouterr().out)
    assert obj["alignment_error"] < 1e-6 and obj["n_start"] == obj["n_end"] == 100
    assert main(["drift", str(gt_file), str(est_file)]) == 0
    assert "alignment_error" in capsys.readouterr().out
    assert main(["drift", str(est_file), str(est_file)]) == 1
    assert "no gap longer than 1.0 s" in capsys.readouterr().err


def test_batch_subcommand(tmp_path, gt, capsys):
    root = tmp_path / "runs"
    write_trajectory(gt, root / "MH_01" / "groundtruth.csv", "euroc")
    write_trajectory(gt, root / "MH_01" / "none" / "nsflow" / "0" / "vio.csv", "vins")
    (root / "MH_01" / "none" / "vins" / "0").mkdir(parents=True)
    out = tmp_path / "tables"
    assert main(["batch", str(root), "--out", str(out), "--plots"]) == 0
    text = capsys.readouterr().out
    assert "| MH_01 | **0.000/0.000** | F |" in text
    assert (out / "ate_table.md").is_file() and (out / "ate_table.csv").is_file()
    assert (out / "ate_plots" / "MH_01_none_nsflow_0.png").is_file()
    assert main(["batch", str(root), "--out", str(out), "--json", "--fail-if", "all"]) == 0
    obj = json.loads(capsys.readouterr().out)
    assert [r["status"] for r in obj["runs"]] == ["ok", "empty"]
    assert main(["batch", str(tmp_path / "none")]) == 1
    assert "batch root is not a directory" in capsys.readouterr().err


def test_usage(capsys):
    assert main(["--help"]) == 0
    assert "ape" in capsys.readouterr().out
    assert main(["batch", "--help"]) == 0
    assert "ROOT/<sequence>/<level>/<method>/<rep>/vio.csv" in capsys.readouterr().out
    assert main([]) == 2
    capsys.readouterr()
    assert main(["a.csv", "b.csv", "--align", "affine"]) == 2
    assert "invalid choice: 'affine'" in capsys.readouterr().err
    assert main(["a.csv", "b.csv", "--rpe-delta", "0"]) == 2
    assert "expected an integer >= 1" in capsys.readouterr().err
    assert build_parser().prog == "nsflow-ate"
