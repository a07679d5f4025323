"""Live node benchmark: the stereo sample replayed at camera rate into ``tracker`` processes over real DDS.

Per method a ``tracker`` process runs the shipped EuRoC stereo config while this process replays the
sample's two 752x480 image topics with sensor-data QoS, as a camera driver would. The node's counters and
latency (image callback to publication, queueing and decoding included) come from its summary file; a
background load can share the cores, standing in for the estimator. With several rounds the methods' runs
alternate (A, B, A, B, ...), so a machine whose load drifts over the minutes hits every method alike, as
the whole-tracker benchmark's frame-by-frame interleaving does; their latencies are pooled.
"""

from __future__ import annotations

import os
import random
import tempfile
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from nsflow_ros.errors import NSFlowError

__all__ = ["STEREO_TOPICS", "feature_agreement", "format_live_table", "merge_rounds", "run_live_benchmark"]

STEREO_TOPICS = ("/cam0/image_raw", "/cam1/image_raw")


def run_live_benchmark(
    seconds: float = 60.0,
    methods: Sequence[str] = ("nsflow", "klt"),
    *,
    rate: float = 1.0,
    seed: int = 0,
    cache_dir: str | Path | None = None,
    progress: bool = False,
    compress: Sequence[str] = ("none",),
    jpeg_quality: int = 90,
    background_load: float = 0.0,
    load_nice: int = 0,
    params: dict[str, Any] | None = None,
    rounds: int = 1,
) -> dict[str, Any]:
    """Replay ``seconds`` of the stereo sample at ``rate`` into a tracker node per method and round.

    Args:
        seconds: length of the sample sequence (20 Hz stereo).
        methods: tracking methods, one node run each per round, in this order.
        rate: replay speed (1.0 = camera rate).
        cache_dir: where the sample is rendered and reused; None = a temporary folder.
        compress: image transports, one node run each per method: ``none`` (raw), ``jpeg``, ``png``.
        background_load: CPU cores of synthetic load during every replay (0 = none).
        load_nice: the load's niceness (> 0: below the tracker's priority).
        params: further tracker node parameters, e.g. ``{"queue_size": 1}``.
        rounds: how many times every run is repeated, the methods alternating; its figures are the
            rounds' merged (:func:`merge_rounds`).

    Returns:
        ``{"setup": ..., run: figures}`` where a run is the method's name, or ``<method>/jpeg<quality>`` /
        ``<method>/png``, whose figures also hold ``"agreement"`` with the method's raw run of the same
        round (:func:`feature_agreement`); :func:`format_live_table` shows them.

    Raises:
        NSFlowError: a tracker node did not come up, or bad arguments.
    """
    import sys

    import rclpy

    from nsflow_ros.background_load import background_load as load
    from nsflow_ros.background_load import load_shares
    from nsflow_ros.data.sample import make_sample_sequence
    from nsflow_ros.resources import STEREO_CONFIG, share_file
    from nsflow_ros.ros.live import run_live
    from nsflow_ros.ros.transport import use_large_image_transport

    if not seconds > 0 or not rate > 0:
        raise NSFlowError(f"seconds and rate must be > 0, got {seconds} and {rate}")
    if rounds < 1:
        raise NSFlowError(f"rounds must be >= 1, got {rounds}")
    bad = [c for c in compress if c not in ("none", "jpeg", "png")]
    if bad or not compress:
        raise NSFlowError(f"compress takes none, jpeg and png, got {', '.join(compress) or 'nothing'}")
    load_shares(background_load)  # a bad load is an error before anything starts
    if not 0 <= load_nice <= 19:
        raise NSFlowError(f"load niceness must be 0-19, got {load_nice}")
    tmp = tempfile.TemporaryDirectory() if cache_dir is None else None
    out: dict[str, Any] = {"setup": {"seconds": seconds, "rate": rate, "size": [752, 480], "stereo": True,
                                     "config": STEREO_CONFIG, "compress": list(compress),
                                     "jpeg_quality": jpeg_quality, "background_load_cores": background_load,
                                     "background_load_nice": load_nice, "rounds": rounds,
                                     "methods": list(methods),
                                     "params": dict(params or {})}}
    try:
        root = Path(tmp.name if tmp else cache_dir)
        seq = make_sample_sequence(root / f"sample-live-seed{seed}-{seconds:g}s", seed=seed, duration=seconds,
                                   stereo=True, formats=("ros2",), progress=progress)
        config = share_file(out["setup"]["config"])
        os.environ.setdefault("ROS_DOMAIN_ID", str(random.randint(100, 200)))  # a private DDS domain
        use_large_image_transport()
        ctx = rclpy.Context()
        rclpy.init(context=ctx)
        try:
            runs: dict[str, list[dict[str, Any]]] = {}
            for r in range(rounds):
                for method in methods:
                    raw: dict[int, dict[int, np.ndarray]] | None = None
                    for codec in compress:
                        name = method if codec == "none" else f"{method}/{codec}"
                        name += f"{jpeg_quality}" if codec == "jpeg" else ""
                        if progress:
                            print(f"[bench] node {name}, round {r + 1} of {rounds}: {seconds:g} s stereo at "
                                  f"rate {rate:g} ...", file=sys.stderr, flush=True)
                        frames: dict[int, dict[int, np.ndarray]] = {}
                        log = root / f"live_{name.replace('/', '_')}_{r}.log"
                        with load(background_load, nice=load_nice):
                            figs, _ = run_live(
                                ctx, seq, config, method, log, seed=seed, rate=rate, topics=STEREO_TOPICS,
                                show_track=False, compress=codec, jpeg_quality=jpeg_quality,
                                frames_out=frames, params=params,
                            )
                        if codec == "none":
                            raw = frames
                        elif raw is not None:
                            figs["agreement"] = feature_agreement(raw, frames)
                        runs.setdefault(name, []).append(figs)
            out.update({name: merge_rounds(figs) for name, figs in runs.items()})
        finally:
            rclpy.shutdown(context=ctx)
    finally:
        if tmp is not None:
            tmp.cleanup()
    return out


