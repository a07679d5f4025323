"""The methods every analysis compares: the tracker's own method objects behind one pair interface.

Each evaluated method wraps a tracking method of the registry :data:`nsflow_ros.core.methods.METHODS`
(the objects :class:`~nsflow_ros.core.tracker.FeatureTracker` deploys): the frame representation comes
from its ``prepare`` and every solve from its ``track_pair`` (or, for the LM solver's recorded history,
``run``), so what is evaluated is the code that is deployed and benchmarked.

* ``NSFlow``: core ``nsflow``, the ONNX encoder's descriptor pyramid through the paper's LM solver;
* ``NSFlow + OpenCV LK``: core ``nsflow_lk``, the same descriptors quantised to uint8 and tracked by
  OpenCV's pyramidal LK (21x21 window, 30 iterations, eps 0.01, as VINS calls it);
* ``LM (intensity)``: core ``classical``, the LM solver on image intensity;
* ``OpenCV KLT``: core ``klt``, ``cv2.calcOpticalFlowPyrLK`` on the gray image as VINS calls it;
* ``OpenCV KLT + CLAHE``: the same on CLAHE-equalised images (VINS ``equalize: 1``: clip limit 3, 8x8
  tiles), the baseline a VINS user picks against changing light.

All of them get the same images, points and initial flow, and by default the tracker's deployed
pyramid depth (:func:`deployed_levels`: the LM solver's 4 levels; OpenCV's maxLevel 3, VINS's).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any, Protocol

import cv2
import numpy as np

from nsflow_ros.core.encoder import Encoder, IntensityEncoder, load_encoder, to_gray
from nsflow_ros.core.errors import CoreError
from nsflow_ros.core.methods import (
    KLT_WINDOW,
    DescriptorKLTMethod,
    TrackingMethod,
    make_method,
)
from nsflow_ros.core.methods import KLTMethod as CoreKLTMethod
from nsflow_ros.core.methods import LMMethod as CoreLMMethod
from nsflow_ros.core.pyramid import DescriptorPyramid, Smoothing
from nsflow_ros.core.solver import LMConfig, TrackResult
from nsflow_ros.core.tracker import TrackerSettings
from nsflow_ros.evaluation.errors import EvaluationError

__all__ = [
    "BASELINES",
    "CLASSICAL",
    "KLT",
    "KLT_CLAHE",
    "METHOD_ORDER",
    "NSFLOW",
    "NSFLOW_LK",
    "EvalMethod",
    "KLTMethod",
    "LMMethod",
    "PairMethod",
    "PairResult",
    "default_methods",
    "deployed_levels",
    "deployed_lm",
]

NSFLOW = "NSFlow"
NSFLOW_LK = "NSFlow + OpenCV LK"
CLASSICAL = "LM (intensity)"
KLT = "OpenCV KLT"
KLT_CLAHE = "OpenCV KLT + CLAHE"
METHOD_ORDER = (NSFLOW, NSFLOW_LK, CLASSICAL, KLT, KLT_CLAHE)
"""Every evaluated method's label, in table order (the learned descriptors first)."""
BASELINES = (CLASSICAL, KLT, KLT_CLAHE)
"""The classical baselines (NSFlow + OpenCV LK uses the learned descriptors: not a baseline)."""

# VINS-Mono's equalisation (feature_tracker.cpp, equalize: 1), as the tracker applies it.
CLAHE_CLIP = 3.0
CLAHE_TILES = (8, 8)


def deployed_lm() -> LMConfig:
    """The LM solver settings the tracker deploys (``TrackerSettings().lm``: 4 levels, margin 1)."""
    return TrackerSettings().lm


def deployed_levels() -> int:
    """Pyramid levels the tracker deploys: the LM solver's, and OpenCV's maxLevel 3 + 1 (VINS)."""
    return deployed_lm().levels


