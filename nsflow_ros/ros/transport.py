"""The DDS transport profile the package's ROS processes use unless the user chose one.

Fast DDS's default shared-memory segment (0.5 MiB) cannot hold two back-to-back 752x480 images, so
best-effort stereo images are lost even for a subscriber that keeps up; ``config/fastdds_large_images.xml``
gives each participant 16 MiB.
"""

from __future__ import annotations

import os
from pathlib import Path

__all__ = ["PROFILE_ENV", "PROFILE_FILE", "use_large_image_transport"]

PROFILE_FILE = "config/fastdds_large_images.xml"
PROFILE_ENV = ("FASTRTPS_DEFAULT_PROFILES_FILE", "FASTDDS_DEFAULT_PROFILES_FILE")
"""The variables Fast DDS reads its XML profiles from (2.x reads the first, 3.x the second)."""


def use_large_image_transport() -> Path | None:
    """Before ``rclpy.init``, point Fast DDS (and child processes) at the shipped profile.

    Returns:
        the profile now in use, or None when the environment names a profiles file or another RMW, or the
        file is not installed.
    """
    if any(os.environ.get(name) for name in PROFILE_ENV):
        return None
    if os.environ.get("RMW_IMPLEMENTATION", "rmw_fastrtps_cpp") not in ("rmw_fastrtps_cpp", ""):
        return None
    from nsflow_ros.resources import ResourceError, share_file

    try:
        path = share_file(PROFILE_FILE)
    except ResourceError:
        return None
    os.environ[PROFILE_ENV[0]] = str(path)
    return path
