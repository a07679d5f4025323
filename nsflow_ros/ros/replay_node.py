"""``ros2 run nsflow_ros replay``: play a bag or ASL folder over ROS 2 topics, optionally perturbed.

Reads ROS 1 bags, ROS 2 bags (sqlite3, mcap) and EuRoC / UMA-VI ASL folders through rosbags (no ROS
installation needed to read), streams them (never loads a whole bag), and publishes the images and IMU
as serialised messages with ``/clock``, paced on wall time by ``--rate``. Images go out with sensor-data
QoS, everything else reliable. ``--perturb`` applies the paper's illumination perturbation on the fly;
``--write-bag`` writes the (perturbed) stream to a new ROS 2 bag instead of publishing; ``--offline``
runs the tracker core straight over the data without middleware (see :mod:`nsflow_ros.offline`).
"""

from __future__ import annotations

import argparse
import importlib
import sys
import time
from collections.abc import Iterable
from pathlib import Path
from typing import Any

from nsflow_ros.data.records import RawMessage
from nsflow_ros.errors import NSFlowError
from nsflow_ros.replay import ReplayOptions, parse_remaps, replay_stream

__all__ = ["main", "message_class", "publish_stream"]


def message_class(msgtype: str) -> Any:
    """The rclpy message class of a ROS 2 type name such as ``sensor_msgs/msg/Image``."""
    pkg, _, name = msgtype.rpartition("/msg/")
    try:
        return getattr(importlib.import_module(f"{pkg}.msg"), name)
    except (ImportError, AttributeError) as err:
        raise NSFlowError(f"message type {msgtype} is not available in this ROS installation") from err


def publish_stream(
    node: Any,
    stream: Iterable[RawMessage],
    *,
    rate: float = 1.0,
    clock: bool = True,
    progress: bool = True,
    total_s: float | None = None,
    publishers: dict[str, Any] | None = None,
) -> int:
    """Publish a message stream from ``node``, paced by the messages' stamps.

    Args:
        node: an rclpy node.
        stream: messages in time order.
        rate: speed factor (1.0 = real time, 0 = as fast as possible).
        clock: publish rosgraph_msgs/Clock with each message's time.
        progress: show a progress bar (seconds of data replayed).
        total_s: length of the stream in seconds, for the progress bar.
        publishers: topic -> publisher, reused and filled across calls (None: new ones per call).

    Returns:
        number of messages published.
    """
    from rclpy.qos import QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
    from rosgraph_msgs.msg import Clock
    from tqdm import tqdm

    pubs: dict[str, Any] = {} if publishers is None else publishers
    clock_pub = node.create_publisher(Clock, "/clock", 10) if clock else None
    reliable = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
    bar = tqdm(total=total_s, unit="s", disable=not progress, desc="replay", bar_format=None)
    t0_data = t0_wall = None
    last = 0.0
    count = 0
    try:
        for msg in stream:
            if msg.topic not in pubs:
                qos = qos_profile_sensor_data if msg.msgtype.endswith("Image") else reliable
                pubs[msg.topic] = node.create_publisher(message_class(msg.msgtype), msg.topic, qos)
            if t0_data is None:
                t0_data, t0_wall = msg.stamp_ns, time.monotonic()
            elapsed = (msg.stamp_ns - t0_data) * 1e-9
            if rate > 0:
                wait = t0_wall + elapsed / rate - time.monotonic()
                if wait > 0:
                    time.sleep(wait)
            if clock_pub is not None:
                stamp = Clock()
                stamp.clock.sec, stamp.clock.nanosec = divmod(msg.stamp_ns, 1_000_000_000)
                clock_pub.publish(stamp)
            pubs[msg.topic].publish(msg.cdr)
            count += 1
            if elapsed - last >= 0.1:
                bar.update(elapsed - last)
                last = elapsed
    finally:
        bar.close()
    return count


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="nsflow-replay", description=__doc__.split("\n\n")[0])
    p.add_argument("path", type=Path, help="ROS 1 .bag, ROS 2 bag folder/.mcap/.db3, or ASL folder")
    p.add_argument("--topics", nargs="+", default=None, help="topics to replay (default: cameras and IMU)")
    p.add_argument("--start", type=float, default=0.0, help="seconds to skip (default 0)")
    p.add_argument("--duration", type=float, default=None, help="seconds to replay (default: all)")
    p.add_argument(
        "--rate", type=float, default=1.0, help="speed factor, 0 = as fast as possible (default 1)"
    )
    p.add_argument(
        "--perturb",
        choices=("none", "small", "large"),
        default="none",
        help="illumination perturbation level (default none)",
    )
    p.add_argument("--seed", type=int, default=0, help="perturbation seed (default 0)")
    p.add_argument("--remap", nargs="+", default=[], metavar="FROM:=TO", help="topic remaps")
    p.add_argument("--no-clock", action="store_true", help="do not publish /clock")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument(
        "--write-bag",
        type=Path,
        default=None,
        help="write the (perturbed) stream to this new ROS 2 bag instead of publishing",
    )
    p.add_argument(
        "--offline",
        type=Path,
        default=None,
        metavar="OUT_DIR",
        help="run the tracker core over the data without ROS and write features + contact sheet",
    )
    p.add_argument(
        "--config", type=Path, default=None, help="VINS config for --offline (default: EuRoC mono)"
    )
    p.add_argument(
        "--method", choices=("nsflow", "classical", "klt"), default="nsflow", help="tracker for --offline"
    )
    return p


