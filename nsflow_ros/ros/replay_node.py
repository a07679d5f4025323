"""``nsflow-replay``: play a bag or ASL folder over ROS 2 topics, optionally perturbed.

This module paces :func:`nsflow_ros.data.replay.replay_stream` on wall time and publishes it; it first waits
for a camera topic's subscribers, so a tracker started just before or after the replay gets the first frame.
"""

from __future__ import annotations

import argparse
import importlib
import sys
import time
from collections.abc import Iterable, Iterator
from itertools import chain
from pathlib import Path
from typing import Any

from nsflow_ros.argtypes import (
    non_negative_float,
    non_negative_int,
    positive_float,
    positive_int,
    program_name,
)
from nsflow_ros.core.methods import METHODS
from nsflow_ros.data.errors import DataError
from nsflow_ros.data.perturb import PERTURBATIONS
from nsflow_ros.data.records import RawMessage
from nsflow_ros.data.replay import COMPRESSIONS, ReplayOptions, parse_remaps, replay_stream
from nsflow_ros.errors import NSFlowError

__all__ = ["DESCRIPTION", "main", "message_class", "publish_stream", "wait_for_subscribers"]

DESCRIPTION = (
    "Play a ROS 1 bag, ROS 2 bag or EuRoC / UMA-VI ASL folder over ROS 2 topics (images with sensor-data "
    "QoS, IMU and the rest reliable, /clock), optionally with the paper's illumination perturbation. "
    "Or, without ROS: write the stream to a new ROS 2 bag (--write-bag), track it offline (--offline), or "
    "track every frame offline and write a VINS-Fusion feature bag with the IMU (--features-bag) for "
    "'rosbag play' into the estimator. ROS arguments after --ros-args (e.g. -r /cam0/image_raw:=/left) "
    "apply to the published topics."
)


def message_class(msgtype: str) -> Any:
    """The rclpy message class of a ROS 2 type name such as ``sensor_msgs/msg/Image``."""
    pkg, _, name = msgtype.rpartition("/msg/")
    try:
        return getattr(importlib.import_module(f"{pkg}.msg"), name)
    except (ImportError, AttributeError) as err:
        raise NSFlowError(f"message type {msgtype} is not available in this ROS installation") from err


def wait_for_subscribers(publishers: Iterable[Any], count: int, timeout: float, settle: float = 0.5) -> bool:
    """Wait until one of ``publishers`` has matched ``count`` subscriptions, or ``timeout`` seconds passed.

    Args:
        count: subscriptions to wait for; 0 returns at once.
        settle: seconds to wait after the match: the publisher sees the subscriber before the subscriber
            has matched the publisher, and a best-effort sample sent in between is lost.

    Returns:
        whether the subscribers matched in time.
    """
    if count <= 0:
        return True
    pubs = list(publishers)
    deadline = time.monotonic() + timeout
    while not any(p.get_subscription_count() >= count for p in pubs):
        if time.monotonic() >= deadline:
            return False
        time.sleep(0.02)
    time.sleep(settle)
    return True


