"""ament_python / pip packaging for nsflow_ros."""

import sys
from glob import glob
from pathlib import Path

from setuptools import find_packages, setup

PACKAGE = "nsflow_ros"

# (console-script name on PATH, name under lib/nsflow_ros for `ros2 run` from a colcon build, target)
TOOLS = [
    ("nsflow-tracker", "tracker", "nsflow_ros.ros.tracker_node:main"),
    ("nsflow-replay", "replay", "nsflow_ros.ros.replay_node:main"),
    ("nsflow-demo", "demo", "nsflow_ros.demo:main"),
    ("nsflow-ate", "ate", "nsflow_ros.ate.cli:main"),
    ("nsflow-bench", "bench", "nsflow_ros.bench:main"),
    ("nsflow-make-sample", "make_sample", "nsflow_ros.data.cli:main"),
    ("nsflow-train", "train", "nsflow_ros.tools:train"),
    ("nsflow-evaluate", "evaluate", "nsflow_ros.evaluation.cli:main"),
    ("nsflow-config", "config", "nsflow_ros.vins.cli:main"),
    ("nsflow-scenes", "scenes", "nsflow_ros.evaluation.scenes:main"),
]


def _ros_layout() -> bool:
    """Whether setup.py runs as colcon (or a ROS user) runs it: ``setup.py install`` / ``develop``.

    colcon builds an ament_python package with ``setup.py ... install --install-scripts lib/<pkg>`` (or
    ``develop`` for --symlink-install), and setup.cfg sends those scripts to lib/nsflow_ros, where
    ``ros2 run`` looks. pip builds a wheel instead (``bdist_wheel`` / ``editable_wheel`` through
    setuptools' PEP 517 backend), whose scripts go on PATH: there only the ``nsflow-*`` names belong.
    """
    commands = set(sys.argv[1:])
    return bool(commands & {"install", "develop"}) and not commands & {"bdist_wheel", "editable_wheel"}


def _console_scripts() -> list[str]:
    scripts = [f"{name}={target}" for name, _, target in TOOLS]
    if _ros_layout():
        scripts += [f"{short}={target}" for _, short, target in TOOLS]
    return scripts


def _data_files() -> list[tuple[str, list[str]]]:
    files = [
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml"]),
    ]
    for folder in ("config", "models", "launch", "rviz"):
        for path in sorted(glob(f"{folder}/**/*", recursive=True)):
            if Path(path).is_file():
                files.append((f"share/{PACKAGE}/{Path(path).parent}", [path]))
    return files


# The ROS 2 Jazzy wheels of what the code imports (package.xml names the same, as rosdep keys).
ROS = [
    "ros-jazzy-rclpy",
    "ros-jazzy-rcl-interfaces",
    "ros-jazzy-ament-index-python",
    "ros-jazzy-sensor-msgs",
    "ros-jazzy-std-msgs",
    "ros-jazzy-geometry-msgs",
    "ros-jazzy-diagnostic-msgs",
    "ros-jazzy-rosgraph-msgs",
    "ros-jazzy-rmw-fastrtps-cpp",
]

# The evaluation, the sample renderer and the demo (textures: scikit-image's and matplotlib's bundled
# photos), the figures and ATE plots (matplotlib), the FLOP count and the benchmark's random encoder (onnx
# builds and reads graphs). The node, the replay and the feature bag need none of them (nsflow_ros/optional.py
# imports them on use and names this extra when one is missing).
EVAL = [
    "scikit-image>=0.22",
    "matplotlib>=3.7",
    "onnx>=1.15",
]

setup(
    name=PACKAGE,
    version="0.1.0",
    packages=find_packages(exclude=["test", "test.*"]),
    data_files=_data_files(),
    python_requires=">=3.10",
    install_requires=[
        "setuptools",
        "numpy>=1.24",
        "opencv-python-headless>=4.8",
        "onnxruntime>=1.17",
        "rosbags>=0.11,!=0.11.6",
        "tqdm",
        "pyyaml",  # params-file checks of the tracker (rclpy needs it too)
        *ROS,
    ],
    extras_require={
        "eval": EVAL,
        "train": ["torch==2.13.0", *EVAL],
        # optional TensorBoard event files of nsflow-train (the CSV log needs nothing)
        "tensorboard": ["tensorboard>=2.14"],
        "test": [
            *EVAL,
            "scipy",  # the tests' own checks (scikit-image brings it already)
            "pytest>=7",
            "ruff",
            "evo>=1.30",
            "colcon-common-extensions",
            "torch==2.13.0",
        ],
    },
    zip_safe=True,
    maintainer="nsflow_ros maintainers",
    maintainer_email="maintainers@nsflow-ros.org",
    description="NSFlow learned LK front-end for VINS on ROS 2 Jazzy",
    license="Apache-2.0",
    entry_points={
        "console_scripts": _console_scripts(),
    },
)
