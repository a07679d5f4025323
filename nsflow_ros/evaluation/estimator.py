"""Run the stock VINS-Fusion estimator (ROS 1) on a feature bag and score its trajectory.

This module only starts subprocesses (no ROS import): a private ``rosmaster`` on a free port, then
``vins_node`` with a copy of the VINS config whose image topics are idle (its own tracker must see no
image; the features come from the bag), then ``rosbag play -q -d 1`` of the bag (Debian's python3-rosbag,
run by the system Python through the workspace's ``devel/setup.bash``, never the caller's venv). When the
play has ended and the estimator has stopped writing, everything is stopped with SIGINT, then SIGKILL.
Each run has its own ``ROS_MASTER_URI``, so runs in parallel cannot collide. Typical use::

    vins = VinsBuild.locate("~/vins_ws")                  # scripts/build_vins_fusion.sh builds it
    vio = run_vins(Path("klt.bag"), Path("config/euroc/euroc_stereo_imu_config.yaml"), vins,
                   Path("runs/klt/0"), timeout_s=120)
    print(score_vio(vio, Path("sample20/groundtruth.csv")).stats.rmse)
"""

from __future__ import annotations

import http.client
import json
import os
import re
import shutil
import signal
import socket
import subprocess
import time
import xmlrpc.client
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from nsflow_ros.ate import APEResult, evaluate_ape, read_trajectory
from nsflow_ros.evaluation.errors import EstimatorError

__all__ = [
    "DEFAULT_WORKSPACE",
    "FEATURE_TOPIC",
    "IDLE_IMAGE_TOPICS",
    "RUN_RECORD",
    "VinsBuild",
    "estimator_config",
    "free_port",
    "run_vins",
    "score_vio",
]

DEFAULT_WORKSPACE = Path("~/vins_ws")
"""Where ``scripts/build_vins_fusion.sh`` builds by default (``$NSFLOW_VINS_WS`` overrides it)."""

IDLE_IMAGE_TOPICS: tuple[str, str] = ("/nsflow_idle/image0", "/nsflow_idle/image1")
"""The image topics the estimator's copy of the config names: nothing publishes them."""

FEATURE_TOPIC = "/feature_tracker/feature"
"""The topic ``vins_node`` takes features from; a run starts the play once it has subscribed."""

RUN_RECORD = "estimator_run.json"
"""Written into the run folder beside ``vio.csv``: the master's URI, the wall time of the run and of its
phases (start until the play, the play, the settle, the stop), the pose count, exit codes. The stock
``vins_node`` aborts on SIGINT (``terminate called without an active exception``: upstream leaves its
sync thread joinable at exit), so its status after the stop is -6; the trajectory is complete by then."""

_SYSTEM_PATH = "/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin"
_POLL_S = 0.02
_LOG_TAIL = 1500


@dataclass(frozen=True)
class VinsBuild:
    """A built VINS-Fusion catkin workspace: its environment script and the estimator binary."""

    workspace: Path
    setup: Path
    vins_node: Path

    @classmethod
    def locate(cls, folder: str | Path | None = None) -> VinsBuild:
        """Find the build in a catkin workspace folder.

        Args:
            folder: the workspace (the folder given to ``scripts/build_vins_fusion.sh``); ``None``:
                ``$NSFLOW_VINS_WS``, else :data:`DEFAULT_WORKSPACE`.

        Returns:
            The build, with absolute paths.

        Raises:
            EstimatorError: naming each missing piece (the folder, ``devel/setup.bash``,
                ``devel/lib/vins/vins_node`` or its executable bit).
        """
        if folder is None:
            folder = os.environ.get("NSFLOW_VINS_WS") or DEFAULT_WORKSPACE
        ws = Path(folder).expanduser()
        hint = f"build it with: scripts/build_vins_fusion.sh {ws}"
        if not ws.is_dir():
            raise EstimatorError(f"VINS-Fusion workspace {ws} does not exist; {hint}")
        setup = ws / "devel" / "setup.bash"
        node = ws / "devel" / "lib" / "vins" / "vins_node"
        missing = []
        if not setup.is_file():
            missing.append(f"{setup} (the workspace's environment script)")
        if not node.is_file():
            missing.append(f"{node} (the estimator)")
        elif not os.access(node, os.X_OK):
            missing.append(f"the executable bit of {node}")
        if missing:
            raise EstimatorError(
                f"{ws} is not a built VINS-Fusion workspace: missing {'; '.join(missing)}; {hint}"
            )
        return cls(ws.resolve(), setup.resolve(), node.resolve())


