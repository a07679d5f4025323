"""The ``tracker`` node's parameters: one table that the node, its ``--help`` and the params file come from.

:data:`PARAMETERS` is the single source of truth: the node declares each entry with its description,
``nsflow-tracker --help`` prints them (:func:`usage`), and ``config/tracker_params.yaml`` is
:func:`render_params_yaml`'s output (a test keeps the shipped file equal to it).

Imports no ROS package, so ``--help`` needs no middleware.
"""

from __future__ import annotations

import math
import textwrap
from dataclasses import dataclass
from typing import Any

from nsflow_ros.ros.errors import ParameterError

__all__ = ["NODE_NAME", "PARAMETERS", "ParamSpec", "render_params_yaml", "spec", "usage"]

NODE_NAME = "nsflow_tracker"

_KINDS = {bool: "boolean", int: "integer", float: "number", str: "string"}


@dataclass(frozen=True)
class ParamSpec:
    """One node parameter.

    Attributes:
        name: the ROS parameter name.
        default: the default value; its Python type is the parameter's type.
        description: what it does, its unit and what special values mean.
        live: True = a change at run time takes effect; False = read-only (a set is refused).
        example: a typical value for error messages (None = the default).
    """

    name: str
    default: bool | int | float | str
    description: str
    live: bool
    example: bool | int | float | str | None = None

    @property
    def kind(self) -> str:
        """The type in words: boolean, integer, number or string."""
        return _KINDS[type(self.default)]

    @property
    def full_description(self) -> str:
        """The description plus whether the parameter can change at run time."""
        when = "Can change at run time." if self.live else "Read-only: set at start-up."
        return f"{self.description} {when}"

    def coerce(self, value: Any) -> bool | int | float | str:
        """Check ``value``'s type; an integer is accepted for a number (``-p F_threshold:=1``).

        Raises:
            ParameterError: naming the parameter, the value given and the type expected.
        """
        want = type(self.default)
        if want is float and isinstance(value, int) and not isinstance(value, bool):
            return float(value)
        if isinstance(value, want) and (want is bool or not isinstance(value, bool)):
            if want is float and not math.isfinite(value):
                raise ParameterError(f"parameter {self.name}: got {value!r}, expected a finite number")
            return value
        got = "no value" if value is None else f"{value!r} ({_KINDS.get(type(value), type(value).__name__)})"
        example = _yaml_value(self.default if self.example is None else self.example)
        raise ParameterError(
            f"parameter {self.name}: got {got}, expected {_article(self.kind)} {self.kind} "
            f"(e.g. -p {self.name}:={example})"
        )


def _article(word: str) -> str:
    return "an" if word[0] in "aeiou" else "a"


_FROM_CONFIG = "-1 = from the VINS config."

