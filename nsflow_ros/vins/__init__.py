"""The VINS side of the front-end: reading VINS-Fusion / VINS-Mono configuration files.

Pure Python (NumPy, OpenCV); imports neither rclpy nor torch.
"""

from __future__ import annotations

from nsflow_ros.vins.config import (
    DEFAULT_FREQ,
    OVERRIDABLE_KEYS,
    Dialect,
    VinsConfig,
    apply_overrides,
    load_vins_config,
)
from nsflow_ros.vins.errors import ConfigError

__all__ = [
    "DEFAULT_FREQ",
    "OVERRIDABLE_KEYS",
    "ConfigError",
    "Dialect",
    "VinsConfig",
    "apply_overrides",
    "load_vins_config",
]
