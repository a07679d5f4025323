"""Offline tracking: the tracker core straight over a bag or ASL folder, no ROS middleware.

Output files (in the output folder):

* ``features.csv`` — one row per published feature, VINS-Fusion layout with the track count added:
  ``stamp_ns,camera_id,feature_id,u,v,x,y,velocity_x,velocity_y,track_count`` (u, v distorted pixels;
  x, y undistorted normalised coordinates);
* ``tracks.png`` — a contact sheet of debug images (circles blue -> red with track length, lines to the
  previous positions);
* ``summary.json`` — the figures of :class:`OfflineSummary`.

Each file is written under a temporary name and renamed when complete, so an interrupted run never
leaves a file that looks finished. When the data is a project sample sequence, the tracking error of
every tracked feature is measured against the exact ground-truth optical flow.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from nsflow_ros.data.records import ImageRecord
from nsflow_ros.errors import NSFlowError
from nsflow_ros.files import atomic_write
from nsflow_ros.replay import ReplayOptions, replay_records
from nsflow_ros.vins.draw import draw_tracks
from nsflow_ros.vins.session import FrontEndSession

__all__ = ["OfflineSummary", "TrackStats", "contact_sheet", "run_offline", "track_legend"]

CSV_HEADER = "stamp_ns,camera_id,feature_id,u,v,x,y,velocity_x,velocity_y,track_count"


@dataclass
class TrackStats:
    """Front-end figures accumulated frame by frame (camera 0).

    Args:
        sample: the sample sequence the frames come from, for errors against ground-truth flow (None:
            no errors are measured).

    Attributes:
        frames: frames processed.
        features: features published, summed over frames.
        tracked: features carried over from the previous frame, summed.
        followers: features of all frames but the first (the ones that could have been carried over).
        lengths: final length (frames) of every track.
        errors: tracking error (px) of each carried-over feature against ground-truth flow, when known.
    """

    sample: Any = None
    frames: int = 0
    features: int = 0
    tracked: int = 0
    followers: int = 0
    lengths: dict[int, int] = field(default_factory=dict)
    errors: list[float] = field(default_factory=list)
    _index: dict[int, int] = field(default_factory=dict, repr=False)
    _prev: tuple[int | None, dict[int, np.ndarray]] | None = field(default=None, repr=False)

    def __post_init__(self) -> None:
        if self.sample is not None:
            self._index = {int(s): i for i, s in enumerate(self.sample.stamps_ns)}

    def add_frame(self, stamp_ns: int, features: dict[int, np.ndarray]) -> None:
        """Add one frame's camera-0 features (id -> distorted pixel), in time order."""
        k = self._index.get(int(stamp_ns))
        carried = [] if self._prev is None else [i for i in features if i in self._prev[1]]
        self.frames += 1
        self.features += len(features)
        if self._prev is not None:
            self.followers += len(features)
        self.tracked += len(carried)
        for i in features:
            self.lengths[i] = self.lengths.get(i, 0) + 1
        if carried and k is not None and self._prev is not None and self._prev[0] is not None:
            p0 = np.array([self._prev[1][i] for i in carried])
            gt, visible = self.sample.flow(self._prev[0], k, p0)
            obs = np.array([features[i] for i in carried])
            self.errors.extend(np.linalg.norm(obs - (p0 + gt), axis=1)[visible].tolist())
        self._prev = (k, features)

    def figures(self) -> dict[str, Any]:
        """Summary numbers: features per frame, mean track length, error median / share within 1 px."""
        lengths = np.array(list(self.lengths.values()) or [0])
        err = np.array(self.errors)
        return {
            "frames": self.frames,
            "features_per_frame": self.features / max(self.frames, 1),
            "tracked_share": self.tracked / max(self.followers, 1),
            "mean_track_length": float(lengths.mean()),
            "tracks_10_frames": int((lengths >= 10).sum()),
            "error_median_px": float(np.median(err)) if err.size else None,
            "error_within_1px": float((err < 1.0).mean()) if err.size else None,
            "error_count": int(err.size),
        }


