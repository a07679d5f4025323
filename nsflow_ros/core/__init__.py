"""The pure NumPy/OpenCV tracking core: encoders, descriptor pyramids, the LM-LK solver, detection.

Nothing here imports rclpy or torch.
"""

from __future__ import annotations

from nsflow_ros.core.detector import detect_corners
from nsflow_ros.core.encoder import (
    DEFAULT_MODEL,
    SHIPPED_MODELS,
    Encoder,
    IntensityEncoder,
    OnnxEncoder,
    load_encoder,
    to_gray,
)
from nsflow_ros.core.errors import CoreError, EncoderError, UnsupportedEncoderError
from nsflow_ros.core.methods import (
    METHODS,
    MethodSpec,
    SolveKind,
    SolvePolicy,
    Solver,
    TrackingMethod,
    klt_track,
    make_method,
)
from nsflow_ros.core.pyramid import DescriptorPyramid, Smoothing, build_pyramid
from nsflow_ros.core.refine import IntensityRefinement, refine
from nsflow_ros.core.solver import IterationRecord, Jacobian, LMConfig, TrackResult, sample_windows, track

__all__ = [
    "DEFAULT_MODEL",
    "METHODS",
    "SHIPPED_MODELS",
    "CoreError",
    "DescriptorPyramid",
    "Encoder",
    "EncoderError",
    "IntensityEncoder",
    "IntensityRefinement",
    "IterationRecord",
    "Jacobian",
    "LMConfig",
    "MethodSpec",
    "OnnxEncoder",
    "Smoothing",
    "SolveKind",
    "SolvePolicy",
    "Solver",
    "TrackResult",
    "TrackingMethod",
    "UnsupportedEncoderError",
    "build_pyramid",
    "detect_corners",
    "klt_track",
    "load_encoder",
    "make_method",
    "refine",
    "sample_windows",
    "to_gray",
    "track",
]
