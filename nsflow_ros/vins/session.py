"""The VINS front-end's frame policy around a tracker, without middleware.

A :class:`FrontEndSession` is what sits between "an image (pair) arrived" and "publish these features": the
ROS node, the offline run and anything else that feeds a VINS estimator share it, so the policy is written
and tested once. Per frame (:meth:`FrontEndSession.process`) it

* skips a frame whose stamp repeats the previous one;
* in the VINS-Fusion layout, resets the tracks when time goes backwards;
* in the VINS-Mono layout, does what VINS-Mono's ``img_callback`` does: drops the first image, asks for an
  estimator restart on a stamp gap > 1 s or time going backwards, throttles publishing to ``freq`` Hz (the
  throttled frames are still tracked, without detecting new corners) and skips the first published frame;
* after ``max_cnt`` is lowered, publishes only the longest ``max_cnt`` tracks (never an id it cut);
* predicts the flow from the gyro samples given to :meth:`FrontEndSession.add_gyro` when that is on;
* counts what it did (:attr:`FrontEndSession.counters`).

:meth:`FrontEndSession.update` is where settings changed at run time land: most apply to the running
tracker; a change of ``method``, ``model_path``, ``num_threads`` or ``equalize`` builds a new tracker (the
tracks restart; ids keep counting up, so an id is never reused).

Imports neither rclpy nor torch.
"""

from __future__ import annotations

import dataclasses
import os
import threading
from collections import Counter
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from nsflow_ros.core.errors import CoreError
from nsflow_ros.core.imu import GyroBuffer
from nsflow_ros.core.tracker import FeatureTracker, FrameFeatures
from nsflow_ros.vins.config import OVERRIDABLE_KEYS, VinsConfig, apply_overrides
from nsflow_ros.vins.errors import ConfigError
from nsflow_ros.vins.messages import LAYOUTS

__all__ = [
    "KEEP",
    "REBUILD_SETTINGS",
    "RESTART_GAP_S",
    "SESSION_SETTINGS",
    "FrameOutcome",
    "FrontEndSession",
]

RESTART_GAP_S = 1.0
"""VINS-Mono: a stamp gap larger than this (seconds) restarts the estimator."""

KEEP = -1
"""A setting's value meaning "the VINS config's value" (or the layout's default for reject_with_f)."""

SESSION_SETTINGS: tuple[str, ...] = (
    *OVERRIDABLE_KEYS,
    "method",
    "model_path",
    "num_threads",
    "reject_with_f",
    "use_imu_prediction",
)
"""Settings :class:`FrontEndSession` takes, at construction and in :meth:`FrontEndSession.update`."""

REBUILD_SETTINGS: frozenset[str] = frozenset({"method", "model_path", "num_threads", "equalize"})
"""Settings whose change builds a new tracker (its encoder or image preparation changes): tracks restart."""


@dataclass(frozen=True)
class FrameOutcome:
    """What :meth:`FrontEndSession.process` did with one frame.

    Attributes:
        features: the features to publish; None when nothing is published for this frame.
        tracked: the tracker ran on the frame (False for policy skips and errors).
        restart: VINS-Mono layout: the estimator must restart (publish ``restart``).
        skipped: why the frame was not tracked: ``first_frame`` / ``restart`` (VINS-Mono policy),
            ``duplicate_stamp`` or ``tracker`` (the tracker refused the frame); None when tracked.
        note: a sentence for the log when something noteworthy happened (a skip, a reset), else "".
    """

    features: FrameFeatures | None
    tracked: bool
    restart: bool = False
    skipped: str | None = None
    note: str = ""


def _unset(value: Any) -> bool:
    """True for the values that mean "default": None, -1 (not a bool) and ""."""
    if value is None or (isinstance(value, str) and value == ""):
        return True
    return not isinstance(value, bool) and isinstance(value, (int, float)) and value == KEEP


