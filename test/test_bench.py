"""Smoke tests of the benchmark command (figures are measured, never asserted against targets)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from onnx_models import conv_encoder

from nsflow_ros.bench import _fit_pass_costs, format_table, main, run_benchmark, solver_cost_model
from nsflow_ros.core import make_method
from nsflow_ros.core.methods import DEPLOYED_LM
from nsflow_ros.errors import NSFlowError
from nsflow_ros.evaluation.timing import make_frames


def test_benchmark_measures_every_stage_beside_opencv(tmp_path):
    model = conv_encoder(tmp_path / "m.onnx", c_in=1, d=2)
    res = run_benchmark(frames=4, points=40, model=str(model), threads=1)
    for mode in ("nsflow", "classical"):
        for stage in ("encoder", "solver", "detection", "total"):
            fig = res[mode][stage]
            assert 0 < fig["median_ms"] <= fig["p90_ms"]
    assert res["opencv_klt"]["klt"]["median_ms"] > 0
    assert res["classical"]["tracked_share"] > 0.5
    assert res["setup"]["encoder_layout"] == "whole frame" and "encoder_752x480_whole_frame" not in res
    assert set(res["solver_cost_model"]) == {"nsflow", "classical"}
    assert set(res["ratios"]) == {
        "classical_solver_vs_klt",
        "nsflow_solver_vs_klt",
        "nsflow_total_vs_klt_total",
    }


def test_a_band_layout_is_timed_beside_the_model_s_own_graph():
    res = run_benchmark(frames=2, points=20, model="default", threads=1)
    assert res["setup"]["encoder_layout"] == "bands"
    assert res["encoder_752x480_whole_frame"]["median_ms"] > 0
    assert "encoder alone 752x480, the model's own graph" in format_table(res)


def test_cli_json_and_errors(tmp_path, capsys):
    model = conv_encoder(tmp_path / "m.onnx", c_in=1, d=1)
    stages_only = ["--tracker-seconds", "0", "--node-seconds", "0"]
    assert main(["--frames", "3", "--points", "20", "--model", str(model), "--json", *stages_only]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["setup"]["descriptor_channels"] == 1
    assert out["setup"]["solver"] == DEPLOYED_LM.as_dict()  # the benchmark times what the tracker runs
    assert main(["--model", str(tmp_path / "missing.onnx"), "--frames", "2", *stages_only]) == 1
    assert "missing.onnx" in capsys.readouterr().err


def test_node_options_reach_the_node_runs_as_parameters(monkeypatch, capsys):
    import nsflow_ros.ros.bench_live as bench_live

    seen = {}

    def fake_run(seconds, methods, **kwargs):
        seen.update(kwargs["params"])
        rounds.append(kwargs["rounds"])
        return {"setup": {}}

    rounds = []

    monkeypatch.setattr(bench_live, "run_live_benchmark", fake_run)
    monkeypatch.setattr(bench_live, "format_live_table", lambda res: "")
    args = ["--tracker-seconds", "0", "--no-stages", "--node-seconds", "1", "--json"]
    extra = ["--queue-size", "2", "--late-frame-ms", "0", "--opencv-threads", "1", "--model", "fast",
             "--threads", "1"]
    assert main([*args, *extra]) == 0
    assert seen == {"queue_size": 2, "late_frame_ms": 0.0, "opencv_threads": 1, "model_path": "fast",
                    "num_threads": 1}
    seen.clear()
    assert main(args) == 0
    assert seen == {}  # the node's own defaults
    assert main([*args, "--node-rounds", "2"]) == 0
    assert rounds == [3, 3, 2]  # three alternating rounds unless told
    capsys.readouterr()


def test_cost_fit_recovers_known_prices():
    work = np.array([[10, 10], [12, 48], [20, 300], [33, 1900], [30, 1500]], np.float64)
    ms = 0.06 * work[:, 0] + 0.0017 * work[:, 1]
    a, b = _fit_pass_costs(work, ms)
    assert a == pytest.approx(0.06) and b == pytest.approx(0.0017)
    with pytest.raises(NSFlowError, match="work counts"):
        _fit_pass_costs(work[:1], ms[:1])


def test_solver_cost_model_counts_the_work_of_real_frames():
    frames = make_frames(3, (320, 240))
    method = make_method("classical")  # the deployed method, as the tracker runs it
    cfg = method.lm
    model = solver_cost_model(method, frames, points=30, repeats=1)
    # at least the starting evaluation and one LM pass per level, every pass evaluating >= 1 point
    assert cfg.levels * 2 <= model["passes"] <= cfg.levels * (cfg.max_iterations + 1)
    assert model["passes"] <= model["point_evaluations"] <= model["passes"] * 30
    assert model["measured_ms"] > 0
    assert model["modelled_ms"] == pytest.approx(model["fixed_ms"] + model["per_point_ms"])
    assert model["fixed_ms"] == pytest.approx(model["fixed_us_per_pass"] * model["passes"] / 1e3)
    with pytest.raises(NSFlowError, match="at least 2 frames"):
        solver_cost_model(method, frames[:1], points=30)
    blank = [np.zeros((240, 320, 3), np.uint8)] * 2
    with pytest.raises(NSFlowError, match="no corners"):
        solver_cost_model(method, blank, points=30)


def test_the_node_table_shows_the_rounds_and_each_method_against_the_baseline():
    from nsflow_ros.bench import bench_tables

    def run(p50, p90, rounds):
        return {"frames_sent": 1200, "tracker_received": 1200, "tracker_processed": 1200,
                "tracker_unchecked": 0, "tracker_superseded": 0, "tracker_latency_ms_p50": p50,
                "tracker_latency_ms_p90": p90, "tracker_cpu_ms_per_frame": 15.0,
                "round_latency_ms_p90": rounds}

    res = {"node_live": {"setup": {"seconds": 20, "rounds": 3, "methods": ["nsflow", "klt"],
                                   "background_load_cores": 0.7},
                         "nsflow": run(14.0, 18.0, [17.0, 18.5, 18.2]),
                         "klt": run(12.0, 15.0, [14.0, 16.0, 15.1])}}
    (t,) = bench_tables(res)
    assert t["columns"][7] == "p90 per round ms"
    assert t["rows"][0][6:8] == ["14.0 / 18.0", "17.0, 18.5, 18.2"]
    assert "3 x 20 s" in t["notes"] and "p90 over klt's: nsflow 1.20x." in t["notes"]
