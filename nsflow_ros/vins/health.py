"""The tracking state: what reaches the estimator, judged as OK, DEGRADED or LOST.

The node's counters say what happened to every image and frame; they cannot say whether the estimator is
fed. A front-end can publish every frame and still give the estimator nothing to work with: no feature
(a mask that blocks the image, a uniform image), or features whose ids never carry over to the next frame
(every track gated by ``max_sigma``), so nothing is triangulated. :class:`HealthMonitor` watches the
published frames (camera 0's ids) and judges each status period from two figures, with the thresholds of
:class:`Thresholds` (the settings ``degraded_features``, ``lost_features``, ``degraded_carried``,
``lost_carried``):

* features published per frame against ``max_cnt`` (the mean of the period);
* the share of the previous published frame's ids that a frame carries on (the median of the period, so a
  track reset costs nothing).

A state gets worse at once and better only when its thresholds are cleared by :data:`RECOVER_MARGIN`, so
a camera on a threshold does not flap. A state other than OK names the likely cause from what the node
knows (:meth:`HealthMonitor.assess`): uniform images, masks that leave little of the image, features gated
by ``max_sigma``, no corners, tracks that do not carry over. The node, the offline run and the feature bag
use it; it imports no ROS package.
"""

from __future__ import annotations

import threading
from collections.abc import Mapping
from dataclasses import dataclass, field, fields
from enum import StrEnum
from typing import Any

import numpy as np

from nsflow_ros.vins.errors import ConfigError

__all__ = [
    "RECOVER_MARGIN",
    "UNIFORM_STD",
    "HealthMonitor",
    "HealthReport",
    "State",
    "Thresholds",
    "check_static_masks",
    "is_uniform",
    "usable_share",
]

RECOVER_MARGIN = 0.2
"""A state improves only when the period's figures clear its thresholds by this share (hysteresis)."""

UNIFORM_STD = 2.0
"""An image whose grey levels vary by less than this (standard deviation, 8-bit) is uniform: all black,
all white or one grey, nothing but sensor noise to track."""

_SUBSAMPLE = 8  # pixels between the samples of a uniformity test: enough for a standard deviation


class State(StrEnum):
    """The tracking state of a status period."""

    OK = "OK"
    """The estimator gets enough features that carry over."""
    DEGRADED = "DEGRADED"
    """Fewer features than ``degraded_features`` x max_cnt, or fewer ids carried than
    ``degraded_carried``: the estimator works on little."""
    LOST = "LOST"
    """Fewer than ``lost_features`` x max_cnt, or fewer carried than ``lost_carried``, or no frame
    published at all: the estimator cannot track."""
    IDLE = "IDLE"
    """No images in the period: nothing to judge (the status line says so)."""

    @property
    def rank(self) -> int:
        """0 for OK (and IDLE), 1 DEGRADED, 2 LOST: higher is worse."""
        return {State.DEGRADED: 1, State.LOST: 2}.get(self, 0)


@dataclass(frozen=True)
class Thresholds:
    """When a period is DEGRADED or LOST (the settings of the same names; see their descriptions).

    Attributes:
        degraded_features, lost_features: features published per frame as a share of ``max_cnt``.
        degraded_carried, lost_carried: the median share of the previous frame's ids carried on.
        mask_min_usable: a mask that leaves less of the image usable is named as a cause (and warned
            about at start-up).

    Raises:
        ConfigError: a share outside [0, 1], or a LOST threshold above its DEGRADED one.
    """

    degraded_features: float = 0.3
    lost_features: float = 0.15
    degraded_carried: float = 0.5
    lost_carried: float = 0.1
    mask_min_usable: float = 0.25

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            if not 0.0 <= value <= 1.0:
                raise ConfigError(f"{f.name} must be a share in [0, 1], got {value}")
        for what in ("features", "carried"):
            lost, degraded = getattr(self, f"lost_{what}"), getattr(self, f"degraded_{what}")
            if lost > degraded:
                raise ConfigError(f"lost_{what} ({lost:g}) must be at most degraded_{what} ({degraded:g})")

    @classmethod
    def from_values(cls, values: Mapping[str, Any]) -> Thresholds:
        """The thresholds from setting values by name (the others at their defaults)."""
        names = {f.name for f in fields(cls)}
        return cls(**{k: float(v) for k, v in values.items() if k in names})


