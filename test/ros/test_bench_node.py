"""The node benchmark runs end to end on a few frames and reports what the core benchmark reads."""

from __future__ import annotations

from nsflow_ros.ros.bench_node import rss_mb, run_node_benchmark


def test_short_stereo_run_reports_latency_and_memory():
    out = run_node_benchmark(12, stereo=True, checkpoints=(4, 12), timeout_s=5.0)
    assert out["lost_frames"] == 0 and out["features_per_frame"] > 20
    assert 0 < out["latency_ms"]["median"] <= out["latency_ms"]["p90"] <= out["latency_ms"]["max"]
    assert out["roundtrip_ms"]["median"] >= out["latency_ms"]["median"] * 0.5
    assert set(out["rss_mb"]) == {"4", "12"} and isinstance(out["rss_growth_mb"], float)
    assert rss_mb() > 10


def test_soak_settings_run_nsflow_at_752x480_stereo_without_drops(capsys, caplog):
    from nsflow_ros.ros.bench_node import main

    assert main(["--frames", "6", "--stereo", "--method", "nsflow", "--width", "752", "--height", "480",
                 "--threads", "1", "--providers", "cuda,cpu"]) == 0
    err = capsys.readouterr().err
    line = err.strip().splitlines()[-1]
    assert line.startswith("node stereo 752x480 nsflow (encoder on CPUExecutionProvider): 6 frames, latency")
    assert "lost 0, dropped 0, unpaired 0" in line
    warned = [r.getMessage() for r in caplog.records if r.name == "nsflow_ros.core.encoder"]
    assert len(warned) == 1 and "CUDAExecutionProvider not in this onnxruntime" in warned[0]
