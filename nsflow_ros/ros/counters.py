"""The ``tracker`` node's counters: one set of names for its status line, /diagnostics and summary file."""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field, fields
from typing import Any

__all__ = ["WINDOWED", "NodeCounters"]


@dataclass
class NodeCounters:
    """What the node saw and did with images and frames (the session counts its own policy).

    Attributes:
        images_received: images that arrived, either camera.
        images_undecodable: images that could not be decoded.
        images_unpaired: stereo images whose partner never came.
        frames_received: frames (image pairs for stereo) queued for the tracker.
        frames_processed: frames the tracker ran on.
        frames_unchecked: of those, frames tracked without the reverse checks because they came late.
        frames_published: feature messages published.
        frames_superseded: frames given up unprocessed for a newer one while the tracker was behind.
        frames_left_at_stop: frames still waiting when the node stopped.
        frames_refused: frames the session refused (duplicate stamp, tracker error).
        frames_missing_upstream: frames lost before the node, inferred from stamp gaps.
        bad: undecodable images and refused frames by cause (logged once per cause).
    """

    images_received: int = 0
    images_undecodable: int = 0
    images_unpaired: int = 0
    frames_received: int = 0
    frames_processed: int = 0
    frames_unchecked: int = 0
    frames_published: int = 0
    frames_superseded: int = 0
    frames_left_at_stop: int = 0
    frames_refused: int = 0
    frames_missing_upstream: int = 0
    bad: Counter[str] = field(default_factory=Counter)

    @property
    def frames_dropped(self) -> int:
        """Frames received but not tracked: superseded, left at the stop, or refused by the session."""
        return self.frames_superseded + self.frames_left_at_stop + self.frames_refused

    def totals(self) -> dict[str, int]:
        """Every count by its name (``bad`` aside), plus ``frames_dropped``."""
        out = {f.name: getattr(self, f.name) for f in fields(self) if f.name != "bad"}
        out["frames_dropped"] = self.frames_dropped
        return out

    def since(self, before: dict[str, Any]) -> dict[str, int]:
        """The change of the :data:`WINDOWED` counts since an earlier :meth:`totals`."""
        now = self.totals()
        return {k: now[k] - before.get(k, 0) for k in WINDOWED}


WINDOWED = (
    "frames_received", "frames_processed", "frames_dropped", "frames_superseded", "frames_unchecked",
    "images_unpaired", "frames_missing_upstream",
)
"""The counts the status line reports per period."""
