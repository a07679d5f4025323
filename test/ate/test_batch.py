"""Batch scoring of a directory of runs into the paper's table (Markdown, CSV), with failures."""

from __future__ import annotations

import csv
import io
from pathlib import Path

import numpy as np
import pytest

from nsflow_ros.ate import (
    ATEError,
    FailureCriteria,
    Trajectory,
    batch_csv,
    batch_markdown,
    discover_runs,
    find_ground_truth,
    runs_csv,
    score_batch,
    write_batch_tables,
    write_trajectory,
)

ASL_GT = Path("mav0/state_groundtruth_estimate0/data.csv")


def _noisy(gt: Trajectory, sigma: float, seed: int, keep: slice = slice(None)) -> Trajectory:
    rng = np.random.default_rng(seed)
    part = gt.take(np.arange(len(gt))[keep])
    pos = part.positions + rng.normal(0.0, sigma, part.positions.shape)
    return Trajectory(part.stamps, pos, part.quaternions, "est").transformed(np.eye(3), np.array([1.0, 2, 3]))


@pytest.fixture
def batch_root(tmp_path, make_traj):
    """Two sequences, three levels, two methods, up to two repetitions; some runs fail on purpose."""
    root = tmp_path / "runs"
    gts = {"MH_01": make_traj(n=300), "V1_02": make_traj(n=300, t0=1403715273.0)}
    for seq, gt in gts.items():
        write_trajectory(gt, root / seq / ASL_GT, "euroc")

    def run(seq: str, level: str, method: str, rep: str, sigma: float, seed: int, **kw) -> Path:
        path = root / seq / level / method / rep / "vio.csv"
        return write_trajectory(_noisy(gts[seq], sigma, seed, **kw), path, "vins")

    run("MH_01", "none", "vins", "0", 0.05, 1)
    run("MH_01", "none", "vins", "1", 0.07, 2)
    run("MH_01", "none", "nsflow", "0", 0.02, 3)
    run("MH_01", "none", "nsflow", "1", 0.03, 4)
    (root / "MH_01" / "large" / "vins" / "0").mkdir(parents=True)  # crashed: no vio.csv at all
    empty = root / "MH_01" / "large" / "vins" / "1" / "vio.csv"
    empty.parent.mkdir(parents=True)
    empty.write_text("")  # crashed after opening the file
    run("MH_01", "large", "nsflow", "0", 0.04, 5)
    run("MH_01", "large", "nsflow", "1", 0.04, 6)
    run("V1_02", "none", "vins", "0", 0.05, 7, keep=slice(0, 60))  # stopped early: too short
    run("V1_02", "none", "nsflow", "0", 0.02, 8)
    run("V1_02", "large", "nsflow", "0", 30.0, 9)  # diverged: RMSE far above 10 m
    nan_run = run("V1_02", "large", "vins", "0", 0.05, 10)
    lines = nan_run.read_text().splitlines()
    lines[100] = lines[100].split(",", 1)[0] + ",nan,nan,nan,1,0,0,0,0,0,0,"
    nan_run.write_text("\n".join(lines) + "\n")
    # A repetition given directly as a TUM file, at a level other than the usual three.
    write_trajectory(_noisy(gts["V1_02"], 0.02, 11), root / "V1_02" / "small" / "nsflow" / "r0.tum", "tum")
    (root / ".cache").mkdir()  # hidden folders are ignored
    return root


def test_discover_runs(batch_root):
    specs = discover_runs(batch_root)
    assert len(specs) == 13
    assert {s.sequence for s in specs} == {"MH_01", "V1_02"}
    assert all("mav0" not in (s.level, s.method) for s in specs)
    assert [s.level for s in specs if s.sequence == "V1_02"] == ["none", "none", "small", "large", "large"]
    tum = [s for s in specs if s.level == "small"]
    assert [(s.method, s.rep, s.path.name) for s in tum] == [("nsflow", "r0", "r0.tum")]
    with pytest.raises(ATEError, match="batch root is not a directory"):
        discover_runs(batch_root / "nope")