_KEY_LINE = re.compile(r"^(?P<key>[A-Za-z_][A-Za-z0-9_]*)[ \t]*:(?P<rest>.*)$")


def _scalar(rest: str) -> str:
    """The value of a top-level ``key: value  # comment`` line, quotes removed."""
    rest = rest.strip()
    if rest[:1] in ("'", '"'):
        end = rest.find(rest[0], 1)
        return rest[1:end] if end > 0 else rest[1:]
    return rest.split("#", 1)[0].strip()


def estimator_config(
    config: Path, out_dir: Path, *, idle_topics: tuple[str, str] = IDLE_IMAGE_TOPICS,
    solver_time: float | None = None,
) -> Path:
    """Write the estimator's copy of a VINS-Fusion config into ``out_dir``.

    The copy is the file line for line, except ``image0_topic`` / ``image1_topic`` (renamed to topics
    nothing publishes, so the estimator's own tracker stays idle) and ``output_path`` (``out_dir``, where
    ``vio.csv`` goes). The camera files the config names (``camN_calib``, relative to the config, as the
    estimator reads them) are copied beside it.

    Args:
        config: the VINS-Fusion config the features were tracked with (OpenCV YAML).
        out_dir: the run folder (created if needed).
        idle_topics: the two image topics to name instead.
        solver_time: ``max_solver_time`` (s) of the copy; None = the config's. The solver stops at this
            wall-clock budget or at ``max_num_iterations``: a budget no solve reaches makes the runs of one
            bag agree on a loaded machine as they do on an idle one.

    Returns:
        The path of the copy, ``out_dir/<config stem>_estimator.yaml``.

    Raises:
        EstimatorError: for an unreadable config, a missing ``image0_topic`` / ``output_path`` (or
            ``image1_topic`` with ``num_of_cam: 2``), or a camera file that does not exist.
    """
    config = Path(config)
    out_dir = Path(out_dir).resolve()
    try:
        lines = config.read_text(encoding="utf-8").splitlines()
    except (OSError, UnicodeDecodeError) as err:
        raise EstimatorError(f"cannot read the VINS config {config}: {err}") from err
    values: dict[str, str] = {}
    for line in lines:
        m = _KEY_LINE.match(line)
        if m:
            values.setdefault(m["key"], _scalar(m["rest"]))
    try:
        num_cam = int(values.get("num_of_cam", "1"))
    except ValueError as err:
        raise EstimatorError(f"{config}: num_of_cam is {values['num_of_cam']!r}, not 1 or 2") from err
    required = ["image0_topic", "output_path"] + (["image1_topic"] if num_cam >= 2 else [])
    absent = [key for key in required if key not in values]
    if absent:
        raise EstimatorError(f"{config}: no {', '.join(absent)} (the estimator's copy must set them)")

    replace = {
        "image0_topic": f'"{idle_topics[0]}"',
        "image1_topic": f'"{idle_topics[1]}"',
        "output_path": f'"{out_dir}/"',
    }
    if solver_time is not None:
        if not solver_time > 0:
            raise EstimatorError(f"solver_time must be > 0 s, got {solver_time}")
        if "max_solver_time" not in values:
            raise EstimatorError(f"{config}: no max_solver_time to set")
        replace["max_solver_time"] = f"{solver_time:g}"
    out: list[str] = []
    for line in lines:
        m = _KEY_LINE.match(line)
        if m and m["key"] in replace:
            line = f"{m['key']}: {replace.pop(m['key'])}   # set by nsflow_ros.evaluation.estimator"
        out.append(line)

    out_dir.mkdir(parents=True, exist_ok=True)
    for cam in range(num_cam):
        key = f"cam{cam}_calib"
        if key not in values:
            raise EstimatorError(f"{config}: no {key} (num_of_cam is {num_cam})")
        src = config.parent / values[key]
        if not src.is_file():
            raise EstimatorError(f"{config}: {key} names {src}, which does not exist")
        dst = out_dir / values[key]
        if src.resolve() != dst.resolve():
            dst.parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(src, dst)
    target = out_dir / f"{config.stem}_estimator.yaml"
    if target.resolve() == config.resolve():
        raise EstimatorError(f"{config}: the estimator's copy would overwrite it; choose another out_dir")
    target.write_text("\n".join(out) + "\n", encoding="utf-8")
    return target


