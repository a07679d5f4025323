"""nsflow_ros: the NSFlow learned LK front-end for VINS, as a ROS 2 Jazzy package.

The core (encoder runtime, Levenberg-Marquardt Lucas-Kanade solver, detector, camera models, tracker)
is pure NumPy/OpenCV/onnxruntime: importing this package imports neither rclpy nor torch.
"""

from __future__ import annotations

from nsflow_ros.errors import NSFlowError

__all__ = ["NSFlowError"]
__version__ = "0.1.0"
