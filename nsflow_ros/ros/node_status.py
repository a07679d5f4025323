"""The ``tracker`` node's status: the period's counts, its level and line, ``/diagnostics`` and the summary.

Pure formatting and bookkeeping around :class:`~nsflow_ros.ros.counters.NodeCounters` and the tracking
state (:mod:`nsflow_ros.vins.health`): :func:`status_level` picks a period's level and message from its
counts, :func:`period_values` and :func:`diagnostic_status` make the ``/diagnostics`` entry,
:func:`period_line` the log line and :func:`summary_line` the line at the stop. :class:`StampGaps` infers
frames lost before the node from each camera's stamps, :class:`StatusWindow` keeps a period's latencies.
"""

from __future__ import annotations

import json
import threading
import time
from collections import deque
from pathlib import Path
from typing import Any

import numpy as np
from diagnostic_msgs.msg import DiagnosticStatus, KeyValue
from rcl_interfaces.msg import ParameterDescriptor

from nsflow_ros.files import atomic_write
from nsflow_ros.ros.counters import CAUSES, DROPPED, Kind, NodeCounters
from nsflow_ros.ros.node_masks import MASK_COUNTS
from nsflow_ros.ros.tracker_params import NODE_NAME, PARAMETERS, coerce
from nsflow_ros.vins.health import HealthMonitor, HealthReport
from nsflow_ros.vins.settings import Mode

__all__ = [
    "DIAGNOSTIC_NAME",
    "TOTALS",
    "ArrivalStamps",
    "StampGaps",
    "StatusWindow",
    "by_cause",
    "covariance_line",
    "cpu_per_frame",
    "declare_parameters",
    "diagnostic_status",
    "health_counters",
    "label",
    "percentile",
    "period_line",
    "period_values",
    "run_counters",
    "startup_line",
    "status_level",
    "summary_line",
    "write_summary",
]

DIAGNOSTIC_NAME = f"{NODE_NAME}: front-end"
"""The node's status name on /diagnostics."""


def percentile(values: list[float], q: float) -> float | None:
    """The ``q``-th percentile of ``values``; None for none."""
    return float(np.percentile(values, q)) if values else None


def cpu_per_frame(cpu_s: float, frames: int) -> float | None:
    """The process's CPU time (all threads) per processed frame, in ms."""
    return cpu_s * 1e3 / frames if frames else None


class StampGaps:
    """Frames lost before the node: an interval of k median periods (k >= 2) means k - 1 were lost."""

    def __init__(self, history: int = 50) -> None:
        self._intervals: deque[float] = deque(maxlen=history)
        self._last: float | None = None

    @property
    def seen(self) -> bool:
        """Whether a stamp has been recorded."""
        return self._last is not None

    @property
    def period(self) -> float | None:
        """The median interval of the recent stamps (s); None before 5 intervals were seen."""
        return float(np.median(self._intervals)) if len(self._intervals) >= 5 else None

    def add(self, stamp: float) -> int:
        """Record a frame's stamp; return how many frames are missing just before it."""
        last, self._last = self._last, stamp
        if last is None or stamp <= last:
            return 0
        dt = stamp - last
        period = self.period
        missing = max(0, round(dt / period) - 1) if period else 0
        if not missing:
            self._intervals.append(dt)
        return missing


class StatusWindow:
    """Counters and latencies since the last status report."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._latencies: list[float] = []
        self._features: list[int] = []
        self._last: dict[str, int] = {}
        self._t = time.monotonic()
        self._idle = 0

    def add(self, latency_ms: float, features: int) -> None:
        """Record one published frame's latency and feature count."""
        with self._lock:
            self._latencies.append(latency_ms)
            self._features.append(features)

    def take(self, counters: NodeCounters) -> dict[str, Any]:
        """The period's figures (every count of ``counters``, features, latency); starts the next period."""
        with self._lock:
            lat, feats = self._latencies, self._features
            self._latencies, self._features = [], []
        now = time.monotonic()
        totals = counters.totals()
        out: dict[str, Any] = {
            "seconds": now - self._t,
            **{k: v - self._last.get(k, 0) for k, v in totals.items()},
            "features": float(np.mean(feats)) if feats else 0.0,
            "latency_p50": percentile(lat, 50),
            "latency_p90": percentile(lat, 90),
        }
        self._idle = self._idle + 1 if out["images_received"] == 0 else 0
        out["quiet"] = self._idle > 1
        self._t = now
        self._last = totals
        return out


