"""The one error class of the ATE subpackage.

Every failure that the scoring tools detect on purpose (a file that cannot be read, a format that cannot be
detected, trajectories that do not overlap in time, too few matched poses, NaNs, a degenerate alignment)
raises :class:`ATEError`, whose message names the file, line or value at fault. The CLI turns it into a
message on stderr and exit code 1. Its ``reason`` tag lets the batch scorer classify a failed run without
parsing messages.
"""

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
"""Values of :attr:`ATEError.reason`.

``missing``: no such file / no trajectory file in a folder; ``empty``: a file or trajectory without poses;
``malformed``: a row that cannot be parsed or a format that cannot be detected; ``nan``: NaN or infinite
values; ``no_overlap``: no stamps within ``max_diff``; ``too_few``: fewer matched poses than needed;
``degenerate``: an alignment that is not determined (all points equal or collinear); ``invalid``: anything
else (bad arguments, shapes).
"""


class ATEError(NSFlowError):
    """A trajectory cannot be read, associated, aligned or scored.

    Args:
        message: what went wrong, naming the file, line or value at fault.
        reason: one of :data:`REASONS` (default ``"invalid"``).

    Attributes:
        reason: the tag given.
    """

    def __init__(self, message: str, *, reason: str = "invalid") -> None:
        super().__init__(message)
        self.reason = reason if reason in REASONS else "invalid"
