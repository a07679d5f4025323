"""Errors of the ROS 2 shell subpackage."""

from __future__ import annotations

from nsflow_ros.errors import NSFlowError

__all__ = ["ParameterError"]


class ParameterError(NSFlowError):
    """A ROS parameter or argument of a node is of the wrong type, out of range or names a missing file.

    The message names the parameter, the value given and what is expected.
    """
