"""Front-end figures against a sample sequence's exact optical flow: the one place tracking is scored.

* :class:`TrackStats` scores a published feature stream (camera 0, id -> pixel, matched by stamp), as the
  offline run, the demo and the evaluation receive it: a feature is carried over when its id was in the
  previous published frame, shares are ratios of sums, and the error is measured from where ground truth
  carries the previous published pixel.
* :class:`FrameQuality` scores the tracker's own frames, as the tracker benchmark does: shares are means of
  per-frame ratios, and the error is measured from the tracker's previous position (stereo matches too).

Points the ground truth marks occluded or outside the image are left out of every error.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

__all__ = ["FrameQuality", "TrackStats"]


@dataclass
class TrackStats:
    """Front-end figures of a published feature stream, accumulated frame by frame (camera 0).

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
        """Add one frame's camera-0 features (id -> (u, v) pixel), in time order.

        A stamp that is not one of the sample's frames measures no error.
        """
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


class FrameQuality:
    """Quality of the tracker's frames over a sample sequence: carried-over share, stereo matches, errors."""

    def __init__(self) -> None:
        self.carried: list[float] = []
        self.matched: list[float] = []
        self.err: list[np.ndarray] = []
        self.stereo_err: list[np.ndarray] = []

    def add_frame(self, sample: Any, i: int, frame: Any, had: int, stereo: bool) -> None:
        """Score frame ``i`` (not the first) of the tracker's output.

        Args:
            sample: the sample sequence (its ``flow`` gives the ground truth).
            i: the frame's index in the sample (> 0).
            frame: the tracker's frame (``.cameras[k].ids / .pixels / .previous``).
            had: camera-0 features of the previous frame.
            stereo: score camera 1's matches too.
        """
        c0 = frame.cameras[0]
        kept = np.isfinite(c0.previous[:, 0])
        if had:
            self.carried.append(int(kept.sum()) / had)
        if kept.any():
            flow, visible = sample.flow(i - 1, i, c0.previous[kept])
            e = np.hypot(*(c0.pixels[kept] - c0.previous[kept] - flow).T)
            self.err.append(e[visible])
        if stereo:
            c1 = frame.cameras[1]
            self.matched.append(len(c1) / max(1, len(c0)))
            if len(c1):
                idx = np.searchsorted(c0.ids, c1.ids)
                flow, visible = sample.flow(i, i, c0.pixels[idx], 0, 1)
                self.stereo_err.append(np.hypot(*(c1.pixels - c0.pixels[idx] - flow).T)[visible])

    def figures(self) -> dict[str, float]:
        """Carried-over share, error median and share over 1 px; the stereo ones when stereo was scored."""
        out: dict[str, float] = {}
        err = np.concatenate(self.err) if self.err else np.zeros(0)
        out["carried_share"] = float(np.mean(self.carried)) if self.carried else float("nan")
        out["error_median_px"] = float(np.median(err)) if err.size else float("nan")
        out["error_over_1px_share"] = float(np.mean(err > 1.0)) if err.size else float("nan")
        if self.matched:
            serr = np.concatenate(self.stereo_err) if self.stereo_err else np.zeros(0)
            out["stereo_matched_share"] = float(np.mean(self.matched))
            out["stereo_error_median_px"] = float(np.median(serr)) if serr.size else float("nan")
            out["stereo_error_over_1px_share"] = float(np.mean(serr > 1.0)) if serr.size else float("nan")
        return out
