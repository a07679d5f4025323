"""The ``tracker`` node's per-frame mask topics: subscriptions, a buffer per camera, the wait and the counts.

Masks (moving objects from a segmentation node) arrive on ``mask_topic`` / ``mask1_topic`` apart from their
frames; :class:`MaskTopics` checks each (encoding, size), reads it in ``mask_convention`` and keeps it in its
camera's :class:`~nsflow_ros.ros.frame_masks.FrameMasks` until the worker takes it for its frame. Every mask
ends used, late, unused, refused or left at the stop; frames tracked without theirs are counted as missing.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
from rclpy.qos import qos_profile_sensor_data
from rclpy.qos_overriding_options import QoSOverridingOptions
from sensor_msgs.msg import Image

from nsflow_ros.core.masks import MASK_CONVENTIONS, binarize
from nsflow_ros.data.images import ImageDecodeError, decode_image
from nsflow_ros.ros.counters import NodeCounters
from nsflow_ros.ros.errors import ParameterError
from nsflow_ros.ros.frame_masks import FrameMasks
from nsflow_ros.stamps import stamp_to_ns
from nsflow_ros.vins.health import check_static_masks
from nsflow_ros.vins.tracker import load_static_masks

__all__ = ["MASK_COUNTS", "MASK_ENCODINGS", "MaskTopics", "static_masks"]

MASK_ENCODINGS = ("mono8", "8UC1")
"""Encodings of the per-frame mask topics (8-bit, one channel)."""
MASK_COUNTS = ("masks_received", "masks_used", "masks_missing", "masks_late", "masks_unused", "masks_refused",
               "masks_left_at_stop")
"""The per-frame mask counts (:meth:`MaskTopics.counters`) as the summary and /diagnostics name them:
received = used + late + unused + refused + left at the stop (missing counts frames, not masks)."""


def static_masks(cfg: Any, mask0: str, mask1: str, convention: str,
                 min_usable: float) -> tuple[tuple[np.ndarray | None, np.ndarray | None], list[str]]:
    """The static masks of ``mask0`` / ``mask1`` ("" = the config's keys) in ``convention``, checked.

    Returns:
        (each camera's mask or None, a warning per mask that leaves less than ``min_usable`` usable).

    Raises:
        ParameterError: an unknown convention. ConfigError: a missing or unreadable mask, one of another
            size, or one that leaves no usable pixel.
    """
    if convention not in MASK_CONVENTIONS:
        raise ParameterError(
            f"parameter mask_convention: got {convention!r}, expected {' or '.join(MASK_CONVENTIONS)}"
        )
    static = load_static_masks(cfg, mask0 or None, mask1 or None, convention)
    names = [f"mask{i} {given or getattr(cfg, f'mask{i}')}" for i, given in enumerate((mask0, mask1))]
    return static, check_static_masks(dict(zip(names, static, strict=True)), min_usable)


class MaskTopics:
    """The node's per-frame mask topics (none when ``topics`` are empty).

    Args:
        node: the node that subscribes and logs.
        topics: ``mask_topic`` and ``mask1_topic`` ("" = none).
        cameras: the config's cameras (1 or 2); config_path: the config, for error messages.
        tolerance: ``stereo_sync_tolerance`` in seconds, the largest stamp difference of a frame and its mask.
        convention: ``mask_convention``.
        stats: the node's counters (a refused mask's precise cause is noted there).
        size: the images' (width, height) now.
        newer_frame: whether a newer frame waits for the tracker (ends a wait for a mask).

    Raises:
        ParameterError: ``mask1_topic`` for a mono config, or without ``mask_topic``.
    """

    def __init__(self, node: Any, topics: Sequence[str], cameras: int, config_path: Any, tolerance: float,
                 convention: str, stats: NodeCounters, size: Callable[[], tuple[int, int]],
                 newer_frame: Callable[[], bool]) -> None:
        if topics[1] and cameras < 2:
            raise ParameterError(f"parameter mask1_topic: {topics[1]!r} given, but {config_path} is mono")
        if topics[1] and not topics[0]:
            raise ParameterError("parameter mask1_topic needs mask_topic (camera 0's masks) too")
        self._node = node
        self._convention = convention
        self._stats = stats
        self._size = size
        self._newer_frame = newer_frame
        self._logged: set[str] = set()
        self.received = 0
        self.refused = 0
        self.waiting = False  # the worker waits for a frame's mask (a frame superseded meanwhile is its)
        self._last: dict[str, int] = {}  # the mask counts at the last status report
        self.buffers: list[FrameMasks | None] = []
        self.subs: list[Any] = []
        for cam, topic in enumerate(topics[:cameras]):
            if not topic:
                self.buffers.append(None)
                continue
            self.buffers.append(FrameMasks(tolerance))
            self.subs.append(node.create_subscription(
                Image, topic, lambda m, c=cam: self.on_mask(c, m), qos_profile_sensor_data,
                qos_overriding_options=QoSOverridingOptions.with_default_policies(),
            ))

    @property
    def active(self) -> bool:
        """Whether the node subscribes to a mask topic."""
        return bool(self.subs)

    def _each(self) -> list[FrameMasks]:
        return [b for b in self.buffers if b is not None]

    def topic(self, cam: int) -> str:
        """The resolved mask topic of a camera, for messages."""
        return self.subs[cam].topic_name if cam < len(self.subs) else f"camera {cam}"

    def note(self, static: tuple[np.ndarray | None, np.ndarray | None], wait_ms: float) -> str:
        """The masks in use, for the start-up line ("" = none)."""
        parts = [f"static mask{i}" for i, m in enumerate(static) if m is not None]
        if self.subs:
            topics = ", ".join(sub.topic_name for sub in self.subs)
            parts.append(f"per-frame masks on {topics} (waiting up to {wait_ms:g} ms)")
        if not parts:
            return ""
        meaning = "usable" if MASK_CONVENTIONS[self._convention] else "masked out"
        return f"; {', '.join(parts)}, read as {self._convention} (255 = {meaning})"

    def _bad(self, cause: str, message: str) -> None:
        """Log a refused mask once per cause; count every one."""
        self.refused += 1
        self._stats.note(cause)  # masks are not images or frames: only their precise cause is kept
        if cause not in self._logged:
            self._logged.add(cause)
            self._node.get_logger().error(
                f"ignoring mask: {message}; frames go on with the static masks (further masks like it are "
                "only counted)"
            )

    def on_mask(self, cam: int, msg: Image) -> None:
        """A per-frame mask: checked (encoding, size), read in mask_convention and kept for its frame."""
        self.received += 1
        topic = self.topic(cam)
        buffer = self.buffers[cam]
        if buffer is not None and buffer.silent and buffer.silences == 1:
            self._node.get_logger().info(
                f"masks on {topic} again: frames wait for theirs again (mask_wait_ms)")
        if msg.encoding not in MASK_ENCODINGS:
            self._bad(f"mask_encoding:{msg.encoding}",
                      f"{topic}: encoding {msg.encoding!r}, expected {' or '.join(MASK_ENCODINGS)}")
            return
        try:
            raw, _ = decode_image(msg, topic)
        except ImageDecodeError as err:
            self._bad(f"mask_{err.cause}", str(err))
            return
        width, height = self._size()
        h, w = raw.shape
        if (w, h) != (width, height):
            self._bad("mask_size", f"{topic}: mask is {w}x{h} but the images are {width}x{height}")
            return
        if buffer is not None:
            buffer.add(stamp_to_ns(msg.header.stamp), binarize(raw, self._convention))

    def take(self, stamp_ns: int, t_recv: float, wait_ms: float) -> tuple[np.ndarray | None, ...]:
        """A frame's masks per camera, each waited for until ``wait_ms`` after its image arrived (``t_recv``,
        perf_counter), or until the next frame arrives (a longer wait would cost that frame), but not on a
        silent topic. () without mask topics."""
        if all(b is None for b in self.buffers):  # (an empty buffer is falsy: test for None)
            return ()
        deadline = t_recv + wait_ms * 1e-3
        masks = []
        for cam, b in enumerate(self.buffers):
            if b is None:
                masks.append(None)
                continue
            silences = b.silences
            self.waiting = True  # a frame superseded meanwhile is the wait's, not the CPU's
            try:
                masks.append(b.take(stamp_ns, deadline - time.perf_counter(), until=self._newer_frame))
            finally:
                self.waiting = False
            if b.silences > silences and f"mask_silent:{cam}" not in self._logged:
                self._logged.add(f"mask_silent:{cam}")
                self._node.get_logger().warning(
                    f"no mask on {self.topic(cam)} within mask_wait_ms {wait_ms:g} ms: frames are tracked "
                    "without waiting for it until a mask comes again (counted as missing) (further ones are "
                    "only counted)")
        return tuple(masks)

    def wake(self) -> None:
        """A frame arrived: a worker waiting for the previous frame's mask tracks it now."""
        for buffer in self._each():
            buffer.wake()

    def set_tolerance(self, seconds: float) -> None:
        """A new ``stereo_sync_tolerance``."""
        for buffer in self._each():
            buffer.tolerance = seconds

    def close(self) -> None:
        """The node stops: a worker waiting for a mask returns at once; waiting masks are left at the stop."""
        for buffer in self._each():
            buffer.close()

    def counters(self) -> dict[str, int]:
        """Per-frame masks received, used, missing (frames tracked without theirs), late, unused, refused
        and left at the stop (:data:`MASK_COUNTS`, in its order; all but two are the buffers' sums)."""
        own = {"masks_received": self.received, "masks_refused": self.refused}
        return {k: own[k] if k in own else sum(getattr(b, k.removeprefix("masks_")) for b in self._each())
                for k in MASK_COUNTS}

    def window(self, c: dict[str, Any]) -> str:
        """The period's mask problems in words ("" = none) from the run's counters; starts the next period."""
        now = {k: c[k] for k in MASK_COUNTS}
        d = {k: now[k] - self._last.get(k, 0) for k in MASK_COUNTS}
        self._last = now
        problems = []
        if d["masks_missing"]:
            problems.append(f"{d['masks_missing']} frames tracked without their mask")
        if d["masks_late"]:
            problems.append(f"{d['masks_late']} masks came after their frame was tracked (see mask_wait_ms)")
        if d["masks_refused"]:
            problems.append(f"{d['masks_refused']} masks refused")
        return "; ".join(problems)
