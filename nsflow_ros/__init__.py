"""nsflow_ros: the NSFlow learned LK front-end for VINS, as a ROS 2 Jazzy package.

The core (encoder runtime, Levenberg-Marquardt Lucas-Kanade solver, detector, camera models, tracker)
is pure NumPy/OpenCV/onnxruntime: importing this package imports neither rclpy nor torch.
"""

from __future__ import annotations

from nsflow_ros.core import (
    CoreError,
    DescriptorPyramid,
    EncoderError,
    IntensityEncoder,
    Jacobian,
    LMConfig,
    OnnxEncoder,
    Smoothing,
    TrackResult,
    build_pyramid,
    detect_corners,
    load_encoder,
    track,
)
from nsflow_ros.errors import NSFlowError

__all__ = [
    "CoreError",
    "DescriptorPyramid",
    "EncoderError",
    "IntensityEncoder",
    "Jacobian",
    "LMConfig",
    "NSFlowError",
    "OnnxEncoder",
    "Smoothing",
    "TrackResult",
    "build_pyramid",
    "detect_corners",
    "load_encoder",
    "track",
]
__version__ = "0.1.0"
