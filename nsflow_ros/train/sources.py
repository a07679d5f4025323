"""Training data sources behind one interface: every source gives perturbed pairs with exact flow.

The ``--data`` kinds are registered in :data:`SOURCES` (photos, scenes, TartanAir, the user's footage);
:class:`MixedSource` draws from several by weight, and :class:`PairStream` indexes a source so that pair
``i`` depends only on the seed and ``i`` (every process, data-loader worker and resumed run sees the
same pairs).
"""

from __future__ import annotations

import itertools
import re
from abc import ABC, abstractmethod
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import ClassVar, Literal

import cv2
import numpy as np

from nsflow_ros.core.detector import detect_corners
from nsflow_ros.train.data import (
    TRAIN_IMAGES,
    Pair,
    PairConfig,
    initial_flow,
    inside,
    load_image,
    make_pair,
    perturb_frames,
)
from nsflow_ros.train.errors import TrainError

__all__ = [
    "DATA_KINDS",
    "SOURCES",
    "DataSpec",
    "FootageSource",
    "MixedSource",
    "PairSource",
    "PairStream",
    "PhotoSource",
    "SceneSource",
    "SourceOptions",
    "TartanAirSource",
    "parse_data_spec",
    "read_footage",
    "tartanair_environments",
]

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".pgm")


@dataclass(frozen=True)
class SourceOptions:
    """What splitting a ``--data`` entry may read beside its path (each kind reads its own fields).

    Attributes:
        seed: seed of the scene pool.
        cache: the scene pool's cache folder when the entry names none.
        color: TartanAir frames as RGB.
        tartanair_val: TartanAir environments held out for validation; None = the last by name when
            there are two or more.
        topics: footage camera topics (None = the default ones).
        holdout: footage share held out at the end.
    """

    seed: int = 0
    cache: Path = Path("cache")
    color: bool = False
    tartanair_val: tuple[str, ...] | None = None
    topics: list[str] | None = None
    holdout: float = 0.2


Split = tuple["PairSource", "PairSource | None"]


class PairSource(ABC):
    """Something that draws training pairs with exact flow.

    A kind of ``--data`` entry is a subclass registered in :data:`SOURCES`; its :meth:`split` is the one
    place that turns an entry into sources, so no caller branches on a kind.
    """

    kind: ClassVar[str] = ""
    path_use: ClassVar[Literal["required", "optional", "none"]] = "none"
    """Whether a ``--data`` entry of this kind needs, may have or takes no path."""

    @classmethod
    def split(cls, path: Path | None, opts: SourceOptions) -> Split:
        """The training source a ``--data`` entry of this kind names, and its held-out validation source.

        Args:
            path: the entry's path (None when it names none).
            opts: settings beside the path.

        Returns:
            (training source, validation source or None when nothing is held out).

        Raises:
            TrainError: the data cannot be read or split (the message names the path).
        """
        raise NotImplementedError  # pragma: no cover - every registered kind overrides it

    def evaluation_frames(self) -> list[np.ndarray]:
        """Frames the end-of-run footage comparison scores models on when this is a validation source;
        empty = validated during training only."""
        return []

    @staticmethod
    def words(description: Mapping[str, object]) -> str:
        """A :meth:`describe` result in words for the model card (its share excluded)."""
        raise NotImplementedError  # pragma: no cover - every registered kind overrides it

    @abstractmethod
    def sample(self, rng: np.random.Generator, cfg: PairConfig, strength: float) -> Pair:
        """One pair (possibly with few or no points), ``strength`` the illumination change in [0, 1]."""

    @abstractmethod
    def describe(self) -> dict[str, object]:
        """What the source reads, for the run folder and the model card (JSON-able)."""


class PhotoSource(PairSource):
    """Random homography pairs of the bundled photos (:func:`~nsflow_ros.train.data.make_pair`)."""

    kind = "photos"

    def __init__(self, images: tuple[str, ...] = TRAIN_IMAGES) -> None:
        if not images:
            raise TrainError("PhotoSource needs at least one photo")
        self.images = tuple(images)
        self._photos = [load_image(n) for n in self.images]

    def sample(self, rng: np.random.Generator, cfg: PairConfig, strength: float) -> Pair:
        src = self._photos[int(rng.integers(len(self._photos)))]
        return make_pair(src, rng, cfg, strength=strength)

    def describe(self) -> dict[str, object]:
        return {"kind": self.kind, "images": list(self.images)}

    @classmethod
    def split(cls, path: Path | None, opts: SourceOptions) -> Split:
        return cls(), None

    @staticmethod
    def words(description: Mapping[str, object]) -> str:
        return "homography pairs of the bundled photos"


