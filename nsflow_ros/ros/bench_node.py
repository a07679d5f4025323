"""Node benchmark: image-received -> features-published latency and memory over many frames.

One process, one rclpy context: a publisher node sends a scikit-image photo panning back and forth, the
``nsflow_tracker`` node tracks it, a receiver node takes the feature clouds. Frames go lock-step (the next
image waits for the previous frame's features), so the latency is the node's own, not queueing; it runs
from the image callback (for stereo, the one that completes the pair) to the return of ``publish``.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
import uuid
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from nsflow_ros.optional import require

__all__ = ["main", "rss_mb", "run_node_benchmark"]


def rss_mb() -> float:
    """Current resident set size of this process in MB (from /proc; 0 where there is none)."""
    try:
        pages = int(Path("/proc/self/statm").read_text().split()[1])
    except (OSError, IndexError, ValueError):
        return 0.0
    return pages * os.sysconf("SC_PAGE_SIZE") / 1e6


def _frames(
    width: int, height: int, n: int = 40, disparity: float = -8.0
) -> tuple[list[np.ndarray], list[np.ndarray]]:
    skdata = require("skimage.data", "the node benchmark's frames (a scikit-image photo)")
    tex = cv2.cvtColor(skdata.coffee(), cv2.COLOR_RGB2GRAY)
    tex = cv2.resize(tex, (2 * width, 2 * height), interpolation=cv2.INTER_AREA)
    left, right = [], []
    for k in range(n):
        # ping-pong pan: content keeps moving smoothly and never jumps when the sequence repeats
        s = k if k < n // 2 else n - k
        ox, oy = width / 2 + 2.5 * s, height / 2 + 1.2 * s
        m = np.float32([[1, 0, -ox], [0, 1, -oy]])
        left.append(cv2.warpAffine(tex, m, (width, height), flags=cv2.INTER_LINEAR))
        m[0, 2] += disparity
        right.append(cv2.warpAffine(tex, m, (width, height), flags=cv2.INTER_LINEAR))
    return left, right


def _write_config(folder: Path, prefix: str, width: int, height: int, stereo: bool) -> Path:
    from nsflow_ros.core.camera import PinholeCamera

    f = 0.8 * width
    cam = PinholeCamera(width=width, height=height, fx=f, fy=f, cx=width / 2, cy=height / 2)
    cam.save_yaml(folder / "cam0.yaml")
    cam.save_yaml(folder / "cam1.yaml")
    path = folder / "bench.yaml"
    path.write_text(
        "%YAML:1.0\nimu: 0\n"
        f"num_of_cam: {2 if stereo else 1}\n"
        f"image0_topic: \"{prefix}/cam0\"\nimage1_topic: \"{prefix}/cam1\"\n"
        "cam0_calib: \"cam0.yaml\"\ncam1_calib: \"cam1.yaml\"\n"
        f"image_width: {width}\nimage_height: {height}\nmax_cnt: 150\nmin_dist: 15\nF_threshold: 1.0\n"
        "show_track: 0\nflow_back: 1\nestimate_extrinsic: 2\n"
        "body_T_cam1: !!opencv-matrix\n   rows: 4\n   cols: 4\n   dt: d\n"
        "   data: [1.0, 0.0, 0.0, 0.1, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0]\n"
    )
    return path


def run_node_benchmark(
    frames: int,
    stereo: bool,
    *,
    width: int = 320,
    height: int = 240,
    method: str = "classical",
    model_path: str | None = None,
    threads: int = 0,
    providers: str = "cpu",
    checkpoints: tuple[int, ...] = (1000, 10000),
    timeout_s: float = 5.0,
    progress: bool = False,
) -> dict[str, Any]:
    """Run the tracker node on ``frames`` synthetic frames (or stereo pairs) and measure latency and memory.

    Args:
        method: a key of :data:`~nsflow_ros.core.methods.METHODS`.
        model_path: ONNX encoder of the learned methods (None = the shipped one).
        threads: the node's ``num_threads`` (0 = all usable cores).
        providers: the node's ``providers``.
        checkpoints: frame counts after which the RSS is recorded (and after the last frame).
        timeout_s: how long to wait for one frame's features before counting it lost.
        progress: print a line every 1,000 frames to stderr.

    Returns:
        dict with frames, stereo, method, encoder_provider, image_size, latency_ms {median, p90, mean,
        max} (in the node), roundtrip_ms {median, p90} (publisher -> receiver), features_per_frame
        (mean), lost_frames, frames_dropped and images_unpaired (the node's counters), rss_mb
        {checkpoint: MB}, rss_growth_mb (last minus first checkpoint reached), wall_s, fps.
    """
    import rclpy
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.parameter import Parameter
    from rclpy.qos import qos_profile_sensor_data
    from sensor_msgs.msg import Image, PointCloud

    from nsflow_ros.core.encoder import encoder_provider
    from nsflow_ros.ros.tracker_node import FEATURE_QOS, TrackerNode, rclpy_image

    left, right = _frames(width, height)
    prefix = f"/nsflow_bench_{uuid.uuid4().hex[:8]}"
    ctx = Context()
    rclpy.init(context=ctx)
    nodes: list[Any] = []
    executor = SingleThreadedExecutor(context=ctx)
    with tempfile.TemporaryDirectory() as tmp:
        config = _write_config(Path(tmp), prefix, width, height, stereo)
        try:
            params = [Parameter("config_file", value=str(config)), Parameter("method", value=method),
                      Parameter("feature_topic", value=f"{prefix}/feature"),
                      Parameter("restart_topic", value=f"{prefix}/restart"),
                      Parameter("num_threads", value=threads), Parameter("providers", value=providers)]
            if model_path:
                params.append(Parameter("model_path", value=str(model_path)))
            tracker = TrackerNode(context=ctx, parameter_overrides=params)
            provider = encoder_provider(tracker.tracker.encoder)
            io = rclpy.create_node(f"bench_io_{uuid.uuid4().hex[:6]}", context=ctx)
            nodes = [tracker, io]
            pubs = [io.create_publisher(Image, f"{prefix}/cam{i}", qos_profile_sensor_data) for i in (0, 1)]
            received: list[tuple[float, int]] = []
            io.create_subscription(
                PointCloud,
                f"{prefix}/feature",
                lambda m: received.append((time.perf_counter(), len(m.points))),
                FEATURE_QOS,
            )
            for node in nodes:
                executor.add_node(node)
            used = pubs[: 2 if stereo else 1]
            end = time.monotonic() + 10.0
            while time.monotonic() < end and not (
                all(p.get_subscription_count() for p in used)
                and tracker._feature_pub.get_subscription_count()
            ):
                executor.spin_once(timeout_sec=0.01)

            # Message templates: only the stamp changes per frame.
            templates = [[rclpy_image(img) for img in imgs] for imgs in (left, right)]

            node_lat = np.zeros(frames)
            trip = np.zeros(frames)
            counts = np.zeros(frames)
            lost = 0
            rss: dict[int, float] = {}
            start = time.perf_counter()
            for k in range(frames):
                t = 1.0 + 0.05 * k
                sec = int(t)
                before = len(received)
                sent = time.perf_counter()
                for cam in range(2 if stereo else 1):
                    msg = templates[cam][k % len(left)]
                    msg.header.stamp.sec = sec
                    msg.header.stamp.nanosec = round((t - sec) * 1e9)
                    pubs[cam].publish(msg)
                deadline = time.monotonic() + timeout_s
                while len(received) == before and time.monotonic() < deadline:
                    executor.spin_once(timeout_sec=0.005)
                if len(received) == before:
                    lost += 1
                    node_lat[k] = trip[k] = np.nan
                else:
                    node_lat[k] = tracker.latencies_ms[-1]
                    trip[k] = (received[-1][0] - sent) * 1e3
                    counts[k] = received[-1][1]
                if k + 1 in checkpoints or k + 1 == frames:
                    rss[k + 1] = rss_mb()
                if progress and (k + 1) % 1000 == 0:
                    print(f"  {k + 1} frames, RSS {rss_mb():.1f} MB", file=sys.stderr)
                if len(received) > 100:  # keep the receiver's list bounded over 10,000 frames
                    received.clear()
            wall = time.perf_counter() - start
            node_counts = tracker.counters()
        finally:
            executor.shutdown()
            for node in nodes:
                node.destroy_node()
            rclpy.shutdown(context=ctx)
    ok = np.isfinite(node_lat)
    reached = sorted(rss)
    return {
        "frames": frames,
        "stereo": stereo,
        "method": method,
        "encoder_provider": provider,
        "image_size": [width, height],
        "latency_ms": {
            "median": float(np.median(node_lat[ok])) if ok.any() else None,
            "p90": float(np.percentile(node_lat[ok], 90)) if ok.any() else None,
            "mean": float(np.mean(node_lat[ok])) if ok.any() else None,
            "max": float(np.max(node_lat[ok])) if ok.any() else None,
        },
        "roundtrip_ms": {
            "median": float(np.median(trip[ok])) if ok.any() else None,
            "p90": float(np.percentile(trip[ok], 90)) if ok.any() else None,
        },
        "features_per_frame": float(np.mean(counts[ok])) if ok.any() else 0.0,
        "lost_frames": lost,
        "frames_dropped": node_counts["frames_dropped"],
        "images_unpaired": node_counts["images_unpaired"],
        "rss_mb": {str(k): round(v, 2) for k, v in rss.items()},
        "rss_growth_mb": round(rss[reached[-1]] - rss[reached[0]], 2) if len(reached) >= 2 else None,
        "wall_s": wall,
        "fps": frames / wall if wall > 0 else None,
    }


def summary_line(res: dict[str, Any]) -> str:
    """One line of a :func:`run_node_benchmark` result: size, method, latency, drops and memory."""
    lat = res["latency_ms"]
    rss = ", ".join(f"{v:.1f} MB after {k} frames" for k, v in res["rss_mb"].items()) or "n/a"
    latency = "n/a" if lat["median"] is None else f"median {lat['median']:.2f} ms, p90 {lat['p90']:.2f} ms"
    return (
        f"node {'stereo' if res['stereo'] else 'mono'} {res['image_size'][0]}x{res['image_size'][1]} "
        f"{res['method']} (encoder on {res['encoder_provider']}): {res['frames']} frames, latency {latency}; "
        f"lost {res['lost_frames']}, dropped {res['frames_dropped']}, unpaired {res['images_unpaired']}; "
        f"RSS {rss}; growth {res['rss_growth_mb']} MB"
    )


def main(argv: list[str] | None = None) -> int:
    """``python -m nsflow_ros.ros.bench_node``: the benchmark as JSON; one line per run on stderr."""
    from nsflow_ros.argtypes import non_negative_int, positive_int
    from nsflow_ros.core.methods import METHODS

    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--frames", type=positive_int, default=1000, help="frames per run (default 1000)")
    p.add_argument("--stereo", action="store_true", help="stereo pairs only (default: mono then stereo)")
    p.add_argument("--mono", action="store_true", help="mono only")
    p.add_argument("--method", choices=tuple(METHODS), default="classical", help="tracking method")
    p.add_argument("--model", default=None, help="ONNX encoder of the learned methods")
    p.add_argument("--width", type=positive_int, default=320, help="image width (default 320)")
    p.add_argument("--height", type=positive_int, default=240, help="image height (default 240)")
    p.add_argument("--threads", type=non_negative_int, default=0,
                   help="the node's num_threads (default 0 = all usable cores)")
    p.add_argument("--providers", default="cpu", help="the node's providers (default cpu)")
    args = p.parse_args(argv)
    modes = [True] if args.stereo else [False] if args.mono else [False, True]
    out = []
    for stereo in modes:
        res = run_node_benchmark(
            args.frames, stereo, width=args.width, height=args.height, method=args.method,
            model_path=args.model, threads=args.threads, providers=args.providers, progress=True,
        )
        print(summary_line(res), file=sys.stderr)
        out.append(res)
    print(json.dumps(out, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
