"""The ``tracker`` node's parameters: a ROS view over :data:`nsflow_ros.vins.settings.SETTINGS`.

``--help`` (:func:`usage`), ``config/tracker_params.yaml`` (:func:`render_params_yaml`) and the type check
of a value ROS hands over (:func:`coerce`). Imports no ROS package, so ``--help`` needs no middleware.
"""

from __future__ import annotations

import math
import textwrap
from typing import Any

from nsflow_ros.ros.errors import ParameterError
from nsflow_ros.vins.errors import ConfigError
from nsflow_ros.vins.settings import KINDS, SETTINGS, Setting, Value, setting

__all__ = ["NODE_NAME", "PARAMETERS", "coerce", "render_params_yaml", "spec", "usage"]

NODE_NAME = "nsflow_tracker"

PARAMETERS: tuple[Setting, ...] = SETTINGS
"""Every parameter of the ``tracker`` node, in the order of the params file."""


def spec(name: str) -> Setting:
    """The settings-table row of a parameter.

    Raises:
        ParameterError: for an unknown name, listing the known ones.
    """
    try:
        return setting(name)
    except ConfigError as err:
        known = ", ".join(p.name for p in SETTINGS)
        raise ParameterError(f"unknown parameter {name!r}; known: {known}") from err


def coerce(p: Setting, value: Any) -> Value:
    """Check a parameter value's type (an integer counts as a number) and its range from the settings table.

    The same rule at start-up and for a change at run time (:meth:`Setting.problem`): -1 only where it is
    the default, a switch 0 or 1, ``downsample`` one of its factors, every bound of the table.

    Raises:
        ParameterError: naming the parameter, the value given and the type (or range) expected.
    """
    want = p.type
    if want is float and isinstance(value, int) and not isinstance(value, bool):
        value = float(value)
    if isinstance(value, want) and (want is bool or not isinstance(value, bool)):
        if want is float and not math.isfinite(value):
            raise ParameterError(f"parameter {p.name}: got {value!r}, expected a finite number")
        problem = p.problem(value)
        if problem is not None and p.choices is not None:  # the tracker's own words for its factors
            raise ParameterError(f"{p.name} must be {problem}, got {value!r}")
        if problem is not None:
            raise ParameterError(f"parameter {p.name}: got {value}, expected {problem}")
        return value
    got = "no value" if value is None else f"{value!r} ({KINDS.get(type(value), type(value).__name__)})"
    example = _yaml_value(p.default if p.example is None else p.example)
    raise ParameterError(
        f"parameter {p.name}: got {got}, expected {_article(p.kind)} {p.kind} (e.g. -p {p.name}:={example})"
    )


def _article(word: str) -> str:
    return "an" if word[0] in "aeiou" else "a"


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
        "nsflow_ros/vins/settings.py). Tracker settings that also exist in the VINS config use -1 for "
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
        "       (sensor_msgs/Imu) with use_imu_prediction; mask_topic, mask1_topic (sensor_msgs/Image mono8,",
        "       per-frame masks stamped like the images)",
        "  out  feature_topic (sensor_msgs/PointCloud), restart_topic (std_msgs/Bool, 'mono' layout),",
        "       image_track_topic (sensor_msgs/Image, with show_track), /diagnostics",
        "       (diagnostic_msgs/DiagnosticArray, every status_period seconds)",
        "",
        "Parameters (-p NAME:=VALUE, or a params file: config/tracker_params.yaml has them all):",
    ]
    for p in PARAMETERS:
        unit = f", {p.unit}" if p.unit else ""
        lines.append(f"  {p.name} ({p.kind}{unit}, default {_yaml_value(p.default)})")
        lines += _wrap(p.full_description, width, "      ")
    lines += [
        "",
        "Examples:",
        f"  {prog} --ros-args -p config_file:=/path/to/vins_config.yaml -p method:=klt",
        f"  {prog} --ros-args --params-file my_tracker_params.yaml -r /cam0/image_raw:=/camera/left",
        f"  {prog} --ros-args -p config_file:=/path/to/vins_config.yaml -p mask0:=body.png "
        "-p mask_topic:=/segmentation/mask",
    ]
    return "\n".join(lines) + "\n"