@dataclass
class OfflineSummary:
    """What :func:`run_offline` did."""

    source: str
    method: str
    perturb: str
    out_dir: str
    figures: dict[str, Any]

    def text(self) -> str:
        f = self.figures
        err = (
            "n/a"
            if f["error_median_px"] is None
            else f"{f['error_median_px']:.3f} px median, {100 * f['error_within_1px']:.1f}% within 1 px"
        )
        return (
            f"{self.source} [{self.method}, perturbation {self.perturb}]: {f['frames']} frames, "
            f"{f['features_per_frame']:.1f} features/frame, mean track length {f['mean_track_length']:.1f}, "
            f"tracking error {err}; outputs in {self.out_dir}"
        )


def _label(tile: np.ndarray, text: str) -> None:
    """White text on a dark box in the tile's top-left corner: readable on any image."""
    font, scale = cv2.FONT_HERSHEY_SIMPLEX, 0.5
    (w, h), base = cv2.getTextSize(text, font, scale, 1)
    cv2.rectangle(tile, (0, 0), (w + 10, h + base + 8), (32, 32, 32), -1)
    cv2.putText(tile, text, (5, h + 4), font, scale, (255, 255, 255), 1, cv2.LINE_AA)


def track_legend(width: int) -> np.ndarray:
    """A legend strip for the VINS debug images: circle colour = track length, green arrow = motion."""
    from nsflow_ros.vins.draw import FULL_TRACK, track_colour

    strip = np.full((30, width, 3), 32, np.uint8)
    font = cv2.FONT_HERSHEY_SIMPLEX
    x = 8
    cv2.putText(strip, "track length:", (x, 20), font, 0.45, (255, 255, 255), 1, cv2.LINE_AA)
    x += 110
    for n in (1, 5, 10, 15, FULL_TRACK):
        cv2.circle(strip, (x, 15), 5, track_colour(n), -1)
        label = f"{n}+" if n == FULL_TRACK else str(n)
        cv2.putText(strip, label, (x + 9, 20), font, 0.45, (255, 255, 255), 1, cv2.LINE_AA)
        x += 45
    x += 15
    cv2.arrowedLine(strip, (x + 30, 15), (x, 15), (0, 255, 0), 1, cv2.LINE_AA, 0, 0.3)
    cv2.putText(strip, "to the previous position; green dots: right camera", (x + 38, 20), font, 0.45,
                (255, 255, 255), 1, cv2.LINE_AA)
    return strip


def contact_sheet(
    images: list[np.ndarray], cols: int = 3, width: int = 376, labels: list[str] | None = None,
    *, legend: bool = False,
) -> np.ndarray:
    """Tile BGR images (scaled to ``width`` px wide) into one sheet.

    Args:
        images: BGR uint8 images.
        cols: tiles per row.
        width: tile width in pixels.
        labels: one caption per image, white on a dark box.
        legend: add a strip explaining the VINS debug images' colours (:func:`track_legend`).
    """
    if not images:
        raise NSFlowError("contact_sheet needs at least one image")
    tiles = []
    for k, img in enumerate(images):
        h = round(img.shape[0] * width / img.shape[1])
        tile = cv2.resize(img, (width, h), interpolation=cv2.INTER_AREA)
        if labels:
            _label(tile, labels[k])
        tiles.append(tile)
    h = max(t.shape[0] for t in tiles)
    tiles = [cv2.copyMakeBorder(t, 0, h - t.shape[0], 0, 0, cv2.BORDER_CONSTANT) for t in tiles]
    while len(tiles) % cols:
        tiles.append(np.zeros_like(tiles[0]))
    rows = [np.hstack(tiles[i : i + cols]) for i in range(0, len(tiles), cols)]
    sheet = np.vstack(rows)
    if legend:
        sheet = np.vstack([sheet, track_legend(sheet.shape[1])])
    return sheet


def _write_png(path: Path, img: np.ndarray) -> None:
    ok, buf = cv2.imencode(".png", img)
    if not ok:
        raise NSFlowError(f"cannot encode {path} as PNG")
    path.write_bytes(buf.tobytes())


