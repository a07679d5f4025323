"""The live node benchmark: a stereo sample replayed at camera rate into a real tracker process."""

from __future__ import annotations

import numpy as np
import pytest

from nsflow_ros.errors import NSFlowError
from nsflow_ros.ros.bench_live import format_live_table, merge_rounds, run_live_benchmark


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


def test_rounds_alternate_and_their_latencies_are_pooled(sample_dir):
    res = run_live_benchmark(1.0, ["klt"], cache_dir=sample_dir, rounds=2)
    fig = res["klt"]
    assert res["setup"]["rounds"] == 2 and fig["rounds"] == 2
    assert fig["frames_sent"] == 40 and fig["tracker_received"] == 40 and fig["tracker_processed"] >= 36
    assert len(fig["round_latency_ms_p90"]) == 2 and "tracker_latencies_ms" not in fig
    lo, hi = min(fig["round_latency_ms_p90"]), max(fig["round_latency_ms_p90"])
    # The pooled samples' p90 lies between the rounds' own, up to the interpolation between neighbouring
    # samples (numpy's linear percentile: a few microseconds here).
    slack = 0.05 * hi
    assert lo - slack <= fig["tracker_latency_ms_p90"] <= hi + slack


def test_rounds_alternate_the_methods(sample_dir, monkeypatch):
    import nsflow_ros.ros.live as live

    order = []

    def fake_run_live(ctx, seq, config, method, log, **kwargs):
        order.append(method)
        return _round([1.0 + len(order)], 1, 1.0), None

    monkeypatch.setattr(live, "run_live", fake_run_live)
    res = run_live_benchmark(1.0, ["nsflow", "klt"], cache_dir=sample_dir, rounds=3)
    assert order == ["nsflow", "klt"] * 3
    assert res["nsflow"]["round_latency_ms_p90"] == [2.0, 4.0, 6.0] and res["klt"]["frames_sent"] == 15


def _round(lat, processed, cpu, share=None):
    f = {"frames_sent": 5, "frames": processed, "tracker_received": 5, "tracker_processed": processed,
         "tracker_unchecked": 0, "tracker_dropped": 5 - processed, "tracker_superseded": 0,
         "tracker_latency_ms_p50": float(np.percentile(lat, 50)), "tracker_latency_ms_p90":
         float(np.percentile(lat, 90)), "tracker_cpu_ms_per_frame": cpu, "tracker_latencies_ms": lat}
    if share is not None:
        f["agreement"] = {"frames": 5, "same_share": share}
    return f


def test_merge_rounds_sums_counts_and_pools_latencies():
    a, b = [10.0, 11.0, 12.0, 13.0, 14.0], [20.0, 30.0, 40.0]
    out = merge_rounds([_round(a, 5, 10.0, 1.0), _round(b, 3, 20.0, 0.5)])
    assert out["frames_sent"] == 10 and out["tracker_processed"] == 8 and out["tracker_dropped"] == 2
    assert out["tracker_latency_ms_p90"] == pytest.approx(np.percentile(a + b, 90))
    assert out["tracker_latency_ms_p50"] == pytest.approx(np.percentile(a + b, 50))
    assert out["tracker_cpu_ms_per_frame"] == pytest.approx((5 * 10.0 + 3 * 20.0) / 8)
    assert out["round_latency_ms_p90"] == pytest.approx([np.percentile(a, 90), np.percentile(b, 90)])
    assert out["agreement"]["same_share"] == pytest.approx(0.75) and "tracker_latencies_ms" not in out
    # one round is that round's figures
    assert merge_rounds([_round(a, 5, 10.0)])["tracker_latency_ms_p90"] == pytest.approx(np.percentile(a, 90))
    # a round whose node wrote no latencies keeps its own percentiles out of the pool, not its counts
    bare = _round(b, 3, 20.0)
    bare["tracker_latencies_ms"] = None
    assert merge_rounds([_round(a, 5, 10.0), bare])["tracker_latency_ms_p90"] == pytest.approx(
        np.percentile(a, 90))
    with pytest.raises(NSFlowError, match="no node runs"):
        merge_rounds([])


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
    with pytest.raises(NSFlowError, match="rounds must be >= 1, got 0"):
        run_live_benchmark(1.0, ["klt"], rounds=0)
    with pytest.raises(NSFlowError, match="compress takes none, jpeg and png, got webp"):
        run_live_benchmark(1.0, ["klt"], compress=("webp",))
    with pytest.raises(NSFlowError, match="background load must be between 0 and 64 cores, got -1"):
        run_live_benchmark(1.0, ["klt"], background_load=-1)