PARAMETERS: tuple[ParamSpec, ...] = (
    ParamSpec(
        "config_file", "config/euroc/euroc_mono_imu_config.yaml",
        "VINS-Fusion or VINS-Mono config file (OpenCV YAML). A relative path is looked up in the package's "
        "share directory (where config/ is installed), then in the working directory.", False),
    ParamSpec(
        "method", "nsflow",
        "Tracking method: 'nsflow' (learned descriptors + Levenberg-Marquardt LK, the paper's tracker), "
        "'nsflow_lk' (the same descriptors as uint8 through OpenCV's pyramidal LK, faster), 'classical' "
        "(the image intensity through the LM solver) or 'klt' (OpenCV calcOpticalFlowPyrLK as VINS-Fusion "
        "calls it: 21x21 window, maxLevel 3, 30 iterations / eps 0.01). A change restarts the tracks (ids "
        "keep counting up).", True),
    ParamSpec(
        "model_path", "",
        "ONNX encoder of the learned methods ('nsflow', 'nsflow_lk'); '' = the model shipped in the "
        "package's models/ folder. Its maps are smoothed as its metadata 'smoothing' declares (the shipped "
        "model: 1.0,1.0). A change restarts the tracks.", True),
    ParamSpec("max_cnt", -1, f"Most features kept per image (VINS max_cnt, >= 1). {_FROM_CONFIG}", True, 150),
    ParamSpec(
        "min_dist", -1, f"Minimum distance between features in pixels (VINS min_dist, >= 0). {_FROM_CONFIG}",
        True, 30),
    ParamSpec(
        "F_threshold", -1.0,
        "RANSAC threshold in pixels of the fundamental-matrix check (VINS F_threshold, > 0; an integer "
        f"is accepted). {_FROM_CONFIG}", True, 1.0),
    ParamSpec(
        "flow_back", -1,
        f"Track back and drop points that do not return within 0.5 px (VINS flow_back), 0/1. {_FROM_CONFIG}",
        True, 1),
    ParamSpec(
        "show_track", -1, f"Publish the image_track debug image (VINS show_track), 0/1. {_FROM_CONFIG}",
        True),
    ParamSpec(
        "freq", -1,
        "Feature publishing rate in Hz of the 'mono' layout (VINS-Mono freq; 0 = 100 Hz, in effect every "
        "image, as in VINS-Mono); frames in between are tracked but not published. The 'fusion' layout "
        f"publishes every frame and ignores it. {_FROM_CONFIG}", True, 10),
    ParamSpec(
        "equalize", -1,
        "Equalise the image (CLAHE) before tracking (VINS-Mono equalize), 0/1. A change restarts the "
        f"tracks. {_FROM_CONFIG}", True),
    ParamSpec(
        "reject_with_f", -1,
        "Fundamental-matrix RANSAC on tracked points, 0/1. -1 = on for the 'mono' layout (VINS-Mono does "
        "it), off for 'fusion' (VINS-Fusion does not).", True),
    ParamSpec(
        "output_layout", "",
        "Feature message layout: 'fusion' (VINS-Fusion channels: id, camera, u, v, vx, vy + 3 zeros) or "
        "'mono' (VINS-Mono channels: id * NUM_OF_CAM + camera, u, v, vx, vy; first frame dropped, freq "
        "throttling, restart on stamp gaps). '' = the dialect of the config file.", False),
    ParamSpec(
        "feature_topic", "/feature_tracker/feature",
        "Topic of the features (sensor_msgs/PointCloud, reliable, keep-last 2000); the VINS estimators "
        "listen here.", False),
    ParamSpec(
        "restart_topic", "/feature_tracker/restart",
        "Topic of the std_msgs/Bool restart signal of the 'mono' layout (stamp gap > 1 s or time going "
        "backwards).", False),
    ParamSpec(
        "image_track_topic", "image_track", "Topic of the debug image (sensor_msgs/Image, bgr8).", False),
    ParamSpec(
        "use_imu_prediction", False,
        "Predict feature positions from the gyroscope (needs imu_topic and body_T_cam0 in the VINS config).",
        False),
    ParamSpec(
        "num_threads", 0, "CPU threads of the encoder; 0 = all usable cores. A change restarts the tracks.",
        True),
    ParamSpec(
        "fisheye_mask", "",
        "Mask image (255 = usable) for a VINS config with fisheye: 1 (VINS-Mono's fisheye mask): tracked "
        "points on its zeros are dropped and no corners are detected there. '' = fisheye_mask.jpg in the "
        "config's folder or its parent, where VINS-Mono keeps it. Unused when the config's fisheye is 0.",
        False),
    ParamSpec(
        "queue_size", 4,
        "Frames waiting for the tracker at most (>= 1). When the tracker falls behind, the oldest waiting "
        "frame is dropped and counted; a small queue keeps the latency low.", False),
    ParamSpec(
        "status_period", 5.0,
        "Seconds between status lines in the log and on /diagnostics (frames received / processed / "
        "dropped, features, latency); 0 = none.", True),
    ParamSpec(
        "summary_file", "",
        "Write the run's counters as JSON to this file when the node stops ('' = no file).", False),
)
"""Every parameter of the ``tracker`` node, in the order of the params file."""

