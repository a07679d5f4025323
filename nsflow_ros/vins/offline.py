"""Offline tracking: the VINS frame policy over a recorded source (bag or ASL folder), no ROS middleware.

Writes ``features.csv`` (one row per published feature, :data:`CSV_HEADER`; u, v distorted pixels, x, y
undistorted normalised coordinates), ``tracks.png`` (a contact sheet of debug images) and ``summary.json``
(:class:`OfflineSummary`), each renamed into place when complete. On a project sample sequence the error
of every tracked feature is measured against the exact optical flow.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from nsflow_ros import threads as process_threads
from nsflow_ros.data.records import ImageRecord
from nsflow_ros.data.replay import ReplayOptions, replay_records
from nsflow_ros.data.scoring import TrackStats
from nsflow_ros.errors import NSFlowError
from nsflow_ros.files import atomic_write
from nsflow_ros.vins.draw import draw_tracks
from nsflow_ros.vins.health import HealthMonitor, usable_share
from nsflow_ros.vins.session import FrontEndSession, Skip
from nsflow_ros.vins.settings import setting
from nsflow_ros.vins.sheet import contact_sheet, write_png

__all__ = ["CSV_HEADER", "OfflineSummary", "run_offline"]

CSV_HEADER = "stamp_ns,camera_id,feature_id,u,v,x,y,velocity_x,velocity_y,track_count"


@dataclass
class OfflineSummary:
    """What :func:`run_offline` did.

    Attributes:
        tracking_state, tracking_cause: the run's tracking state judged as the node judges a status
            period (:class:`~nsflow_ros.vins.health.HealthMonitor`), and its likely cause when not OK.
    """

    source: str
    method: str
    perturb: str
    out_dir: str
    figures: dict[str, Any]
    tracking_state: str = ""
    tracking_cause: str = ""

    def text(self) -> str:
        f = self.figures
        err = (
            "n/a"
            if f["error_median_px"] is None
            else f"{f['error_median_px']:.3f} px median, {100 * f['error_within_1px']:.1f}% within 1 px"
        )
        state = f"; tracking {self.tracking_state}: {self.tracking_cause}" if self.tracking_cause else ""
        return (
            f"{self.source} [{self.method}, perturbation {self.perturb}]: {f['frames']} frames, "
            f"{f['features_per_frame']:.1f} features/frame, mean track length {f['mean_track_length']:.1f}, "
            f"tracking error {err}{state}; outputs in {self.out_dir}"
        )


def _sample_of(path: Path) -> Any:
    """The SampleSequence a path belongs to, or None."""
    from nsflow_ros.data.errors import DataError
    from nsflow_ros.data.sample import SampleSequence, is_sample

    for cand in (path, *path.parents[:3]):
        if is_sample(cand):
            try:
                return SampleSequence.load(cand)
            except DataError:
                return None
    return None


def run_offline(
    opts: ReplayOptions,
    out_dir: str | Path,
    *,
    config: str | Path | None = None,
    method: str = "nsflow",
    overrides: dict[str, Any] | None = None,
    masks: tuple[np.ndarray | None, ...] | None = None,
    sheet_frames: int = 6,
    progress: bool = True,
    opencv_threads: int | None = None,
) -> OfflineSummary:
    """Track a recorded sequence with the core tracker and write features, a contact sheet and a summary.

    Args:
        opts: what to read; the tracker uses camera 0 (mono).
        out_dir: output folder (created).
        config: VINS config file (default: the shipped EuRoC mono config).
        method: a key of :data:`nsflow_ros.core.methods.METHODS`.
        overrides: further tracker settings.
        masks: static masks per camera (camera 0's is used); None = the config's mask0 key, if any.
        sheet_frames: debug images in the contact sheet, spread over the sequence.
        opencv_threads: OpenCV's threads during the run; None = the node's ``opencv_threads`` default.

    Raises:
        NSFlowError: a bad source, config or model; the outputs of the frames before a damaged part of a
            bag are still written.
    """
    from nsflow_ros.progress import progress_bar
    from nsflow_ros.resources import DEFAULT_CONFIG, share_file
    from nsflow_ros.vins.config import load_vins_config

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    cfg = load_vins_config(config or share_file(DEFAULT_CONFIG))
    # the same frame policy as the node (duplicate stamps, VINS-Mono's first frame and freq), camera 0 only
    fixed = {"stereo": False, **(overrides or {})}
    session = FrontEndSession(cfg, {"method": method}, masks=masks, tracker_overrides=fixed)
    stats = TrackStats(_sample_of(Path(opts.path)))
    rows: list[str] = []
    sheet: list[tuple[int, np.ndarray]] = []
    error: NSFlowError | None = None
    health = HealthMonitor()  # the node's default thresholds
    bar = progress_bar(desc=f"offline {method}", unit="frame", enabled=progress)
    cv = int(setting("opencv_threads").default) if opencv_threads is None else opencv_threads
    with process_threads.opencv_threads(cv):
        try:
            for rec in replay_records(replace(opts, topics=[cfg.image0_topic])):
                if not isinstance(rec, ImageRecord):
                    continue
                image = rec.for_tracker()
                outcome = session.process(rec.stamp_ns * 1e-9, image)
                if outcome.skipped is Skip.TRACKER:
                    raise NSFlowError(f"frame at {rec.stamp_ns} ns: {outcome.note}")
                feats = outcome.features
                bar.update(1)
                if feats is None:
                    continue
                cf = feats.cameras[0]
                health.add_frame(cf.ids, image=image, usable=usable_share(session.tracker.mask))
                stats.add_frame(rec.stamp_ns, {int(i): p for i, p in zip(cf.ids, cf.pixels, strict=True)})
                for j in range(len(cf.ids)):
                    rows.append(
                        f"{rec.stamp_ns},0,{cf.ids[j]},{cf.pixels[j, 0]:.4f},{cf.pixels[j, 1]:.4f},"
                        f"{cf.undistorted[j, 0]:.6f},{cf.undistorted[j, 1]:.6f},{cf.velocities[j, 0]:.6f},"
                        f"{cf.velocities[j, 1]:.6f},{cf.track_counts[j]}"
                    )
                if stats.frames % 10 == 5 and len(sheet) < 4 * sheet_frames:
                    sheet.append((stats.frames, draw_tracks(feats, rec.gray())))
        except NSFlowError as err:
            error = err  # keep what was processed; report after writing
        finally:
            bar.close()
    atomic_write(out / "features.csv", lambda p: p.write_text(CSV_HEADER + "\n" + "\n".join(rows) + "\n"))
    if sheet:
        pick = [sheet[round(i)] for i in np.linspace(0, len(sheet) - 1, min(sheet_frames, len(sheet)))]
        img = contact_sheet([im for _, im in pick], labels=[f"{method} frame {n}" for n, _ in pick],
                            legend=True)
        atomic_write(out / "tracks.png", lambda p: write_png(p, img))
    report = health.run_report(max_cnt=session.tracker.settings.max_cnt, gated=session.counters.gated)
    summary = OfflineSummary(str(opts.path), method, opts.perturb, str(out), stats.figures(),
                             report.state.value, report.cause)
    atomic_write(out / "summary.json", lambda p: p.write_text(json.dumps(asdict(summary), indent=2)))
    if error is not None:
        raise NSFlowError(
            f"{error} (the {stats.frames} frames before it were processed and written to {out})"
        )
    return summary