class SceneSource(PairSource):
    """Crops of stereo and temporal pairs rendered from the sample scenes (:mod:`~nsflow_ros.train.scenes`).

    Args:
        cache: folder of the scenes' sample-sequence metadata (made once, reused).
        seed: seed of the pool's frame gaps.
    """

    kind = "scenes"
    path_use = "optional"

    def __init__(self, cache: Path, seed: int = 0) -> None:
        from nsflow_ros.train.scenes import SCENE_SEEDS, ScenePool

        self.cache = Path(cache)
        self.seeds = SCENE_SEEDS
        self.pool = ScenePool(self.cache, seeds=SCENE_SEEDS, seed=seed)

    def sample(self, rng: np.random.Generator, cfg: PairConfig, strength: float) -> Pair:
        from nsflow_ros.train.scenes import make_scene_pair

        return make_scene_pair(self.pool, rng, cfg, strength=strength)

    def describe(self) -> dict[str, object]:
        return {"kind": self.kind, "sequence_seeds": list(self.seeds), "rendered_pairs": len(self.pool)}

    @classmethod
    def split(cls, path: Path | None, opts: SourceOptions) -> Split:
        return cls(path or opts.cache, seed=opts.seed), None

    @staticmethod
    def words(description: Mapping[str, object]) -> str:
        return f"crops of rendered sample-scene pairs (sequence seeds {description.get('sequence_seeds')})"


# -- TartanAir --------------------------------------------------------------------------------------------

_FRAME = re.compile(r"^(\d+)_left\.png$")


@dataclass(frozen=True)
class _FlowPair:
    image1: Path
    image2: Path
    flow: Path
    mask: Path
    environment: str


def tartanair_environments(root: str | Path) -> list[str]:
    """The environment folders of a TartanAir root (those holding ``Easy`` or ``Hard``), sorted.

    Raises:
        TrainError: the root does not exist or holds no environment.
    """
    base = Path(root)
    if not base.is_dir():
        raise TrainError(f"TartanAir folder not found: {base}")
    envs = sorted(
        d.name for d in base.iterdir() if d.is_dir() and any((d / lvl).is_dir() for lvl in ("Easy", "Hard"))
    )
    if not envs:
        raise TrainError(
            f"{base} holds no TartanAir environment (expected <env>/<Easy|Hard>/<Pxxx>/image_left/)"
        )
    return envs


