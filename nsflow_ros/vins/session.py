"""The VINS front-end's frame policy around a tracker, shared by the node, offline run and feature bag.

Per frame (:meth:`FrontEndSession.process`) a session

* skips a frame whose stamp repeats the previous one;
* in the VINS-Fusion layout, resets the tracks when time goes backwards;
* in the VINS-Mono layout, does what VINS-Mono's ``img_callback`` does: drops the first image, asks for an
  estimator restart on a stamp gap > 1 s or time going backwards, throttles publishing to ``freq`` Hz (the
  throttled frames are still tracked, without detecting new corners) and skips the first published frame;
* with ``publish_rate`` (either layout; for ``mono`` it replaces ``freq``) publishes at most that many frames
  a second with VINS-Mono's rate control, every frame still tracked, and gives the published features
  velocities over the interval since the previous published frame, so that the estimator's velocities
  match the frames it gets;
* after ``max_cnt`` is lowered, publishes only the longest ``max_cnt`` tracks (never an id it cut);
* predicts the flow from the gyro samples of :meth:`FrontEndSession.add_gyro` when that is on;
* applies the static masks of every tracker it builds and each frame's own masks (moving objects), taken
  from the images' full resolution to the tracker's.

Settings changed at run time land in :meth:`FrontEndSession.update`.
"""

from __future__ import annotations

import dataclasses
import os
import threading
from collections import Counter
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from enum import StrEnum
from typing import Any

import numpy as np

from nsflow_ros.core.errors import CoreError
from nsflow_ros.core.imu import GyroBuffer
from nsflow_ros.core.masks import check_mask
from nsflow_ros.core.tracker import FeatureTracker, FrameFeatures
from nsflow_ros.vins.config import VinsConfig, apply_overrides
from nsflow_ros.vins.errors import ConfigError
from nsflow_ros.vins.messages import LAYOUTS
from nsflow_ros.vins.settings import (
    SESSION_SETTINGS,
    SETTINGS,
    TRACKER_SETTINGS,
    Mode,
    Setting,
    is_unset,
    session_tracker_fields,
    setting,
)
from nsflow_ros.vins.tracker import load_static_masks, tracker_from_config

__all__ = ["RESTART_GAP_S", "FrameOutcome", "FrontEndSession", "SessionCounters", "Skip"]

RESTART_GAP_S = 1.0
"""VINS-Mono: a stamp gap larger than this (seconds) restarts the estimator."""

_SESSION = tuple(s for s in SETTINGS if s.session)


class Skip(StrEnum):
    """Why :meth:`FrontEndSession.process` did not track a frame."""

    FIRST_FRAME = "first_frame"
    """VINS-Mono layout: the first image (at start or after a restart) is dropped."""
    RESTART = "restart"
    """VINS-Mono layout: a stamp gap or time going backwards; the estimator must restart."""
    DUPLICATE_STAMP = "duplicate_stamp"
    """The stamp repeats the previous frame's."""
    TRACKER = "tracker"
    """The tracker refused the frame (wrong size, missing stereo image, ...)."""


@dataclass(frozen=True)
class FrameOutcome:
    """What :meth:`FrontEndSession.process` did with one frame.

    Attributes:
        features: the features to publish; None when nothing is published for this frame.
        tracked: the tracker ran on the frame (False for policy skips and errors).
        restart: VINS-Mono layout: the estimator must restart (publish ``restart``).
        skipped: why the frame was not tracked; None when tracked.
        note: a sentence for the log when something noteworthy happened (a skip, a reset), else "".
        held: why a tracked frame has no features to publish: ``throttled`` (``publish_rate`` / ``freq``)
            or ``first_published`` (VINS-Mono skips its first published frame); "" otherwise.
    """

    features: FrameFeatures | None
    tracked: bool
    restart: bool = False
    skipped: Skip | None = None
    note: str = ""
    held: str = ""


@dataclass
class SessionCounters:
    """What a :class:`FrontEndSession` did, counted frame by frame.

    Attributes:
        tracked: frames the tracker ran on.
        published: frames with features to publish.
        skipped: frames not tracked, by reason.
        restarts: VINS-Mono estimator restarts asked for.
        resets: track resets after time went backwards (VINS-Fusion layout).
        throttled: frames tracked but not published (VINS-Mono ``freq``, ``publish_rate``).
        rebuilds: new trackers built after a setting change.
        gated: tracked features dropped by the ``max_sigma`` gate.
    """

    tracked: int = 0
    published: int = 0
    skipped: Counter[Skip] = field(default_factory=Counter)
    restarts: int = 0
    resets: int = 0
    throttled: int = 0
    rebuilds: int = 0
    gated: int = 0


