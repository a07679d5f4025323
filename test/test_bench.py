"""Smoke tests of the benchmark command (figures are measured, never asserted against targets)."""

from __future__ import annotations

import json

from onnx_models import conv_encoder

from nsflow_ros.bench import main, run_benchmark


def test_benchmark_measures_every_stage_beside_opencv(tmp_path):
    model = conv_encoder(tmp_path / "m.onnx", c_in=1, d=2)
    res = run_benchmark(frames=4, points=40, model=str(model), threads=1)
    for mode in ("nsflow", "classical"):
        for stage in ("encoder", "solver", "detection", "total"):
            fig = res[mode][stage]
            assert 0 < fig["median_ms"] <= fig["p90_ms"]
    assert res["opencv_klt"]["klt"]["median_ms"] > 0
    assert res["classical"]["tracked_share"] > 0.5
    assert set(res["ratios"]) == {
        "classical_solver_vs_klt",
        "nsflow_solver_vs_klt",
        "nsflow_total_vs_klt_total",
    }


def test_cli_json_and_errors(tmp_path, capsys):
    model = conv_encoder(tmp_path / "m.onnx", c_in=1, d=1)
    assert main(["--frames", "3", "--points", "20", "--model", str(model), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["setup"]["descriptor_channels"] == 1
    assert main(["--model", str(tmp_path / "missing.onnx"), "--frames", "2"]) == 1
    assert "missing.onnx" in capsys.readouterr().err