def free_port() -> int:
    """A TCP port on 127.0.0.1 that nothing listens on now (the kernel's pick)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


class _Transport(xmlrpc.client.Transport):
    """XML-RPC to the master with a short timeout (a hung master must not hang the run)."""

    def make_connection(self, host: object) -> http.client.HTTPConnection:
        conn = super().make_connection(host)  # type: ignore[arg-type]
        conn.timeout = 2.0
        return conn


def _master_call(master_uri: str, method: str) -> object | None:
    """The value of a master API call (``getPid``, ``getSystemState``); ``None`` if it does not answer."""
    try:
        proxy = xmlrpc.client.ServerProxy(master_uri, transport=_Transport())
        code, _msg, value = getattr(proxy, method)("/nsflow_estimator")
    except (OSError, ValueError, xmlrpc.client.Error, http.client.HTTPException):
        return None
    return value if code == 1 else None


def _subscribed_topics(master_uri: str) -> set[str] | None:
    """Topics with a subscriber, from the master's ``getSystemState``; ``None`` if it does not answer."""
    state = _master_call(master_uri, "getSystemState")
    if not isinstance(state, list) or len(state) < 2:
        return None
    return {str(entry[0]) for entry in state[1]}


def _ros_env(master_uri: str, out_dir: Path) -> dict[str, str]:
    """A clean environment for the ROS 1 processes: the system PATH (no venv, no PYTHONPATH), the
    run's own master, loopback addresses, logs inside the run folder."""
    return {
        "PATH": _SYSTEM_PATH,
        "HOME": os.environ.get("HOME", str(out_dir)),
        "LANG": "C.UTF-8",
        "ROS_MASTER_URI": master_uri,
        "ROS_IP": "127.0.0.1",
        "ROS_HOME": str(out_dir / "ros_home"),
        "ROS_LOG_DIR": str(out_dir / "ros_log"),
    }


def _start(
    name: str, argv: Sequence[str], vins: VinsBuild, env: dict[str, str], out_dir: Path
) -> subprocess.Popen:
    """Start ``argv`` in a new session under the workspace's environment, output to ``<name>.log``."""
    cmd = ["bash", "-c", 'source "$0" >/dev/null && exec "$@"', str(vins.setup), *argv]
    with open(out_dir / f"{name}.log", "wb") as log:
        try:
            return subprocess.Popen(
                cmd,
                cwd=out_dir,
                env=env,
                stdin=subprocess.DEVNULL,
                stdout=log,
                stderr=subprocess.STDOUT,
                start_new_session=True,
            )
        except OSError as err:
            raise EstimatorError(f"cannot start {name} ({' '.join(argv)}): {err}") from err


def _stop(proc: subprocess.Popen, grace_s: float) -> int:
    """SIGINT the process's group, wait ``grace_s``, then SIGKILL it; returns the exit status."""
    for sig, wait_s in ((signal.SIGINT, grace_s), (signal.SIGKILL, None)):
        if proc.poll() is not None:
            break
        try:
            os.killpg(proc.pid, sig)
        except ProcessLookupError:
            break
        try:
            proc.wait(wait_s)
        except subprocess.TimeoutExpired:
            continue
    return proc.wait()


def _log_tail(out_dir: Path, name: str) -> str:
    try:
        text = (out_dir / f"{name}.log").read_bytes()[-_LOG_TAIL:].decode("utf-8", "replace").strip()
    except OSError:
        return f"(no {name}.log)"
    return f"last lines of {out_dir / (name + '.log')}:\n{text}" if text else f"{name}.log is empty"


def _died(out_dir: Path, name: str, proc: subprocess.Popen, when: str) -> EstimatorError:
    return EstimatorError(f"{name} exited with status {proc.returncode} {when}; {_log_tail(out_dir, name)}")


