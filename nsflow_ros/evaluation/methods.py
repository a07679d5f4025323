"""The methods every analysis compares, behind one pair-tracking interface.

* ``NSFlow``: the shipped (or a given) ONNX encoder's descriptor maps through the project's LM solver;
* ``LM (intensity)``: the same solver on image intensity (:class:`~nsflow_ros.core.IntensityEncoder`);
* ``OpenCV KLT``: ``cv2.calcOpticalFlowPyrLK`` as VINS calls it (21x21 window, 30 iterations, eps 0.01).

All three get the same images, points, initial flow and number of pyramid levels.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Protocol

import cv2
import numpy as np

from nsflow_ros.core.encoder import Encoder, IntensityEncoder, load_encoder, to_gray
from nsflow_ros.core.errors import CoreError
from nsflow_ros.core.pyramid import DescriptorPyramid, build_pyramid
from nsflow_ros.core.solver import LMConfig, TrackResult, track
from nsflow_ros.evaluation.errors import EvaluationError

__all__ = [
    "CLASSICAL",
    "KLT",
    "NSFLOW",
    "KLTMethod",
    "LMMethod",
    "PairMethod",
    "PairResult",
    "default_methods",
]

NSFLOW = "NSFlow"
CLASSICAL = "LM (intensity)"
KLT = "OpenCV KLT"


@dataclass(frozen=True)
class PairResult:
    """Flow of N points from image 1 to image 2.

    Attributes:
        flow: (N, 2) float64, new position = points + flow (may be non-finite where status is False).
        status: (N,) bool, the method's own tracked flag.
    """

    flow: np.ndarray
    status: np.ndarray


class PairMethod(Protocol):
    """What an analysis needs of a method."""

    name: str
    levels: int

    def track(
        self, image1: np.ndarray, image2: np.ndarray, points: np.ndarray, flow0: np.ndarray | None = None
    ) -> PairResult: ...


def _check_points(points: np.ndarray, flow0: np.ndarray | None) -> tuple[np.ndarray, np.ndarray | None]:
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 2:
        raise EvaluationError(f"points must be (N, 2), got {pts.shape}")
    if flow0 is not None:
        flow0 = np.asarray(flow0, dtype=np.float64)
        if flow0.shape != pts.shape:
            raise EvaluationError(f"flow0 must have the shape of points {pts.shape}, got {flow0.shape}")
    return pts, flow0


class LMMethod:
    """The project's LM solver on an encoder's descriptor maps.

    Args:
        name: label in tables and plots.
        encoder: any :class:`~nsflow_ros.core.Encoder`.
        config: solver settings (its ``levels`` is the pyramid depth).
    """

    def __init__(self, name: str, encoder: Encoder, config: LMConfig | None = None) -> None:
        self.name = name
        self.encoder = encoder
        self.config = config or LMConfig()

    @property
    def levels(self) -> int:
        return self.config.levels

    def encode(self, image: np.ndarray) -> np.ndarray:
        """The full-resolution descriptor map of an image (cache it to build pyramids of several depths)."""
        try:
            return self.encoder(image)
        except CoreError as err:
            raise EvaluationError(f"{self.name}: {err}") from err

    def pyramid_of(self, desc: np.ndarray, levels: int | None = None) -> DescriptorPyramid:
        """The pyramid of a descriptor map from :meth:`encode`, ``levels`` deep (None = the config's)."""
        try:
            return build_pyramid(desc, self.config.levels if levels is None else levels)
        except CoreError as err:
            raise EvaluationError(f"{self.name}: {err}") from err

    def pyramid(self, image: np.ndarray) -> DescriptorPyramid:
        """The descriptor pyramid of an image (cache it when one image is tracked many times)."""
        return self.pyramid_of(self.encode(image))

    def track_pyramids(
        self,
        pyr1: DescriptorPyramid,
        pyr2: DescriptorPyramid,
        points: np.ndarray,
        flow0: np.ndarray | None = None,
        *,
        record: bool = False,
        config: LMConfig | None = None,
    ) -> TrackResult:
        """Track on pre-built pyramids; ``record`` keeps the per-iteration history."""
        pts, flow0 = _check_points(points, flow0)
        return track(pyr1, pyr2, pts, flow0, config or self.config, record=record)

    def track(
        self, image1: np.ndarray, image2: np.ndarray, points: np.ndarray, flow0: np.ndarray | None = None
    ) -> PairResult:
        res = self.track_pyramids(self.pyramid(image1), self.pyramid(image2), points, flow0)
        return PairResult(res.flow, res.status)


class KLTMethod:
    """OpenCV's pyramidal Lucas-Kanade, with VINS's settings.

    Args:
        levels: pyramid levels (OpenCV ``maxLevel`` = levels - 1).
        window: window side in pixels (VINS: 21).
        max_iterations: iteration limit per level (VINS: 30).
        eps: OpenCV's step-size stop test (VINS: 0.01).
    """

    name = KLT

    def __init__(
        self, levels: int = 3, window: int = 21, max_iterations: int = 30, eps: float = 0.01
    ) -> None:
        if levels < 1:
            raise EvaluationError(f"levels must be >= 1, got {levels}")
        self.levels = levels
        self.window = window
        self.max_iterations = max_iterations
        self.eps = eps

    def with_iterations(self, max_iterations: int) -> KLTMethod:
        """A copy limited to ``max_iterations`` per level (for convergence curves)."""
        return KLTMethod(self.levels, self.window, max_iterations, self.eps)

    def track(
        self, image1: np.ndarray, image2: np.ndarray, points: np.ndarray, flow0: np.ndarray | None = None
    ) -> PairResult:
        pts, flow0 = _check_points(points, flow0)
        n = len(pts)
        if n == 0:
            return PairResult(np.zeros((0, 2)), np.zeros(0, bool))
        try:
            g1, g2 = to_gray(image1), to_gray(image2)
        except CoreError as err:
            raise EvaluationError(f"{self.name}: {err}") from err
        p1 = pts.astype(np.float32).reshape(-1, 1, 2)
        flags = 0
        p2 = None
        if flow0 is not None:
            p2 = (pts + flow0).astype(np.float32).reshape(-1, 1, 2)
            flags = cv2.OPTFLOW_USE_INITIAL_FLOW
        criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, self.max_iterations, self.eps)
        new, status, _ = cv2.calcOpticalFlowPyrLK(
            g1,
            g2,
            p1,
            p2,
            winSize=(self.window, self.window),
            maxLevel=self.levels - 1,
            criteria=criteria,
            flags=flags,
        )
        flow = new.reshape(-1, 2).astype(np.float64) - pts
        ok = status.reshape(-1).astype(bool) & np.isfinite(flow).all(axis=1)
        return PairResult(flow, ok)


def default_methods(
    model: str | None = None, levels: int = 3, threads: int | None = None
) -> list[PairMethod]:
    """NSFlow (``model``, None = the shipped encoder), LM on intensity and OpenCV KLT, all at ``levels``."""
    if levels < 1:
        raise EvaluationError(f"levels must be >= 1, got {levels}")
    cfg = replace(LMConfig(), levels=levels)
    try:
        encoder = load_encoder(model, threads=threads)
    except CoreError as err:
        raise EvaluationError(str(err)) from err
    return [LMMethod(NSFLOW, encoder, cfg), LMMethod(CLASSICAL, IntensityEncoder(), cfg), KLTMethod(levels)]
