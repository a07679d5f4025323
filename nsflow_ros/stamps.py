"""``builtin_interfaces/Time`` stamps as numbers (no ROS import: anything with ``sec`` and ``nanosec``)."""

from __future__ import annotations

from typing import Any

__all__ = ["stamp_to_ns", "stamp_to_s"]


def stamp_to_ns(stamp: Any) -> int:
    """Nanoseconds of a ``builtin_interfaces/Time``."""
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def stamp_to_s(stamp: Any) -> float:
    """Seconds of a ``builtin_interfaces/Time``, as ``sec + nanosec * 1e-9`` in float64."""
    return float(stamp.sec) + float(stamp.nanosec) * 1e-9
