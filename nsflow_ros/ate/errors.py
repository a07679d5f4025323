"""The one error class of the ATE subpackage, tagged with a reason so that the batch scorer classifies
a failed run without parsing messages."""

from __future__ import annotations

from nsflow_ros.errors import NSFlowError

__all__ = ["REASONS", "ATEError"]

REASONS: tuple[str, ...] = (
    "invalid",
    "missing",
    "empty",
    "malformed",
    "nan",
    "no_overlap",
    "too_few",
    "degenerate",
)
"""Values of :attr:`ATEError.reason`: no file, no poses, an unparsable row or format, NaN / inf, no stamp
overlap, too few matched poses, an undetermined alignment, anything else (bad arguments, shapes)."""


class ATEError(NSFlowError):
    """A trajectory cannot be read, associated, aligned or scored; the message names the file, line or
    value at fault, ``reason`` is one of :data:`REASONS` (another value becomes ``"invalid"``)."""

    def __init__(self, message: str, *, reason: str = "invalid") -> None:
        super().__init__(message)
        self.reason = reason if reason in REASONS else "invalid"