@dataclass(frozen=True)
class HealthReport:
    """One judgement of :meth:`HealthMonitor.assess`.

    Attributes:
        state: the state now.
        previous: the state of the period before.
        cause: the likely cause in words ("" when OK or IDLE).
        frames: published frames judged.
        features: features published per frame (mean).
        carried: the median share of the previous frame's ids carried on; None when no frame had a
            previous frame with features.
        gated: features dropped by ``max_sigma`` in the period.
    """

    state: State
    previous: State
    cause: str = ""
    frames: int = 0
    features: float = 0.0
    carried: float | None = None
    gated: int = 0

    @property
    def recovered(self) -> bool:
        """The state got better than the period before's DEGRADED or LOST."""
        return self.previous.rank > self.state.rank and self.state is not State.IDLE

    @property
    def text(self) -> str:
        """The state in a few words, for the status line: "OK", "LOST: images uniform (...); 0 ...",
        "OK: recovered from LOST"."""
        if self.state is State.IDLE:
            return "IDLE"
        figures = ""
        if self.frames:
            figures = f"{self.features:.0f} features/frame"
            if self.carried is not None:
                figures += f", {100 * self.carried:.0f} % of ids carried"
        if self.state is State.OK:
            return f"OK: recovered from {self.previous}" if self.recovered else "OK"
        words = "; ".join(w for w in (self.cause, figures) if w)
        again = f" (better than {self.previous})" if self.recovered else ""
        return f"{self.state}{again}: {words}" if words else str(self.state)


@dataclass
class _Window:
    """The figures of published frames over a span (a status period, or the whole run)."""

    frames: int = 0
    features: int = 0
    uniform: int = 0
    carried: list[float] = field(default_factory=list)
    usable_sum: float = 0.0
    usable_frames: int = 0
    carried_bins: np.ndarray = field(default_factory=lambda: np.zeros(101, np.int64))

    def add(self, n: int, carried: float | None, uniform: bool, usable: float | None, keep: bool) -> None:
        self.frames += 1
        self.features += n
        self.uniform += uniform
        if carried is not None:
            if keep:
                self.carried.append(carried)
            self.carried_bins[round(100 * carried)] += 1  # the run's median in bounded memory
        if usable is not None:
            self.usable_sum += usable
            self.usable_frames += 1

    def median_carried(self) -> float | None:
        if self.carried:
            return float(np.median(self.carried))
        total = int(self.carried_bins.sum())
        if not total:
            return None
        return float(np.searchsorted(np.cumsum(self.carried_bins), (total + 1) / 2)) / 100


class HealthMonitor:
    """The tracking state of the published frames (see the module docstring); thread-safe.

    Args:
        thresholds: when a period is DEGRADED or LOST; may be replaced at run time (:attr:`thresholds`).
    """

    def __init__(self, thresholds: Thresholds | None = None) -> None:
        self.thresholds = thresholds or Thresholds()
        self.state = State.IDLE
        self.cause = ""
        self.periods: dict[str, int] = {s.value: 0 for s in State}
        """Status periods judged, by state."""
        self._lock = threading.Lock()
        self._period = _Window()
        self._run = _Window()
        self._prev_ids: np.ndarray | None = None

    def add_frame(self, ids: np.ndarray, *, image: np.ndarray | None = None,
                  usable: float | None = None) -> None:
        """Record one published frame.

        Args:
            ids: camera 0's feature ids as published.
            image: camera 0's image, for the uniformity test (None = not tested).
            usable: the share of camera 0's image its masks leave usable (None = no mask).
        """
        uniform = image is not None and is_uniform(image)
        ids = np.asarray(ids)
        with self._lock:
            prev, self._prev_ids = self._prev_ids, ids
            carried = None
            if prev is not None and prev.size:
                carried = float(np.count_nonzero(np.isin(prev, ids))) / prev.size
            self._period.add(ids.size, carried, uniform, usable, keep=True)
            self._run.add(ids.size, carried, uniform, usable, keep=False)

    def assess(
        self, *, max_cnt: int, gated: int = 0, images: int = 1, tracked: int | None = None
    ) -> HealthReport:
        """Judge the period since the last call and start the next one.

        Args:
            max_cnt: the tracker's max_cnt now.
            gated: features the ``max_sigma`` gate dropped in the period.
            images: images received in the period (0 = IDLE).
            tracked: frames tracked in the period (None = as many as published); 0 is LOST whatever was
                published meanwhile, and tracked frames that were all held back by ``publish_rate`` keep
                the state as it was.

        Returns:
            the judgement; :attr:`state` and :attr:`cause` follow it.
        """
        with self._lock:
            window, self._period = self._period, _Window()
        previous = self.state
        if not images:
            report = HealthReport(State.IDLE, previous)
        elif tracked == 0:  # a frame of the period before may have been published since: not this one's
            report = HealthReport(State.LOST, previous, "no frame reached the estimator")
        elif not window.frames and tracked:  # tracked, all held back by publish_rate: nothing new
            report = HealthReport(previous, previous, self.cause)
        else:
            report = self._judge(window, max_cnt, gated, previous, hysteresis=True)
        self.state, self.cause = report.state, report.cause
        self.periods[report.state.value] += 1
        return report

    def run_report(self, *, max_cnt: int, gated: int = 0) -> HealthReport:
        """The whole run judged as one period (no hysteresis): the offline run's and the feature bag's
        verdict, and the node's when no period was judged."""
        with self._lock:
            window = self._run
        return self._judge(window, max_cnt, gated, State.OK, hysteresis=False)

    def _judge(self, w: _Window, max_cnt: int, gated: int, previous: State, hysteresis: bool) -> HealthReport:
        if not w.frames:
            return HealthReport(State.LOST, previous, "no frame reached the estimator", gated=gated)
        features = w.features / w.frames
        carried = w.median_carried()
        state = self._level(features / max(max_cnt, 1), carried, 1.0)
        if hysteresis and previous.rank > state.rank:  # better: only by a margin, never flapping
            strict = self._level(features / max(max_cnt, 1), carried, 1.0 + RECOVER_MARGIN)
            state = strict if strict.rank < previous.rank else previous
        cause = "" if state is State.OK else self._cause(w, features / max(max_cnt, 1), carried, gated)
        return HealthReport(state, previous, cause, w.frames, features, carried, gated)

    def _level(self, share: float, carried: float | None, scale: float) -> State:
        t = self.thresholds
        carried = 1.0 if carried is None else carried  # no frame to carry from: features alone decide
        if share < t.lost_features * scale or carried < t.lost_carried * scale:
            return State.LOST
        if share < t.degraded_features * scale or carried < t.degraded_carried * scale:
            return State.DEGRADED
        return State.OK

    def _cause(self, w: _Window, share: float, carried: float | None, gated: int) -> str:
        """The likely cause of a DEGRADED or LOST period, most specific first."""
        if 2 * w.uniform >= w.frames:
            return (f"images uniform ({w.uniform} of {w.frames} frames all one grey level: exposure, lens "
                    "cap or camera driver)")
        usable = w.usable_sum / w.usable_frames if w.usable_frames else None
        if usable is not None and usable < self.thresholds.mask_min_usable:
            return f"masks leave {100 * usable:.0f} % of the image usable"
        per_frame = gated / w.frames
        lost_ids = w.features / w.frames * (1.0 - (carried or 0.0))  # ids per frame that did not carry on
        if gated and per_frame >= 0.5 * lost_ids:  # the gate, not the flow, ends most tracks
            if carried is not None and carried == 0.0:
                return f"every tracked feature gated by max_sigma ({per_frame:.0f} per frame)"
            return f"max_sigma gated {per_frame:.0f} tracked features per frame"
        if share < self.thresholds.degraded_features:
            what = "no corners" if w.features == 0 else "few corners"
            return f"{what} detected (a view without texture, or max_cnt / min_dist)"
        return "tracks do not carry over from frame to frame (fast motion, blur or a lighting change)"


