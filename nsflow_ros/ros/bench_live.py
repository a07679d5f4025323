"""Live node benchmark: the stereo sample replayed at camera rate into ``tracker`` processes over real DDS.

For each method, a ``tracker`` node process runs the shipped EuRoC stereo config while this process
replays the sample sequence's two 752x480 image topics at ``rate`` (1.0 = the camera's 20 Hz) with
sensor-data QoS, as a camera driver would, through the shipped Fast DDS profile. Reported per method:
image pairs sent, received and processed by the node, dropped (the node's own count of frames it could
not keep up with; superseded: given up for a newer frame), feature messages out, the node's
image-to-features latency (p50, p90: from the image callback, queueing included, to the publication) and
its CPU time per processed frame, from the node's summary file. A background load
(:func:`nsflow_ros.background_load.background_load`) can share the cores, standing in for the estimator.
"""

from __future__ import annotations

import os
import random
import tempfile
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from nsflow_ros.errors import NSFlowError

__all__ = ["STEREO_TOPICS", "format_live_table", "run_live_benchmark"]

STEREO_TOPICS = ("/cam0/image_raw", "/cam1/image_raw")


def run_live_benchmark(
    seconds: float = 60.0,
    methods: Sequence[str] = ("nsflow", "klt"),
    *,
    rate: float = 1.0,
    seed: int = 0,
    cache_dir: str | Path | None = None,
    progress: bool = False,
    background_load: float = 0.0,
    params: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """Replay ``seconds`` of the stereo sample at ``rate`` into a tracker node per method.

    Args:
        seconds: length of the sample sequence (20 Hz stereo).
        methods: tracking methods, one node run each, in this order.
        rate: replay speed (1.0 = camera rate).
        seed: the sample sequence's seed.
        cache_dir: where the sample (ROS 2 bag) is rendered and reused; None = a temporary folder.
        progress: print a line per run to stderr.
        background_load: CPU cores of synthetic load running during every replay (0 = none).
        params: further tracker node parameters, e.g. ``{"queue_size": 1}``.

    Returns:
        ``{"setup": ..., method: {"frames_sent", "tracker_received", "tracker_processed",
        "tracker_dropped", "tracker_superseded", "frames" (feature messages out), "tracker_latency_ms_p50",
        "..._p90", "tracker_cpu_ms_per_frame", ...}}``.

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
    load_shares(background_load)  # a bad load is an error before anything starts
    tmp = tempfile.TemporaryDirectory() if cache_dir is None else None
    out: dict[str, Any] = {"setup": {"seconds": seconds, "rate": rate, "size": [752, 480], "stereo": True,
                                     "config": STEREO_CONFIG, "background_load_cores": background_load,
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
            for method in methods:
                if progress:
                    print(f"[bench] node {method}: {seconds:g} s stereo at rate {rate:g} ...",
                          file=sys.stderr, flush=True)
                with load(background_load):
                    figs, _ = run_live(ctx, seq, config, method, root / f"live_{method}.log", seed=seed,
                                       rate=rate, topics=STEREO_TOPICS, show_track=False, params=params)
                out[method] = figs
        finally:
            rclpy.shutdown(context=ctx)
    finally:
        if tmp is not None:
            tmp.cleanup()
    return out


def format_live_table(res: dict[str, Any]) -> str:
    """The live runs as a text table."""
    s = res["setup"]
    lines = [
        f"tracker node, {s['seconds']:g} s stereo sample ({s['size'][0]}x{s['size'][1]}) replayed at rate "
        f"{s['rate']:g} over DDS (shipped Fast DDS profile), background load "
        f"{s.get('background_load_cores', 0):g} core"
        + "".join(f", {k} {v}" for k, v in s.get("params", {}).items()),
        "",
        f"{'method':11s}{'sent':>6s}{'recv':>6s}{'proc':>6s}{'drop':>6s}{'supers':>7s}{'out':>6s}"
        f"{'processed':>11s}{'lat p50 ms':>12s}{'lat p90 ms':>12s}{'CPU ms/fr':>11s}",
    ]
    for m, f in res.items():
        if m == "setup":
            continue

        def num(key: str, fmt: str = "d", f: dict[str, Any] = f) -> str:
            v = f.get(key)
            return "?" if v is None else format(v, fmt)

        sent, proc = f.get("frames_sent") or 0, f.get("tracker_processed") or 0
        lines.append(
            f"{m:11s}{num('frames_sent'):>6s}{num('tracker_received'):>6s}{num('tracker_processed'):>6s}"
            f"{num('tracker_dropped'):>6s}{num('tracker_superseded'):>7s}{num('frames'):>6s}"
            f"{(proc / sent if sent else 0):11.1%}"
            f"{num('tracker_latency_ms_p50', '.1f'):>12s}{num('tracker_latency_ms_p90', '.1f'):>12s}"
            f"{num('tracker_cpu_ms_per_frame', '.1f'):>11s}"
        )
    lines.append("sent: image pairs replayed; recv / proc / drop: pairs the node received / tracked / "
                 "did not track; supers: of those dropped, superseded by a newer pair while the tracker "
                 "was busy; out: feature messages received back; CPU ms/fr: the node process's CPU time "
                 "per tracked pair")
    return "\n".join(lines)
