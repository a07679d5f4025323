"""Tracking methods: one object per method, chosen once from :data:`METHODS`, then called.

A method knows two things: how it represents a frame (:meth:`TrackingMethod.prepare`: a descriptor
pyramid, the gray image, a uint8 descriptor pyramid) and, for each kind of solve the VINS tracker runs
(:class:`SolveKind`: forward, flow-back, left -> right, right -> left), which start, which levels and
which points it uses (:meth:`TrackingMethod.solve`). The tracker's routine is method-blind: it asks for
a solve and its check, and applies the same thresholds and border rule whatever the method. Each method
wraps its solver in exactly one place (:meth:`TrackingMethod.track_pair`), which the tracker, the
evaluation suite and the benchmark all call, so what is deployed, evaluated and benchmarked is the same
code.

The methods:

* ``nsflow``: the learned ONNX encoder's descriptor pyramid through the paper's LM solver (Algorithm 1,
  :func:`nsflow_ros.core.solver.track`);
* ``classical``: the same solver on image intensity;
* ``klt``: OpenCV's ``calcOpticalFlowPyrLK`` on the gray image, called exactly as VINS-Fusion calls it (the
  baseline);
* ``nsflow_lk``: the learned descriptors quantised to uint8 and tracked by OpenCV's pyramidal LK with
  VINS-Fusion's arguments (the first author's own deployment path, LET-NET2 style).

Known starts (LM methods): a check (flow-back, right -> left) starts at the point it must return to, and
a forward or stereo solve may start from a per-point prior (the point's previous flow, the id's previous
disparity). A solve from a trusted start needs fewer pyramid levels; points without one (a feature new
since the last frame) start from the median of the others' flows on one level more
(``LMMethod.fill_levels``), all in the same call (:func:`nsflow_ros.core.solver.track` ``first_level``),
with the fine window on every level. Only a solve where no point has a prior runs from zero flow on the
whole pyramid, with the solver's coarse window. The VINS-Fusion-exact ``klt`` baseline ignores priors,
as VINS does.
"""

from __future__ import annotations

import enum
from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any, ClassVar

import cv2
import numpy as np

from nsflow_ros.core.encoder import Encoder, IntensityEncoder, load_encoder
from nsflow_ros.core.errors import CoreError
from nsflow_ros.core.pyramid import DescriptorPyramid, Smoothing, build_pyramid
from nsflow_ros.core.solver import Jacobian, LMConfig, TrackResult, track

__all__ = [
    "KLT_CRITERIA",
    "KLT_GUIDED_MAX_LEVEL",
    "KLT_MAX_LEVEL",
    "KLT_WINDOW",
    "METHODS",
    "DescriptorKLTMethod",
    "KLTMethod",
    "LMMethod",
    "SolveKind",
    "TrackingMethod",
    "klt_track",
    "make_method",
    "method_encoder",
    "pyramid_smoothing",
    "quantise_descriptors",
]

# VINS-Fusion's calcOpticalFlowPyrLK arguments (feature_tracker.cpp): window, full-pyramid maxLevel, the
# maxLevel of the calls that start from a given flow (prediction, flow-back), and the stop criteria.
KLT_WINDOW = (21, 21)
KLT_MAX_LEVEL = 3
KLT_GUIDED_MAX_LEVEL = 1
KLT_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 30, 0.01)


class SolveKind(enum.Enum):
    """The solves of one VINS tracker frame.

    FORWARD tracks the previous frame's points into the current frame; FLOW_BACK tracks the result back
    to check it; STEREO tracks left points into the right image; STEREO_BACK tracks those back.
    """

    FORWARD = "forward"
    FLOW_BACK = "flow_back"
    STEREO = "stereo"
    STEREO_BACK = "stereo_back"

    @property
    def is_check(self) -> bool:
        """A check starts next to its answer: the point the forward solve came from."""
        return self in (SolveKind.FLOW_BACK, SolveKind.STEREO_BACK)


