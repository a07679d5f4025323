"""Sensor data for nsflow_ros: the built-in synthetic sample sequence and the data I/O layer.

Pure Python (NumPy, OpenCV, rosbags): no rclpy, no torch.
"""

from __future__ import annotations

from nsflow_ros.data.camera import EUROC_CAM0, EUROC_CAM1, PinholeRadtan
from nsflow_ros.data.errors import DataError
from nsflow_ros.data.images import decode_image, to_gray
from nsflow_ros.data.messages import image_message, record_to_cdr
from nsflow_ros.data.motion import (
    EUROC_IMU_NOISE,
    NO_IMU_NOISE,
    ImuNoise,
    ImuSamples,
    Trajectory,
    quaternion_to_rotation,
    rotation_to_quaternion,
    synthesize_imu,
)
from nsflow_ros.data.perturb import (
    LEVELS,
    PERTURBATIONS,
    DarkPerturber,
    IlluminationPerturber,
    PerturbLevel,
    make_perturber,
    perturb_pair,
    perturb_records,
)
from nsflow_ros.data.records import ImageRecord, ImuRecord, RawMessage, Record
from nsflow_ros.data.sample import SampleSequence, make_sample_sequence
from nsflow_ros.data.scene import Rendered, Renderer, Scene, flow_between, ray_depth
from nsflow_ros.data.sources import (
    IMAGE_TOPICS,
    IMU_TOPICS,
    SensorSource,
    detect_kind,
    read_raw_messages,
    read_records,
)
from nsflow_ros.data.writers import AslWriter, BagWriter, write_ros2_bag

__all__ = [
    "EUROC_CAM0",
    "EUROC_CAM1",
    "EUROC_IMU_NOISE",
    "IMAGE_TOPICS",
    "IMU_TOPICS",
    "LEVELS",
    "NO_IMU_NOISE",
    "PERTURBATIONS",
    "AslWriter",
    "BagWriter",
    "DarkPerturber",
    "DataError",
    "IlluminationPerturber",
    "ImageRecord",
    "ImuNoise",
    "ImuRecord",
    "ImuSamples",
    "PerturbLevel",
    "PinholeRadtan",
    "RawMessage",
    "Record",
    "Rendered",
    "Renderer",
    "SampleSequence",
    "Scene",
    "SensorSource",
    "Trajectory",
    "decode_image",
    "detect_kind",
    "flow_between",
    "image_message",
    "make_perturber",
    "make_sample_sequence",
    "perturb_pair",
    "perturb_records",
    "quaternion_to_rotation",
    "ray_depth",
    "read_raw_messages",
    "read_records",
    "record_to_cdr",
    "rotation_to_quaternion",
    "synthesize_imu",
    "to_gray",
    "write_ros2_bag",
]