def publish_stream(
    node: Any,
    stream: Iterable[RawMessage],
    *,
    rate: float = 1.0,
    clock: bool = True,
    progress: bool = True,
    total_s: float | None = None,
    publishers: dict[str, Any] | None = None,
    wait_subscribers: int = 0,
    wait_timeout: float = 10.0,
) -> int:
    """Publish a message stream from ``node``, paced by the messages' stamps.

    Args:
        rate: speed factor (1.0 = real time, 0 = as fast as possible).
        clock: publish rosgraph_msgs/Clock with each message's time.
        progress: show a progress bar (seconds of data replayed).
        total_s: length of the stream in seconds, for the progress bar.
        publishers: topic -> publisher, reused and filled across calls (None: new ones per call).
        wait_subscribers: before the first message, create the publishers of the first second's topics
            and wait until a camera topic has this many subscribers (0 = no wait).
        wait_timeout: seconds to wait for them at most; then publishing starts anyway, with a warning.

    Returns:
        number of messages published.

    Raises:
        DataError: where the stream stops being readable (a truncated bag), after publishing every message
            before it; the message says how many were published, as ``--features-bag`` says how many frames
            it wrote.
    """
    from rclpy.qos import QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
    from rosgraph_msgs.msg import Clock

    from nsflow_ros.progress import progress_bar

    pubs: dict[str, Any] = {} if publishers is None else publishers
    clock_pub = node.create_publisher(Clock, "/clock", 10) if clock else None
    reliable = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)

    def publisher(msg: RawMessage) -> Any:
        if msg.topic not in pubs:
            qos = qos_profile_sensor_data if msg.msgtype.endswith("Image") else reliable
            pubs[msg.topic] = node.create_publisher(message_class(msg.msgtype), msg.topic, qos)
        return pubs[msg.topic]

    messages = iter(stream)
    if wait_subscribers > 0:
        head, cut = _head(messages, 1.0)
        for msg in head:
            publisher(msg)
        cameras = [pubs[m.topic] for m in head if m.msgtype.endswith("Image")]
        if not wait_for_subscribers(cameras or pubs.values(), wait_subscribers, wait_timeout):
            node.get_logger().warning(
                f"no {wait_subscribers} subscriber(s) on a camera topic after {wait_timeout:g} s; "
                "publishing anyway"
            )
        messages = chain(head, messages if cut is None else _raise(cut))
    # the bar counts tenths of seconds as integers: no 2.5700000000000003 s
    fmt = "{desc}: {percentage:3.0f}%|{bar}| {postfix} [{elapsed}<{remaining}]"
    if not total_s:
        fmt = "{desc}: {postfix} [{elapsed}]"
    total = None if total_s is None else round(total_s * 10)
    bar = progress_bar(total=total, enabled=progress, desc="replay", bar_format=fmt)
    t0_data = t0_wall = None
    shown = 0
    count = 0
    try:
        for msg in messages:
            pub = publisher(msg)
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
            pub.publish(msg.cdr)
            count += 1
            tenths = int(elapsed * 10)
            if tenths > shown:
                bar.set_postfix_str(_progress_text(tenths, total_s), refresh=False)
                bar.update(tenths - shown)
                shown = tenths
    except DataError as err:  # the data ends here: say so, with what went out before it
        raise DataError(f"{err} (the {count} messages before it were published)") from err
    finally:
        bar.close()
    return count


def _progress_text(tenths: int, total_s: float | None) -> str:
    done = f"{tenths / 10:.1f}"
    return f"{done} s" if total_s is None else f"{done}/{total_s:.1f} s"


def _head(messages: Iterator[RawMessage], seconds: float) -> tuple[list[RawMessage], DataError | None]:
    """The first ``seconds`` of data (at least one message), taken from ``messages``; with the error that
    ended the data sooner, so that the messages read before it are still published."""
    head: list[RawMessage] = []
    try:
        for msg in messages:
            head.append(msg)
            if msg.stamp_ns - head[0].stamp_ns >= seconds * 1e9:
                break
    except DataError as err:
        return head, err
    return head, None


