"""Root of the project's exception hierarchy.

Every subpackage defines one small error class deriving from :class:`NSFlowError`, so callers (and the
CLIs, which turn known errors into exit code 1) can catch the project's own failures in one place.
"""

from __future__ import annotations

__all__ = ["NSFlowError"]


class NSFlowError(Exception):
    """Base class of every error raised on purpose by nsflow_ros."""
