"""Replay a recording (ROS 1 / ROS 2 bag or EuRoC ASL folder) into the tracker node: the demo as a launch.

    nsflow-make-sample out/sample                        # or any EuRoC bag / ASL folder
    ros2 launch nsflow_ros replay.launch.py path:=out/sample/asl rviz:=true
    ros2 launch nsflow_ros replay.launch.py path:=MH_01_easy.bag \
        config_file:=config/euroc/euroc_stereo_imu_config.yaml rate:=0.5

The replay waits for the tracker to subscribe, publishes /clock, and the tracker runs on that clock.
Every argument of tracker.launch.py passes through.
"""

from __future__ import annotations

from launch.actions import DeclareLaunchArgument, IncludeLaunchDescription
from launch.launch_description_sources import PythonLaunchDescriptionSource
from launch.substitutions import LaunchConfiguration, PathJoinSubstitution
from launch_ros.actions import Node
from launch_ros.substitutions import FindPackageShare

from launch import LaunchDescription

PACKAGE = "nsflow_ros"

# Passed on to tracker.launch.py as they are.
TRACKER_ARGUMENTS = {
    "config_file": "",
    "params_file": "",
    "method": "",
    "model_path": "",
    "image_transport": "",
    "providers": "",
    "namespace": "",
    "rviz": "false",
    "fixed_frame": "cam0",
}

REPLAY_ARGUMENTS = {
    "path": (None, "required: ROS 1 .bag, ROS 2 bag folder / .mcap / .db3, or EuRoC ASL folder to replay"),
    "rate": ("1.0", "replay speed factor (0 = as fast as possible)"),
    "start": ("0.0", "seconds to skip"),
    "perturb": ("none", "perturbation: none, small, large (illumination) or dark (low light with noise)"),
}


def generate_launch_description() -> LaunchDescription:
    """The launch description: the replay process and tracker.launch.py on the replay's clock."""
    arguments = [
        DeclareLaunchArgument(n, description=t) if d is None
        else DeclareLaunchArgument(n, default_value=d, description=t)
        for n, (d, t) in REPLAY_ARGUMENTS.items()
    ]
    arguments += [
        DeclareLaunchArgument(n, default_value=d, description="see tracker.launch.py")
        for n, d in TRACKER_ARGUMENTS.items()
    ]
    tracker = IncludeLaunchDescription(
        PythonLaunchDescriptionSource(PathJoinSubstitution([FindPackageShare(PACKAGE), "launch",
                                                            "tracker.launch.py"])),
        launch_arguments={**{n: LaunchConfiguration(n) for n in TRACKER_ARGUMENTS},
                          "use_sim_time": "true"}.items(),
    )
    replay = Node(
        package=PACKAGE,
        executable="replay",
        arguments=[LaunchConfiguration("path"), "--rate", LaunchConfiguration("rate"), "--start",
                   LaunchConfiguration("start"), "--perturb", LaunchConfiguration("perturb"),
                   "--wait-subscribers", "1", "--wait-timeout", "30"],
        output="screen",
    )
    return LaunchDescription([*arguments, tracker, replay])
