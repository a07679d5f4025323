"""The ``tracker`` node's counters: one table of causes for its status line, /diagnostics and summary file.

Every image that reaches the node ends in exactly one place: part of a frame, or counted under one image
cause (undecodable, wrong encoding, wrong size, unpaired). Every frame ends tracked or under one frame
cause (repeated stamp, superseded, ...). A new cause is one more :class:`Cause` row in :data:`CAUSES`; its
counter, status-line words, ``/diagnostics`` key-values and summary-file key follow from the row.
"""

from __future__ import annotations

import threading
from collections import Counter
from dataclasses import dataclass, field, fields
from enum import StrEnum
from typing import Any

__all__ = ["CAUSES", "DROPPED", "Cause", "CauseLog", "Kind", "NodeCounters", "cause", "image_cause"]


class Kind(StrEnum):
    """What a cause says about the input or the node (it sets the status level)."""

    REFUSED = "refused"
    """Bad input: the image or frame cannot be used (WARN; ERROR when nothing was tracked)."""
    BEHIND = "behind"
    """The tracker was busy: the node itself gave the frame up (WARN, "falling behind")."""
    WAIT = "wait"
    """The tracker waited for a frame's per-frame mask and the frame behind it was given up (WARN, names
    mask_wait_ms, never "falling behind")."""
    POLICY = "policy"
    """The VINS front-end's policy skipped the frame (INFO: it is what VINS-Mono does)."""
    STOP = "stop"
    """Still waiting when the node stopped (summary only)."""
    EVENT = "event"
    """Something noteworthy about a frame that was still tracked (not a loss; WARN)."""
    HELD = "held"
    """Tracked but not published by the publishing policy (``publish_rate``, ``freq``; not a loss; INFO):
    frames processed = published + held."""


@dataclass(frozen=True)
class Cause:
    """One reason an image or frame was not tracked (or an event of a tracked frame).

    Attributes:
        key: the counter's name without its unit, e.g. ``undecodable``; the summary file's key is
            ``<unit>s_<key>`` (``images_undecodable``).
        unit: ``image`` (counted before pairing, per camera image) or ``frame`` (an image or stereo pair).
        label: the words of the status line and ``/diagnostics``, e.g. ``wrong size``.
        kind: what it says (:class:`Kind`).
        meaning: one sentence for the documentation.
    """

    key: str
    unit: str
    label: str
    kind: Kind
    meaning: str

    @property
    def name(self) -> str:
        """The summary file's key: ``images_undecodable``, ``frames_superseded``, ..."""
        return f"{self.unit}s_{self.key}"


CAUSES: tuple[Cause, ...] = (
    Cause("undecodable", "image", "undecodable", Kind.REFUSED,
          "data that does not decode: a truncated or corrupt JPEG / PNG, raw data shorter or longer than "
          "step x height, a step shorter than a row"),
    Cause("wrong_encoding", "image", "wrong encoding", Kind.REFUSED,
          "an encoding or compressed format the node does not take (bayer_rggb8, 32FC1, webp, "
          "compressedDepth, 16-bit colour, ...)"),
    Cause("wrong_size", "image", "wrong size", Kind.REFUSED,
          "decoded to another size than the VINS config's image_width x image_height"),
    Cause("unpaired", "image", "unpaired", Kind.REFUSED,
          "stereo images whose partner never came within stereo_sync_tolerance (or was refused)"),
    Cause("repeated_stamp", "frame", "repeated stamp", Kind.REFUSED,
          "the frame's stamp repeats the previous frame's"),
    Cause("stamp_backwards", "frame", "stamp backwards", Kind.REFUSED,
          "VINS-Mono layout: the stamp is older than the previous frame's; the frame is dropped and the "
          "estimator restarts"),
    Cause("tracker_error", "frame", "tracker error", Kind.REFUSED,
          "the tracker raised on the frame (the log names the error once)"),
    Cause("superseded", "frame", "superseded", Kind.BEHIND,
          "given up unprocessed for a newer frame while the tracker was busy: the node is falling behind"),
    Cause("mask_wait", "frame", "superseded while waiting for a mask", Kind.WAIT,
          "given up for a newer frame while the tracker waited for the frame before it to get its per-frame "
          "mask (mask_wait_ms), not for the CPU"),
    Cause("first_frame", "frame", "first frame (VINS-Mono)", Kind.POLICY,
          "VINS-Mono layout: the first image, at start and after a restart, is dropped as VINS-Mono does"),
    Cause("restart", "frame", "restart (stamp jump)", Kind.POLICY,
          "VINS-Mono layout: a stamp more than 1 s after the previous frame's; the estimator restarts"),
    Cause("left_at_stop", "frame", "left at the stop", Kind.STOP,
          "still waiting for the tracker when the node stopped"),
    Cause("reset_backwards", "frame", "stamp backwards (tracks reset)", Kind.EVENT,
          "VINS-Fusion layout: the stamp is older than the previous frame's; the tracks restart and the "
          "frame is tracked (it also counts as processed)"),
    Cause("throttled", "frame", "held back (publish rate)", Kind.HELD,
          "tracked but not published: publish_rate (or VINS-Mono's freq) lets only that many frames a "
          "second through to the estimator (it also counts as processed)"),
    Cause("first_published", "frame", "held back (VINS-Mono's first published frame)", Kind.HELD,
          "VINS-Mono layout: tracked but not published, as VINS-Mono skips its first published frame (it "
          "also counts as processed)"),
)
"""Every cause, in the order of the status line. Add a row here for a new one (see the module docstring)."""

_BY_KEY = {c.key: c for c in CAUSES}