class TartanAirSource(PairSource):
    """Consecutive frame pairs of TartanAir trajectories with their ground-truth flow.

    Layout (TartanAir's tools): ``<root>/<env>/<Easy|Hard>/<Pxxx>/image_left/NNNNNN_left.png``,
    ``flow/NNNNNN_MMMMMM_flow.npy`` (float32 (H, W, 2), M = N + 1) and ``flow/NNNNNN_MMMMMM_mask.npy``
    (uint8 (H, W), 0 = valid). A pair is the same random crop of both frames; its keypoints are GFTT
    corners on integer pixels (where the flow file is exact) whose flow is valid and lands inside frame 2.

    Args:
        root: the folder holding the environments.
        environments: the environments to use (None = all).
        color: frames as RGB instead of gray.

    Raises:
        TrainError: the root holds no environment, an environment named is missing, a trajectory has a
            frame without its flow or mask file, or no pair is found.
    """

    kind = "tartanair"
    path_use = "required"

    def __init__(self, root: str | Path, environments: list[str] | None = None, color: bool = False) -> None:
        self.root = Path(root)
        present = tartanair_environments(self.root)
        envs = present if environments is None else list(environments)
        missing = [e for e in envs if e not in present]
        if missing:
            raise TrainError(f"TartanAir environments {missing} not in {self.root} (present: {present})")
        self.environments = envs
        self.color = color
        self.pairs: list[_FlowPair] = []
        for env in envs:
            for traj in sorted((self.root / env).glob("*/P*")):
                self.pairs += self._index(traj, env)
        if not self.pairs:
            raise TrainError(f"no TartanAir frame pairs under {self.root} in environments {envs}")

    @staticmethod
    def _index(traj: Path, env: str) -> list[_FlowPair]:
        images = traj / "image_left"
        if not images.is_dir():
            raise TrainError(f"TartanAir trajectory {traj} has no image_left folder")
        frames = sorted((int(m.group(1)), p) for p in images.iterdir() if (m := _FRAME.match(p.name)))
        out = []
        for (i, p1), (j, p2) in itertools.pairwise(frames):
            if j != i + 1:
                continue
            stem = traj / "flow" / f"{i:06d}_{j:06d}"
            flow, mask = Path(f"{stem}_flow.npy"), Path(f"{stem}_mask.npy")
            for f in (flow, mask):
                if not f.is_file():
                    raise TrainError(f"missing TartanAir file {f} (flow of frames {p1.name} -> {p2.name})")
            out.append(_FlowPair(p1, p2, flow, mask, env))
        return out

    def _read(self, path: Path) -> np.ndarray:
        img = cv2.imread(str(path), cv2.IMREAD_COLOR if self.color else cv2.IMREAD_GRAYSCALE)
        if img is None:
            raise TrainError(f"cannot read image {path}")
        return cv2.cvtColor(img, cv2.COLOR_BGR2RGB) if self.color else img

    @staticmethod
    def _load(path: Path, shape: tuple[int, ...], dtype: str) -> np.ndarray:
        try:
            arr = np.load(path)
        except (OSError, ValueError) as err:
            raise TrainError(f"cannot read {path}: {err}") from err
        if arr.shape != shape:
            raise TrainError(f"{path} has shape {arr.shape}, expected {shape} ({dtype}) like its frames")
        return arr

    def sample(self, rng: np.random.Generator, cfg: PairConfig, strength: float) -> Pair:
        fp = self.pairs[int(rng.integers(len(self.pairs)))]
        im1, im2 = self._read(fp.image1), self._read(fp.image2)
        h, w = im1.shape[:2]
        if im2.shape != im1.shape:
            raise TrainError(f"{fp.image2} is {im2.shape[:2]}, {fp.image1} is {(h, w)}")
        flow = self._load(fp.flow, (h, w, 2), "float32 flow").astype(np.float64)
        mask = self._load(fp.mask, (h, w), "uint8 mask")
        if cfg.width > w or cfg.height > h:
            raise TrainError(
                f"crop {cfg.width}x{cfg.height} is larger than the frames {w}x{h} of {fp.image1}"
            )
        x0 = int(rng.integers(0, w - cfg.width + 1))
        y0 = int(rng.integers(0, h - cfg.height + 1))
        sl = (slice(y0, y0 + cfg.height), slice(x0, x0 + cfg.width))
        f1, f2, fl, mk = im1[sl], im2[sl], flow[sl], mask[sl]
        yy, xx = np.mgrid[0 : cfg.height, 0 : cfg.width]
        target = np.stack([xx + fl[..., 0], yy + fl[..., 1]], -1).reshape(-1, 2)
        r = cfg.window // 2
        ok = (mk == 0).reshape(-1) & np.isfinite(target).all(1) & inside(target, cfg.width, cfg.height, r)
        valid = ok.reshape(cfg.height, cfg.width).astype(np.uint8) * 255
        f1, f2 = perturb_frames(f1, f2, rng, strength)
        gray = cv2.cvtColor(f1, cv2.COLOR_RGB2GRAY) if self.color else f1
        pts = detect_corners(gray, cfg.max_points, min_distance=cfg.min_distance, mask=valid)
        pts = pts[inside(pts, cfg.width, cfg.height, r)]
        ij = np.rint(pts).astype(np.int64)
        pts = ij.astype(np.float64)
        gt = fl[ij[:, 1], ij[:, 0]] if len(ij) else np.zeros((0, 2))
        return Pair(f1, f2, pts, gt, initial_flow(gt, rng, cfg), np.full((3, 3), np.nan))

    def describe(self) -> dict[str, object]:
        return {
            "kind": self.kind,
            "path": str(self.root),
            "environments": self.environments,
            "pairs": len(self.pairs),
            "color": self.color,
        }

    @classmethod
    def split(cls, path: Path | None, opts: SourceOptions) -> Split:
        """Hold out ``opts.tartanair_val`` (default: the last environment when another is left to train on).

        Raises:
            TrainError: a held-out environment is not in the folder, or every environment is held out.
        """
        assert path is not None
        envs = tartanair_environments(path)
        if opts.tartanair_val is not None:
            held = list(opts.tartanair_val)
        else:
            held = envs[-1:] if len(envs) > 1 else []
        unknown = [e for e in held if e not in envs]
        if unknown:
            raise TrainError(f"validation environments {unknown} not in {path} (present: {envs})")
        train_envs = [e for e in envs if e not in held]
        if not train_envs:
            raise TrainError(f"every environment of {path} is held out for validation: {held}")
        train = cls(path, train_envs, color=opts.color)
        return train, cls(path, held, color=opts.color) if held else None

    @staticmethod
    def words(description: Mapping[str, object]) -> str:
        envs = ", ".join(str(e) for e in description.get("environments", []))  # type: ignore[attr-defined]
        pairs = description.get("pairs")
        return f"TartanAir `{description.get('path')}`, environments {envs} ({pairs} pairs)"


