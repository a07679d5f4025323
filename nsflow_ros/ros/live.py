"""A live run over ROS 2: a sample sequence replayed into a ``tracker`` node process, its output collected.

The demo and the live node benchmark share it: this process publishes the images as a camera driver would
and collects the tracker process's feature clouds and debug images, scored against the exact flow.
"""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import qos_profile_sensor_data
from sensor_msgs.msg import CompressedImage, Image, PointCloud

from nsflow_ros.data.replay import ReplayOptions, replay_stream
from nsflow_ros.data.scoring import TrackStats
from nsflow_ros.errors import NSFlowError
from nsflow_ros.ros.replay_node import publish_stream
from nsflow_ros.ros.tracker_node import FEATURE_QOS
from nsflow_ros.stamps import stamp_to_ns

__all__ = ["run_live"]


class _Collector:
    """A node that records feature clouds (VINS-Fusion layout) and debug images."""

    def __init__(self, ctx: Any, feature_topic: str) -> None:
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
    compress: str = "none",
    jpeg_quality: int = 90,
    frames_out: dict[int, dict[int, np.ndarray]] | None = None,
    params: dict[str, Any] | None = None,
) -> tuple[dict[str, Any], Any]:
    """Replay ``seq`` over ROS 2 into a ``tracker`` node process started for it, and collect its output.

    Args:
        ctx: an initialised rclpy context.
        seq: a :class:`~nsflow_ros.data.sample.SampleSequence` with its ROS 2 bag.
        config: VINS config file whose image topics are ``topics``.
        log: the tracker's log file; its summary goes beside it (``.summary.json``).
        level, seed: illumination perturbation level and seed.
        rate: replay speed factor (1.0 = camera rate).
        compress: ``none``, or replay CompressedImage (``jpeg`` / ``png``) into a tracker with
            ``image_transport:=compressed``.
        frames_out: filled with the camera-0 features received, stamp -> {id: (u, v)}.
        params: further tracker node parameters (``-p name:=value``).

    Returns:
        (track figures of camera 0 plus the tracker's own counters, the middle debug image or None).

    Raises:
        NSFlowError: the tracker node did not come up.
    """
    summary_file = log.with_suffix(".summary.json")
    summary_file.unlink(missing_ok=True)
    cmd = [
        sys.executable, "-m", "nsflow_ros.ros.tracker_node", "--ros-args",
        "-p", f"config_file:={config}",
        "-p", f"method:={method}",
        "-p", f"show_track:={int(show_track)}",
        "-p", f"summary_file:={summary_file}",
        *(a for k, v in (params or {}).items() for a in ("-p", f"{k}:={v}")),
    ]
    if compress != "none":
        cmd += ["-p", "image_transport:=compressed"]
        topics = tuple(f"{t}/compressed" for t in topics)
    collector = _Collector(ctx, "/feature_tracker/feature")
    executor = SingleThreadedExecutor(context=ctx)
    spin = threading.Thread(target=executor.spin, daemon=True)
    proc: subprocess.Popen[bytes] | None = None
    sent = 0
    # everything from the spin thread's start on is undone in the finally: a stop signal (the demo's
    # Ctrl-C) may arrive at any line, and a spin thread or tracker process left behind aborts the exit
    try:
        executor.add_node(collector.node)
        spin.start()
        with log.open("wb") as out:
            proc = subprocess.Popen(cmd, stdout=out, stderr=subprocess.STDOUT)
        node = collector.node
        if not _wait_for(lambda: all(node.count_subscribers(t) > 0 for t in topics), 60.0, proc):
            tail = log.read_text(errors="replace")[-2000:]
            raise NSFlowError(
                f"the tracker node ({method}) did not come up; its log {log} ends with:\n{tail}"
            )
        sources = [t.removesuffix("/compressed") for t in topics] if compress != "none" else list(topics)
        opts = ReplayOptions(seq.ros2_dir, sources, perturb=level, seed=seed, rate=rate, compress=compress,
                             jpeg_quality=jpeg_quality)
        # the publishers first, matched with the tracker's subscriptions both ways, so the first frame is
        # not lost (a reader drops samples of a writer it has not matched yet)
        kind = Image if compress == "none" else CompressedImage
        pubs = {t: node.create_publisher(kind, t, qos_profile_sensor_data) for t in topics}
        _wait_for(lambda: all(p.get_subscription_count() > 0 for p in pubs.values()), 30.0, proc)
        time.sleep(0.5)
        sent = publish_stream(node, replay_stream(opts), rate=rate, clock=False, progress=False,
                              publishers=pubs)
        frames_sent = sent // len(topics)
        # let the last frames through the tracker before stopping it
        _wait_for(lambda: len(collector.frames) >= frames_sent, 5.0)
        time.sleep(0.3)
    finally:
        if proc is not None and proc.poll() is None:
            proc.send_signal(signal.SIGINT)
            try:
                proc.wait(10)
            except subprocess.TimeoutExpired:
                proc.kill()
        executor.shutdown()
        if spin.is_alive():  # out of rclpy's wait before its node goes
            spin.join(5.0)
        collector.node.destroy_node()
    with collector.lock:
        frames, debug = dict(collector.frames), dict(collector.debug)
    if frames_out is not None:
        frames_out.update(frames)
    figures = _stats(frames, seq)
    figures["frames_sent"] = sent // len(topics)
    # what the tracker itself saw: frames that reached it and frames it tracked (its summary file)
    counters = _read_summary(summary_file)
    for key in ("frames_received", "frames_processed", "frames_unchecked", "frames_dropped",
                "frames_superseded", "latency_ms_p50", "latency_ms_p90", "cpu_ms_per_frame"):
        figures[f"tracker_{key.removeprefix('frames_')}"] = counters.get(key)
    figures["tracker_latencies_ms"] = counters.get("latencies_ms")
    # the debug image of the sequence's middle frame (or the nearest one drawn): the same frame for every run
    target = int(seq.stamps_ns[len(seq) // 2])
    mid = min(debug, key=lambda t: abs(t - target)) if debug else None
    return figures, (debug[mid] if mid is not None else None)