_COUNTS = ("frames_sent", "frames", "tracker_received", "tracker_processed", "tracker_unchecked",
           "tracker_dropped", "tracker_superseded")


def merge_rounds(rounds: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """One method's node runs merged: counts summed, latencies pooled, CPU per pair over all the pairs.

    Args:
        rounds: :func:`~nsflow_ros.ros.live.run_live` figures, each with the node's per-pair latencies
            (``tracker_latencies_ms``; a run without them counts for its counts and CPU only).

    Returns:
        The first round's figures with the counts summed over the rounds, ``tracker_latency_ms_p50`` /
        ``_p90`` over every pair's latency, ``tracker_cpu_ms_per_frame`` weighted by pairs tracked,
        ``rounds`` and ``round_latency_ms_p90`` (each round's own p90: the spread), ``agreement`` the
        rounds' mean share; without the latencies list.

    Raises:
        NSFlowError: no rounds.
    """
    if not rounds:
        raise NSFlowError("no node runs to merge")
    out = {k: v for k, v in rounds[0].items() if k != "tracker_latencies_ms"}
    for key in _COUNTS:
        values = [f.get(key) for f in rounds]
        out[key] = None if any(v is None for v in values) else int(sum(values))
    lat = [np.asarray(f.get("tracker_latencies_ms") or [], np.float64) for f in rounds]
    pooled = np.concatenate(lat)
    if pooled.size:
        out["tracker_latency_ms_p50"] = float(np.percentile(pooled, 50))
        out["tracker_latency_ms_p90"] = float(np.percentile(pooled, 90))
    cpu = [(f.get("tracker_cpu_ms_per_frame"), f.get("tracker_processed") or 0) for f in rounds]
    if all(c is not None for c, _ in cpu) and sum(n for _, n in cpu):
        out["tracker_cpu_ms_per_frame"] = sum(c * n for c, n in cpu) / sum(n for _, n in cpu)
    out["rounds"] = len(rounds)
    out["round_latency_ms_p90"] = [f.get("tracker_latency_ms_p90") for f in rounds]
    shares = [f["agreement"]["same_share"] for f in rounds
              if (f.get("agreement") or {}).get("same_share") is not None]
    if shares:
        out["agreement"] = {**rounds[0]["agreement"], "same_share": float(np.mean(shares))}
    return out


def feature_agreement(
    reference: dict[int, dict[int, np.ndarray]], other: dict[int, dict[int, np.ndarray]], within: float = 0.1
) -> dict[str, Any]:
    """How far one run's features (stamp -> {id: (u, v)}) are from a reference run's, in the frames of both.

    Features are matched by position, each with its nearest in the same frame, since ids diverge once one
    track differs.

    Returns:
        ``{"frames": frames compared, "identical_frames": frames whose feature positions are equal,
        "same_share": share of reference features with one of the other run within ``within`` px,
        "median_px": median distance to the nearest one}``.
    """
    common = sorted(set(reference) & set(other))
    identical, same, total, dists = 0, 0, 0, []
    for stamp in common:
        a = np.array(list(reference[stamp].values()), np.float64).reshape(-1, 2)
        b = np.array(list(other[stamp].values()), np.float64).reshape(-1, 2)
        identical += bool(a.shape == b.shape and np.array_equal(np.sort(a, axis=0), np.sort(b, axis=0)))
        if not len(a) or not len(b):
            total += len(a)
            continue
        d = np.sqrt(((a[:, None, :] - b[None, :, :]) ** 2).sum(-1)).min(axis=1)
        same += int((d <= within).sum())
        total += len(a)
        dists.append(d)
    return {
        "frames": len(common),
        "identical_frames": identical,
        "same_share": same / total if total else None,
        "median_px": float(np.median(np.concatenate(dists))) if dists else None,
    }


def format_live_table(res: dict[str, Any]) -> str:
    """The live runs as a text table."""
    s = res["setup"]
    lines = [
        f"tracker node, {s['seconds']:g} s stereo sample ({s['size'][0]}x{s['size'][1]}) replayed at rate "
        f"{s['rate']:g} over DDS (shipped Fast DDS profile), background load "
        f"{s.get('background_load_cores', 0):g} core"
        + (f" at nice {s['background_load_nice']}" if s.get("background_load_nice") else "")
        + "".join(f", {k} {v}" for k, v in s.get("params", {}).items()),
        "",
        f"{'method':14s}{'sent':>6s}{'recv':>6s}{'proc':>6s}{'late':>6s}{'drop':>6s}{'supers':>7s}"
        f"{'out':>6s}"
        f"{'processed':>11s}{'lat p50 ms':>12s}{'lat p90 ms':>12s}{'CPU ms/fr':>11s}{'same feat':>11s}",
    ]
    for m, f in res.items():
        if m == "setup":
            continue

        def num(key: str, fmt: str = "d", f: dict[str, Any] = f) -> str:
            v = f.get(key)
            return "?" if v is None else format(v, fmt)

        sent, proc = f.get("frames_sent") or 0, f.get("tracker_processed") or 0
        share = (f.get("agreement") or {}).get("same_share")
        lines.append(
            f"{m:14s}{num('frames_sent'):>6s}{num('tracker_received'):>6s}{num('tracker_processed'):>6s}"
            f"{num('tracker_unchecked'):>6s}{num('tracker_dropped'):>6s}{num('tracker_superseded'):>7s}"
            f"{num('frames'):>6s}"
            f"{(proc / sent if sent else 0):11.1%}"
            f"{num('tracker_latency_ms_p50', '.1f'):>12s}{num('tracker_latency_ms_p90', '.1f'):>12s}"
            f"{num('tracker_cpu_ms_per_frame', '.1f'):>11s}"
            f"{'' if share is None else format(share, '.1%'):>11s}"
        )
    lines.append("sent: image pairs replayed; recv / proc / drop: pairs the node received / tracked / "
                 "did not track; late: of those tracked, pairs that waited over late_frame_ms and were "
                 "tracked without the reverse checks; supers: of those dropped, superseded by a newer "
                 "pair while the tracker was busy; out: feature messages received back; CPU ms/fr: the "
                 "node process's CPU time per tracked pair")
    if any("agreement" in f for m, f in res.items() if m != "setup"):
        lines.append("method/jpegN, method/png: images as CompressedImage (decoding in the latency); same "
                     "feat: share of the raw run's camera-0 features within 0.1 px in the same frame")
    return "\n".join(lines)