TOTALS = ("images_received", "frames_received", "frames_processed", "frames_unchecked", "frames_dropped",
           "frames_published", "frames_missing_upstream")
"""The plain counts on /diagnostics (the causes follow them)."""


def by_cause(window: dict[str, Any], kind: Kind) -> str:
    """ "300 undecodable images, 2 repeated stamp frames" for the causes of ``kind`` counted in ``window``."""
    return ", ".join(
        f"{window[c.name]} {c.unit}s {c.label}" if window[c.name] != 1 else f"1 {c.unit} {c.label}"
        for c in CAUSES if c.kind is kind and window[c.name]
    )


def status_level(window: dict[str, Any], topics: list[str]) -> tuple[int, str]:
    """A status period's /diagnostics level and message.

    OK while everything is tracked; WARN when something was refused, superseded or lost upstream, or when
    nothing was tracked without a refusal; ERROR when images came, nothing was tracked and something was
    refused. Every count named by cause.
    """
    if window["images_received"] == 0:
        return DiagnosticStatus.OK, f"no images on {', '.join(topics)}"
    parts = []
    if refused := by_cause(window, Kind.REFUSED):
        parts.append(f"refused {refused}")
    if window["frames_superseded"]:
        parts.append(f"falling behind: {window['frames_superseded']} of {window['frames_received']} frames "
                     "superseded by newer ones")
    if waited := by_cause(window, Kind.WAIT):  # the mask's wait, not the CPU
        parts.append(f"{waited} (mask_wait_ms)")
    if window["frames_missing_upstream"]:
        parts.append(f"{window['frames_missing_upstream']} frames missing before the node (stamp gaps)")
    if events := by_cause(window, Kind.EVENT):
        parts.append(events)
    level = DiagnosticStatus.WARN if parts else DiagnosticStatus.OK
    if policy := by_cause(window, Kind.POLICY):
        parts.append(f"skipped by the VINS-Mono policy: {policy}")
    if window["frames_processed"] == 0:
        level = DiagnosticStatus.ERROR if refused else DiagnosticStatus.WARN
        waiting = f"{window['images_received']} images received, none tracked yet"
        return level, "nothing tracked: " + ("; ".join(parts) if parts else waiting)
    return level, "tracking" + (": " + "; ".join(parts) if parts else "")


def label(name: str) -> str:
    """A counter's name as /diagnostics shows it: frames_received -> "frames received"."""
    return name.replace("_", " ")


def period_values(c: dict[str, Any], window: dict[str, Any], health: HealthReport, provider: str,
                  masks: bool) -> dict[str, Any]:
    """The /diagnostics key-values of a status period: totals, the period's counts, state and figures.

    Args:
        c: the run's counters (``TrackerNode.counters``).
        window: the period's counts (:meth:`StatusWindow.take`).
        health: the period's tracking state; provider: the encoder's execution provider.
        masks: with mask topics (their counts are added).
    """
    return {
        **{label(k): c[k] for k in TOTALS},
        **{f"{label(k)} (period)": window[k] for k in TOTALS},
        **{f"{x.unit}s {x.label}": c[x.name] for x in CAUSES},
        **{f"{x.unit}s {x.label} (period)": window[x.name] for x in CAUSES},
        "frames missing upstream (period)": window["frames_missing_upstream"],
        "features per frame (period)": window["features"],
        "latency p50 ms (period)": window["latency_p50"],
        "latency p90 ms (period)": window["latency_p90"],
        "tracking state": health.state.value,
        "tracking state cause": health.cause,
        "ids carried (period)": health.carried,
        "features gated (period)": health.gated,
        "method": c["method"],
        "encoder provider": provider,
        "CPU ms per frame": c["cpu_ms_per_frame"],
        **({label(k): c[k] for k in MASK_COUNTS} if masks else {}),
    }


def diagnostic_status(level: int, message: str, hardware_id: str, values: dict[str, Any]) -> DiagnosticStatus:
    """The node's /diagnostics entry: numbers as text, floats with one decimal, None as ""."""
    return DiagnosticStatus(
        level=level,
        name=DIAGNOSTIC_NAME,
        message=message,
        hardware_id=hardware_id,
        values=[KeyValue(key=k, value="" if v is None else f"{v:.1f}" if isinstance(v, float)
                         else str(v)) for k, v in values.items()],
    )


