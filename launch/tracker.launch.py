"""Bring up the nsflow_ros tracker node, and RViz2 showing its debug image and features.

    ros2 launch nsflow_ros tracker.launch.py config_file:=/path/to/vins_config.yaml
    ros2 launch nsflow_ros tracker.launch.py config_file:=my.yaml params_file:=my_tracker_params.yaml \
        providers:=tensorrt,cuda,cpu image_transport:=compressed rviz:=true
    ros2 launch nsflow_ros tracker.launch.py config_file:=my.yaml mask0:=body_cam0.png \
        mask_topic:=/segmentation/mask mask_convention:=openvins

A node parameter given as an argument overrides the params file; one left empty keeps the params file's
value (or the node's default). ``ros2 launch nsflow_ros tracker.launch.py --show-args`` lists them.
"""

from __future__ import annotations

from launch.actions import DeclareLaunchArgument, OpaqueFunction
from launch.conditions import IfCondition
from launch.substitutions import LaunchConfiguration, PathJoinSubstitution
from launch_ros.actions import Node
from launch_ros.substitutions import FindPackageShare

from launch import LaunchDescription

PACKAGE = "nsflow_ros"

# Node parameters (rows of nsflow_ros.vins.settings.SETTINGS) that are launch arguments of the same name.
NODE_PARAMETERS = ("config_file", "method", "model_path", "image_transport", "providers", "mask0", "mask1",
                   "mask_convention", "mask_topic", "mask1_topic")

ARGUMENTS = {
    "config_file": ("", "VINS-Fusion / VINS-Mono config file ('' = the params file's, else the shipped EuRoC "
                        "mono config)"),
    "params_file": ("", "ROS 2 params file of the node (config/tracker_params.yaml lists every parameter)"),
    "method": ("", "tracking method: nsflow, nsflow_lk, classical or klt ('' = params file / nsflow)"),
    "model_path": ("", "encoder of the learned methods: an ONNX file, or a shipped model by name, default or "
                       "fast (one channel, less CPU beside an estimator) ('' = params file / default)"),
    "image_transport": ("", "raw or compressed ('' = params file / raw)"),
    "providers": ("", "onnxruntime execution providers of the encoder, best first, e.g. cuda,cpu "
                      "('' = params file / cpu)"),
    "mask0": ("", "static mask image of camera 0: no features on its masked pixels ('' = params file / the "
                  "VINS config's mask0 key / none)"),
    "mask1": ("", "static mask image of camera 1 (stereo) ('' = params file / config's mask1 / none)"),
    "mask_convention": ("", "vins (255 = usable) or openvins (255 = masked out) ('' = params file / vins)"),
    "mask_topic": ("", "per-frame masks of camera 0, sensor_msgs/Image mono8 stamped like the images, e.g. "
                       "moving objects from a segmentation node ('' = params file / none)"),
    "mask1_topic": ("", "per-frame masks of camera 1 (stereo) ('' = params file / none)"),
    "namespace": ("", "namespace of the node (the feature topic is absolute: /feature_tracker/feature)"),
    "use_sim_time": ("false", "use /clock (true when replaying a bag with its clock)"),
    "rviz": ("false", "start RViz2 with the image_track image and the feature cloud"),
    "rviz_config": ("", "RViz2 config ('' = the package's rviz/nsflow.rviz)"),
    "fixed_frame": ("cam0", "RViz2 fixed frame: the frame_id of the camera images"),
}


def _tracker(context, *_args, **_kwargs):
    def value(name: str) -> str:
        return LaunchConfiguration(name).perform(context).strip()

    parameters: list = []
    if value("params_file"):
        parameters.append(value("params_file"))
    given = {name: value(name) for name in NODE_PARAMETERS if value(name)}
    given["use_sim_time"] = value("use_sim_time").lower() in ("true", "1", "yes")
    parameters.append(given)
    return [
        Node(
            package=PACKAGE,
            executable="tracker",
            namespace=value("namespace"),
            parameters=parameters,
            output="screen",
            emulate_tty=True,
        )
    ]


def _rviz(context, *_args, **_kwargs):
    config = LaunchConfiguration("rviz_config").perform(context).strip()
    if not config:
        config = PathJoinSubstitution([FindPackageShare(PACKAGE), "rviz", "nsflow.rviz"]).perform(context)
    return [
        Node(
            package="rviz2",
            executable="rviz2",
            arguments=["-d", config, "-f", LaunchConfiguration("fixed_frame").perform(context)],
            parameters=[{"use_sim_time": LaunchConfiguration("use_sim_time").perform(context).lower()
                         in ("true", "1", "yes")}],
            output="screen",
        )
    ]


def generate_launch_description() -> LaunchDescription:
    """The launch description: the arguments, the tracker node and (``rviz:=true``) RViz2."""
    return LaunchDescription(
        [DeclareLaunchArgument(name, default_value=default, description=text)
         for name, (default, text) in ARGUMENTS.items()]
        + [
            OpaqueFunction(function=_tracker),
            OpaqueFunction(function=_rviz, condition=IfCondition(LaunchConfiguration("rviz"))),
        ]
    )
