"""The main job (``make demo`` / ``nsflow-demo``): the whole system on built-in data, over real ROS 2 topics.

1. makes (or reuses) a synthetic EuRoC-like sample sequence (ROS 2 mcap bag) with exact ground truth;
2. for each illumination perturbation level (none / small / large) and each method (NSFlow, NSFlow
   descriptors through OpenCV's LK, and VINS's own KLT front-end),
   starts the ``tracker`` node as its own process, replays the sequence to it over DDS, and receives its
   ``/feature_tracker/feature`` point clouds and ``image_track`` debug images in a collector node;
3. prints frames, features per frame, mean track length and the tracking error of every carried-over
   feature against the ground-truth optical flow, with the frames the tracker received and processed;
4. writes the debug images as a PNG contact sheet and the figures as JSON.
"""

from __future__ import annotations

import argparse
import json
import os
import random
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

from nsflow_ros.argtypes import non_negative_float, positive_float, program_name
from nsflow_ros.errors import NSFlowError
from nsflow_ros.files import atomic_write
from nsflow_ros.stamps import stamp_to_ns

__all__ = ["main", "run_demo", "run_live"]


class _Collector:
    """A node that records feature clouds (VINS-Fusion layout) and debug images."""

    def __init__(self, ctx: Any, feature_topic: str) -> None:
        from rclpy.node import Node
        from rclpy.qos import qos_profile_sensor_data
        from sensor_msgs.msg import Image, PointCloud

        from nsflow_ros.ros.tracker_node import FEATURE_QOS

        self.node = Node("nsflow_demo", context=ctx)
        self.frames: dict[int, dict[int, np.ndarray]] = {}
        self.debug: dict[int, Any] = {}
        self.lock = threading.Lock()
        self.node.create_subscription(PointCloud, feature_topic, self._on_features, FEATURE_QOS)
        self.node.create_subscription(Image, "/image_track", self._on_debug, qos_profile_sensor_data)

    def _on_features(self, msg: Any) -> None:
        stamp = stamp_to_ns(msg.header.stamp)
        ch = msg.channels
        ids, cam = np.asarray(ch[0].values), np.asarray(ch[1].values)
        uv = np.stack([np.asarray(ch[2].values), np.asarray(ch[3].values)], axis=1)
        left = cam == 0
        with self.lock:
            self.frames[stamp] = {int(i): p for i, p in zip(ids[left], uv[left], strict=True)}

    def _on_debug(self, msg: Any) -> None:
        stamp = stamp_to_ns(msg.header.stamp)
        with self.lock:
            self.debug[stamp] = msg


def _stats(frames: dict[int, dict[int, np.ndarray]], seq: Any) -> dict[str, Any]:
    from nsflow_ros.offline import TrackStats

    stats = TrackStats(seq)
    for stamp in sorted(frames):
        stats.add_frame(stamp, frames[stamp])
    return stats.figures()


def _wait_for(cond: Any, timeout: float, proc: subprocess.Popen[bytes] | None = None) -> bool:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if cond():
            return True
        if proc is not None and proc.poll() is not None:
            return False
        time.sleep(0.05)
    return False


def _read_summary(path: Path) -> dict[str, Any]:
    """The tracker node's summary file ({} when it wrote none, e.g. it was killed)."""
    try:
        return dict(json.loads(path.read_text()))
    except (OSError, ValueError):
        return {}


