"""Locate the package's shared files (config/, models/) in an install or in a source checkout."""

from __future__ import annotations

import contextlib
from pathlib import Path

from nsflow_ros.errors import NSFlowError

__all__ = ["DEFAULT_CONFIG", "STEREO_CONFIG", "ResourceError", "share_dir", "share_file"]

PACKAGE = "nsflow_ros"

DEFAULT_CONFIG = "config/euroc/euroc_mono_imu_config.yaml"
"""The VINS config used when none is given (the node's ``config_file`` default), relative to the share
directory (:func:`share_file`)."""

STEREO_CONFIG = "config/euroc/euroc_stereo_imu_config.yaml"
"""The shipped stereo VINS config (EuRoC cam0 + cam1), relative to the share directory."""


class ResourceError(NSFlowError):
    """A shared file of the package cannot be found."""


def _candidates() -> list[Path]:
    found: list[Path] = []
    # Source checkout (or editable pip install): the repository root is the package's parent.
    found.append(Path(__file__).resolve().parent.parent)
    # colcon / ament install: <prefix>/share/nsflow_ros, found through the ament index if present.
    try:
        from ament_index_python.packages import PackageNotFoundError, get_package_share_directory

        # ament_index raises OSError when AMENT_PREFIX_PATH is unset (no ROS environment sourced)
        with contextlib.suppress(PackageNotFoundError, OSError):
            found.append(Path(get_package_share_directory(PACKAGE)))
    except ImportError:
        pass
    # pip install with data_files: <sys.prefix>/share/nsflow_ros.
    import sys

    found.append(Path(sys.prefix) / "share" / PACKAGE)
    return found


def share_dir() -> Path:
    """Return the directory that holds config/ and models/.

    Raises:
        ResourceError: when no candidate directory has a config/ or models/ folder.
    """
    for cand in _candidates():
        if (cand / "config").is_dir() or (cand / "models").is_dir():
            return cand
    tried = ", ".join(str(c) for c in _candidates())
    raise ResourceError(f"cannot find the nsflow_ros share directory (tried {tried})")


def share_file(relative: str | Path) -> Path:
    """Return the path of a shared file such as ``models/nsflow_encoder.onnx``.

    Raises:
        ResourceError: naming the relative path and the directories searched.
    """
    for cand in _candidates():
        path = cand / relative
        if path.exists():
            return path
    tried = ", ".join(str(c / relative) for c in _candidates())
    raise ResourceError(f"cannot find shared file {relative} (tried {tried})")
