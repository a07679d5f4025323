"""nsflow-evaluate: a quick run writes the report, figures and JSON; known errors exit 1 with a message."""

from __future__ import annotations

import json

import numpy as np
import pytest
from onnx_models import conv_encoder

from nsflow_ros.evaluation import cli
from nsflow_ros.evaluation.context import EvalContext
from nsflow_ros.evaluation.errors import EvaluationError
from nsflow_ros.evaluation.registry import ANALYSES, Analysis, select
from nsflow_ros.evaluation.report import headline_table, machine_info, now, run_analyses, write_report
from nsflow_ros.evaluation.section import HeadlineRow, Section

MINE = "pairs,trackable,convergence,capture"


def test_quick_run_writes_report_with_headline_table_figures_and_json(tmp_path, capsys):
    out = tmp_path / "ev"
    assert cli.main(["--quick", "--out", str(out), "--only", MINE, "--no-progress"]) == 0
    report = (out / "report.md").read_text()
    methods = "NSFlow | NSFlow + OpenCV LK | LM (intensity) | OpenCV KLT | OpenCV KLT + CLAHE"
    head = f"| metric | {methods} | target | met |"
    assert head in report
    assert f"nsflow-evaluate --quick --out {out} --only {MINE} --no-progress" in report
    assert "Quick mode" in report and "onnxruntime" in report and "CPUs" in report
    for png in ("pairs_boxplot.png", "trackable_heatmap.png", "convergence.png", "capture.png"):
        assert (out / png).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
        assert f"]({png})" in report
    results = json.loads((out / "results.json").read_text())  # strict JSON: no NaN/inf literals
    assert set(results["sections"]) == {"pairs", "trackable", "convergence", "capture"}
    assert results["headline"] and not results["failures"]
    assert not list(out.glob(".*partial*"))
    assert "wrote" in capsys.readouterr().out


def test_missing_model_exits_1_naming_the_path(tmp_path, capsys):
    missing = tmp_path / "nowhere" / "enc.onnx"
    assert cli.main(["--quick", "--out", str(tmp_path / "o"), "--model", str(missing)]) == 1
    err = capsys.readouterr().err
    assert str(missing) in err and err.startswith("nsflow-evaluate:")
    assert not (tmp_path / "o" / "report.md").exists()


def test_unknown_analysis_key_exits_1(tmp_path, capsys):
    assert cli.main(["--quick", "--out", str(tmp_path), "--only", "pairs,nope"]) == 1
    assert "'nope'" in capsys.readouterr().err
    with pytest.raises(EvaluationError, match="no analysis left"):
        select(["pairs"], ["pairs"])


def test_given_model_is_used_and_named(tmp_path):
    model = conv_encoder(tmp_path / "tiny.onnx", c_in=1, d=3)
    out = tmp_path / "ev"
    args = ["--quick", "--out", str(out), "--only", "pairs", "--model", str(model), "--no-progress"]
    assert cli.main(args) == 0
    assert str(model) in (out / "report.md").read_text()


def test_a_shipped_model_by_name_and_a_method_that_cannot_take_it_left_out_and_said(tmp_path, capsys):
    out = tmp_path / "ev"
    args = ["--quick", "--out", str(out), "--only", "pairs,efficiency", "--model", "fast", "--no-progress"]
    assert cli.main(args) == 0  # the fast model's unbounded descriptors: OpenCV's LK cannot track them
    report = (out / "report.md").read_text()
    assert "nsflow_encoder_fast.onnx" in report
    assert "- left out: NSFlow + OpenCV LK: nsflow_lk quantises descriptors" in report
    assert "left out NSFlow + OpenCV LK" in capsys.readouterr().err
    results = json.loads((out / "results.json").read_text())
    assert set(results["machine"]["left_out"]) == {"NSFlow + OpenCV LK"} and not results["failures"]
    # the other methods still ran; the one left out has no values
    row = next(r for r in results["headline"] if r["section"] == "pairs")
    assert "NSFlow + OpenCV LK" not in row["values"] and row["values"]["OpenCV KLT"] != "-"


def test_a_failing_analysis_is_reported_and_the_others_still_run(tmp_path):
    def broken(ctx):
        raise EvaluationError("no data for this one")

    def fine(ctx):
        row = HeadlineRow("m", {"NSFlow": "1.0"}, "< 2", True)
        data = {"x": np.float64(np.nan), "arr": np.arange(3)}
        return Section("fine", "Fine", "body text", headline=[row], data=data)

    ctx = EvalContext(methods=[], out_dir=tmp_path, progress=False)
    result = run_analyses(ctx, [Analysis("broken", "b", broken), Analysis("fine", "f", fine)])
    assert result.failures == {"broken": "no data for this one"}
    assert [s.key for s in result.sections] == ["fine"] and set(result.seconds) == {"broken", "fine"}
    report, res = write_report(tmp_path, result, machine_info(None), "nsflow-evaluate", now())
    text = report.read_text()
    assert "## Failed analyses" in text and "no data for this one" in text and "body text" in text
    data = json.loads(res.read_text())
    assert data["sections"]["fine"]["data"] == {"x": "nan", "arr": [0, 1, 2]}


def test_headline_table_marks_missing_values_and_unmet_targets():
    s = Section("k", "t", "", headline=[
        HeadlineRow("a", {"NSFlow": "1", "OpenCV KLT": "2"}, "<= 1.2x KLT", False),
        HeadlineRow("b", {"LM (intensity)": "3"}),
    ])  # fmt: skip
    lines = headline_table([s]).splitlines()
    assert lines[2] == "| a | 1 | - | - | 2 | - | <= 1.2x KLT | **no** |"
    assert lines[3] == "| b | - | - | 3 | - | - | - | - |"
    assert headline_table([]).startswith("_No headline")


def test_registry_keys_are_unique_and_listed(capsys):
    keys = [a.key for a in ANALYSES]
    assert len(keys) == len(set(keys)) and {"pairs", "trackable", "convergence", "capture"} <= set(keys)
    assert cli.main(["--list"]) == 0
    listing = capsys.readouterr().out
    assert all(k in listing for k in keys)


def test_the_evaluation_command_imports_neither_torch_nor_rclpy():
    import subprocess
    import sys

    code = (
        "import sys, nsflow_ros.evaluation.cli, nsflow_ros.evaluation.registry; "
        "print(sorted(m for m in ('rclpy', 'torch') if m in sys.modules))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"