def run_live(
    ctx: Any,
    seq: Any,
    config: Path,
    method: str,
    log: Path,
    *,
    level: str = "none",
    seed: int = 0,
    rate: float = 1.0,
    topics: tuple[str, ...] = ("/cam0/image_raw",),
    show_track: bool = True,
) -> tuple[dict[str, Any], Any]:
    """Replay ``seq`` over ROS 2 into a ``tracker`` node process started for it, and collect its output.

    The replay publishes from this process (context ``ctx``) at ``rate`` with sensor-data QoS, as a
    camera driver would; the tracker runs as its own process with the VINS config ``config``.

    Args:
        ctx: an initialised rclpy context.
        seq: a :class:`~nsflow_ros.data.sample.SampleSequence` with its ROS 2 bag.
        config: VINS config file (mono or stereo: ``topics`` must be its image topics).
        method: tracking method.
        log: the tracker's log file; its summary goes beside it (``.summary.json``).
        level, seed: illumination perturbation level and seed.
        rate: replay speed factor (1.0 = camera rate).
        topics: image topics to replay.
        show_track: have the tracker publish its debug image.

    Returns:
        (track figures of camera 0 plus the tracker's own counters, the middle debug image or None).

    Raises:
        NSFlowError: the tracker node did not come up.
    """
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import qos_profile_sensor_data
    from sensor_msgs.msg import Image

    from nsflow_ros.replay import ReplayOptions, replay_stream
    from nsflow_ros.ros.replay_node import publish_stream

    collector = _Collector(ctx, "/feature_tracker/feature")
    executor = SingleThreadedExecutor(context=ctx)
    executor.add_node(collector.node)
    spin = threading.Thread(target=executor.spin, daemon=True)
    spin.start()
    summary_file = log.with_suffix(".summary.json")
    summary_file.unlink(missing_ok=True)
    cmd = [
        sys.executable, "-m", "nsflow_ros.ros.tracker_node", "--ros-args",
        "-p", f"config_file:={config}",
        "-p", f"method:={method}",
        "-p", f"show_track:={int(show_track)}",
        "-p", f"summary_file:={summary_file}",
    ]
    with log.open("wb") as out:
        proc = subprocess.Popen(cmd, stdout=out, stderr=subprocess.STDOUT)
    sent = 0
    try:
        node = collector.node
        if not _wait_for(lambda: all(node.count_subscribers(t) > 0 for t in topics), 60.0, proc):
            tail = log.read_text(errors="replace")[-2000:]
            raise NSFlowError(
                f"the tracker node ({method}) did not come up; its log {log} ends with:\n{tail}"
            )
        opts = ReplayOptions(seq.ros2_dir, list(topics), perturb=level, seed=seed, rate=rate)
        # the publishers first, matched with the tracker's subscriptions both ways, so the first frame is
        # not lost (a reader drops samples of a writer it has not matched yet)
        pubs = {t: node.create_publisher(Image, t, qos_profile_sensor_data) for t in topics}
        _wait_for(lambda: all(p.get_subscription_count() > 0 for p in pubs.values()), 30.0, proc)
        time.sleep(0.5)
        sent = publish_stream(node, replay_stream(opts), rate=rate, clock=False, progress=False,
                              publishers=pubs)
        frames_sent = sent // len(topics)
        # let the last frames through the tracker before stopping it
        _wait_for(lambda: len(collector.frames) >= frames_sent, 5.0)
        time.sleep(0.3)
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGINT)
            try:
                proc.wait(10)
            except subprocess.TimeoutExpired:
                proc.kill()
        executor.shutdown()
        collector.node.destroy_node()
    with collector.lock:
        frames, debug = dict(collector.frames), dict(collector.debug)
    figures = _stats(frames, seq)
    figures["frames_sent"] = sent // len(topics)
    # what the tracker itself saw: frames that reached it and frames it tracked (its summary file)
    counters = _read_summary(summary_file)
    for key in ("frames_received", "frames_processed", "frames_dropped", "latency_ms_p50", "latency_ms_p90"):
        figures[f"tracker_{key.removeprefix('frames_')}"] = counters.get(key)
    # the debug image of the sequence's middle frame (or the nearest one drawn): the same frame for every run
    target = int(seq.stamps_ns[len(seq) // 2])
    mid = min(debug, key=lambda t: abs(t - target)) if debug else None
    return figures, (debug[mid] if mid is not None else None)


def run_demo(
    out_dir: Path,
    *,
    duration: float = 4.0,
    seed: int = 0,
    rate: float = 1.0,
    levels: tuple[str, ...] = ("none", "small", "large"),
    methods: tuple[str, ...] = ("nsflow", "nsflow_lk", "klt"),
) -> dict[str, Any]:
    """Run the demo; see the module docstring. Returns the figures per level and method."""
    import rclpy

    from nsflow_ros.core.encoder import DEFAULT_MODEL
    from nsflow_ros.data.images import image_for_tracker
    from nsflow_ros.data.sample import make_sample_sequence
    from nsflow_ros.offline import _write_png, contact_sheet
    from nsflow_ros.resources import ResourceError, share_file
    from nsflow_ros.ros.transport import use_large_image_transport

    out_dir.mkdir(parents=True, exist_ok=True)
    notes = []
    try:
        share_file(DEFAULT_MODEL)
    except ResourceError:
        from nsflow_ros.core.methods import METHODS

        if any(METHODS[m].learned for m in methods):
            methods = tuple(m for m in methods if not METHODS[m].learned)
            notes.append(f"no trained encoder at {DEFAULT_MODEL}: the learned methods are skipped")
    print(f"[demo] sample sequence ({duration:.0f} s, 752x480 mono, seed {seed}) ...", flush=True)
    seq = make_sample_sequence(
        out_dir / "sample", seed=seed, duration=duration, stereo=False, formats=("ros2",), progress=True
    )
    config = share_file("config/euroc/euroc_mono_imu_config.yaml")
    # a private DDS domain, so the demo neither hears nor disturbs other ROS 2 graphs on this machine
    os.environ.setdefault("ROS_DOMAIN_ID", str(random.randint(100, 200)))
    use_large_image_transport()  # this process and the tracker nodes it starts
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    results: dict[str, dict[str, Any]] = {}
    sheet, labels = [], []
    try:
        for level in levels:
            for method in methods:
                print(f"[demo] {method:9s} perturbation {level:5s}: replaying over ROS 2 ...", flush=True)
                figs, dbg = run_live(
                    ctx, seq, config, method, out_dir / f"tracker_{method}_{level}.log",
                    level=level, seed=seed, rate=rate,
                )
                results.setdefault(level, {})[method] = figs
                if dbg is not None:
                    sheet.append(image_for_tracker(dbg))
                    labels.append(f"{method}, {level} perturbation")
    finally:
        rclpy.shutdown(context=ctx)
    summary = {
        "sequence": str(seq.root),
        "duration_s": duration,
        "seed": seed,
        "notes": notes,
        "results": results,
    }
    atomic_write(out_dir / "summary.json", lambda p: p.write_text(json.dumps(summary, indent=2)))
    if sheet:
        img = contact_sheet(sheet, cols=len(methods), labels=labels, legend=True)
        atomic_write(out_dir / "tracks.png", lambda p: _write_png(p, img))
    return summary


def format_summary(summary: dict[str, Any]) -> str:
    """The demo's table."""
    head = (
        f"{'perturbation':12s} {'method':10s} {'sent':>5s} {'recv':>5s} {'proc':>5s} {'out':>5s} "
        f"{'feat/frame':>10s} {'track len':>9s} {'err median px':>13s} {'<1 px':>7s}"
    )
    lines = [head, "-" * len(head)]
    for level, per in summary["results"].items():
        for method, f in per.items():
            med = "n/a" if f["error_median_px"] is None else f"{f['error_median_px']:.3f}"
            within = "n/a" if f["error_within_1px"] is None else f"{100 * f['error_within_1px']:.1f}%"
            recv, proc = (
                "?" if f.get(k) is None else str(f[k]) for k in ("tracker_received", "tracker_processed")
            )
            lines.append(
                f"{level:12s} {method:10s} {f['frames_sent']:5d} {recv:>5s} {proc:>5s} {f['frames']:5d} "
                f"{f['features_per_frame']:10.1f} {f['mean_track_length']:9.1f} {med:>13s} {within:>7s}"
            )
    lines.append(
        "sent: frames replayed; recv / proc: frames the tracker node received / tracked (from its summary); "
        "out: feature messages the demo received"
    )
    lines += [f"note: {n}" for n in summary["notes"]]
    return "\n".join(lines)


def main(args: list[str] | None = None) -> int:
    """Entry point of ``nsflow-demo`` / ``ros2 run nsflow_ros demo``."""
    p = argparse.ArgumentParser(
        prog=program_name("nsflow-demo"),
        description="The whole system on built-in data over real ROS 2 topics: makes a synthetic EuRoC-like "
        "sequence, replays it with no, small and large illumination perturbation to the tracker node "
        "(NSFlow, NSFlow descriptors through OpenCV's LK, VINS's KLT), and prints frames, features per "
        "frame, track length and the tracking error against the exact ground-truth flow; writes a "
        "contact sheet and the figures.",
    )
    p.add_argument("--out", type=Path, default=Path("out/demo"), help="output folder (default out/demo)")
    p.add_argument(
        "--duration", type=positive_float, default=4.0, help="seconds of sample sequence (default 4)"
    )
    p.add_argument("--seed", type=int, default=0, help="sequence and perturbation seed (default 0)")
    p.add_argument(
        "--rate",
        type=non_negative_float,
        default=1.0,
        help="replay speed factor (default 1.0 = real time, 0 = as fast as possible)",
    )
    opts = p.parse_args(args)
    t0 = time.monotonic()
    from nsflow_ros.ros.signals import StopRequested, StopSignals

    try:
        with StopSignals(raise_now=True):
            summary = run_demo(opts.out, duration=opts.duration, seed=opts.seed, rate=opts.rate)
    except NSFlowError as err:
        print(f"nsflow-demo: {err}", file=sys.stderr)
        return 1
    except (KeyboardInterrupt, StopRequested):
        print("nsflow-demo: stopped", file=sys.stderr)
        return 0
    print()
    print(format_summary(summary))
    print(
        f"\ncontact sheet: {opts.out / 'tracks.png'}; figures: {opts.out / 'summary.json'} "
        f"({time.monotonic() - t0:.0f} s)"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