def period_line(message: str, window: dict[str, Any]) -> str:
    """The status line of a period in which images came: the message, then the period's counts."""
    line = (
        f"{message} (last {window['seconds']:.1f} s: {window['images_received']} images, "
        f"{window['frames_received']} frames received, {window['frames_processed']} processed, "
        f"{window['frames_dropped']} dropped"
    )
    if window["latency_p50"] is not None:
        line += (
            f"; {window['features']:.0f} features/frame, latency p50 {window['latency_p50']:.1f} ms, "
            f"p90 {window['latency_p90']:.1f} ms"
        )
    return line + ")"


def summary_line(c: dict[str, Any], masks: bool) -> str:
    """One line at the stop: images and frames received / processed / published, every cause, latency,
    the mask counts (``masks``: with mask topics) and the run's tracking state."""
    if not c["images_received"]:
        return "no images received"
    lat = (
        f"; latency p50 {c['latency_ms_p50']:.1f} ms, p90 {c['latency_ms_p90']:.1f} ms"
        if c["latency_ms_p50"] is not None
        else ""
    )
    causes = ", ".join(f"{x.unit}s {x.label} {c[x.name]}" for x in CAUSES if c[x.name]) or "none"
    return (
        f"images received {c['images_received']}, frames received {c['frames_received']}, processed "
        f"{c['frames_processed']} (late, without the reverse checks: {c['frames_unchecked']}), published "
        f"{c['frames_published']}, dropped {c['frames_dropped']}; by cause: {causes}; frames missing "
        f"before the node (stamp gaps) {c['frames_missing_upstream']}{lat}"
        f"{_mask_summary(c) if masks else ''}{_health_summary(c)}"
    )


def _health_summary(c: dict[str, Any]) -> str:
    """The run's tracking state for the summary line."""
    periods = ", ".join(f"{k} {n}" for k, n in c["tracking_periods"].items() if n)
    cause = f": {c['tracking_cause']}" if c["tracking_cause"] else ""
    carried = "" if c["ids_carried"] is None else f", {100 * c['ids_carried']:.0f} % of ids carried"
    return (f"; tracking state {c['tracking_state']}{cause} ({c['features_per_frame']:.0f} features/frame"
            f"{carried}{'; status periods ' + periods if periods else ''})")


def _mask_summary(c: dict[str, Any]) -> str:
    """The per-frame mask counts for the summary line."""
    return (f"; masks received {c['masks_received']}, missing (frames tracked without theirs) "
            f"{c['masks_missing']}, used {c['masks_used']}, late {c['masks_late']}, unused "
            f"{c['masks_unused']}, refused {c['masks_refused']}, left at the stop "
            f"{c['masks_left_at_stop']}")


def declare_parameters(node: Any) -> dict[str, Any]:
    """Declare every parameter of the settings table on ``node``; their values, checked (:func:`coerce`).

    Raises:
        ParameterError: a value of the wrong type or out of range.
    """
    values: dict[str, Any] = {}
    for ps in PARAMETERS:
        # dynamic typing so that a slip (-p F_threshold:=1) reaches spec.coerce and gets a clear answer
        desc = ParameterDescriptor(
            description=ps.full_description,
            additional_constraints=f"{ps.kind} (checked by the node)",
            read_only=ps.mode is Mode.READ_ONLY,
            dynamic_typing=True,
        )
        values[ps.name] = coerce(ps, node.declare_parameter(ps.name, ps.default, desc).value)
    return values


def startup_line(cfg: Any, session: Any, provider: str, transport: str, images: list[str], imu: str | None,
                 features: str) -> str:
    """The start-up line: the config, the method and its provider, the settings, the topics as resolved."""
    s = session.tracker.settings
    return (
        f"{cfg.dialect} config {cfg.path} ({'stereo' if s.stereo else 'mono'}, {cfg.image_width}x"
        f"{cfg.image_height}); method {s.method} (encoder on {provider}), "
        f"layout {session.layout}, max_cnt {s.max_cnt}, min_dist "
        f"{s.min_dist:g}, flow_back {s.flow_back}, F-RANSAC {s.reject_with_f}, IMU prediction "
        f"{imu is not None}"
        + (f", downsample {s.downsample}" if s.downsample != 1 else "")
        + (f", publish_rate {session.publish_rate:g} Hz" if session.publish_rate else "")
        + "; "
        f"{transport} images on {', '.join(images)}"
        + (f", IMU on {imu}" if imu is not None else "")
        + f"; features on {features}"
    )


