"""The live node benchmark: a stereo sample replayed at camera rate into a real tracker process."""

from __future__ import annotations

import pytest

from nsflow_ros.errors import NSFlowError
from nsflow_ros.ros.bench_live import format_live_table, run_live_benchmark


def test_klt_node_keeps_up_with_a_short_stereo_replay(tmp_path):
    # with a light background load and the node's queue of one passed through
    res = run_live_benchmark(1.0, ["klt"], cache_dir=tmp_path, background_load=0.3, params={"queue_size": 1})
    assert res["setup"]["background_load_cores"] == 0.3 and res["setup"]["params"] == {"queue_size": 1}
    fig = res["klt"]
    assert fig["frames_sent"] == 20
    # every pair reached the node (the shipped transport holds two 752x480 images) and was tracked
    assert fig["tracker_received"] == 20
    assert fig["tracker_processed"] + fig["tracker_dropped"] == fig["tracker_received"]
    assert fig["tracker_processed"] >= 18 and fig["frames"] >= 18
    assert 0 < fig["tracker_latency_ms_p50"] <= fig["tracker_latency_ms_p90"]
    # what the node gave up is counted, and its CPU time per tracked pair is reported
    assert 0 <= fig["tracker_superseded"] <= fig["tracker_dropped"]
    assert fig["tracker_cpu_ms_per_frame"] > 0
    table = format_live_table(res)
    assert "klt" in table and "lat p90 ms" in table and "CPU ms/fr" in table
    assert "background load 0.3 core, queue_size 1" in table


def test_bad_arguments_are_errors():
    with pytest.raises(NSFlowError, match="must be > 0"):
        run_live_benchmark(0.0, ["klt"])
    with pytest.raises(NSFlowError, match="background load must be between 0 and 64 cores, got -1"):
        run_live_benchmark(1.0, ["klt"], background_load=-1)
