"""The data layer's error type."""

from __future__ import annotations

from nsflow_ros.errors import NSFlowError

__all__ = ["DataError"]


class DataError(NSFlowError):
    """Reading, writing or generating sensor data failed.

    Messages name what is at fault: the path, the topic, the encoding or the value, and what was
    expected instead.
    """