def _start_master(
    vins: VinsBuild, out_dir: Path, deadline: float, tries: int = 3
) -> tuple[subprocess.Popen, str, dict[str, str]]:
    """Start ``rosmaster --core`` on a free port and wait until it answers; a port taken between the
    pick and the bind (another run) costs one more try."""
    for _ in range(tries):
        port = free_port()
        uri = f"http://127.0.0.1:{port}/"
        env = _ros_env(uri, out_dir)
        proc = _start("rosmaster", ["rosmaster", "--core", "-p", str(port), "-w", "3"], vins, env, out_dir)
        while time.monotonic() < deadline:
            if proc.poll() is not None:
                break
            pid = _master_call(uri, "getPid")
            if pid == proc.pid:
                return proc, uri, env
            if pid is not None:  # another run's master took the port first; ours will exit
                _stop(proc, 2.0)
                break
            time.sleep(_POLL_S)
        else:
            _stop(proc, 2.0)
            raise EstimatorError(
                f"rosmaster on port {port} did not answer within the start-up limit; "
                f"{_log_tail(out_dir, 'rosmaster')}"
            )
    raise _died(out_dir, "rosmaster", proc, f"at start ({tries} ports tried)")


def _wait_quiet(vio: Path, node: subprocess.Popen, settle_s: float, deadline: float) -> bool:
    """Wait until ``vio`` has not changed for ``settle_s`` (the estimator has caught up: True), the node
    has exited or the deadline passes (False)."""
    last, since = None, time.monotonic()
    while time.monotonic() < deadline and node.poll() is None:
        try:
            stat = vio.stat()
            sig: tuple[int, int] | None = (stat.st_size, stat.st_mtime_ns)
        except OSError:
            sig = None
        now = time.monotonic()
        if sig != last:
            last, since = sig, now
        elif now - since >= settle_s:
            return True
        time.sleep(_POLL_S)
    return False


