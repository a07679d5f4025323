"""Training pairs rendered from the project's synthetic sample scenes: real 3D motion with exact flow.

Unlike the photo homographies these look like the tracker's input (:mod:`nsflow_ros.data.sample`: depth
discontinuities, occlusions, textureless walls), as stereo pairs at the EuRoC baseline or two frames of
the left camera a few frames apart. Rendering costs more than a training step, so a :class:`ScenePool`
renders a fixed set of pairs once and each training pair is a random crop of one of them.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from nsflow_ros.core.detector import detect_corners
from nsflow_ros.train.data import Pair, PairConfig, initial_flow, inside, perturb_frames
from nsflow_ros.train.errors import TrainError

__all__ = ["SCENE_SEEDS", "RenderedPair", "ScenePool", "make_scene_pair"]

SCENE_SEEDS = (1, 2)
"""Sample-sequence seeds of the training scenes (the evaluation uses seed 0)."""


@dataclass(frozen=True)
class RenderedPair:
    """Two rendered frames with GFTT corners of the first and their exact, visible flow.

    Attributes:
        kind: "stereo" (left -> right, same instant) or "temporal" (left camera, frame i -> i + k).
        image1, image2: (H, W) uint8 frames.
        points: (N, 2) corners in frame 1.
        flow: (N, 2) their flow into frame 2.
    """

    kind: str
    image1: np.ndarray
    image2: np.ndarray
    points: np.ndarray
    flow: np.ndarray


class ScenePool:
    """A fixed set of rendered frame pairs from sample sequences.

    Args:
        root: folder for the sample sequences' metadata (made once, reused).
        seeds: sample-sequence seeds.
        frames: frame pairs per seed, spread over the flight, alternately stereo and temporal.
        duration: seconds of flight per sequence.
        max_gap: temporal pairs are frames i and i + k with k uniform in [1, max_gap].
        points: GFTT corners per rendered frame.
        seed: seed of the frame gaps.

    Raises:
        TrainError: a sequence cannot be made, or no pair has corners.
    """

    def __init__(
        self,
        root: Path,
        seeds: tuple[int, ...] = SCENE_SEEDS,
        frames: int = 12,
        duration: float = 6.0,
        max_gap: int = 4,
        points: int = 800,
        seed: int = 0,
    ) -> None:
        from nsflow_ros.data.errors import DataError
        from nsflow_ros.data.sample import make_sample_sequence

        rng = np.random.default_rng([seed, 0x5CE])
        pairs: list[RenderedPair] = []
        for s in seeds:
            try:
                seq = make_sample_sequence(
                    Path(root) / f"sample-seed{s}-{duration:g}s-stereo-meta",
                    seed=s,
                    duration=duration,
                    stereo=True,
                    formats=(),
                    progress=False,
                )
            except (DataError, OSError) as err:
                raise TrainError(f"cannot make the sample sequence of seed {s} under {root}: {err}") from err
            n = len(seq)
            for k, i in enumerate(np.linspace(0, n - 1 - max_gap, frames).round().astype(int)):
                stereo = k % 2 == 0
                j = int(i) if stereo else int(i) + int(rng.integers(1, max_gap + 1))
                left = seq.image(int(i), 0)
                other = seq.image(j, 1 if stereo else 0)
                pts = detect_corners(left, points, min_distance=6.0)
                if len(pts) == 0:
                    continue
                flow, visible = seq.flow(int(i), j, pts, 0, 1 if stereo else 0)
                keep = visible & np.isfinite(flow).all(1)
                kind = "stereo" if stereo else "temporal"
                pairs.append(RenderedPair(kind, left, other, pts[keep], flow[keep]))
        if not any(len(p.points) for p in pairs):
            raise TrainError(f"the sample scenes of seeds {seeds} gave no corners")
        self.pairs = pairs

    def __len__(self) -> int:
        return len(self.pairs)


def make_scene_pair(
    pool: ScenePool, rng: np.random.Generator, cfg: PairConfig | None = None, strength: float = 1.0
) -> Pair:
    """A training pair: the same random crop of both frames of a random pooled pair (so the flow stays
    exact), with its own lighting change (``strength``) and initial flow; possibly without points.

    Raises:
        TrainError: the crop is larger than the rendered frames.
    """
    cfg = cfg or PairConfig()
    src = pool.pairs[int(rng.integers(len(pool.pairs)))]
    h, w = src.image1.shape
    if cfg.width > w or cfg.height > h:
        raise TrainError(f"crop {cfg.width}x{cfg.height} is larger than the rendered frames {w}x{h}")
    x0 = int(rng.integers(0, w - cfg.width + 1))
    y0 = int(rng.integers(0, h - cfg.height + 1))
    f1 = src.image1[y0 : y0 + cfg.height, x0 : x0 + cfg.width]
    f2 = src.image2[y0 : y0 + cfg.height, x0 : x0 + cfg.width]
    f1, f2 = perturb_frames(f1, f2, rng, strength)
    pts = src.points - (x0, y0)
    frame = (cfg.width, cfg.height, cfg.window // 2)
    keep = np.flatnonzero(inside(pts, *frame) & inside(pts + src.flow, *frame))
    if len(keep) > cfg.max_points:
        keep = np.sort(rng.choice(keep, cfg.max_points, replace=False))
    pts, gt = pts[keep], src.flow[keep]
    return Pair(f1, f2, pts, gt, initial_flow(gt, rng, cfg), np.full((3, 3), np.nan))