def klt_track(
    image1: np.ndarray,
    image2: np.ndarray,
    pts: np.ndarray,
    start: np.ndarray | None = None,
    max_level: int = KLT_MAX_LEVEL,
    *,
    window: tuple[int, int] = KLT_WINDOW,
    criteria: tuple[int, int, float] = KLT_CRITERIA,
) -> tuple[np.ndarray, np.ndarray]:
    """One ``cv2.calcOpticalFlowPyrLK`` call (VINS-Fusion's window and criteria by default).

    The project's only call of OpenCV's LK: the ``klt`` and ``nsflow_lk`` methods, the evaluation and the
    benchmark all go through it.

    Args:
        image1: uint8 image (1-4 channels) the points lie in.
        image2: image to track them into.
        pts: points in image 1.
        start: initial positions in image 2 (``OPTFLOW_USE_INITIAL_FLOW``, as VINS's predicted and
            flow-back calls); None starts from ``pts``.
        max_level: OpenCV ``maxLevel`` (VINS: 3, or 1 when starting from ``start``).
        window: window size (VINS: 21x21).
        criteria: stop criteria (VINS: COUNT|EPS, 30, 0.01).

    Returns:
        (positions in image 2, OpenCV's status); lost points keep their start position.

    Shape:
        pts, start: (N, 2). Returns (N, 2) float64 and (N,) bool.
    """
    n = pts.shape[0]
    if n == 0:
        return np.zeros((0, 2)), np.zeros(0, bool)
    p1 = np.ascontiguousarray(pts, dtype=np.float32).reshape(-1, 1, 2)
    flags, p2 = 0, None
    if start is not None:
        p2 = np.ascontiguousarray(start, dtype=np.float32).reshape(-1, 1, 2).copy()
        flags = cv2.OPTFLOW_USE_INITIAL_FLOW
    new, status, _ = cv2.calcOpticalFlowPyrLK(
        image1, image2, p1, p2, winSize=window, maxLevel=max_level, criteria=criteria, flags=flags
    )
    out = new.reshape(-1, 2).astype(np.float64)
    ok = status.reshape(-1).astype(bool) & np.isfinite(out).all(axis=1)
    return np.where(ok[:, None], out, pts), ok


def quantise_descriptors(desc: np.ndarray) -> np.ndarray:
    """Descriptors in [0, 1] as uint8 (x 255, rounded, clipped): the input OpenCV's LK takes.

    Shape:
        desc: (H, W, C) float, C <= 4. Returns (H, W, C) uint8.
    """
    if desc.ndim != 3 or not 1 <= desc.shape[2] <= 4:
        raise CoreError(f"OpenCV's LK takes 1-4 descriptor channels, got shape {desc.shape}")
    return cv2.convertScaleAbs(desc, alpha=255.0)