DROPPED: frozenset[Kind] = frozenset({Kind.REFUSED, Kind.BEHIND, Kind.WAIT, Kind.POLICY, Kind.STOP})
"""The kinds of cause that end a frame untracked (EVENT and HELD frames are tracked)."""

_IMAGE_CAUSES = {"encoding": "wrong_encoding", "format": "wrong_encoding", "size": "wrong_size"}
"""The image decoder's cause prefixes (:class:`~nsflow_ros.data.images.ImageDecodeError`) that are not
``undecodable``."""


def cause(key: str) -> Cause:
    """The :data:`CAUSES` row of ``key``.

    Raises:
        KeyError: naming the unknown key and the known ones.
    """
    try:
        return _BY_KEY[key]
    except KeyError:
        raise KeyError(f"unknown counter cause {key!r}; known: {', '.join(_BY_KEY)}") from None


def image_cause(detail: str) -> str:
    """The :data:`CAUSES` key of an image decoder's cause (``"format:webp"`` -> ``"wrong_encoding"``)."""
    return _IMAGE_CAUSES.get(detail.partition(":")[0], "undecodable")


@dataclass
class NodeCounters:
    """What the node saw and did with images and frames; thread-safe (callbacks and the worker count).

    Attributes:
        images_received: images that arrived, either camera.
        frames_received: frames (image pairs for stereo) queued for the tracker.
        frames_processed: frames the tracker ran on.
        frames_unchecked: of those, frames tracked without the reverse checks because they came late.
        frames_published: feature messages published.
        frames_missing_upstream: frames of which no image reached the node, inferred from stamp gaps.
        lost: images and frames by :data:`CAUSES` key.
        detail: the same by the precise cause logged once (``format:webp``, ``truncated:png``, ...).
    """

    images_received: int = 0
    frames_received: int = 0
    frames_processed: int = 0
    frames_unchecked: int = 0
    frames_published: int = 0
    frames_missing_upstream: int = 0
    lost: Counter[str] = field(default_factory=Counter)
    detail: Counter[str] = field(default_factory=Counter)
    _lock: threading.Lock = field(default_factory=threading.Lock, repr=False, compare=False)

    def count(self, key: str, n: int = 1, detail: str | None = None) -> None:
        """Count ``n`` images or frames under cause ``key`` (and its precise ``detail``, if given)."""
        cause(key)
        with self._lock:
            self.lost[key] += n
            if detail is not None:
                self.detail[detail] += n

    def note(self, detail: str, n: int = 1) -> None:
        """Count ``n`` under a precise cause only, for inputs that are not images or frames (masks)."""
        with self._lock:
            self.detail[detail] += n

    def add(self, name: str, n: int = 1) -> None:
        """Add ``n`` to a plain counter (``frames_processed`` ...) under the lock."""
        with self._lock:
            setattr(self, name, getattr(self, name) + n)

    def of(self, kind: Kind, unit: str | None = None) -> int:
        """The sum of the causes of one kind (and unit)."""
        with self._lock:
            return sum(self.lost[c.key] for c in CAUSES if c.kind is kind and unit in (None, c.unit))

    # the names the summary file, the benchmarks and earlier tools read
    @property
    def images_undecodable(self) -> int:
        return self.lost["undecodable"]

    @property
    def images_unpaired(self) -> int:
        return self.lost["unpaired"]

    @property
    def frames_superseded(self) -> int:
        return self.lost["superseded"]

    @property
    def frames_left_at_stop(self) -> int:
        return self.lost["left_at_stop"]

    @property
    def frames_refused(self) -> int:
        """Frames refused as bad input (repeated stamp, stamp backwards, tracker error)."""
        return self.of(Kind.REFUSED, "frame")

    @property
    def frames_dropped(self) -> int:
        """Frames received but not tracked, all causes: received = processed + dropped (+ in flight)."""
        return sum(self.lost[c.key] for c in CAUSES if c.unit == "frame" and c.kind in DROPPED)

    def totals(self) -> dict[str, int]:
        """Every count by its name: the plain counters, one ``<unit>s_<key>`` per cause, the sums."""
        with self._lock:
            out = {f.name: getattr(self, f.name) for f in fields(self)
                   if isinstance(getattr(self, f.name), int)}
            out.update({c.name: self.lost[c.key] for c in CAUSES})
        out["frames_refused"] = self.frames_refused
        out["frames_dropped"] = self.frames_dropped
        return out

    def since(self, before: dict[str, Any]) -> dict[str, int]:
        """The change of every count of :meth:`totals` since an earlier :meth:`totals`."""
        return {k: v - before.get(k, 0) for k, v in self.totals().items()}


class CauseLog:
    """Each precise cause logged once, every occurrence counted: the node's log stays readable under a
    stream of bad input.

    Args:
        stats: where occurrences are counted.
        logger: anything with ``error`` and ``warning`` methods (the node's logger).
    """

    def __init__(self, stats: NodeCounters, logger: Any) -> None:
        self._stats = stats
        self._logger = logger
        self._logged: set[str] = set()

    def bad(self, key: str, detail: str, message: str, n: int = 1) -> None:
        """Count ``n`` images or frames under cause ``key``; log once per precise ``detail``."""
        self._stats.count(key, n, detail)
        if detail not in self._logged:
            self._logged.add(detail)
            c = cause(key)
            what = "image" if c.unit == "image" else "frame"
            self._logger.error(
                f"skipping {what} ({c.label}): {message} (further {what}s like it are only counted)"
            )

    def once(self, key: str, message: str) -> None:
        """Log a warning the first time ``key`` happens; after that it is only counted."""
        if key not in self._logged:
            self._logged.add(key)
            self._logger.warning(f"{message} (further ones are only counted)")