def health_counters(monitor: HealthMonitor, max_cnt: int, gated: int) -> dict[str, Any]:
    """The run's tracking state (the whole run judged as one period) and the status periods by state."""
    run = monitor.run_report(max_cnt=max_cnt, gated=gated)
    return {
        "tracking_state": run.state.value,
        "tracking_cause": run.cause,
        "tracking_state_last": monitor.state.value,
        "tracking_periods": dict(monitor.periods),
        "features_per_frame": run.features,
        "ids_carried": run.carried,
    }


class ArrivalStamps:
    """Every camera's image stamps as they arrive: frames lost before the node and the frame period.

    Args:
        cameras: 1 (mono) or 2 (stereo).
    """

    def __init__(self, cameras: int) -> None:
        self.cameras = cameras
        self._gaps = [StampGaps() for _ in range(cameras)]
        self._missing = [0] * cameras

    def add(self, cam: int, stamp: float) -> int:
        """Record an image's stamp; returns the frames missing upstream so far: a frame is missing when no
        camera delivered it, the smallest count of the cameras heard from."""
        self._missing[cam] += self._gaps[cam].add(stamp)
        return min(m for m, g in zip(self._missing, self._gaps, strict=True) if g.seen)

    def period(self) -> float | None:
        """The frame period measured from the stamps of the first camera that has enough of them (s)."""
        return next((g.period for g in self._gaps if g.period is not None), None)

    def tolerance_problem(self, tolerance: float) -> str | None:
        """Why ``tolerance`` cannot pair stereo images safely; None when it can or no period is measured.

        At half the frame period or more, an image can pair with the other camera's image of the next frame.
        """
        period = self.period()
        if self.cameras == 1 or period is None or tolerance < period / 2:
            return None
        return (
            f"stereo_sync_tolerance: got {tolerance:g} s, expected less than half the frame period measured "
            f"from the image stamps ({period * 1e3:.1f} ms, {1 / period:.1f} Hz), i.e. < {period / 2:.4g} s: "
            "images of different frames would pair"
        )


def covariance_line(tracker: Any) -> str:
    """What the covariance channels are scaled by, and whether the scale was fitted (start-up)."""
    s = tracker.settings
    scale = tracker.method.covariance_scale
    return (f"covariance scale {scale.scale:.4g}, floor {scale.floor:.3g} px^2{scale.tail_text} "
            f"({scale.source}), max_sigma {s.max_sigma:g} px (0 = off)")


def run_counters(node: str, session: Any, stats: NodeCounters, cpu_s: float, latencies: list[float],
                 track_images: int, masks: dict[str, int], health: HealthMonitor) -> dict[str, Any]:
    """The run's counters (the summary file): images and frames received / processed / dropped by cause,
    CPU and latency, the masks' counts and the tracking state.

    Args:
        node: the node's fully qualified name; session: its FrontEndSession; stats: its counters.
        cpu_s: the process's CPU time since the start; latencies: the recent latencies (ms).
        track_images: debug images published; masks: :meth:`MaskTopics.counters`; health: the monitor.
    """
    s = stats
    settings = session.tracker.settings
    return {
        "node": node,
        "method": settings.method,
        "stereo": bool(settings.stereo),
        **s.totals(),
        "frames_skipped_by_policy": s.of(Kind.POLICY),
        "dropped": {c.key: s.lost[c.key] for c in CAUSES if c.unit == "frame" and c.kind in DROPPED},
        "cpu_ms_per_frame": cpu_per_frame(cpu_s, s.frames_processed),
        "track_images_published": track_images,
        "restarts": session.counters.restarts,
        "features_gated": session.counters.gated,
        "latency_ms_p50": percentile(latencies, 50),
        "latency_ms_p90": percentile(latencies, 90),
        **masks,
        **health_counters(health, settings.max_cnt, session.counters.gated),
    }


def write_summary(path: Path, counters: dict[str, Any]) -> Path:
    """Write the run's counters as JSON, renamed into place when complete; returns ``path``."""
    text = json.dumps(counters, indent=2)
    atomic_write(path, lambda tmp: tmp.write_text(text))
    return path