class TrackingMethod(ABC):
    """A tracking method: a frame representation plus a rule per :class:`SolveKind`.

    Subclasses set ``name`` and implement :meth:`prepare`, :meth:`track_pair` and :meth:`solve`.
    """

    name: ClassVar[str]
    encoder: Encoder | None = None

    def encoder_input(self, image: np.ndarray, gray: np.ndarray) -> np.ndarray:
        """What the encoder gets: the gray image for gray encoders (already made), else the image."""
        if self.encoder is None or getattr(self.encoder, "input_channels", 3) == 1:
            return gray
        return image

    @abstractmethod
    def prepare(self, image: np.ndarray, gray: np.ndarray) -> Any:
        """The frame's representation (computed once per image, used by every solve it takes part in).

        Args:
            image: the image as received (uint8 gray or BGR); the CLAHE'd gray when equalising.
            gray: its gray version (CLAHE'd when equalising).
        """

    @abstractmethod
    def track_pair(
        self, frame1: Any, frame2: Any, pts: np.ndarray, start: np.ndarray | None = None,
        levels: int | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """The method's one solver call: ``pts`` of frame 1 into frame 2.

        Args:
            frame1, frame2: representations from :meth:`prepare`.
            pts: (N, 2) points in frame 1.
            start: (N, 2) initial positions in frame 2; None = ``pts``.
            levels: pyramid levels; None = the method's full pyramid.

        Returns:
            (N, 2) finite positions (the start where lost) and (N,) status.
        """

    @abstractmethod
    def solve(
        self, kind: SolveKind, frame1: Any, frame2: Any, pts: np.ndarray,
        start: np.ndarray | None = None, prior: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """One solve of the tracker: the method picks start, levels and points for ``kind``.

        Args:
            kind: which solve.
            frame1, frame2: representations from :meth:`prepare`.
            pts: (N, 2) points in frame 1.
            start: (N, 2) trusted start in frame 2: the IMU prediction (FORWARD) or the point the check
                must return to (FLOW_BACK, STEREO_BACK); None = none.
            prior: (N, 2) untrusted guess in frame 2, NaN where there is none: the point moved as in
                the previous frame (FORWARD), the id's previous disparity (STEREO).

        Returns:
            (N, 2) finite positions and (N,) status.
        """


def _fill_prior(pts: np.ndarray, prior: np.ndarray, known: np.ndarray) -> np.ndarray:
    """Flows from a prior known where ``known`` (at least one point); the others take the median flow."""
    flow = np.empty((pts.shape[0], 2))
    flow[known] = prior[known] - pts[known]
    flow[~known] = np.median(flow[known], axis=0)
    return flow


def pyramid_smoothing(encoder: Encoder) -> Smoothing | None:
    """What an LM method smooths in ``encoder``'s pyramid: the coarse part of the encoder's declared
    smoothing (the encoder has applied the fine part to its map already); None when there is none."""
    coarse = encoder.smoothing.coarse
    return Smoothing(coarse=coarse) if coarse > 0 else None


class LMMethod(TrackingMethod):
    """An encoder's descriptor pyramid through the paper's LM solver (``nsflow``, ``classical``).

    Args:
        name: registry name.
        encoder: the descriptor encoder.
        lm: solver settings; ``lm.levels`` is the full pyramid.
        prior_levels: levels for points with a prior (previous flow / disparity); 0 = ignore priors.
        check_levels: levels of a check solve started at its answer; 0 = the full pyramid. Two levels
            with the residual test catch the occluded points that the full-pyramid check catches (the
            occlusion test), at half its cost.
        predicted_levels: levels of a forward solve from the IMU prediction (VINS: one level).
        fill_levels: levels for the points of a prior solve that have no prior of their own (they
            start from the median of the others' flows); 0 = the full pyramid. The coarsest level
            does more harm than good from a start that close: on the 752x480 sample sequence, 3
            levels instead of 4 cut the stereo matches more than 1 px off from 2.2 % to 1.0 % and
            the stereo frame time by 4 %. Such a solve (every point near its start) also keeps the
            fine window on every level: ``lm.coarse_window`` serves solves from zero flow, and here it
            cost 2-3 % of the frame for no better tracks.
        max_residual: the residual test of forward and stereo solves: a point is lost when its final
            residual energy exceeds this fraction of its template's contrast energy (sum of squared
            deviations from the window mean); inf = no test. See :meth:`residual_ratio`. On the 752x480
            sample sequence true tracks have ratios of 0.01-0.1 (95 % below 0.06), points tracked onto an
            occluder 0.3-10.
        check_iterations: K_max of check solves; 0 = the solver's (checks start at their answer and
            stop in 2-3 iterations, so a cap changes little: measured 1 % of the frame time at 4-6).
        check_jacobian: the Jacobian of check solves, whatever ``lm.jacobian`` is. The paper's forward
            one by default: ESM's step treats the two frames alike, so where an ESM solve stalled off
            the answer (a step that LM keeps rejecting) an ESM check started there stalls too and
            "returns" to the start; a forward check slides to the nearest minimum instead. With ESM
            forward solves on the 752x480 sample sequence, carried features more than 1 px off fell
            from 0.72 % (ESM checks) to 0.47 % (forward checks; forward everywhere: 0.39 %, ``klt``
            0.54 %), at the same speed.
        check_eps: the stop tolerance of check solves, whatever ``lm.eps`` is. A check starts at its
            answer, and a loose stop test lets it stop there: with the tracker's looser 0.03 on every
            solve, a point tracked onto an occluder passed its flow-back check on a synthetic sequence
            where 0.01 caught it.

    The pyramid's coarser levels are smoothed as the encoder declares (``encoder.smoothing.coarse``; its
    ``fine`` part the encoder has applied already): the shipped NSFlow model declares it, intensity not.
    """

    def __init__(
        self, name: str, encoder: Encoder, lm: LMConfig, *, prior_levels: int = 2, check_levels: int = 2,
        predicted_levels: int = 1, fill_levels: int = 3, max_residual: float = 0.5,
        check_iterations: int = 0, check_jacobian: Jacobian = Jacobian.FORWARD, check_eps: float = 0.01,
    ) -> None:
        self.name = name  # type: ignore[misc]
        self.encoder = encoder
        self.lm = lm
        for label, v in (("prior_levels", prior_levels), ("check_levels", check_levels),
                         ("fill_levels", fill_levels)):
            if v < 0:
                raise CoreError(f"{label} must be >= 0, got {v}")
        if predicted_levels < 1:
            raise CoreError(f"predicted_levels must be >= 1, got {predicted_levels}")
        self.prior_levels = prior_levels
        self.check_levels = check_levels
        self.predicted_levels = predicted_levels
        self.fill_levels = fill_levels
        if not max_residual > 0:
            raise CoreError(f"max_residual must be > 0, got {max_residual}")
        self.max_residual = max_residual
        if check_iterations < 0:
            raise CoreError(f"check_iterations must be >= 0, got {check_iterations}")
        self.check_iterations = check_iterations
        if not isinstance(check_jacobian, Jacobian):
            raise CoreError(f"check_jacobian must be a Jacobian, got {check_jacobian!r}")
        self.check_jacobian = check_jacobian
        if not check_eps > 0:
            raise CoreError(f"check_eps must be > 0, got {check_eps}")
        self.check_eps = check_eps
        self.pyramid_smoothing = pyramid_smoothing(encoder)

    @staticmethod
    def residual_ratio(result: TrackResult) -> np.ndarray:
        """Residual energy 2 S over the template's contrast energy, per point (0 = a perfect match).

        A point tracked onto something else (an occluder, a repeated structure) keeps a residual of the
        order of its template's contrast (ratio ~1); a true match leaves image noise (~0.01-0.1).
        """
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.where(result.contrast > 0, 2.0 * result.cost / result.contrast, np.inf)

    def prepare(self, image: np.ndarray, gray: np.ndarray) -> DescriptorPyramid:
        desc = self.encoder(self.encoder_input(image, gray))
        return build_pyramid(desc, self.lm.levels, self.pyramid_smoothing)

    def run(
        self, frame1: DescriptorPyramid, frame2: DescriptorPyramid, pts: np.ndarray,
        flow0: np.ndarray | None = None, config: LMConfig | None = None, *, record: bool = False,
        first_level: np.ndarray | None = None,
    ) -> TrackResult:
        """The solver call itself (:func:`~nsflow_ros.core.solver.track`), with its full result."""
        return track(frame1, frame2, pts, flow0, config or self.lm, record=record, first_level=first_level)

    def track_pair(
        self, frame1: DescriptorPyramid, frame2: DescriptorPyramid, pts: np.ndarray,
        start: np.ndarray | None = None, levels: int | None = None, first_level: np.ndarray | None = None,
        *, residual_test: bool = False, max_iterations: int | None = None, jacobian: Jacobian | None = None,
        eps: float | None = None, coarse_window: bool = True,
    ) -> tuple[np.ndarray, np.ndarray]:
        cfg = replace(self.lm, levels=levels or self.lm.levels,
                      max_iterations=max_iterations or self.lm.max_iterations,
                      jacobian=jacobian or self.lm.jacobian, eps=eps or self.lm.eps,
                      coarse_window=self.lm.coarse_window if coarse_window else None)
        flow0 = None if start is None else start - pts
        res = self.run(frame1, frame2, pts, flow0, cfg, first_level=first_level)
        status = res.status
        if residual_test and np.isfinite(self.max_residual) and status.any():
            status = status & (self.residual_ratio(res) <= self.max_residual)
        return np.where(np.isfinite(res.flow), pts + res.flow, pts), status

    def solve(
        self, kind: SolveKind, frame1: DescriptorPyramid, frame2: DescriptorPyramid, pts: np.ndarray,
        start: np.ndarray | None = None, prior: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        if kind.is_check:
            # Started at its answer; the full pyramid only when asked (check_levels 0).
            return self.track_pair(frame1, frame2, pts, start, self.check_levels or None,
                                   max_iterations=self.check_iterations or None, jacobian=self.check_jacobian,
                                   eps=self.check_eps)
        if start is not None:  # the IMU prediction, trusted as VINS trusts it
            usable = np.isfinite(start).all(axis=1)
            return self.track_pair(
                frame1, frame2, pts, np.where(usable[:, None], start, pts), self.predicted_levels,
                residual_test=True,
            )
        known = np.zeros(len(pts), bool)
        if self.prior_levels > 0 and prior is not None:
            known = np.isfinite(prior).all(axis=1)
        if prior is None or not known.any():  # no prior, or the median of nothing: all from zero flow
            return self.track_pair(frame1, frame2, pts, residual_test=True)
        flow0 = _fill_prior(pts, prior, known)
        first = np.where(known, self.prior_levels, self.fill_levels or self.lm.levels).astype(np.int64) - 1
        # Every point starts near its answer: the coarse window, there for starts far off, is not needed.
        return self.track_pair(frame1, frame2, pts, pts + flow0, first_level=first, residual_test=True,
                               coarse_window=False)


class KLTMethod(TrackingMethod):
    """OpenCV's pyramidal LK on the gray image, call for call as VINS-Fusion's ``trackImage`` (``klt``).

    Args:
        window: window side (VINS: 21).
        max_iterations, eps: stop criteria (VINS: 30, 0.01).
    """

    name = "klt"

    def __init__(self, window: int = KLT_WINDOW[0], max_iterations: int = 30, eps: float = 0.01) -> None:
        self.window = (window, window)
        self.criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, max_iterations, eps)

    def prepare(self, image: np.ndarray, gray: np.ndarray) -> Any:
        return gray  # VINS hands OpenCV the images; OpenCV builds its pyramids per call

    def track_pair(
        self, frame1: Any, frame2: Any, pts: np.ndarray, start: np.ndarray | None = None,
        levels: int | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        max_level = KLT_MAX_LEVEL if levels is None else levels - 1
        return klt_track(frame1, frame2, pts, start, max_level, window=self.window, criteria=self.criteria)

    def solve(
        self, kind: SolveKind, frame1: Any, frame2: Any, pts: np.ndarray,
        start: np.ndarray | None = None, prior: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        # VINS-Fusion: the predicted forward call and the flow-back start at the given positions with
        # maxLevel 1; the plain forward call, both stereo calls use maxLevel 3 from the point itself.
        if kind in (SolveKind.FORWARD, SolveKind.FLOW_BACK) and start is not None:
            usable = np.isfinite(start).all(axis=1)
            guided = np.where(usable[:, None], start, pts)
            return self.track_pair(frame1, frame2, pts, guided, KLT_GUIDED_MAX_LEVEL + 1)
        return self.track_pair(frame1, frame2, pts)


class DescriptorKLTMethod(KLTMethod):
    """The learned descriptors as uint8, tracked by OpenCV's pyramidal LK with VINS's calls (``nsflow_lk``).

    Each frame is encoded and quantised once. OpenCV builds its pyramids inside every call, as for
    ``klt`` (its Python binding takes no pre-built pyramid). The maps are not smoothed: a model's declared
    smoothing is chosen for the LM solver's 11x11 window, and on OpenCV's 21x21 one it cost more under
    light than it gave (evaluation: trackable region under a lighting change 91.2 -> 86.5 %, illumination
    pairs 99.2 -> 98.7 %; demo tracks 6-8 % shorter).

    Args:
        encoder: the descriptor encoder (1-4 channels in [0, 1]), without smoothing (``load_encoder(...,
            smoothing=Smoothing())``; the registry loads it so).
        window, max_iterations, eps: as :class:`KLTMethod`.

    Raises:
        CoreError: an encoder that smooths its maps.
    """

    name = "nsflow_lk"

    def __init__(
        self, encoder: Encoder, window: int = KLT_WINDOW[0], max_iterations: int = 30, eps: float = 0.01
    ) -> None:
        super().__init__(window, max_iterations, eps)
        if encoder.smoothing.fine > 0:
            raise CoreError(
                f"nsflow_lk tracks unsmoothed descriptors, but the encoder smooths them "
                f"({encoder.smoothing}); load it with smoothing=Smoothing()"
            )
        self.encoder = encoder

    def prepare(self, image: np.ndarray, gray: np.ndarray) -> np.ndarray:
        return quantise_descriptors(self.encoder(self.encoder_input(image, gray)))


MethodFactory = Callable[..., TrackingMethod]


@dataclass(frozen=True)
class _Entry:
    factory: MethodFactory
    learned: bool  # needs the ONNX encoder
    summary: str
    smoothed: bool = True  # applies the model's declared smoothing (the LM methods do)


def _nsflow(encoder: Encoder, lm: LMConfig) -> TrackingMethod:
    return LMMethod("nsflow", encoder, lm)


def _classical(encoder: Encoder, lm: LMConfig) -> TrackingMethod:
    return LMMethod("classical", encoder, lm)


def _klt(encoder: Encoder | None, lm: LMConfig) -> TrackingMethod:
    return KLTMethod()


def _nsflow_lk(encoder: Encoder, lm: LMConfig) -> TrackingMethod:
    return DescriptorKLTMethod(encoder)


METHODS: dict[str, _Entry] = {
    "nsflow": _Entry(_nsflow, True, "learned encoder + the paper's LM solver (NumPy)"),
    "classical": _Entry(_classical, False, "image intensity + the same LM solver"),
    "klt": _Entry(_klt, False, "OpenCV calcOpticalFlowPyrLK on the gray image, as VINS-Fusion calls it"),
    "nsflow_lk": _Entry(
        _nsflow_lk, True, "learned encoder as uint8 + OpenCV's pyramidal LK (VINS's calls)", smoothed=False
    ),
}
"""The registry of tracking methods: name -> factory, whether it needs the learned encoder, summary."""


def make_method(
    name: str,
    *,
    lm: LMConfig | None = None,
    encoder: Encoder | None = None,
    model_path: str | None = None,
    threads: int | None = None,
) -> TrackingMethod:
    """Build the tracking method ``name`` from :data:`METHODS`.

    Args:
        name: a key of :data:`METHODS`.
        lm: LM solver settings (LM methods); None = ``LMConfig(levels=4)``, the tracker's.
        encoder: encoder to use instead of the method's own (tests, benchmarks); not for ``klt``.
        model_path: ONNX encoder for the learned methods; None = the shipped model.
        threads: encoder threads; None = all usable cores.

    Returns:
        the method.

    Raises:
        CoreError: unknown name, or an encoder given to ``klt``.
        EncoderError: the learned model cannot be loaded.
    """
    entry = _entry(name)
    if name == "klt" and encoder is not None:
        raise CoreError("method 'klt' tracks the gray image with OpenCV; an encoder cannot be given")
    if encoder is None:
        encoder = method_encoder(name, model_path, threads)
    return entry.factory(encoder, lm or LMConfig(levels=4))


def _entry(name: str) -> _Entry:
    entry = METHODS.get(name)
    if entry is None:
        raise CoreError(f"method must be one of {tuple(METHODS)}, got {name!r}")
    return entry


def method_encoder(name: str, model_path: str | None = None, threads: int | None = None) -> Encoder | None:
    """The encoder :func:`make_method` gives method ``name`` when none is passed.

    The learned model for ``nsflow`` (smoothed as the model declares) and ``nsflow_lk`` (unsmoothed),
    intensity for ``classical``, None for ``klt``.

    Raises:
        CoreError: unknown name.
        EncoderError: the learned model cannot be loaded.
    """
    entry = _entry(name)
    if name == "klt":
        return None
    if not entry.learned:
        return IntensityEncoder()
    smoothing = None if entry.smoothed else Smoothing()  # None: as the model declares
    return load_encoder(model_path, threads=threads, smoothing=smoothing)