class FrontEndSession:
    """A tracker plus the VINS front-end frame policy (see the module docstring).

    Args:
        config: the VINS config (cameras, topics and the file's tracker settings).
        settings: values by name from :data:`SESSION_SETTINGS`; -1, None or "" keep the default (the VINS
            config's value; for ``reject_with_f`` on in the VINS-Mono layout, off in VINS-Fusion's).
        layout: feature message layout, ``fusion`` or ``mono``; None = the config's dialect.
        fisheye_mask: mask image for a config with ``fisheye: 1``; None = where VINS-Mono keeps it.
        tracker_overrides: further :class:`~nsflow_ros.core.tracker.TrackerSettings` fields, fixed for the
            session (e.g. ``{"stereo": False}`` to track camera 0 of a stereo config).

    Raises:
        ConfigError: an unknown setting, a bad value or layout (the message names it).
        NSFlowError: CoreError / EncoderError when the tracker cannot be built.
    """

    def __init__(
        self,
        config: VinsConfig,
        settings: Mapping[str, Any] | None = None,
        *,
        layout: str | None = None,
        fisheye_mask: str | os.PathLike[str] | None = None,
        tracker_overrides: Mapping[str, Any] | None = None,
    ) -> None:
        self.layout = layout or config.dialect
        if self.layout not in LAYOUTS:
            raise ConfigError(f"output layout must be one of {LAYOUTS}, got {self.layout!r}")
        self._base_config = config
        self._fisheye_mask = fisheye_mask
        self._fixed = dict(tracker_overrides or {})
        self._settings: dict[str, Any] = {}
        self._check_names(settings or {})
        self._settings.update(settings or {})
        self.config, overrides = self._resolve(self._settings)
        self.tracker = self._build(overrides)
        self.gyro: GyroBuffer | None = GyroBuffer() if overrides["use_imu_prediction"] else None
        self._gyro_lock = threading.Lock()  # IMU messages may arrive on another thread than the frames
        self.counters: Counter[str] = Counter()
        self._id_offset = 0
        self._withheld: set[int] = set()  # ids cut after max_cnt was lowered (see _trim)
        self._last_stamp: float | None = None
        self._reset_mono_state()

    # -- settings --------------------------------------------------------------------------------------

    @staticmethod
    def _check_names(settings: Mapping[str, Any]) -> None:
        unknown = sorted(set(settings) - set(SESSION_SETTINGS))
        if unknown:
            raise ConfigError(f"unknown front-end setting(s) {unknown}; valid: {list(SESSION_SETTINGS)}")

    def _resolve(self, settings: Mapping[str, Any]) -> tuple[VinsConfig, dict[str, Any]]:
        """The effective VINS config and the tracker overrides for ``settings``."""
        cfg = apply_overrides(self._base_config, {k: settings.get(k) for k in OVERRIDABLE_KEYS})
        reject = settings.get("reject_with_f")
        method = settings.get("method")
        threads = settings.get("num_threads")
        overrides: dict[str, Any] = {
            "method": "nsflow" if _unset(method) else str(method),
            "model_path": None if _unset(settings.get("model_path")) else str(settings["model_path"]),
            "num_threads": None if _unset(threads) or threads == 0 else int(threads),
            "reject_with_f": self.layout == "mono" if _unset(reject) else bool(reject),
            "use_imu_prediction": bool(settings.get("use_imu_prediction") or False),
        }
        return cfg, overrides

    def _build(self, overrides: Mapping[str, Any]) -> FeatureTracker:
        return FeatureTracker.from_vins_config(
            self.config, {**overrides, **self._fixed}, fisheye_mask=self._fisheye_mask
        )

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

    def update(self, **settings: Any) -> list[str]:
        """Change settings of the running session; all or nothing.

        Args:
            **settings: names from :data:`SESSION_SETTINGS`; -1, None or "" restore the default.

        Returns:
            what changed, one sentence per change, for the log ([] when nothing changed).

        Raises:
            ConfigError: an unknown name or a bad value; NSFlowError (CoreError, EncoderError) when the new
                tracker cannot be built. The session is unchanged when it raises.
        """
        self._check_names(settings)
        imu = settings.get("use_imu_prediction", self.gyro is not None)
        if bool(imu) != (self.gyro is not None):
            raise ConfigError("use_imu_prediction cannot change while the session runs")
        merged = {**self._settings, **settings}
        cfg, overrides = self._resolve(merged)
        old_cfg, old = self._resolve(self._settings)
        changed = {k for k in OVERRIDABLE_KEYS if getattr(cfg, k) != getattr(old_cfg, k)}
        changed |= {k for k in overrides if overrides[k] != old[k]}
        notes = []
        if changed & REBUILD_SETTINGS:
            prev_config, self.config = self.config, cfg
            try:
                tracker = self._build(overrides)
            except Exception:
                self.config = prev_config
                raise
            self._id_offset += self.tracker.next_id
            self.tracker = tracker
            self._withheld.clear()
            self.counters["rebuilds"] += 1
            what = ", ".join(sorted(changed & REBUILD_SETTINGS))
            notes.append(f"{what} changed: new tracker, tracks restart (ids continue from {self._id_offset})")
        elif changed:
            soft = {
                "max_cnt": int(cfg.max_cnt),
                "min_dist": float(cfg.min_dist),
                "F_threshold": float(cfg.F_threshold),
                "flow_back": bool(cfg.flow_back),
                "reject_with_f": overrides["reject_with_f"],
            }
            try:
                new = self.tracker.settings.with_overrides(soft)
            except CoreError as err:
                raise ConfigError(str(err)) from err
            self.tracker.settings = new
            self.config = cfg
        if "freq" in changed:
            self._first_time = self._last_time
            self._pub_count = 0
        self._settings = merged
        for key in sorted(changed - REBUILD_SETTINGS):
            value = overrides[key] if key in overrides else getattr(cfg, key)
            notes.append(f"{key} is now {value}")
        return notes

    # -- frames ----------------------------------------------------------------------------------------

    def _reset_mono_state(self) -> None:
        self._first_image = True
        self._first_time = 0.0
        self._last_time = 0.0
        self._pub_count = 1
        self._init_pub = False

    def add_gyro(self, stamp: float, rate: tuple[float, float, float] | np.ndarray) -> None:
        """Store one gyro sample (rad/s, IMU frame); ignored unless ``use_imu_prediction`` is on.

        Safe to call from another thread than :meth:`process`.
        """
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
            return None, note
        self._last_time = stamp
        freq = self.freq
        elapsed = stamp - self._first_time
        rate = self._pub_count / elapsed if elapsed > 0 else float("inf")
        if round(rate) <= freq:
            if abs(rate - freq) < 0.01 * freq:  # reset the frequency control near the target
                self._first_time = stamp
                self._pub_count = 0
            return True, ""
        return False, ""

    def process(
        self, stamp: float, image0: np.ndarray, image1: np.ndarray | None = None
    ) -> FrameOutcome:
        """Apply the frame policy to one frame and track it.

        Args:
            stamp: the frame's time in seconds.
            image0: camera-0 image, uint8 (H, W) or (H, W, 3).
            image1: camera-1 image of the same stamp (stereo).

        Returns:
            what to publish and what happened (:class:`FrameOutcome`); counted in :attr:`counters`.
        """
        out = self._process(stamp, image0, image1)
        if out.tracked:
            self.counters["tracked"] += 1
        if out.features is not None:
            self.counters["published"] += 1
        if out.skipped:
            self.counters[f"skipped:{out.skipped}"] += 1
        if out.restart:
            self.counters["restarts"] += 1
        return out

    def _process(self, stamp: float, image0: np.ndarray, image1: np.ndarray | None) -> FrameOutcome:
        last = self._last_stamp
        if last is not None and stamp == last:
            return FrameOutcome(None, False, skipped="duplicate_stamp",
                                note=f"stamp {stamp:.9f} repeats the previous frame's")
        publish = True
        note = ""
        if self.layout == "mono":
            gate, note = self._mono_gate(stamp)
            if gate is None:
                restart = bool(note)
                return FrameOutcome(None, False, restart=restart,
                                    skipped="restart" if restart else "first_frame", note=note)
            publish = gate
        elif last is not None and stamp < last:
            note = f"time went backwards ({last:.3f} -> {stamp:.3f} s): tracks reset"
            self.tracker.reset()
            self.counters["resets"] += 1
        gyro = None
        prev = self.tracker.last_stamp
        if self.gyro is not None and prev is not None:
            with self._gyro_lock:
                gyro = self.gyro.window(prev, stamp)
        try:
            frame = self.tracker.process(stamp, image0, image1, gyro, detect=publish)
        except CoreError as err:
            return FrameOutcome(None, False, skipped="tracker", note=str(err))
        self._last_stamp = stamp
        if self.gyro is not None:
            with self._gyro_lock:
                self.gyro.prune(stamp)
        if self.layout == "mono":
            if not publish:
                self.counters["throttled"] += 1
                return FrameOutcome(None, True, note=note)
            self._pub_count += 1
            if not self._init_pub:  # VINS-Mono skips the first published frame
                self._init_pub = True
                return FrameOutcome(None, True, note=note)
        return FrameOutcome(self._shift_ids(self._trim(frame)), True, note=note)

    def _trim(self, frame: FrameFeatures) -> FrameFeatures:
        """At most ``max_cnt`` features, the longest tracks first, after ``max_cnt`` was lowered.

        The tracker keeps tracking what it had (VINS only stops detecting), so the excess is cut here, and
        an id cut once is never published again: the estimator assumes an id's observations are contiguous.
        """
        cam0 = frame.cameras[0]
        limit = int(self.config.max_cnt)
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


def _subset(cam: Any, rows: np.ndarray) -> Any:
    """The rows of one camera's features (every per-feature array field)."""
    n = len(cam)
    changes = {
        f.name: getattr(cam, f.name)[rows]
        for f in dataclasses.fields(cam)
        if isinstance(getattr(cam, f.name), np.ndarray) and getattr(cam, f.name).shape[:1] == (n,)
    }
    return dataclasses.replace(cam, **changes)