def _raise(err: DataError) -> Iterator[RawMessage]:
    raise err
    yield  # a generator: raises when the messages before it are used up


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog=program_name("nsflow-replay"), description=DESCRIPTION)
    p.add_argument("path", type=Path, help="ROS 1 .bag, ROS 2 bag folder/.mcap/.db3, or ASL folder")
    p.add_argument(
        "--topics",
        nargs="+",
        default=None,
        metavar="TOPIC",
        help="topics to replay; each must exist in the source (default: the EuRoC / UMA-VI camera and IMU "
        "topics present). With --offline / --features-bag they must include the config's camera topics",
    )
    p.add_argument("--start", type=non_negative_float, default=0.0, help="seconds to skip (default 0)")
    p.add_argument("--duration", type=positive_float, default=None, help="seconds to replay (default: all)")
    p.add_argument(
        "--rate", type=non_negative_float, default=1.0,
        help="speed factor, 0 = as fast as possible (default 1)",
    )
    p.add_argument(
        "--perturb",
        choices=tuple(PERTURBATIONS),
        default="none",
        help="perturbation of the images: the paper's illumination levels small / large, or dark (five "
        "stops under-exposed with a real sensor's shot and read noise, gained back up; docs/evaluation.md) "
        "(default none)",
    )
    p.add_argument("--seed", type=int, default=0, help="perturbation seed (default 0)")
    p.add_argument(
        "--compress",
        choices=COMPRESSIONS,
        default="none",
        help="publish the camera images as sensor_msgs/CompressedImage of this codec on <topic>/compressed, "
        "as image_transport's compressed plugin does (for the tracker's image_transport:=compressed; "
        "default none: sensor_msgs/Image)",
    )
    p.add_argument(
        "--jpeg-quality", type=positive_int, default=90, metavar="N",
        help="JPEG quality 1..100 with --compress jpeg (default 90)",
    )
    p.add_argument(
        "--remap",
        action="append",
        nargs="+",
        default=[],
        metavar="FROM:=TO",
        help="rename a topic, e.g. --remap /cam0/image_raw:=/left; repeat for more",
    )
    p.add_argument(
        "--wait-subscribers",
        type=non_negative_int,
        default=1,
        metavar="N",
        help="before publishing, wait until N subscribers listen to a camera topic (default 1; 0 = no wait)",
    )
    p.add_argument(
        "--wait-timeout",
        type=non_negative_float,
        default=10.0,
        metavar="S",
        help="seconds to wait for them at most, then publish anyway (default 10)",
    )
    p.add_argument("--no-clock", action="store_true", help="do not publish /clock")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    mode = p.add_mutually_exclusive_group()
    mode.add_argument(
        "--write-bag",
        type=Path,
        default=None,
        metavar="OUT",
        help="write the (perturbed) stream to this new ROS 2 bag instead of publishing",
    )
    mode.add_argument(
        "--offline",
        type=Path,
        default=None,
        metavar="OUT_DIR",
        help="track camera 0 without ROS and write features.csv, tracks.png and summary.json here",
    )
    mode.add_argument(
        "--features-bag",
        type=Path,
        default=None,
        metavar="OUT",
        help="track every frame without ROS and write /feature_tracker/feature (VINS-Fusion layout) plus the "
        "IMU to this new bag: OUT.bag = ROS 1, any other name = ROS 2 (mcap folder)",
    )
    p.add_argument(
        "--features-bag-format",
        choices=("ros1", "ros2"),
        default=None,
        help="format of --features-bag (default: ros1 for a .bag name, else ros2)",
    )
    p.add_argument(
        "--config",
        type=Path,
        default=None,
        help="VINS config for --offline / --features-bag: cameras, topics, max_cnt, min_dist, ...; "
        "num_of_cam: 2 tracks stereo (default: the shipped EuRoC mono config)",
    )
    p.add_argument(
        "--method",
        choices=tuple(METHODS),
        default="nsflow",
        help="tracker for --offline / --features-bag: "
        + "; ".join(f"{name} = {entry.summary}" for name, entry in METHODS.items())
        + " (default nsflow)",
    )
    p.add_argument(
        "--model", default=None,
        help="encoder of the learned methods for --offline / --features-bag: an ONNX file, or a shipped "
        "model by name, default (also fast) or d4 (as the node's model_path parameter; default: the "
        "method's: d4 for nsflow_lk, else default)",
    )
    p.add_argument(
        "--downsample", type=int, default=1, metavar="N",
        help="for --offline / --features-bag: track on images decimated by N (1, 2 or 4, for cameras larger "
        "than 752x480) and write the features in the config's full-resolution calibration (as the node's "
        "downsample parameter; default 1)",
    )
    p.add_argument(
        "--publish-rate", type=non_negative_float, default=None, metavar="HZ",
        help="for --features-bag: track every frame but write at most HZ feature messages a second, with "
        "velocities over the written interval (as the node's publish_rate parameter; default: every frame)",
    )
    p.add_argument(
        "--max-sigma", type=non_negative_float, default=None, metavar="PX",
        help="for --features-bag: leave out features whose predicted standard deviation exceeds PX (as the "
        "node's max_sigma parameter; default 0 = off)",
    )
    p.add_argument(
        "--mask0", type=Path, default=None, metavar="IMAGE",
        help="static mask image of camera 0 for --offline / --features-bag (as the node's mask0 parameter: "
        "no feature on its masked pixels; default: the config's mask0 key, else none)",
    )
    p.add_argument(
        "--mask1", type=Path, default=None, metavar="IMAGE",
        help="static mask image of camera 1 for --features-bag with a stereo config (as the node's mask1)",
    )
    p.add_argument(
        "--mask-convention", choices=("vins", "openvins"), default="vins",
        help="how --mask0 / --mask1 and the config's mask keys mark pixels: vins = 255 where features may "
        "be, openvins = 255 where none may be (default vins; as the node's mask_convention)",
    )
    p.add_argument(
        "--providers", default="cpu",
        help="onnxruntime execution providers of the encoder for --offline / --features-bag, best first, "
        "e.g. cuda,cpu (default cpu; as the node's providers parameter)",
    )
    return p