def main(args: list[str] | None = None) -> int:
    """Entry point of ``nsflow-replay`` / ``ros2 run nsflow_ros replay``."""
    argv = sys.argv[1:] if args is None else args
    if "--ros-args" in argv:
        argv = argv[: argv.index("--ros-args")]
    opts = _parser().parse_args(argv)
    try:
        ropts = ReplayOptions(
            opts.path,
            opts.topics,
            opts.start,
            opts.duration,
            opts.rate,
            opts.perturb,
            opts.seed,
            parse_remaps(opts.remap),
        )
        if opts.offline is not None:
            from nsflow_ros.allocator import keep_large_buffers
            from nsflow_ros.offline import run_offline

            keep_large_buffers()  # the tracker runs in this process

            summary = run_offline(
                ropts, opts.offline, config=opts.config, method=opts.method, progress=not opts.no_progress
            )
            print(summary.text())
            return 0
        if opts.write_bag is not None:
            from nsflow_ros.data.writers import write_ros2_bag
            from nsflow_ros.replay import replay_records

            n = write_ros2_bag(opts.write_bag, replay_records(ropts))
            print(f"wrote {n} messages to {opts.write_bag}")
            return 0
        return _publish(ropts, clock=not opts.no_clock, progress=not opts.no_progress)
    except NSFlowError as err:
        print(f"nsflow-replay: {err}", file=sys.stderr)
        return 1


def _publish(ropts: ReplayOptions, *, clock: bool, progress: bool) -> int:
    import rclpy

    from nsflow_ros.ros.signals import StopRequested, StopSignals, init_without_signal_handlers
    from nsflow_ros.ros.transport import use_large_image_transport

    use_large_image_transport()
    init_without_signal_handlers()
    node = rclpy.create_node("nsflow_replay")
    # SIGINT / SIGTERM stop the replay between messages; the context stays valid for the last log line
    stop = StopSignals(raise_now=True).install()
    try:
        n = publish_stream(
            node,
            replay_stream(ropts),
            rate=ropts.rate,
            clock=clock,
            progress=progress,
            total_s=ropts.duration,
        )
        node.get_logger().info(f"replayed {n} messages from {ropts.path}")
    except (KeyboardInterrupt, StopRequested):
        node.get_logger().info("replay stopped")
    finally:
        node.destroy_node()
        if rclpy.ok():
            rclpy.shutdown()
        stop.restore()
    return 0


if __name__ == "__main__":
    sys.exit(main())