def run_vins(
    features_bag: Path,
    config: Path,
    vins: VinsBuild,
    out_dir: Path,
    *,
    timeout_s: float,
    settle_s: float = 2.0,
    play_args: Sequence[str] = ("-q", "-d", "1"),
    startup_timeout_s: float = 30.0,
    stop_timeout_s: float = 10.0,
    solver_time: float | None = None,
) -> Path:
    """Play a feature bag into the stock estimator and return the trajectory it wrote.

    Args:
        features_bag: a ROS 1 feature bag (``nsflow-replay --features-bag X.bag``: features and IMU).
        config: the VINS-Fusion config the features were tracked with; the estimator gets a copy
            (:func:`estimator_config`).
        vins: the build (:meth:`VinsBuild.locate`).
        out_dir: the run folder: the config copy, ``vio.csv``, each process's log, :data:`RUN_RECORD`.
        timeout_s: the whole run's limit in seconds (start, play, settle).
        settle_s: after the play, wait until ``vio.csv`` has not changed for this long.
        play_args: options of ``rosbag play`` before the bag (``-d 1``: a second for subscribers to
            connect after each advertise; ``-q``: no progress line, which fills the log by 17 kB/s).
        startup_timeout_s: limit for the master to answer and ``vins_node`` to subscribe.
        stop_timeout_s: grace after SIGINT before SIGKILL, per process.
        solver_time: the copy's ``max_solver_time`` (:func:`estimator_config`); None = the config's.

    Returns:
        ``out_dir/vio.csv``, holding at least one pose.

    Raises:
        EstimatorError: for a missing bag, a bad config, ``rosmaster`` / ``vins_node`` / ``rosbag play``
            that died or did not start in time, a run over ``timeout_s``, or no pose in ``vio.csv``; the
            message quotes the end of the failing process's log.
    """
    bag = Path(features_bag).resolve()
    if not bag.is_file():
        raise EstimatorError(f"feature bag {bag} does not exist")
    out_dir = Path(out_dir).resolve()
    cfg = estimator_config(Path(config), out_dir, solver_time=solver_time)
    vio = out_dir / "vio.csv"
    vio.unlink(missing_ok=True)
    (out_dir / RUN_RECORD).unlink(missing_ok=True)

    t0 = time.monotonic()
    deadline = t0 + timeout_s
    start_deadline = min(deadline, t0 + startup_timeout_s)
    procs: dict[str, subprocess.Popen] = {}
    record: dict[str, object] = {"bag": str(bag), "config": str(cfg)}
    try:
        master, uri, env = _start_master(vins, out_dir, start_deadline)
        procs["rosmaster"] = master
        record["master_uri"] = uri
        node = _start("vins_node", [str(vins.vins_node), str(cfg)], vins, env, out_dir)
        procs["vins_node"] = node
        while FEATURE_TOPIC not in (_subscribed_topics(uri) or set()):
            if node.poll() is not None:
                raise _died(out_dir, "vins_node", node, "before it subscribed to " + FEATURE_TOPIC)
            if master.poll() is not None:
                raise _died(out_dir, "rosmaster", master, "while vins_node started")
            if time.monotonic() > start_deadline:
                limit = min(timeout_s, startup_timeout_s)
                raise EstimatorError(
                    f"vins_node did not subscribe to {FEATURE_TOPIC} within {limit:g} s; "
                    f"{_log_tail(out_dir, 'vins_node')}"
                )
            time.sleep(_POLL_S)
        t_play = time.monotonic()
        record["start_s"] = round(t_play - t0, 3)
        play = _start("rosbag_play", ["rosbag", "play", *play_args, str(bag)], vins, env, out_dir)
        procs["rosbag_play"] = play
        while play.poll() is None:
            if node.poll() is not None:
                raise _died(out_dir, "vins_node", node, "during the play")
            if time.monotonic() > deadline:
                raise EstimatorError(
                    f"the run took longer than timeout_s={timeout_s:g} s (the play had not ended)"
                )
            time.sleep(_POLL_S)
        if play.returncode != 0:
            raise _died(out_dir, "rosbag_play", play, f"playing {bag}")
        t_quiet = time.monotonic()
        record["play_s"] = round(t_quiet - t_play, 3)
        quiet = _wait_quiet(vio, node, settle_s, deadline)
        record["settle_s"] = round(time.monotonic() - t_quiet, 3)
        if node.poll() is not None:
            raise _died(out_dir, "vins_node", node, "after the play")
        if not quiet:
            raise EstimatorError(
                f"the run took longer than timeout_s={timeout_s:g} s (vins_node was still writing {vio} "
                f"{record['settle_s']:g} s after the play ended: the trajectory would be cut short)"
            )
    finally:
        t_stop = time.monotonic()
        codes = {name: _stop(proc, stop_timeout_s) for name, proc in reversed(procs.items())}
    record["stop_s"] = round(time.monotonic() - t_stop, 3)
    record["exit_status_after_stop"] = codes
    record["wall_s"] = round(time.monotonic() - t0, 3)
    try:
        poses = sum(1 for line in vio.read_text(encoding="utf-8").splitlines() if line.strip())
    except OSError:
        poses = 0
    if poses == 0:
        raise EstimatorError(
            f"vins_node wrote no pose to {vio} (did it initialise? is the bag's IMU topic the config's?); "
            f"{_log_tail(out_dir, 'vins_node')}"
        )
    record["poses"] = poses
    (out_dir / RUN_RECORD).write_text(json.dumps(record, indent=2) + "\n", encoding="utf-8")
    return vio


def score_vio(vio: Path, ground_truth: Path, *, align: str = "se3", max_diff: float = 0.01) -> APEResult:
    """The ATE of an estimator trajectory against ground truth, as ``nsflow-ate GT VIO --align se3``.

    Args:
        vio: the ``vio.csv`` :func:`run_vins` returned (VINS format).
        ground_truth: the sample's ``groundtruth.csv`` (or an ASL / EuRoC ground-truth file or folder).
        align: ``"se3"`` (the project's figures), ``"sim3"`` or ``"none"``.
        max_diff: stamp association tolerance in seconds.

    Returns:
        The APE result: ``.stats.rmse`` in metres, the matched poses, the alignment.

    Raises:
        ATEError: for an unreadable trajectory, too few matched poses or a degenerate alignment.
    """
    ref = read_trajectory(ground_truth)
    est = read_trajectory(vio, "vins")
    return evaluate_ape(ref, est, align=align, max_diff=max_diff)