def _sample_of(path: Path) -> Any:
    """The SampleSequence a path belongs to, or None."""
    from nsflow_ros.data.errors import DataError
    from nsflow_ros.data.sample import SampleSequence, _is_sample

    for cand in (path, *path.parents[:3]):
        if _is_sample(cand):
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
    sheet_frames: int = 6,
    progress: bool = True,
) -> OfflineSummary:
    """Track a recorded sequence with the core tracker and write features, a contact sheet and a summary.

    Args:
        opts: what to read (path, topics, window, perturbation); the tracker uses camera 0 (mono).
        out_dir: output folder (created).
        config: VINS config file (default: the shipped EuRoC mono config).
        method: ``nsflow``, ``classical`` or ``klt`` (see :data:`nsflow_ros.core.tracker.METHODS`).
        overrides: further tracker settings.
        sheet_frames: debug images in the contact sheet, spread over the sequence.
        progress: show a progress bar.

    Returns:
        the summary (also written as summary.json).

    Raises:
        NSFlowError: a bad source (DataError), config (ConfigError) or model (EncoderError); outputs of
            the frames processed before a damaged part of a bag are still written.
    """
    from tqdm import tqdm

    from nsflow_ros.resources import share_file
    from nsflow_ros.vins.config import load_vins_config

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    cfg = load_vins_config(config or share_file("config/euroc/euroc_mono_imu_config.yaml"))
    # the same frame policy as the node (duplicate stamps, VINS-Mono's first frame and freq), camera 0 only
    fixed = {"stereo": False, **(overrides or {})}
    session = FrontEndSession(cfg, {"method": method}, tracker_overrides=fixed)
    stats = TrackStats(_sample_of(Path(opts.path)))
    rows: list[str] = []
    sheet: list[tuple[int, np.ndarray]] = []
    error: NSFlowError | None = None
    bar = tqdm(desc=f"offline {method}", unit="frame", disable=not progress)
    try:
        for rec in replay_records(replace(opts, topics=[cfg.image0_topic])):
            if not isinstance(rec, ImageRecord):
                continue
            gray = rec.gray()
            outcome = session.process(rec.stamp_ns * 1e-9, gray)
            if outcome.skipped == "tracker":
                raise NSFlowError(f"frame at {rec.stamp_ns} ns: {outcome.note}")
            feats = outcome.features
            bar.update(1)
            if feats is None:
                continue
            cf = feats.cameras[0]
            stats.add_frame(rec.stamp_ns, {int(i): p for i, p in zip(cf.ids, cf.pixels, strict=True)})
            for j in range(len(cf.ids)):
                rows.append(
                    f"{rec.stamp_ns},0,{cf.ids[j]},{cf.pixels[j, 0]:.4f},{cf.pixels[j, 1]:.4f},"
                    f"{cf.undistorted[j, 0]:.6f},{cf.undistorted[j, 1]:.6f},{cf.velocities[j, 0]:.6f},"
                    f"{cf.velocities[j, 1]:.6f},{cf.track_counts[j]}"
                )
            if stats.frames % 10 == 5 and len(sheet) < 4 * sheet_frames:
                sheet.append((stats.frames, draw_tracks(feats, gray)))
    except NSFlowError as err:
        error = err  # keep what was processed; report after writing
    finally:
        bar.close()
    atomic_write(out / "features.csv", lambda p: p.write_text(CSV_HEADER + "\n" + "\n".join(rows) + "\n"))
    if sheet:
        pick = [sheet[round(i)] for i in np.linspace(0, len(sheet) - 1, min(sheet_frames, len(sheet)))]
        img = contact_sheet([im for _, im in pick], labels=[f"{method} frame {n}" for n, _ in pick],
                            legend=True)
        atomic_write(out / "tracks.png", lambda p: _write_png(p, img))
    summary = OfflineSummary(str(opts.path), method, opts.perturb, str(out), stats.figures())
    atomic_write(out / "summary.json", lambda p: p.write_text(json.dumps(asdict(summary), indent=2)))
    if error is not None:
        raise NSFlowError(
            f"{error} (the {stats.frames} frames before it were processed and written to {out})"
        )
    return summary