# -- the user's footage -----------------------------------------------------------------------------------


def read_footage(
    path: str | Path, topics: list[str] | None = None, stride: int = 1, max_frames: int = 400
) -> list[np.ndarray]:
    """(H, W) uint8 frames of a bag, an ASL folder or a folder of images, in time order.

    Args:
        path: ROS 1 / ROS 2 bag or ASL folder (``nsflow_ros.data.sources.SensorSource``), or a folder of
            image files (read in name order).
        topics: camera topics of a bag or ASL folder (None = ``/cam0/image_raw`` and ``/cam1/image_raw``,
            those present).
        stride: keep every ``stride``-th frame.
        max_frames: at most this many frames, spread evenly over the kept ones.

    Raises:
        TrainError: the path is none of these, a topic is missing, or no frame is found.
    """
    from nsflow_ros.data.errors import DataError
    from nsflow_ros.data.records import ImageRecord
    from nsflow_ros.data.sources import SensorSource

    if stride < 1 or max_frames < 2:
        raise TrainError(f"footage stride must be >= 1 and max_frames >= 2, got {stride}, {max_frames}")
    src = Path(path)
    frames: list[np.ndarray] = []
    files = sorted(p for p in src.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES) if src.is_dir() else []
    if files:
        for f in files[::stride]:
            img = cv2.imread(str(f), cv2.IMREAD_GRAYSCALE)
            if img is None:
                raise TrainError(f"cannot read image {f}")
            frames.append(img)
    else:
        try:
            k = 0
            for rec in SensorSource(src, topics=topics):
                if isinstance(rec, ImageRecord):
                    if k % stride == 0:
                        frames.append(rec.gray())
                    k += 1
        except DataError as err:
            raise TrainError(f"footage {src}: {err}") from err
    if not frames:
        what = f"topics {topics}" if topics else "the default camera topics"
        raise TrainError(f"footage {src} holds no image frames on {what}")
    if len(frames) > max_frames:
        keep = np.linspace(0, len(frames) - 1, max_frames).round().astype(int)
        frames = [frames[i] for i in keep]
    return frames


class FootageSource(PairSource):
    """Random homography pairs of the user's own frames, made as the photo pairs are (exact flow).

    The last ``holdout`` share of the frames (in time order) is kept apart (:meth:`heldout`).

    Args:
        path: bag, ASL folder or image folder (:func:`read_footage`).
        topics: camera topics (bags and ASL folders).
        holdout: share of frames at the end kept for validation, in [0, 1).
        stride: keep every ``stride``-th frame.
        max_frames: at most this many frames.
        frames: the frames themselves (instead of reading ``path``).
    """

    kind = "footage"
    path_use = "required"

    def __init__(
        self,
        path: str | Path,
        topics: list[str] | None = None,
        holdout: float = 0.2,
        stride: int = 1,
        max_frames: int = 400,
        frames: list[np.ndarray] | None = None,
    ) -> None:
        if not 0.0 <= holdout < 1.0:
            raise TrainError(f"footage holdout must be in [0, 1), got {holdout}")
        self.path = Path(path)
        self.topics = topics
        all_frames = frames if frames is not None else read_footage(path, topics, stride, max_frames)
        n_hold = round(holdout * len(all_frames))
        if holdout > 0 and len(all_frames) >= 2:
            n_hold = max(1, min(n_hold, len(all_frames) - 1))
        self.frames = all_frames[: len(all_frames) - n_hold]
        self.held = all_frames[len(all_frames) - n_hold :]
        if not self.frames:
            raise TrainError(f"footage {self.path} leaves no training frame after the held-out share")

    def sample(self, rng: np.random.Generator, cfg: PairConfig, strength: float) -> Pair:
        return make_pair(self.frames[int(rng.integers(len(self.frames)))], rng, cfg, strength=strength)

    def heldout(self) -> FootageSource | None:
        """The held-out frames as a source of their own (None without any)."""
        if not self.held:
            return None
        return FootageSource(self.path, self.topics, holdout=0.0, frames=list(self.held))

    def describe(self) -> dict[str, object]:
        h, w = self.frames[0].shape
        return {
            "kind": self.kind,
            "path": str(self.path),
            "topics": self.topics,
            "frames": len(self.frames),
            "heldout_frames": len(self.held),
            "size": [w, h],
        }

    @classmethod
    def split(cls, path: Path | None, opts: SourceOptions) -> Split:
        assert path is not None
        train = cls(path, opts.topics, holdout=opts.holdout)
        return train, train.heldout()

    def evaluation_frames(self) -> list[np.ndarray]:
        return self.frames

    @staticmethod
    def words(description: Mapping[str, object]) -> str:
        return (
            f"footage `{description.get('path')}`, {description.get('frames')} frames as random homography "
            f"pairs ({description.get('heldout_frames')} later frames held out)"
        )