class FrontEndSession:
    """A tracker plus the VINS front-end frame policy (see the module docstring).

    Args:
        settings: values by name from :data:`~nsflow_ros.vins.settings.SESSION_SETTINGS`; -1, None or ""
            keep the default.
        layout: feature message layout, ``fusion`` or ``mono``; None = the config's dialect.
        fisheye_mask: mask image for a config with ``fisheye: 1``; None = where VINS-Mono keeps it.
        masks: static masks per camera, uint8 0 / 255 at the images' full size
            (:func:`~nsflow_ros.vins.tracker.load_static_masks`), kept for every tracker the session
            builds; None = the config's mask0 / mask1 keys (255 = usable), if any.
        tracker_overrides: further :class:`~nsflow_ros.core.tracker.TrackerSettings` fields, fixed for the
            session (e.g. ``{"stereo": False}`` to track camera 0 of a stereo config).

    Raises:
        ConfigError: an unknown setting, a bad value or layout.
        NSFlowError: the tracker cannot be built.
    """

    def __init__(
        self,
        config: VinsConfig,
        settings: Mapping[str, Any] | None = None,
        *,
        layout: str | None = None,
        fisheye_mask: str | os.PathLike[str] | None = None,
        masks: Sequence[np.ndarray | None] | None = None,
        tracker_overrides: Mapping[str, Any] | None = None,
    ) -> None:
        self.layout = layout or config.dialect
        if self.layout not in LAYOUTS:
            raise ConfigError(f"output layout must be one of {LAYOUTS}, got {self.layout!r}")
        self._base_config = config
        self._fisheye_mask = fisheye_mask
        self._masks = load_static_masks(config) if masks is None else tuple(masks)
        self._fixed = dict(tracker_overrides or {})
        self._check_names(settings or {})
        self._settings: dict[str, Any] = dict(settings or {})
        self.config, self._fields = self._resolve(self._settings)
        self.tracker = self._build()
        self.gyro: GyroBuffer | None = GyroBuffer() if self._fields["use_imu_prediction"] else None
        self._gyro_lock = threading.Lock()  # IMU messages may arrive on another thread than the frames
        self.counters = SessionCounters()
        self._id_offset = 0
        self._withheld: set[int] = set()  # ids cut after max_cnt was lowered (see _trim)
        self._last_stamp: float | None = None
        self._last_published: tuple[float, tuple[tuple[np.ndarray, np.ndarray], ...]] | None = None
        self._reset_mono_state()

    # -- settings --------------------------------------------------------------------------------------

    @staticmethod
    def _check_names(settings: Mapping[str, Any]) -> None:
        unknown = sorted(set(settings) - set(SESSION_SETTINGS))
        if unknown:
            raise ConfigError(f"unknown front-end setting(s) {unknown}; valid: {list(SESSION_SETTINGS)}")

    def _resolve(self, settings: Mapping[str, Any]) -> tuple[VinsConfig, dict[str, Any]]:
        """The effective VINS config and the session's own fields for ``settings``: the TrackerSettings
        fields, and ``publish_rate`` (None when unset: the layout's default)."""
        cfg = apply_overrides(
            self._base_config, {s.vins_key: settings.get(s.name) for s in _SESSION if s.vins_key}
        )
        fields = session_tracker_fields(settings, self.layout)
        rate = settings.get("publish_rate")
        fields["publish_rate"] = None if is_unset(rate) else setting("publish_rate").check(rate)
        return cfg, fields

    def _build(self) -> FeatureTracker:
        tracker_fields = {k: v for k, v in self._fields.items() if k in TRACKER_SETTINGS}
        tracker = tracker_from_config(
            self.config, {**tracker_fields, **self._fixed}, fisheye_mask=self._fisheye_mask, masks=self._masks
        )
        tracker.warm_up()
        return tracker

    @staticmethod
    def _value(s: Setting, config: VinsConfig, fields: Mapping[str, Any]) -> Any:
        """A session setting's effective value: the config's for a VINS key, else the tracker field's."""
        return getattr(config, s.vins_key) if s.vins_key is not None else fields[s.name]

    @property
    def settings(self) -> dict[str, Any]:
        """The settings as given (unset ones absent)."""
        return dict(self._settings)

    @property
    def show_track(self) -> bool:
        """Whether the debug image is wanted (VINS ``show_track``)."""
        return bool(self.config.show_track)

    @property
    def freq(self) -> int:
        """Publishing rate in Hz of the VINS-Mono layout (``freq: 0`` reads as 100, i.e. every image)."""
        return int(self.config.freq)

    @property
    def publish_rate(self) -> float | None:
        """The ``publish_rate`` given (Hz; 0 = every frame), None when unset (the layout's default)."""
        return self._fields["publish_rate"]

    def update(self, **settings: Any) -> list[str]:
        """Change settings of the running session, all or nothing, as each one's :class:`Mode` says.

        A live change updates the running tracker, a rebuild builds a new tracker (tracks restart, ids keep
        counting up), a read-only one is refused; -1, None or "" restore the default.

        Returns:
            one sentence per change, for the log.

        Raises:
            ConfigError: an unknown name, a bad value or a read-only setting changed; NSFlowError when the
                new tracker cannot be built. The session is unchanged when it raises.
        """
        self._check_names(settings)
        merged = {**self._settings, **settings}
        cfg, fields = self._resolve(merged)
        changed = [
            s for s in _SESSION if self._value(s, cfg, fields) != self._value(s, self.config, self._fields)
        ]
        refused = [s.name for s in changed if s.mode is Mode.READ_ONLY]
        if refused:
            raise ConfigError(f"{', '.join(refused)} cannot change while the session runs")
        rebuild = sorted(s.name for s in changed if s.mode is Mode.REBUILD)
        live = [s for s in changed if s.mode is Mode.LIVE]
        notes = []
        if rebuild:
            self._rebuild(cfg, fields)
            what = ", ".join(rebuild)
            notes.append(f"{what} changed: new tracker, tracks restart (ids continue from {self._id_offset})")
        elif live:
            self._apply_live(cfg, fields, [s.name for s in live if s.tracker])
        if any(s.name in ("freq", "publish_rate") for s in changed):
            self._first_time = self._last_time
            self._pub_count = 0
            self._last_published = None
        self._settings = merged
        for s in sorted(live, key=lambda s: s.name):
            notes.append(f"{s.name} is now {self._value(s, cfg, fields)}")
        return notes

    def _rebuild(self, config: VinsConfig, fields: dict[str, Any]) -> None:
        """Build a new tracker for new settings; ids continue after the old tracker's."""
        prev = self.config, self._fields
        self.config, self._fields = config, fields
        try:
            tracker = self._build()
        except Exception:
            self.config, self._fields = prev
            raise
        self._id_offset += self.tracker.next_id
        self.tracker = tracker
        self._withheld.clear()
        self._last_published = None  # the new tracker's ids start again
        self.counters.rebuilds += 1

    def _apply_live(self, config: VinsConfig, fields: dict[str, Any], names: list[str]) -> None:
        """Give the running tracker new values of live settings (the one place its settings change)."""
        target = {**config.tracker_fields(), **fields}
        try:
            self.tracker.update_settings({**{n: target[n] for n in names}, **self._fixed})
        except CoreError as err:
            raise ConfigError(str(err)) from err
        self.config, self._fields = config, fields

    # -- frames ----------------------------------------------------------------------------------------

    def _reset_mono_state(self) -> None:
        self._first_image = True
        self._first_time = 0.0
        self._last_time = 0.0
        self._pub_count = 1
        self._init_pub = False
        self._rate_started = False  # publish_rate in the 'fusion' layout: its first frame seen

    def add_gyro(self, stamp: float, rate: tuple[float, float, float] | np.ndarray) -> None:
        """Store one gyro sample (rad/s, IMU frame) when ``use_imu_prediction`` is on; thread-safe."""
        if self.gyro is not None:
            with self._gyro_lock:
                self.gyro.add(stamp, rate)

    def _mono_gate(self, stamp: float) -> tuple[bool | None, str]:
        """VINS-Mono's img_callback bookkeeping: (None = skip the frame, else whether to publish, note)."""
        if self._first_image:
            self._first_image = False
            self._first_time = self._last_time = stamp
            return None, ""
        if stamp - self._last_time > RESTART_GAP_S or stamp < self._last_time:
            note = (
                f"image stamp discontinuity ({self._last_time:.3f} -> {stamp:.3f} s): "
                "restarting the estimator"
            )
            self._first_image = True
            self._last_time = 0.0
            self._pub_count = 1
            self.tracker.reset()
            self._last_stamp = None
            self._last_published = None
            return None, note
        self._last_time = stamp
        rate = self.publish_rate
        return self._rate_due(stamp, self.freq if rate is None else rate), ""

    def _rate_due(self, stamp: float, freq: float) -> bool:
        """VINS-Mono's rate control: publish while the published frames per second, rounded, are at most
        ``freq`` (0 = every frame); near the target the count starts over from this frame."""
        if freq <= 0:
            return True
        elapsed = stamp - self._first_time
        rate = self._pub_count / elapsed if elapsed > 0 else float("inf")
        if round(rate) <= freq:
            if abs(rate - freq) < 0.01 * freq:  # reset the frequency control near the target
                self._first_time = stamp
                self._pub_count = 0
            return True
        return False

    def _fusion_gate(self, stamp: float) -> bool:
        """Whether the 'fusion' layout publishes this frame: every frame, or ``publish_rate``'s control
        (the first frame is published and starts the count)."""
        rate = self.publish_rate
        if not rate:
            return True
        if not self._rate_started:
            self._rate_started = True
            self._first_time = stamp
            self._pub_count = 0
            return True
        return self._rate_due(stamp, rate)

    def process(
        self,
        stamp: float,
        image0: np.ndarray,
        image1: np.ndarray | None = None,
        *,
        checks: bool = True,
        frame_masks: Sequence[np.ndarray | None] = (),
    ) -> FrameOutcome:
        """Apply the frame policy to one frame (``stamp`` in seconds, uint8 images) and track it.

        ``checks`` False tracks it without the reverse checks (:meth:`FeatureTracker.process`).
        ``frame_masks`` are this frame's masks per camera (camera 0 first; None = none), uint8 0 / 255 of
        the images' size; a mask the tracker refuses refuses the frame as a bad image does.

        Returns:
            what to publish and what happened; counted in :attr:`counters`.
        """
        out = self._process(stamp, image0, image1, checks, frame_masks)
        c = self.counters
        c.tracked += out.tracked
        c.published += out.features is not None
        c.restarts += out.restart
        if out.skipped is not None:
            c.skipped[out.skipped] += 1
        return out

    def _process(
        self,
        stamp: float,
        image0: np.ndarray,
        image1: np.ndarray | None,
        checks: bool,
        frame_masks: Sequence[np.ndarray | None],
    ) -> FrameOutcome:
        last = self._last_stamp
        if last is not None and stamp == last:
            return FrameOutcome(None, False, skipped=Skip.DUPLICATE_STAMP,
                                note=f"stamp {stamp:.9f} repeats the previous frame's")
        publish = True
        note = ""
        if self.layout == "mono":
            gate, note = self._mono_gate(stamp)
            if gate is None:
                restart = bool(note)
                return FrameOutcome(None, False, restart=restart,
                                    skipped=Skip.RESTART if restart else Skip.FIRST_FRAME, note=note)
            publish = gate
        else:
            if last is not None and stamp < last:
                note = f"time went backwards ({last:.3f} -> {stamp:.3f} s): tracks reset"
                self.tracker.reset()
                self.counters.resets += 1
                self._reset_mono_state()
                self._last_published = None
            publish = self._fusion_gate(stamp)
        gyro = None
        prev = self.tracker.last_stamp
        if self.gyro is not None and prev is not None:
            with self._gyro_lock:
                gyro = self.gyro.window(prev, stamp)
        # VINS-Mono detects new corners only on published frames; VINS-Fusion's front-end on every frame
        detect = publish or self.layout != "mono"
        try:
            masks = [self._frame_mask(m, i) for i, m in enumerate(frame_masks)]
            frame = self.tracker.process(
                stamp, image0, image1, gyro, detect=detect, checks=checks, frame_masks=masks
            )
        except CoreError as err:
            return FrameOutcome(None, False, skipped=Skip.TRACKER, note=str(err))
        self._last_stamp = stamp
        self.counters.gated += frame.gated
        if self.gyro is not None:
            with self._gyro_lock:
                self.gyro.prune(stamp)
        if not publish:
            self.counters.throttled += 1
            return FrameOutcome(None, True, note=note, held="throttled")
        self._pub_count += 1
        if self.layout == "mono" and not self._init_pub:  # VINS-Mono skips the first published frame
            self._init_pub = True
            return FrameOutcome(None, True, note=note, held="first_published")
        if self.publish_rate:
            frame = self._interval_velocities(frame)
        return FrameOutcome(self._shift_ids(self._trim(frame)), True, note=note)

    def _interval_velocities(self, frame: FrameFeatures) -> FrameFeatures:
        """Velocities over the interval since the previous published frame (0 for ids it did not have),
        so that the estimator, which sees only the published frames, gets consistent ones."""
        last = self._last_published
        cams = []
        for k, cam in enumerate(frame.cameras):
            vel = np.zeros_like(cam.undistorted)
            if last is not None and k < len(last[1]) and frame.stamp > last[0]:
                ids0, un0 = last[1][k]
                rows, found = _find(cam.ids, ids0)
                vel[found] = (cam.undistorted[found] - un0[rows[found]]) / (frame.stamp - last[0])
            cams.append(dataclasses.replace(cam, velocities=vel))
        self._last_published = (frame.stamp, tuple((c.ids, c.undistorted) for c in frame.cameras))
        return dataclasses.replace(frame, cameras=tuple(cams))

    def _frame_mask(self, mask: np.ndarray | None, camera: int) -> np.ndarray | None:
        """A frame mask checked against the images' size (CoreError); the tracker decimates it."""
        if mask is None or camera >= len(self.tracker.cameras):
            return mask  # the tracker names a mask for a camera it lacks
        full = (self.config.image_width, self.config.image_height)
        return check_mask(mask, full, f"frame mask {camera}", "the images' size")

    def _trim(self, frame: FrameFeatures) -> FrameFeatures:
        """At most ``max_cnt`` features, the longest tracks first, after ``max_cnt`` was lowered.

        An id cut once is never published again: the estimator assumes an id's observations are contiguous.
        """
        cam0 = frame.cameras[0]
        limit = self.tracker.settings.max_cnt
        if not self._withheld and len(cam0) <= limit:
            return frame
        keep = ~np.isin(cam0.ids, np.fromiter(self._withheld, np.int64, len(self._withheld)))
        rows = np.flatnonzero(keep)
        if rows.size > limit:
            order = np.lexsort((cam0.ids[rows], -cam0.track_counts[rows]))  # longest first, then oldest id
            cut = rows[order[limit:]]
            self._withheld.update(cam0.ids[cut].tolist())
            keep[cut] = False
        self._withheld.intersection_update(cam0.ids.tolist())  # ids never come back once gone
        kept_ids = cam0.ids[keep]
        cams = tuple(
            _subset(c, keep if i == 0 else np.isin(c.ids, kept_ids)) for i, c in enumerate(frame.cameras)
        )
        return dataclasses.replace(frame, cameras=cams)

    def _shift_ids(self, frame: FrameFeatures) -> FrameFeatures:
        """Ids of a rebuilt tracker continue after the previous tracker's (never reused)."""
        if not self._id_offset:
            return frame
        cams = tuple(dataclasses.replace(c, ids=c.ids + self._id_offset) for c in frame.cameras)
        return dataclasses.replace(frame, cameras=cams)


def _find(ids: np.ndarray, table: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For each of ``ids``, its row in ``table`` and whether it is there. Shape: (N,) -> (N,), (N,)."""
    if not table.size:
        return np.zeros(ids.shape, np.int64), np.zeros(ids.shape, bool)
    order = np.argsort(table, kind="stable")
    pos = np.clip(np.searchsorted(table[order], ids), 0, table.size - 1)
    found = table[order][pos] == ids
    return order[pos], found


def _subset(cam: Any, rows: np.ndarray) -> Any:
    """The rows of one camera's features (every per-feature array field)."""
    n = len(cam)
    changes = {
        f.name: getattr(cam, f.name)[rows]
        for f in dataclasses.fields(cam)
        if isinstance(getattr(cam, f.name), np.ndarray) and getattr(cam, f.name).shape[:1] == (n,)
    }
    return dataclasses.replace(cam, **changes)