_BY_NAME = {p.name: p for p in PARAMETERS}


def spec(name: str) -> ParamSpec:
    """The :class:`ParamSpec` of a parameter.

    Raises:
        ParameterError: for an unknown name, listing the known ones.
    """
    try:
        return _BY_NAME[name]
    except KeyError:
        raise ParameterError(f"unknown parameter {name!r}; known: {', '.join(_BY_NAME)}") from None


def _yaml_value(value: bool | int | float | str) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return f'"{value}"'
    return repr(value)


def _wrap(text: str, width: int, indent: str) -> list[str]:
    return textwrap.wrap(
        text, width, initial_indent=indent, subsequent_indent=indent, break_on_hyphens=False
    )


def render_params_yaml(width: int = 110) -> str:
    """The params file (``--params-file``) with every parameter at its default, described in comments."""
    intro = (
        f"ROS 2 parameters of the {NODE_NAME} node, each at its default (this file is generated from "
        "nsflow_ros/ros/tracker_params.py). Tracker settings that also exist in the VINS config use -1 for "
        "'take the value from the VINS config file'; any other value overrides the file. Switches "
        "(flow_back, show_track, equalize) are integers for that reason: -1 = from the config, 0 = off, "
        "1 = on. Strings use '' for 'default'."
    )
    head = [
        *_wrap(intro, width, "# "),
        "#",
        "#   ros2 run nsflow_ros tracker --ros-args --params-file config/tracker_params.yaml",
        f"{NODE_NAME}:",
        "  ros__parameters:",
    ]
    body: list[str] = []
    for p in PARAMETERS:
        if body:
            body.append("")
        body += _wrap(p.full_description, width, "    # ")
        body.append(f"    {p.name}: {_yaml_value(p.default)}")
    return "\n".join(head + body) + "\n"


def usage(prog: str = "nsflow-tracker", width: int = 100) -> str:
    """The ``--help`` text: what the node does, its topics and every parameter with its default."""
    lines = [
        f"usage: {prog} [-h] [--ros-args [-p NAME:=VALUE ...] [--params-file FILE] [-r FROM:=TO ...]]",
        "",
        "The nsflow_tracker node: tracks features in camera images (NSFlow learned optical flow, or OpenCV's",
        "KLT) and publishes them in the VINS-Fusion / VINS-Mono layout, so an unchanged VINS estimator uses",
        "them instead of its own tracker.",
        "",
        "Topics (names from the VINS config; remap them with -r):",
        "  in   image0_topic, image1_topic for stereo (sensor_msgs/Image; sensor-data QoS, overridable with",
        "       -p qos_overrides.<topic>.subscription.reliability:=reliable etc.); imu_topic",
        "       (sensor_msgs/Imu) with use_imu_prediction",
        "  out  feature_topic (sensor_msgs/PointCloud), restart_topic (std_msgs/Bool, 'mono' layout),",
        "       image_track_topic (sensor_msgs/Image, with show_track), /diagnostics",
        "       (diagnostic_msgs/DiagnosticArray, every status_period seconds)",
        "",
        "Parameters (-p NAME:=VALUE, or a params file: config/tracker_params.yaml has them all):",
    ]
    for p in PARAMETERS:
        lines.append(f"  {p.name} ({p.kind}, default {_yaml_value(p.default)})")
        lines += _wrap(p.full_description, width, "      ")
    lines += [
        "",
        "Examples:",
        f"  {prog} --ros-args -p config_file:=/path/to/vins_config.yaml -p method:=klt",
        f"  {prog} --ros-args --params-file my_tracker_params.yaml -r /cam0/image_raw:=/camera/left",
    ]
    return "\n".join(lines) + "\n"