# -- mixing and indexing ----------------------------------------------------------------------------------


class MixedSource(PairSource):
    """Several sources, one drawn per pair with probability proportional to its weight (> 0).

    A single source is used without a draw, so its pairs are those it gives alone.
    """

    kind = "mixed"

    def __init__(self, parts: list[tuple[PairSource, float]]) -> None:
        if not parts:
            raise TrainError("no training data source given")
        bad = [w for _, w in parts if not (w > 0 and np.isfinite(w))]
        if bad:
            raise TrainError(f"data source weights must be finite and > 0, got {bad}")
        self.sources = [s for s, _ in parts]
        total = float(sum(w for _, w in parts))
        self.shares = [w / total for _, w in parts]
        self._cum = np.cumsum(self.shares)

    def sample(self, rng: np.random.Generator, cfg: PairConfig, strength: float) -> Pair:
        if len(self.sources) == 1:
            return self.sources[0].sample(rng, cfg, strength)
        k = min(int(np.searchsorted(self._cum, rng.uniform(), side="right")), len(self.sources) - 1)
        return self.sources[k].sample(rng, cfg, strength)

    def describe(self) -> dict[str, object]:
        parts = zip(self.sources, self.shares, strict=True)
        return {"kind": self.kind, "sources": [{**s.describe(), "share": round(p, 6)} for s, p in parts]}


@dataclass(frozen=True)
class PairStream:
    """An indexed stream of training pairs: pair ``i`` depends only on ``seed`` and ``i``.

    A pair with fewer than ``min_points`` keypoints is redrawn, ``attempts`` times at most.
    """

    source: PairSource
    cfg: PairConfig = field(default_factory=PairConfig)
    seed: int = 0
    min_points: int = 4
    attempts: int = 50

    def __getitem__(self, index: int) -> Pair:
        for attempt in range(self.attempts):
            rng = np.random.default_rng([self.seed, int(index), attempt])
            pair = self.source.sample(rng, self.cfg, float(rng.uniform(self.cfg.light_min, 1.0)))
            if len(pair.points) >= self.min_points:
                return pair
        raise TrainError(
            f"{self.attempts} pairs in a row from {self.source.describe()} had fewer than {self.min_points} "
            "keypoints: the frames are too flat or too small for the crop"
        )


# -- the registry and the command line --------------------------------------------------------------------

SOURCES: Mapping[str, type[PairSource]] = {
    cls.kind: cls for cls in (PhotoSource, SceneSource, TartanAirSource, FootageSource)
}
"""Every ``--data`` kind and the source class that builds and splits it."""

DATA_KINDS = tuple(SOURCES)

@dataclass(frozen=True)
class DataSpec:
    """One ``--data KIND[:PATH][:WEIGHT]`` argument: a kind of :data:`SOURCES`, its path, its weight."""

    kind: str
    path: Path | None = None
    weight: float = 1.0

    def split(self, opts: SourceOptions) -> Split:
        """The training source this entry names and its held-out validation source (None without one)."""
        return SOURCES[self.kind].split(self.path, opts)


def parse_data_spec(text: str) -> DataSpec:
    """``KIND[:PATH][:WEIGHT]`` -> :class:`DataSpec` (a path may itself hold colons).

    Raises:
        TrainError: an unknown kind, a missing path for tartanair / footage, or a weight <= 0.
    """
    kind, _, rest = text.partition(":")
    if kind not in DATA_KINDS:
        raise TrainError(f"--data {text!r}: kind must be one of {DATA_KINDS}")
    path_text, weight = rest, 1.0
    head, sep, tail = rest.rpartition(":")
    if sep or rest:
        try:
            weight = float(tail if sep else rest)
            path_text = head if sep else ""
        except ValueError:
            path_text = rest
    if not (weight > 0 and np.isfinite(weight)):
        raise TrainError(f"--data {text!r}: weight must be finite and > 0, got {weight}")
    path = Path(path_text) if path_text else None
    use = SOURCES[kind].path_use
    if use == "required" and path is None:
        raise TrainError(f"--data {text!r}: {kind} needs a path ({kind}:PATH[:WEIGHT])")
    if use == "none" and path is not None:
        raise TrainError(f"--data {text!r}: {kind} takes no path ({kind}[:WEIGHT])")
    return DataSpec(kind, path, weight)