def test_score_batch_table(batch_root):
    result = score_batch(batch_root, methods=["vins", "nsflow"])
    assert result.sequences == ("MH_01", "V1_02")
    assert result.levels == ("none", "small", "large")
    assert result.methods == ("vins", "nsflow")
    by_key = {(r.spec.sequence, r.spec.level, r.spec.method, r.spec.rep): r for r in result.runs}
    assert by_key["MH_01", "large", "vins", "0"].category == "empty"
    assert by_key["MH_01", "large", "vins", "1"].category == "empty"
    assert by_key["V1_02", "none", "vins", "0"].category == "too short"
    assert "span 19.7% of the ground truth" in by_key["V1_02", "none", "vins", "0"].reason
    assert by_key["V1_02", "large", "nsflow", "0"].category == "diverged"
    assert "ATE RMSE" in by_key["V1_02", "large", "nsflow", "0"].reason
    nan_reason = by_key["V1_02", "large", "vins", "0"].reason
    assert nan_reason.startswith("diverged:") and "line 101" in nan_reason

    cell = result.cell("MH_01", "none", "vins")
    assert cell is not None and not cell.failed and len(cell.values) == 2
    expected = [by_key["MH_01", "none", "vins", r].stats.rmse for r in ("0", "1")]
    assert cell.mean == pytest.approx(np.mean(expected))
    assert cell.median == pytest.approx(np.median(expected))
    assert 0.05 < cell.mean < 0.15
    assert result.cell("MH_01", "large", "vins").failed
    assert result.cell("MH_01", "small", "vins") is None

    md = batch_markdown(result, digits=3)
    lines = md.splitlines()
    header = next(line for line in lines if line.startswith("| Seq."))
    assert header == (
        "| Seq. | none: vins | none: nsflow | small: vins | small: nsflow | large: vins | large: nsflow |"
    )
    mh = next(line for line in lines if line.startswith("| MH_01"))
    cells = [c.strip() for c in mh.strip("|").split("|")]
    assert cells[0] == "MH_01"
    assert cells[1] == f"{cell.mean:.3f}/{cell.median:.3f}"
    assert cells[2].startswith("**") and cells[3] == "-" and cells[5] == "F"
    v1 = next(line for line in lines if line.startswith("| V1_02"))
    assert [c.strip() for c in v1.strip("|").split("|")][5:] == ["F", "F"]
    assert "Failed runs:" in md and "MH_01 / large / vins / 0: empty" in md

    rows = list(csv.reader(io.StringIO(batch_csv(result))))
    assert rows[0][:3] == ["sequence", "none:vins:mean", "none:vins:median"]
    assert len(rows[0]) == 1 + 2 * 6
    assert rows[1][0] == "MH_01" and float(rows[1][1]) == pytest.approx(cell.mean, abs=1e-6)
    assert rows[1][9:11] == ["F", "F"] and rows[1][5:7] == ["", ""]

    runs = list(csv.DictReader(io.StringIO(runs_csv(result))))
    assert len(runs) == 13
    statuses = {r["status"] for r in runs}
    assert statuses == {"ok", "empty", "too short", "diverged"}
    assert all(r["rmse"] for r in runs if r["status"] == "ok")


def test_failure_policies(batch_root):
    lenient = score_batch(
        batch_root, criteria=FailureCriteria(fail_if="all", max_rmse=100.0, min_coverage=0.1)
    )
    assert not lenient.cell("V1_02", "none", "vins").failed  # 19.7% coverage is enough now
    assert not lenient.cell("V1_02", "large", "nsflow").failed  # 100 m is "not diverged" now
    assert lenient.cell("MH_01", "large", "vins").failed  # every repetition failed
    majority = score_batch(batch_root, criteria=FailureCriteria(fail_if="majority"))
    assert majority.cell("MH_01", "large", "vins").failed
    with pytest.raises(ATEError, match="fail_if must be one of"):
        FailureCriteria(fail_if="some")
    with pytest.raises(ATEError, match="min_coverage must be within"):
        FailureCriteria(min_coverage=2.0)
    with pytest.raises(ATEError, match="max_rmse must be positive"):
        FailureCriteria(max_rmse=0.0)


def test_write_tables_and_plots(batch_root, tmp_path):
    result = score_batch(batch_root, levels=["none"], methods=["nsflow"], plot_dir=tmp_path / "plots")
    assert [r.spec.level for r in result.runs] == ["none"] * 3
    pngs = sorted(p.name for p in (tmp_path / "plots").iterdir())
    assert pngs == ["MH_01_none_nsflow_0.png", "MH_01_none_nsflow_1.png", "V1_02_none_nsflow_0.png"]
    assert (tmp_path / "plots" / pngs[0]).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    files = write_batch_tables(result, tmp_path / "tables")
    assert sorted(p.name for p in files.values()) == ["ate_table.csv", "ate_table.md", "ate_table_runs.csv"]
    assert "| MH_01 |" in files["markdown"].read_text()


def test_ground_truth_lookup(tmp_path, make_traj):
    gt = make_traj(n=50)
    with pytest.raises(ATEError, match="no ground truth for sequence 'MH_01'") as info:
        find_ground_truth(tmp_path, "MH_01")
    assert "groundtruth.csv" in str(info.value) and "MH_01.txt" in str(info.value)
    write_trajectory(gt, tmp_path / "MH_01.txt", "tum")
    assert find_ground_truth(tmp_path, "MH_01").name == "MH_01.txt"
    write_trajectory(gt, tmp_path / "MH_01" / "groundtruth.csv", "euroc")
    assert find_ground_truth(tmp_path, "MH_01").name == "groundtruth.csv"


def test_separate_ground_truth_root_and_missing_ground_truth(tmp_path, make_traj):
    gt = make_traj(n=100)
    write_trajectory(gt, tmp_path / "euroc" / "MH_01" / ASL_GT, "euroc")
    write_trajectory(
        _noisy(gt, 0.01, 1), tmp_path / "runs" / "MH_01" / "none" / "m" / "0" / "vio.csv", "vins"
    )
    result = score_batch(tmp_path / "runs", gt_root=tmp_path / "euroc")
    assert [r.ok for r in result.runs] == [True]
    with pytest.raises(ATEError, match="no ground truth for sequence 'MH_01'"):
        score_batch(tmp_path / "runs")
    (tmp_path / "nothing").mkdir()
    with pytest.raises(ATEError, match="no runs found"):
        score_batch(tmp_path / "nothing")