def is_uniform(image: np.ndarray) -> bool:
    """Whether an image is uniform (:data:`UNIFORM_STD`), from every 8th pixel of each row and column."""
    view = image[::_SUBSAMPLE, ::_SUBSAMPLE]
    return bool(view.size) and float(view.std()) < UNIFORM_STD


def usable_share(*masks: np.ndarray | None, step: int = 4) -> float | None:
    """The share of the image usable in every given mask (255 = usable), from every ``step``-th pixel.

    The masks may be at different resolutions (a full-resolution per-frame mask and a tracker's decimated
    static one): each is sampled at the same image positions. None when no mask is given.
    """
    given = [m for m in masks if m is not None]
    if not given:
        return None
    rows = min(m.shape[0] for m in given)
    usable: np.ndarray | None = None
    for m in given:
        k = step * max(m.shape[0] // rows, 1)
        view = m[::k, ::k] > 0
        usable = view if usable is None or usable.shape != view.shape else usable & view
    assert usable is not None
    return float(np.count_nonzero(usable)) / max(usable.size, 1)


def check_static_masks(masks: Mapping[str, np.ndarray | None], min_usable: float) -> list[str]:
    """Start-up check of static masks: the warnings for masks that leave little of their image usable.

    Args:
        masks: name for the messages (e.g. "mask0 body.png") -> uint8 mask, 255 = usable (None = none).
        min_usable: the share below which a mask is warned about (``mask_min_usable``).

    Returns:
        one sentence per mask that leaves less than ``min_usable`` of its image usable.

    Raises:
        ConfigError: a mask that leaves no usable pixel at all (nothing could ever be tracked).
    """
    warnings = []
    for name, mask in masks.items():
        if mask is None:
            continue
        share = float(np.count_nonzero(mask)) / max(mask.size, 1)
        if share == 0.0:
            raise ConfigError(
                f"{name} leaves no usable pixel: nothing can be tracked (a pixel is usable above 127 of "
                "255 as mask_convention reads it; a 16-bit mask image is read as its high byte)"
            )
        if share < min_usable:
            warnings.append(
                f"{name} leaves {100 * share:.1f} % of the image usable, less than mask_min_usable "
                f"{min_usable:g}: expect fewer features than max_cnt, crowded in that part"
            )
    return warnings
