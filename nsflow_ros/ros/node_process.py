"""The ``tracker`` node's process: its command line, the ROS arguments checked in one line, start and stop.

:func:`main` is ``nsflow-tracker`` / ``ros2 run nsflow_ros tracker`` (re-exported by
:mod:`nsflow_ros.ros.tracker_node`): ``--help`` without middleware, a malformed ``-p`` or params file
refused in one line before rcl sees it, then the node spun until SIGINT / SIGTERM, its summary logged and
written, exit code 0 (1 on a start-up error).
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import TYPE_CHECKING

import rclpy
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor

from nsflow_ros.allocator import keep_large_buffers
from nsflow_ros.errors import NSFlowError
from nsflow_ros.ros.errors import ParameterError
from nsflow_ros.ros.signals import StopRequested, StopSignals, init_without_signal_handlers
from nsflow_ros.ros.tracker_params import NODE_NAME, usage
from nsflow_ros.ros.transport import use_large_image_transport

if TYPE_CHECKING:
    from nsflow_ros.ros.tracker_node import TrackerNode

__all__ = ["main"]


def _program(argv0: str | None) -> str:
    name = Path(argv0 or "nsflow-tracker").name
    if name == "tracker":
        return "ros2 run nsflow_ros tracker"
    return name if name.startswith("nsflow") else "nsflow-tracker"


def _check_ros_args(ros_args: list[str]) -> None:
    """Reject, in one line where rcl would write many, a malformed -p or a params file that cannot be read.

    Raises:
        ParameterError: naming the argument or the file.
    """
    for k, arg in enumerate(ros_args):
        if arg in ("-p", "--param"):
            value = ros_args[k + 1] if k + 1 < len(ros_args) else ""
            if ":=" not in value or value.startswith(":="):
                raise ParameterError(f"{arg} {value}: expected NAME:=VALUE, e.g. -p max_cnt:=150")
        if arg == "--params-file":
            if k + 1 >= len(ros_args):
                raise ParameterError("--params-file needs a file name")
            path = Path(ros_args[k + 1])
            if not path.is_file():
                what = "is not a file" if path.exists() else "does not exist"
                raise ParameterError(f"--params-file {path}: {what} (expected a ROS 2 parameters YAML file)")
            try:
                text = path.read_text(errors="replace")
            except OSError as err:
                raise ParameterError(f"--params-file {path}: cannot read it ({err.strerror})") from err
            _check_yaml(path, text)


def _check_yaml(path: Path, text: str) -> None:
    """A params file must be YAML mapping node names to ``ros__parameters``."""
    try:
        import yaml
    except ImportError:  # rcl checks it then
        return
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as err:
        where = getattr(err, "problem_mark", None)
        line = f" at line {where.line + 1}" if where is not None else ""
        raise ParameterError(f"--params-file {path}: not valid YAML{line}") from err
    if not isinstance(data, dict) or not all(
        isinstance(v, dict) and "ros__parameters" in v for v in data.values()
    ):
        raise ParameterError(
            f"--params-file {path}: expected 'node_name: {{ros__parameters: {{...}}}}' entries "
            "(see config/tracker_params.yaml)"
        )


def _rcl_message(err: Exception) -> str:
    """The first sentence of an rcl error, without the C source locations."""
    text = str(err).split(", at /")[0]
    return text.removeprefix("failed to initialize rcl: ")


def main(args: list[str] | None = None) -> int:
    """Entry point of ``ros2 run nsflow_ros tracker`` / ``nsflow-tracker``; ``args`` include the program.

    Returns:
        0 after a normal stop or ``--help``; 1 on a start-up error; 2 on an unknown argument.
    """
    argv = list(sys.argv if args is None else args)
    prog = _program(argv[0] if argv else None)
    user = argv[1:]
    ros_args: list[str] = []
    if "--ros-args" in user:
        ros_args = user[user.index("--ros-args") + 1 :]
        user = user[: user.index("--ros-args")]
    if "-h" in user or "--help" in user:
        print(usage(prog), end="")
        return 0
    if user:
        print(f"usage: {prog} [-h] [--ros-args ...]\n{prog}: error: unrecognized arguments: {' '.join(user)}",
              file=sys.stderr)
        return 2
    try:
        _check_ros_args(ros_args)
    except ParameterError as err:
        print(f"{NODE_NAME}: error: {err}", file=sys.stderr)
        return 1
    keep_large_buffers()  # per-frame buffers stay on the heap (nsflow_ros.allocator)
    profile = use_large_image_transport()
    with StopSignals() as stop:
        try:
            init_without_signal_handlers(argv)
        except Exception as err:
            print(f"{NODE_NAME}: error: bad ROS arguments: {_rcl_message(err)}", file=sys.stderr)
            return 1
        return _run(stop, profile)


def _run(stop: StopSignals, profile: Path | None) -> int:
    from nsflow_ros.ros.tracker_node import TrackerNode  # the node module re-exports main: not at import

    node: TrackerNode | None = None
    executor: SingleThreadedExecutor | None = None
    code = 0
    try:
        node = TrackerNode()
        if profile is not None:
            node.get_logger().info(f"Fast DDS transports from {profile} (FASTRTPS_DEFAULT_PROFILES_FILE)")
        executor = SingleThreadedExecutor()
        executor.add_node(node)
        # Short waits: a signal only sets a flag, seen here within 0.2 s.
        while not stop.requested.is_set() and rclpy.ok():
            executor.spin_once(timeout_sec=0.2)
    except NSFlowError as err:
        print(f"{NODE_NAME}: error: {err}", file=sys.stderr)
        code = 1
    except (KeyboardInterrupt, ExternalShutdownException, StopRequested):
        pass  # a stop while starting up, or a second signal
    finally:
        if node is not None:
            node.stop_worker()
            if rclpy.ok():
                node.get_logger().info(f"shutting down: {node.summary()}")
            try:
                node.write_summary_file()
            except OSError as err:
                print(f"{NODE_NAME}: error: cannot write the summary file: {err}", file=sys.stderr)
                code = code or 1
            if executor is not None:
                executor.shutdown(timeout_sec=1.0)
            node.destroy_node()
        if rclpy.ok():
            rclpy.shutdown()
    return code