@dataclass(frozen=True)
class PairResult:
    """Flow of N points from image 1 to image 2.

    Attributes:
        flow: (N, 2) float64, new position = points + flow (meaningless where status is False).
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


class EvalMethod:
    """A core tracking method under an evaluation label, at a given pyramid depth.

    Args:
        name: label in tables and plots.
        core: the tracking method (:func:`nsflow_ros.core.methods.make_method` or one of its classes).
        levels: pyramid levels of every solve (OpenCV ``maxLevel`` = levels - 1).
        equalize: CLAHE the gray image first, as the tracker does with ``equalize`` on.
    """

    def __init__(self, name: str, core: TrackingMethod, levels: int, *, equalize: bool = False) -> None:
        if levels < 1:
            raise EvaluationError(f"levels must be >= 1, got {levels}")
        self.name = name
        self.core = core
        self.levels = int(levels)
        self.equalize = bool(equalize)
        self._clahe = cv2.createCLAHE(clipLimit=CLAHE_CLIP, tileGridSize=CLAHE_TILES) if equalize else None

    @property
    def encoder(self) -> Encoder | None:
        """The core method's descriptor encoder (None for OpenCV's KLT on the gray image)."""
        return self.core.encoder

    @property
    def tracker_overrides(self) -> dict[str, Any]:
        """The :class:`~nsflow_ros.core.tracker.TrackerSettings` fields that make the tracker run this."""
        return {"method": self.core.name, "equalize": self.equalize}

    def prepare(self, image: np.ndarray) -> Any:
        """The image's representation (the core method's ``prepare``, as the tracker calls it).

        Raises:
            EvaluationError: a bad image or an encoder that fails.
        """
        try:
            gray = to_gray(image)
            if self._clahe is not None:
                gray = self._clahe.apply(gray)
                return self.core.prepare(gray, gray)
            return self.core.prepare(image, gray)
        except CoreError as err:
            raise EvaluationError(f"{self.name}: {err}") from err

    def track_frames(
        self, frame1: Any, frame2: Any, points: np.ndarray, flow0: np.ndarray | None = None,
        levels: int | None = None,
    ) -> PairResult:
        """Track on representations from :meth:`prepare` (the core method's ``track_pair``).

        Args:
            frame1, frame2: representations of the two images.
            points: (N, 2) points in image 1.
            flow0: (N, 2) initial flow; None = zero.
            levels: pyramid levels of this solve, at most :attr:`levels` (an LM pyramid is built that
                deep; the solver uses its first levels, and fewer on images too small for them);
                None = :attr:`levels`.

        Returns:
            the flow and status.
        """
        pts, flow0 = _check_points(points, flow0)
        lev = self.levels if levels is None else int(levels)
        if not 1 <= lev <= self.levels:
            raise EvaluationError(f"{self.name}: levels must be in 1..{self.levels}, got {lev}")
        if len(pts) == 0:
            return PairResult(np.zeros((0, 2)), np.zeros(0, bool))
        start = None if flow0 is None else pts + flow0
        try:
            new, status = self.core.track_pair(frame1, frame2, pts, start, lev)
        except CoreError as err:
            raise EvaluationError(f"{self.name}: {err}") from err
        return PairResult(new - pts, np.asarray(status, bool))

    def track(
        self, image1: np.ndarray, image2: np.ndarray, points: np.ndarray, flow0: np.ndarray | None = None
    ) -> PairResult:
        """Track ``points`` of image 1 into image 2 from ``flow0`` (None = zero) at :attr:`levels`."""
        return self.track_frames(self.prepare(image1), self.prepare(image2), points, flow0)


class LMMethod(EvalMethod):
    """The paper's LM solver on an encoder's descriptor pyramid (core ``nsflow`` / ``classical``).

    Args:
        name: label in tables and plots.
        encoder: any :class:`~nsflow_ros.core.Encoder`; an :class:`IntensityEncoder` makes the core
            ``classical`` method, anything else ``nsflow``.
        config: solver settings (its ``levels`` is the pyramid depth); None = :func:`deployed_lm`.
    """

    core: CoreLMMethod

    def __init__(self, name: str, encoder: Encoder, config: LMConfig | None = None) -> None:
        cfg = config or deployed_lm()
        key = "classical" if isinstance(encoder, IntensityEncoder) else "nsflow"
        try:
            core = make_method(key, lm=cfg, encoder=encoder)
        except CoreError as err:
            raise EvaluationError(f"{name}: {err}") from err
        super().__init__(name, core, cfg.levels)

    @property
    def config(self) -> LMConfig:
        """The solver settings of the core method."""
        return self.core.lm

    def run(
        self, frame1: DescriptorPyramid, frame2: DescriptorPyramid, points: np.ndarray,
        flow0: np.ndarray | None = None, *, config: LMConfig | None = None, record: bool = False,
    ) -> TrackResult:
        """The solver's full result (core ``run``); ``record`` keeps the per-iteration history.

        Args:
            frame1, frame2: pyramids from :meth:`prepare`.
            points: (N, 2) points in image 1.
            flow0: (N, 2) initial flow; None = zero.
            config: solver settings for this call; None = :attr:`config`.
            record: keep the history.
        """
        pts, flow0 = _check_points(points, flow0)
        try:
            return self.core.run(frame1, frame2, pts, flow0, config, record=record)
        except CoreError as err:
            raise EvaluationError(f"{self.name}: {err}") from err


class KLTMethod(EvalMethod):
    """OpenCV's pyramidal LK with VINS's settings (core ``klt``, or ``nsflow_lk`` with an encoder).

    Args:
        levels: pyramid levels (OpenCV ``maxLevel`` = levels - 1); None = :func:`deployed_levels`.
        window: window side in pixels (VINS: 21).
        max_iterations: iteration limit per level (VINS: 30).
        eps: OpenCV's step-size stop test (VINS: 0.01).
        encoder: track this encoder's descriptors quantised to uint8 (core ``nsflow_lk``) instead of the
            gray image (core ``klt``).
        equalize: CLAHE the gray image first (VINS ``equalize: 1``).
        name: label; None = ``OpenCV KLT`` / ``OpenCV KLT + CLAHE`` / ``NSFlow + OpenCV LK``.
    """

    def __init__(
        self, levels: int | None = None, window: int = KLT_WINDOW[0], max_iterations: int = 30,
        eps: float = 0.01, *, encoder: Encoder | None = None, equalize: bool = False, name: str | None = None,
    ) -> None:
        if max_iterations < 1:
            raise EvaluationError(f"max_iterations must be >= 1, got {max_iterations}")
        core: CoreKLTMethod
        if encoder is None:
            core = CoreKLTMethod(window, max_iterations, eps)
            label = KLT_CLAHE if equalize else KLT
        else:
            core = DescriptorKLTMethod(encoder, window, max_iterations, eps)
            label = NSFLOW_LK if not equalize else f"{NSFLOW_LK} + CLAHE"
        super().__init__(name or label, core, deployed_levels() if levels is None else levels,
                         equalize=equalize)  # fmt: skip
        self.window = window
        self.max_iterations = max_iterations
        self.eps = eps

    def with_iterations(self, max_iterations: int) -> KLTMethod:
        """A copy limited to ``max_iterations`` per level (convergence curves); same representation."""
        return KLTMethod(
            self.levels, self.window, max_iterations, self.eps, encoder=self.encoder, equalize=self.equalize,
            name=self.name,
        )


def default_methods(
    model: str | None = None, levels: int | None = None, threads: int | None = None
) -> list[EvalMethod]:
    """Every evaluated method (:data:`METHOD_ORDER`), all at ``levels`` (None = the deployed depth).

    Args:
        model: NSFlow ONNX encoder (None = the shipped one); NSFlow + OpenCV LK uses the same, without
            its declared smoothing (as the tracker's ``nsflow_lk``).
        levels: pyramid levels of every method; None = :func:`deployed_levels`.
        threads: encoder threads (None = all usable cores).

    Returns:
        NSFlow, NSFlow + OpenCV LK, LM (intensity), OpenCV KLT, OpenCV KLT + CLAHE.

    Raises:
        EvaluationError: bad levels, or the model cannot be loaded.
    """
    lev = deployed_levels() if levels is None else levels
    if lev < 1:
        raise EvaluationError(f"levels must be >= 1, got {lev}")
    cfg = replace(deployed_lm(), levels=lev)
    try:
        encoder = load_encoder(model, threads=threads)
        unsmoothed = load_encoder(model, threads=threads, smoothing=Smoothing())  # as nsflow_lk loads it
    except CoreError as err:
        raise EvaluationError(str(err)) from err
    return [
        LMMethod(NSFLOW, encoder, cfg),
        KLTMethod(lev, encoder=unsmoothed),
        LMMethod(CLASSICAL, IntensityEncoder(), cfg),
        KLTMethod(lev),
        KLTMethod(lev, equalize=True),
    ]
