"""The live node benchmark: a stereo sample replayed at camera rate into a real tracker process."""

from __future__ import annotations

import pytest

from nsflow_ros.errors import NSFlowError
from nsflow_ros.ros.bench_live import format_live_table, run_live_benchmark


@pytest.fixture(scope="module")
def sample_dir(tmp_path_factory):
    """One rendered sample for the module's node runs (rendering costs more than a 1 s run)."""
    return tmp_path_factory.mktemp("live_sample")


def test_klt_node_keeps_up_with_a_short_stereo_replay(sample_dir):
    # with a light background load and the node's queue of one passed through
    res = run_live_benchmark(
        1.0, ["klt"], cache_dir=sample_dir, background_load=0.3, params={"queue_size": 1}
    )
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


def test_png_compressed_node_run_reproduces_the_raw_features(sample_dir):
    res = run_live_benchmark(1.0, ["klt"], cache_dir=sample_dir, compress=("none", "png"))
    raw, png = res["klt"], res["klt/png"]
    assert png["frames_sent"] == 20 and png["tracker_processed"] >= 18
    agree = png["agreement"]
    assert agree["frames"] >= 18
    # no frame dropped and none tracked late (without its checks): the same tracks, over the frames both
    # recorders heard (a recorder may join after the first messages)
    same_frames = raw["tracker_processed"] == png["tracker_processed"] == 20
    if same_frames and raw["tracker_unchecked"] == png["tracker_unchecked"] == 0:
        assert agree["identical_frames"] == agree["frames"]
        assert agree["same_share"] == 1.0 and agree["median_px"] == 0.0
    else:  # a dropped or late frame starts other tracks, but the frames before it agree
        assert agree["same_share"] > 0.5
    assert raw["tracker_processed"] >= 18
    assert "klt/png" in format_live_table(res) and "same feat" in format_live_table(res)


def test_feature_agreement_matches_by_position():
    import numpy as np

    from nsflow_ros.ros.bench_live import feature_agreement

    a = {1: {0: np.array([10.0, 10.0]), 1: np.array([50.0, 20.0])}, 2: {0: np.array([1.0, 1.0])}}
    b = {1: {7: np.array([50.0, 20.0]), 8: np.array([10.05, 10.0])}, 3: {0: np.array([1.0, 1.0])}}
    out = feature_agreement(a, b)
    assert out["frames"] == 1 and out["identical_frames"] == 0
    assert out["same_share"] == 1.0 and abs(out["median_px"] - 0.025) < 1e-9
    assert feature_agreement(a, a)["identical_frames"] == 2


def test_bad_arguments_are_errors():
    with pytest.raises(NSFlowError, match="must be > 0"):
        run_live_benchmark(0.0, ["klt"])
    with pytest.raises(NSFlowError, match="compress takes none, jpeg and png, got webp"):
        run_live_benchmark(1.0, ["klt"], compress=("webp",))
    with pytest.raises(NSFlowError, match="background load must be between 0 and 64 cores, got -1"):
        run_live_benchmark(1.0, ["klt"], background_load=-1)
