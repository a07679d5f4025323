"""Errors of the VINS interface subpackage."""

from __future__ import annotations

from nsflow_ros.errors import NSFlowError

__all__ = ["ConfigError"]


class ConfigError(NSFlowError):
    """A VINS configuration file or a tracker setting is missing, malformed or out of range.

    The message names the file (or the setting) and the key at fault.
    """