def _remaps(groups: list[list[str]]) -> list[str]:
    """Flatten ``--remap`` values; several after one ``--remap`` still work, with a note."""
    if any(len(g) > 1 for g in groups):
        print(
            f"{program_name('nsflow-replay')}: note: several remaps after one --remap are deprecated; "
            "repeat --remap FROM:=TO for each",
            file=sys.stderr,
        )
    return [item for g in groups for item in g]


def main(args: list[str] | None = None) -> int:
    """Entry point of ``nsflow-replay`` / ``ros2 run nsflow_ros replay``.

    Returns:
        0 on success, 1 on a known error (one line on stderr), 2 on bad arguments (argparse).
    """
    argv = list(sys.argv[1:] if args is None else args)
    ros_args: list[str] = []
    if "--ros-args" in argv:
        argv, ros_args = argv[: argv.index("--ros-args")], argv[argv.index("--ros-args") :]
    parser = _parser()
    opts = parser.parse_args(argv)
    if opts.compress != "none" and (opts.write_bag or opts.offline or opts.features_bag):
        parser.error("--compress applies to publishing, not to --write-bag / --offline / --features-bag")
    if opts.publish_rate is not None and opts.features_bag is None:
        parser.error("--publish-rate applies to --features-bag")
    if opts.max_sigma is not None and opts.features_bag is None:
        parser.error("--max-sigma applies to --features-bag")
    if opts.downsample != 1 and opts.offline is None and opts.features_bag is None:
        parser.error("--downsample applies to --offline / --features-bag (the node has its parameter)")
    tracked = opts.offline is not None or opts.features_bag is not None
    if (opts.mask0 or opts.mask1) and not tracked:
        parser.error("--mask0 / --mask1 apply to --offline / --features-bag")
    if opts.jpeg_quality > 100:
        parser.error(f"--jpeg-quality: expected 1..100, got {opts.jpeg_quality}")
    prog = program_name("nsflow-replay")
    try:
        from nsflow_ros.data.sources import detect_kind

        detect_kind(opts.path)  # a missing or foreign input fails here, before any output exists
        ropts = ReplayOptions(
            opts.path,
            opts.topics,
            opts.start,
            opts.duration,
            opts.rate,
            opts.perturb,
            opts.seed,
            parse_remaps(_remaps(opts.remap)),
            compress=opts.compress,
            jpeg_quality=opts.jpeg_quality,
        )
        if opts.offline is not None or opts.features_bag is not None:
            from nsflow_ros.ros.replay_tracked import run_tracked

            return run_tracked(opts, ropts, prog)
        if opts.write_bag is not None:
            from nsflow_ros.data.replay import replay_records
            from nsflow_ros.data.writers import write_ros2_bag

            n = write_ros2_bag(opts.write_bag, replay_records(ropts))
            print(f"wrote {n} messages to {opts.write_bag}")
            return 0
        return _publish(ropts, opts, ros_args)
    except NSFlowError as err:
        print(f"{prog}: {err}", file=sys.stderr)
        return 1
    except OSError as err:  # an output that cannot be written (disk full, permissions)
        print(f"{prog}: cannot write {err.filename}: {err.strerror}", file=sys.stderr)
        return 1


def _publish(ropts: ReplayOptions, opts: argparse.Namespace, ros_args: list[str]) -> int:
    """Publish the stream of ``ropts`` over ROS 2 with the clock, progress and wait that ``opts`` ask for."""
    import rclpy

    from nsflow_ros.ros.signals import StopRequested, StopSignals, init_without_signal_handlers
    from nsflow_ros.ros.transport import use_large_image_transport

    use_large_image_transport()
    # --ros-args remaps apply to the publishers
    init_without_signal_handlers(args=["nsflow-replay", *ros_args])
    node = rclpy.create_node("nsflow_replay")
    # SIGINT / SIGTERM stop the replay between messages; the context stays valid for the last log line
    stop = StopSignals(raise_now=True).install()
    try:
        n = publish_stream(
            node,
            replay_stream(ropts),
            rate=ropts.rate,
            clock=not opts.no_clock,
            progress=not opts.no_progress,
            total_s=ropts.duration,
            wait_subscribers=opts.wait_subscribers,
            wait_timeout=opts.wait_timeout,
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
