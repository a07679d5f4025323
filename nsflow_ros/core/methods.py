"""Tracking methods: one registry, :data:`METHODS`, whose entries are each method's whole configuration.

A :class:`MethodSpec` says where a method's descriptors come from and how it solves (LM settings and
:class:`SolvePolicy`, or OpenCV's LK arguments); :func:`make_method` builds the method from it, so the
tracker, the evaluation and the benchmarks run the same code with the same settings.

* ``nsflow``: the learned ONNX encoder's descriptor pyramid through the LM solver;
* ``classical``: the same solver on image intensity;
* ``klt``: OpenCV's ``calcOpticalFlowPyrLK`` on the gray image, called as VINS-Fusion calls it (the baseline);
* ``nsflow_lk``: the learned descriptors quantised to uint8 through the same OpenCV calls.
"""

from __future__ import annotations

import enum
import functools
from abc import ABC, abstractmethod
from collections.abc import Mapping
from dataclasses import dataclass, replace
from types import MappingProxyType
from typing import Any

import cv2
import numpy as np

from nsflow_ros.core.checks import CovarianceCheck
from nsflow_ros.core.covariance import (
    CovarianceScale,
    err_covariance,
    lm_covariance,
    read_scale,
    template_hessian,
)
from nsflow_ros.core.encoder import Encoder, ExecutionProviders, IntensityEncoder, load_encoder
from nsflow_ros.core.errors import CoreError, UnsupportedEncoderError
from nsflow_ros.core.pyramid import DescriptorPyramid, Smoothing, build_pyramid
from nsflow_ros.core.refine import (
    IntensityRefinement,
    StepTemplate,
    blurred_level,
    gray_level,
    refine,
    step_template,
)
from nsflow_ros.core.solver import Jacobian, LMConfig, TrackResult, track

__all__ = [
    "BASELINE",
    "CHECK_LEVELS",
    "CLAHE",
    "COVARIANCE_SCALES",
    "DEPLOYED_LM",
    "KLT_CRITERIA",
    "KLT_GUIDED_MAX_LEVEL",
    "KLT_MAX_LEVEL",
    "KLT_WINDOW",
    "METHODS",
    "PAPER_LM",
    "PREDICTED_LEVELS",
    "Clahe",
    "DescriptorKLTMethod",
    "EncoderSource",
    "KLTConfig",
    "KLTMethod",
    "LMMethod",
    "MethodSpec",
    "SolveKind",
    "SolvePolicy",
    "Solver",
    "TrackingMethod",
    "declared_residual",
    "klt_track",
    "klt_track_error",
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

CHECK_LEVELS = 2
"""Levels of an LM check solve: two catch the occluded points a full-pyramid check does, at half its cost."""
PREDICTED_LEVELS = 1
"""Levels of an LM forward solve from the IMU prediction: the fine level suffices from so close a start."""


@dataclass(frozen=True)
class Clahe:
    """Contrast-limited histogram equalisation (clip limit, tile grid), applied when the tracker equalises."""

    clip: float = 3.0
    tiles: tuple[int, int] = (8, 8)

    def create(self) -> cv2.CLAHE:
        """An OpenCV CLAHE object with these parameters."""
        return cv2.createCLAHE(clipLimit=self.clip, tileGridSize=self.tiles)


CLAHE = Clahe()
"""VINS-Mono's equalisation (``equalize: 1``)."""

DEPLOYED_LM = LMConfig(
    levels=6, margin=1, tail_share=0.4, tail_passes=2, jacobian=Jacobian.ESM, eps=0.05, zero_mean=True,
    coarse_window=21, coarse_from=2,
)
"""The LM solver settings the tracker deploys; each difference from :data:`PAPER_LM` has a measured reason
(docs/design.md has the measurement behind each):

* ``levels`` 6: the learned map's coarse levels carry little (it is trained at one scale): from zero flow,
  4 levels lost flows of 30 px and more, which a 10 Hz camera in flight sees; only solves from zero flow
  start that high;
* ``margin`` 1: a point is kept until its window reaches past the edge, as OpenCV's LK allows;
* ``tail_share`` 0.4 after ``tail_passes`` 2: a level ends when only stragglers are left;
* ``jacobian`` ESM: a wider basin at a small cost;
* ``zero_mean``: a lighting change's offset between descriptor windows costs nothing;
* ``eps`` 0.05: pays back part of the zero-mean sums' cost at the same accuracy;
* ``coarse_window`` 21 from level ``coarse_from`` 2: a wider basin for solves from zero flow.
"""

PAPER_LM = LMConfig()
"""The paper's Algorithm 1 as written (the solver's defaults)."""


class Solver(enum.Enum):
    """Which LM configuration :func:`make_method` gives an LM method."""

    DEPLOYED = "deployed"
    """:data:`DEPLOYED_LM` and the default :class:`SolvePolicy`."""
    PAPER = "paper"
    """:data:`PAPER_LM` and :meth:`SolvePolicy.paper` (the tracker's checks and IMU prediction unchanged)."""


@dataclass(frozen=True)
class SolvePolicy:
    """How an LM method runs each kind of tracker solve (see :meth:`LMMethod.solve`).

    Attributes:
        prior_levels: levels for points with a prior (previous flow / disparity); 0 = ignore priors.
        fill_levels: levels for the points of a prior solve without a prior of their own (started from
            their neighbours' flows, ``fill_neighbours``); 0 = the full pyramid.
        fill_neighbours: such a point starts from the median flow of this many nearest points with a
            prior; 0 = of all of them. The flow varies across the image with depth and rotation: from
            the median of all, a new corner started 3.3 px off in the median and most ended at their
            first step (docs/design.md).
        stereo_levels: levels of a stereo solve without any prior (a first frame's matches); 0 = the full
            pyramid. A disparity is bounded by the baseline, and the levels a temporal solve from zero
            needs made the coarse alignment of a left / right pair under unequal light worse.
        max_residual: a forward or stereo solve loses a point whose :meth:`LMMethod.residual_ratio`
            exceeds this (true tracks: 0.01-0.1, tracks onto an occluder: 0.3-10); inf = no test.
        check_jacobian: the Jacobian of check solves: forward, because an ESM check started where an
            ESM solve stalled stalls there too and "returns".
        check_eps: the stop tolerance of check solves: a check starts at its answer, so a loose test
            would stop it there.

    Raises:
        CoreError: a negative level count, a residual bound <= 0, a non-:class:`Jacobian` or eps <= 0.
    """

    prior_levels: int = 2
    fill_levels: int = 3
    fill_neighbours: int = 5
    stereo_levels: int = 4
    max_residual: float = 0.5
    check_jacobian: Jacobian = Jacobian.FORWARD
    check_eps: float = 0.01

    def __post_init__(self) -> None:
        for label in ("prior_levels", "fill_levels", "fill_neighbours", "stereo_levels"):
            if getattr(self, label) < 0:
                raise CoreError(f"SolvePolicy.{label} must be >= 0, got {getattr(self, label)}")
        if not self.max_residual > 0:
            raise CoreError(f"SolvePolicy.max_residual must be > 0, got {self.max_residual}")
        if not isinstance(self.check_jacobian, Jacobian):
            raise CoreError(f"SolvePolicy.check_jacobian must be a Jacobian, got {self.check_jacobian!r}")
        if not self.check_eps > 0:
            raise CoreError(f"SolvePolicy.check_eps must be > 0, got {self.check_eps}")

    @classmethod
    def paper(cls) -> SolvePolicy:
        """Every solve from zero flow on the full pyramid, without the residual test (Algorithm 1)."""
        return cls(prior_levels=0, fill_levels=0, stereo_levels=0, max_residual=float("inf"))


@dataclass(frozen=True)
class KLTConfig:
    """OpenCV LK's window and stop criteria (VINS-Fusion's values by default).

    Raises:
        CoreError: a window that is not odd and >= 3, max_iterations < 1 or eps <= 0.
    """

    window: int = KLT_WINDOW[0]
    max_iterations: int = 30
    eps: float = 0.01

    def __post_init__(self) -> None:
        if self.window < 3 or self.window % 2 == 0:
            raise CoreError(f"KLTConfig.window must be odd and >= 3, got {self.window}")
        if self.max_iterations < 1:
            raise CoreError(f"KLTConfig.max_iterations must be >= 1, got {self.max_iterations}")
        if not self.eps > 0:
            raise CoreError(f"KLTConfig.eps must be > 0, got {self.eps}")

    @property
    def criteria(self) -> tuple[int, int, float]:
        """OpenCV's ``TermCriteria`` tuple."""
        return (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, self.max_iterations, self.eps)


class EncoderSource(enum.Enum):
    """Where a method's descriptors come from."""

    LEARNED = "learned"  # the ONNX encoder
    INTENSITY = "intensity"  # IntensityEncoder
    NONE = "none"  # OpenCV tracks the gray image


class SolveKind(enum.Enum):
    """The solves of one VINS tracker frame: previous -> current, left -> right, and each one's check back."""

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
    """:func:`klt_track_error` without OpenCV's ``err``: (positions in image 2, status)."""
    new, ok, _ = klt_track_error(image1, image2, pts, start, max_level, window=window, criteria=criteria)
    return new, ok


def klt_track_error(
    image1: np.ndarray,
    image2: np.ndarray,
    pts: np.ndarray,
    start: np.ndarray | None = None,
    max_level: int = KLT_MAX_LEVEL,
    *,
    window: tuple[int, int] = KLT_WINDOW,
    criteria: tuple[int, int, float] = KLT_CRITERIA,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One ``cv2.calcOpticalFlowPyrLK`` call (VINS-Fusion's arguments by default): the project's only one.

    Args:
        image1, image2: uint8 images (1-4 channels); ``pts`` lie in image 1.
        start: initial positions in image 2 (``OPTFLOW_USE_INITIAL_FLOW``); None starts from ``pts``.
        max_level, window, criteria: OpenCV's ``maxLevel``, ``winSize`` and ``criteria``.

    Returns:
        (positions in image 2, OpenCV's status, OpenCV's ``err``: the mean absolute window difference at
        the solution, 0 where lost); lost points keep their start position.

    Shape:
        pts, start: (N, 2). Returns (N, 2) float64, (N,) bool and (N,) float64.
    """
    n = pts.shape[0]
    if n == 0:
        return np.zeros((0, 2)), np.zeros(0, bool), np.zeros(0)
    p1 = np.ascontiguousarray(pts, dtype=np.float32).reshape(-1, 1, 2)
    flags, p2 = 0, None
    if start is not None:
        p2 = np.ascontiguousarray(start, dtype=np.float32).reshape(-1, 1, 2).copy()
        flags = cv2.OPTFLOW_USE_INITIAL_FLOW
    new, status, err = cv2.calcOpticalFlowPyrLK(
        image1, image2, p1, p2, winSize=window, maxLevel=max_level, criteria=criteria, flags=flags
    )
    out = new.reshape(-1, 2).astype(np.float64)
    with np.errstate(invalid="ignore"):  # OpenCV leaves a lost point's err unset (may be a NaN pattern)
        err = err.reshape(-1).astype(np.float64)
    ok = status.reshape(-1).astype(bool) & np.isfinite(out).all(axis=1)  # the err leaves the track alone
    return np.where(ok[:, None], out, pts), ok, np.where(ok & np.isfinite(err), err, 0.0)


def quantise_descriptors(desc: np.ndarray) -> np.ndarray:
    """Descriptors in [0, 1] as uint8 (x 255, rounded, clipped): the input OpenCV's LK takes.

    Shape:
        desc: (H, W, C) float, C <= 4. Returns (H, W, C) uint8.
    """
    if desc.ndim != 3 or not 1 <= desc.shape[2] <= 4:
        raise CoreError(f"OpenCV's LK takes 1-4 descriptor channels, got shape {desc.shape}")
    return cv2.convertScaleAbs(desc, alpha=255.0)


class TrackingMethod(ABC):
    """A frame representation plus a rule per :class:`SolveKind`; ``spec`` is what it was built from."""

    spec: MethodSpec
    encoder: Encoder | None = None

    @property
    def name(self) -> str:
        """The registry name."""
        return self.spec.name

    @property
    def covariance_scale(self) -> CovarianceScale:
        """The fitted scale of this method's covariances: its model's (metadata or sidecar file), else its
        registry entry's; read once (CoreError: a malformed stored scale)."""
        found = getattr(self, "_covariance_scale", None)
        if found is None:
            enc = self.encoder
            found = read_scale(self.name, getattr(enc, "metadata", None), getattr(enc, "path", None),
                               self.spec.covariance_scale)
            self._covariance_scale = found
        return found

    def encoder_input(self, image: np.ndarray, gray: np.ndarray) -> np.ndarray:
        """What the encoder gets: the gray image for gray encoders, else the image."""
        if self.encoder is None or getattr(self.encoder, "input_channels", 3) == 1:
            return gray
        return image

    @abstractmethod
    def prepare(self, image: np.ndarray, gray: np.ndarray) -> Any:
        """The frame's representation, computed once per image from it and its gray version (uint8)."""

    @abstractmethod
    def track_pair(
        self, frame1: Any, frame2: Any, pts: np.ndarray, start: np.ndarray | None = None,
        levels: int | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """The method's one solver call: ``pts`` (N, 2) of frame 1 into frame 2.

        Args:
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
            start: (N, 2) trusted start in frame 2: the IMU prediction (FORWARD) or the point the check
                must return to (FLOW_BACK, STEREO_BACK); None = none.
            prior: (N, 2) untrusted guess in frame 2, NaN where there is none: the point moved as in
                the previous frame (FORWARD), the id's previous disparity (STEREO).

        Returns:
            (N, 2) finite positions and (N,) status.
        """

    @abstractmethod
    def solve_with_covariance(
        self, kind: SolveKind, frame1: Any, frame2: Any, pts: np.ndarray,
        start: np.ndarray | None = None, prior: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`solve`, and each point's calibrated covariance in frame 2
        (:mod:`~nsflow_ros.core.covariance`): (N, 3) [sigma_uu, sigma_uv, sigma_vv], px^2, meaningless where
        the status is False."""


def _fill_prior(pts: np.ndarray, prior: np.ndarray, known: np.ndarray, neighbours: int = 0) -> np.ndarray:
    """Flows from a prior known where ``known`` (at least one point); each other point takes the median
    flow of its ``neighbours`` nearest points with a prior (0, or fewer of them: of all).

    Shape:
        pts, prior: (N, 2). known: (N,). Returns (N, 2).
    """
    flow = np.empty((pts.shape[0], 2))
    flow[known] = prior[known] - pts[known]
    unknown = np.flatnonzero(~known)
    if not 0 < neighbours < int(known.sum()):
        flow[unknown] = np.median(flow[known], axis=0)
        return flow
    # (unknown x known) squared distances: a few thousand per frame, far below one solve's cost
    gap = pts[unknown, None, :] - pts[None, known, :]
    nearest = np.argpartition(np.einsum("ukd,ukd->uk", gap, gap), neighbours - 1, axis=1)[:, :neighbours]
    flow[unknown] = np.median(flow[known][nearest], axis=1)
    return flow


@functools.lru_cache(maxsize=32)
def _solve_config(
    lm: LMConfig, levels: int, jacobian: Jacobian, eps: float, coarse_window: int | None
) -> LMConfig:
    """``lm`` with one solve's levels, Jacobian, tolerance and coarse window, made once per combination (a
    frame runs a few solves, each of which would otherwise validate a new config)."""
    return replace(lm, levels=levels, jacobian=jacobian, eps=eps, coarse_window=coarse_window)


def pyramid_smoothing(encoder: Encoder) -> Smoothing | None:
    """The coarse part of ``encoder``'s declared smoothing, which an LM method applies to its pyramid."""
    coarse = encoder.smoothing.coarse
    return Smoothing(coarse=coarse) if coarse > 0 else None


def declared_residual(lm: LMConfig, encoder: Encoder) -> LMConfig:
    """``lm`` with the bias-and-gain residual on the finest levels ``encoder`` declares
    (``Encoder.gain_levels``), where ``lm`` compares windows up to an offset (``zero_mean``); the paper's
    settings (plain SSD) stay as they are."""
    levels = encoder.gain_levels
    if levels <= 0 or not lm.zero_mean:
        return lm
    return replace(lm, gain=True, gain_levels=levels)


class LMMethod(TrackingMethod):
    """An encoder's descriptor pyramid through the LM solver (``nsflow``, ``classical``).

    A check starts at the point it must return to; a forward or stereo solve starts points with a prior
    from it on fewer levels and the others from their nearest neighbours' median flow; only a solve
    without any prior runs from zero flow with the coarse window, on the whole pyramid (a stereo one on
    ``policy.stereo_levels``).

    Raises:
        CoreError: a spec without LM settings or solve policy.
    """

    def __init__(self, spec: MethodSpec, encoder: Encoder) -> None:
        if spec.lm is None or spec.policy is None:
            raise CoreError(f"method {spec.name!r}: an LM method needs lm and policy in its spec")
        self.spec = spec
        self.encoder = encoder
        self.lm: LMConfig = declared_residual(spec.lm, encoder)
        self.policy: SolvePolicy = spec.policy
        self.pyramid_smoothing = pyramid_smoothing(encoder)
        self.refinement: IntensityRefinement | None = spec.refine
        # The step of each kind of solve, settled once: a temporal track the step refuses ends, so its
        # step takes a wider shift and the noise floor; a refused stereo match (or check) gets the
        # descriptors' levels instead, which beat the step above the plain residual limit. While the
        # camera's images are noisy (:attr:`noise`) every step compares them blurred, and the stereo
        # step (and the temporal one with ``noisy_temporal``) takes the noisy window.
        r = spec.refine
        self._steps: dict[tuple[bool, bool], IntensityRefinement] = {}
        if r is not None:
            kinds = {True: replace(r, max_shift=r.temporal_max_shift), False: replace(r, residual_floor=0.0)}
            for temporal, base in kinds.items():
                self._steps[temporal, False] = base
                widen = not temporal or r.noisy_temporal
                self._steps[temporal, True] = replace(base, window=r.noisy_window) if widen else base
        self.noise = 0.0
        """The last temporal step's median residual ratio, in the plain images' units: the images' noise,
        which decides whether the steps from its frame 2 on compare blurred images (and the stereo step's
        window; :attr:`IntensityRefinement.noisy_ratio`)."""
        self.noisy = False
        """Whether the stream is noisy: :attr:`noise` over ``noisy_ratio``, or over half of it once noisy."""
        self._noise_frame: DescriptorPyramid | None = None  # that step's frame 2
        self._template_memo: tuple[DescriptorPyramid, bool, StepTemplate] | None = None
        self._blur_memo: list[tuple[DescriptorPyramid, tuple[np.ndarray, ...]]] = []

    @staticmethod
    def residual_ratio(result: TrackResult) -> np.ndarray:
        """Residual energy 2 S over the template's contrast energy, per point: about 1 for a point tracked
        onto something else, image noise (0.01-0.1) for a true match."""
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.where(result.contrast > 0, 2.0 * result.cost / result.contrast, np.inf)

    def pyramid(self, desc: np.ndarray) -> DescriptorPyramid:
        """The solver's pyramid of a descriptor map from :attr:`encoder` (``lm.levels`` deep)."""
        return build_pyramid(desc, self.lm.levels, self.pyramid_smoothing)

    def prepare(self, image: np.ndarray, gray: np.ndarray) -> DescriptorPyramid:
        pyr = self.pyramid(self.encoder(self.encoder_input(image, gray)))
        return pyr if self.refinement is None else replace(pyr, image=gray_level(gray))

    def track_pair_result(
        self, frame1: DescriptorPyramid, frame2: DescriptorPyramid, pts: np.ndarray,
        flow0: np.ndarray | None = None, config: LMConfig | None = None, *, record: bool = False,
        first_level: np.ndarray | None = None, finest_level: int = 0,
    ) -> TrackResult:
        """The solver call itself (:func:`~nsflow_ros.core.solver.track`) with its full result; ``config``
        None = :attr:`lm`."""
        return track(frame1, frame2, pts, flow0, config or self.lm, record=record, first_level=first_level,
                     finest_level=finest_level)

    def track_pair(
        self, frame1: DescriptorPyramid, frame2: DescriptorPyramid, pts: np.ndarray,
        start: np.ndarray | None = None, levels: int | None = None, first_level: np.ndarray | None = None,
        *, residual_test: bool = False, jacobian: Jacobian | None = None, eps: float | None = None,
        coarse_window: bool = True,
    ) -> tuple[np.ndarray, np.ndarray]:
        new, status, _ = self._track_pair(frame1, frame2, pts, start, levels, first_level,
                                          residual_test=residual_test, jacobian=jacobian, eps=eps,
                                          coarse_window=coarse_window)
        return new, status

    def _track_pair(
        self, frame1: DescriptorPyramid, frame2: DescriptorPyramid, pts: np.ndarray,
        start: np.ndarray | None = None, levels: int | None = None, first_level: np.ndarray | None = None,
        *, residual_test: bool = False, jacobian: Jacobian | None = None, eps: float | None = None,
        coarse_window: bool = True, finest_level: int = 0,
    ) -> tuple[np.ndarray, np.ndarray, TrackResult]:
        """:meth:`track_pair` with the solver's full result; the residual test needs level 0's contrast,
        so a solve that ends above it (``finest_level``) skips it."""
        lm = self.lm
        cfg = _solve_config(lm, levels or lm.levels, jacobian or lm.jacobian, eps or lm.eps,
                            lm.coarse_window if coarse_window else None)
        flow0 = None if start is None else start - pts
        res = self.track_pair_result(frame1, frame2, pts, flow0, cfg, first_level=first_level,
                                     finest_level=finest_level)
        status = res.status
        if residual_test and not finest_level and np.isfinite(self.policy.max_residual) and status.any():
            status = status & (self.residual_ratio(res) <= self.policy.max_residual)
        return np.where(np.isfinite(res.flow), pts + res.flow, pts), status, res

    def solve(
        self, kind: SolveKind, frame1: DescriptorPyramid, frame2: DescriptorPyramid, pts: np.ndarray,
        start: np.ndarray | None = None, prior: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        new, status, _ = self.solve_result(kind, frame1, frame2, pts, start, prior)
        return new, status

    def solve_with_covariance(
        self, kind: SolveKind, frame1: DescriptorPyramid, frame2: DescriptorPyramid, pts: np.ndarray,
        start: np.ndarray | None = None, prior: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        new, status, res = self.solve_result(kind, frame1, frame2, pts, start, prior)
        return new, status, self.result_covariance(res, frame2)

    def result_covariance(self, result: TrackResult, frame2: DescriptorPyramid) -> np.ndarray:
        """The calibrated covariances of a solve's :class:`TrackResult` into ``frame2`` (N, 3): from the
        solver's own final J^T J and cost, a few operations per point, no pass over the window."""
        elements = self.lm.window * self.lm.window * frame2.channels
        return self.covariance_scale.apply(lm_covariance(result.hessian, result.cost, elements))

    def solve_result(
        self, kind: SolveKind, frame1: DescriptorPyramid, frame2: DescriptorPyramid, pts: np.ndarray,
        start: np.ndarray | None = None, prior: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray, TrackResult]:
        """:meth:`solve` with the solver's full result (cost, J^T J, ...), e.g. for the evaluation.

        With an intensity step (:attr:`refinement`), the pyramid solve stops at the step's ``from_level``
        and the step on the images finishes it (the checks' too, unless ``checks`` is off; from the IMU
        prediction the step follows the one-level solve); the points it does not keep get the descriptors'
        remaining levels, except in a temporal solve, where they end (``retrack_refused`` off). A kept
        point's row of the result holds the step's J^T J and its cost rescaled to the descriptor window's
        degrees of freedom, so that :meth:`result_covariance` is the step's covariance there.
        """
        step = self.refinement
        step_applies = (step is not None and (step.checks or not kind.is_check) and frame1.image is not None
                        and frame2.image is not None)
        if not step_applies:
            return self._descriptor_solve(kind, frame1, frame2, pts, start, prior)
        assert step is not None
        # From the IMU prediction the descriptor solve has one level only: the step follows it whole.
        finest = 0 if start is not None and not kind.is_check else step.from_level
        # A check keeps its own tolerance: it starts at its answer, where a loose test would stop it.
        eps = step.coarse_eps if finest and not kind.is_check else None
        new, status, res = self._descriptor_solve(kind, frame1, frame2, pts, start, prior, finest, eps)
        temporal = kind is SolveKind.FORWARD
        # The stream's noise applies where the stream goes on (this frame 1 is the last temporal step's
        # frame 2), so a solve of unrelated images gets the plain images and window whatever came before.
        noisy = frame1 is self._noise_frame and self.noisy
        config = self._steps[temporal, noisy]
        blur = noisy and step.noisy_blur > 0
        images = (self._blurred(frame1), self._blurred(frame2)) if blur else (frame1.image, frame2.image)
        template = self._step_template(frame1, pts, config.window, blur)
        done = refine(*images, pts, new, status, config, template)
        if temporal:  # a step that refined nothing leaves the stream's noise as it was
            if np.isfinite(done.median_ratio):
                self.noise = done.median_ratio / (step.noisy_blur_ratio if blur else 1.0)
            self.noisy = self.noise > step.noisy_ratio * (0.5 if noisy else 1.0)
            self._noise_frame = frame2
        new, kept = done.positions, done.kept
        flow, hessian, cost = res.flow.copy(), res.hessian.copy(), res.cost.copy()
        contrast = res.contrast.copy()
        rest = np.flatnonzero(status & ~kept) if finest else np.zeros(0, np.int64)
        status = status.copy()
        if rest.size and temporal and not step.retrack_refused:
            status[rest] = False  # the track ends here; the detector fills its place
        elif rest.size:  # the descriptors' own last levels, from where the coarse levels left them
            p = self.policy
            fine_new, fine_status, fine = (
                self._track_pair(frame1, frame2, pts[rest], new[rest], finest, jacobian=p.check_jacobian,
                                 eps=p.check_eps) if kind.is_check
                else self._track_pair(frame1, frame2, pts[rest], new[rest], finest, residual_test=True))
            new[rest], status[rest] = fine_new, fine_status
            flow[rest], hessian[rest], cost[rest] = fine.flow, fine.hessian, fine.cost
            contrast[rest] = fine.contrast
        dof = self.lm.window * self.lm.window * frame2.channels - 2
        win = config.window
        flow[kept] = new[kept] - pts[kept]
        hessian[kept] = done.hessian[kept]
        cost[kept] = done.cost[kept] * dof / (win * win - 2)
        contrast[kept] = done.contrast[kept]
        merged = TrackResult(flow, status, cost, res.iterations, contrast, res.history, hessian)
        return new, status, merged

    def _step_template(
        self, frame1: DescriptorPyramid, pts: np.ndarray, window: int, blur: bool = False
    ) -> StepTemplate:
        """:func:`~nsflow_ros.core.refine.step_template` of ``frame1`` (``blur``: its blurred image) at
        ``pts`` in ``window``, kept for the next call: a stereo solve's template (this frame's left image at
        its features) is the next frame's temporal one, so the tracker reads each left window once."""
        assert self.refinement is not None and frame1.image is not None
        memo = self._template_memo
        if (memo is not None and memo[0] is frame1 and memo[1] == blur
                and memo[2].rows.shape[-1] == window * window and np.array_equal(memo[2].points, pts)):
            return memo[2]
        image = self._blurred(frame1) if blur else frame1.image
        template = step_template(image, pts, window, self.refinement.affine)
        self._template_memo = (frame1, blur, template)
        return template

    def _blurred(self, frame: DescriptorPyramid) -> tuple[np.ndarray, ...]:
        """``frame``'s image under the noisy streams' blur, kept for the frame's next steps (the last three
        frames: a temporal step's two and the stereo step's right one)."""
        assert self.refinement is not None and frame.image is not None
        for kept, image in self._blur_memo:
            if kept is frame:
                return image
        image = blurred_level(frame.image, self.refinement.noisy_blur)
        self._blur_memo = [*self._blur_memo[-2:], (frame, image)]
        return image

    def _descriptor_solve(
        self, kind: SolveKind, frame1: DescriptorPyramid, frame2: DescriptorPyramid, pts: np.ndarray,
        start: np.ndarray | None = None, prior: np.ndarray | None = None, finest: int = 0,
        eps: float | None = None,
    ) -> tuple[np.ndarray, np.ndarray, TrackResult]:
        """The pyramid solve of :meth:`solve_result`, ending at level ``finest`` (``eps`` None: the
        method's own)."""
        p = self.policy
        if kind.is_check:
            return self._track_pair(frame1, frame2, pts, start, CHECK_LEVELS, jacobian=p.check_jacobian,
                                    eps=p.check_eps, finest_level=finest)
        if start is not None:  # the IMU prediction, trusted as VINS trusts it
            usable = np.isfinite(start).all(axis=1)
            return self._track_pair(
                frame1, frame2, pts, np.where(usable[:, None], start, pts), PREDICTED_LEVELS,
                residual_test=True,
            )
        known = np.zeros(len(pts), bool)
        if p.prior_levels > 0 and prior is not None:
            known = np.isfinite(prior).all(axis=1)
        if prior is None or not known.any():  # no prior, or the median of nothing: all from zero flow
            levels = p.stereo_levels if kind is SolveKind.STEREO else 0
            return self._track_pair(frame1, frame2, pts, levels=levels or None, residual_test=True,
                                    finest_level=finest, eps=eps)
        flow0 = _fill_prior(pts, prior, known, p.fill_neighbours)
        first = np.where(known, p.prior_levels, p.fill_levels or self.lm.levels).astype(np.int64) - 1
        # Every point starts near its answer: the coarse window, there for starts far off, is not needed.
        return self._track_pair(frame1, frame2, pts, pts + flow0, first_level=first, residual_test=True,
                                coarse_window=False, finest_level=finest, eps=eps)


class KLTMethod(TrackingMethod):
    """OpenCV's pyramidal LK on the gray image, call for call as VINS-Fusion's ``trackImage`` (``klt``).

    ``spec`` None = ``klt``'s.

    Raises:
        CoreError: a spec without OpenCV LK settings.
    """

    def __init__(self, spec: MethodSpec | None = None) -> None:
        spec = spec or METHODS["klt"]
        if spec.klt is None:
            raise CoreError(f"method {spec.name!r}: an OpenCV LK method needs klt in its spec")
        self.spec = spec
        self.window = (spec.klt.window, spec.klt.window)
        self.criteria = spec.klt.criteria
        self._hessian_memo: tuple[Any, np.ndarray, np.ndarray] | None = None

    def prepare(self, image: np.ndarray, gray: np.ndarray) -> Any:
        return gray  # VINS hands OpenCV the images; OpenCV builds its pyramids per call

    def track_pair(
        self, frame1: Any, frame2: Any, pts: np.ndarray, start: np.ndarray | None = None,
        levels: int | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        new, status, _ = self._track_error(frame1, frame2, pts, start, levels)
        return new, status

    def _track_error(
        self, frame1: Any, frame2: Any, pts: np.ndarray, start: np.ndarray | None = None,
        levels: int | None = None,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        max_level = KLT_MAX_LEVEL if levels is None else levels - 1
        return klt_track_error(frame1, frame2, pts, start, max_level, window=self.window,
                               criteria=self.criteria)

    def _solve_error(
        self, kind: SolveKind, frame1: Any, frame2: Any, pts: np.ndarray, start: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        # VINS-Fusion: the predicted forward call and the flow-back start at the given positions with
        # maxLevel 1; the plain forward call, both stereo calls use maxLevel 3 from the point itself.
        if kind in (SolveKind.FORWARD, SolveKind.FLOW_BACK) and start is not None:
            usable = np.isfinite(start).all(axis=1)
            guided = np.where(usable[:, None], start, pts)
            return self._track_error(frame1, frame2, pts, guided, KLT_GUIDED_MAX_LEVEL + 1)
        return self._track_error(frame1, frame2, pts)

    def solve(
        self, kind: SolveKind, frame1: Any, frame2: Any, pts: np.ndarray,
        start: np.ndarray | None = None, prior: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        new, status, _ = self._solve_error(kind, frame1, frame2, pts, start)
        return new, status

    def solve_with_covariance(
        self, kind: SolveKind, frame1: Any, frame2: Any, pts: np.ndarray,
        start: np.ndarray | None = None, prior: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        new, status, err = self._solve_error(kind, frame1, frame2, pts, start)
        # OpenCV keeps J^T J to itself: the template's gradients read once, the residual from its err.
        cov = np.full((len(pts), 3), np.nan)
        if status.any():
            hess = self._template_hessian(frame1, pts)
            channels = 1 if np.ndim(frame1) == 2 else np.shape(frame1)[2]
            cov[status] = self.covariance_scale.apply(
                err_covariance(hess[status], err[status], self.window[0] ** 2 * channels))
        return new, status, cov

    def _template_hessian(self, frame1: Any, pts: np.ndarray) -> np.ndarray:
        """:func:`~nsflow_ros.core.covariance.template_hessian`, kept for the next call: a stereo solve's
        template (this frame's left image at its features) is the next frame's temporal one, the same
        array at the same points, so the tracker reads each left window once."""
        memo = self._hessian_memo
        if memo is not None and memo[0] is frame1 and np.array_equal(memo[1], pts):
            return memo[2]
        hess = template_hessian(frame1, pts, self.window[0])
        self._hessian_memo = (frame1, np.array(pts, copy=True), hess)
        return hess


class DescriptorKLTMethod(KLTMethod):
    """The learned descriptors as uint8, tracked by OpenCV's pyramidal LK with VINS's calls (``nsflow_lk``).

    The encoder (1-4 channels in [0, 1]) must not smooth: smoothing chosen for the LM solver's 11x11
    window costs more than it gives on OpenCV's 21x21 one (docs/design.md).

    Raises:
        CoreError: an encoder that smooths its maps.
        UnsupportedEncoderError: a model that declares unbounded descriptors (a head other than sigmoid in
            its metadata ``spec``, as the fast model), which uint8 would fold.
    """

    def __init__(self, spec: MethodSpec, encoder: Encoder) -> None:
        super().__init__(spec)
        if encoder.smoothing.fine > 0:
            raise CoreError(
                f"{spec.name} tracks unsmoothed descriptors, but the encoder smooths them "
                f"({encoder.smoothing}); load it with smoothing=Smoothing()"
            )
        head = getattr(encoder, "head", None)  # declared by an ONNX model's metadata
        if head not in (None, "sigmoid"):
            raise UnsupportedEncoderError(
                f"{spec.name} quantises descriptors in [0, 1] to uint8, but the model "
                f"{getattr(encoder, 'path', '')} declares head {head!r} (unbounded descriptors); track its "
                "descriptors with method 'nsflow'"
            )
        self.encoder = encoder

    def prepare(self, image: np.ndarray, gray: np.ndarray) -> np.ndarray:
        return quantise_descriptors(self.encoder(self.encoder_input(image, gray)))


@dataclass(frozen=True)
class MethodSpec:
    """One tracking method's whole configuration: what :func:`make_method` builds and the tracker runs.

    Attributes:
        name: registry name (the tracker's ``method`` setting).
        label: name in evaluation tables and plots.
        summary: one line for help texts and the README.
        smoothed: whether the learned model's declared smoothing is applied.
        lm, policy: LM solver settings and solve policy (LM methods only).
        klt: OpenCV LK's window and criteria (OpenCV methods only).
        clahe: the equalisation applied when the tracker equalises.
        covariance_scale: the fitted calibration (scale and floor) of the covariances of a method without
            a model (:mod:`~nsflow_ros.core.covariance`); None = none fitted (a learned method's is its
            model's).
        default_model: the shipped model (a name in :data:`~nsflow_ros.core.encoder.SHIPPED_MODELS`) a
            learned method loads when none is given: OpenCV's LK needs descriptors in [0, 1].
        refine: the intensity step that finishes forward and stereo solves on the image (LM methods).
        check: how the tracker checks this method's tracks when ``flow_back`` is on: by each point's
            covariance and epipolar distance (LM methods, whose covariance comes with the solve), or
            None: VINS's reverse solves.

    Raises:
        CoreError: neither or both of (lm, policy) and klt.
    """

    name: str
    label: str
    summary: str
    encoder: EncoderSource
    smoothed: bool = True
    lm: LMConfig | None = None
    policy: SolvePolicy | None = None
    klt: KLTConfig | None = None
    clahe: Clahe = CLAHE
    covariance_scale: CovarianceScale | None = None
    default_model: str = "default"
    refine: IntensityRefinement | None = None
    check: CovarianceCheck | None = None

    def __post_init__(self) -> None:
        is_lm = self.lm is not None and self.policy is not None
        if is_lm == (self.klt is not None) or (self.lm is None) != (self.policy is None):
            raise CoreError(
                f"method {self.name!r}: give lm and policy (LM solver) or klt (OpenCV LK), not both"
            )
        if self.check is not None and not is_lm:
            raise CoreError(f"method {self.name!r}: only an LM method's covariance comes with its solve")

    @property
    def learned(self) -> bool:
        """Whether the method needs the learned ONNX encoder."""
        return self.encoder is EncoderSource.LEARNED

    @property
    def is_lm(self) -> bool:
        """Whether the method runs the LM solver (else OpenCV's LK)."""
        return self.lm is not None

    def with_solver(self, solver: Solver | str) -> MethodSpec:
        """This spec with the LM settings of ``solver`` (OpenCV methods: unchanged); CoreError: unknown."""
        try:
            which = Solver(solver)
        except ValueError:
            raise CoreError(f"solver must be one of {[s.value for s in Solver]}, got {solver!r}") from None
        if not self.is_lm:
            return self
        if which is Solver.PAPER:
            return replace(self, lm=PAPER_LM, policy=SolvePolicy.paper())
        return replace(self, lm=DEPLOYED_LM, policy=SolvePolicy())

    def with_levels(self, levels: int) -> MethodSpec:
        """This spec with ``levels`` pyramid levels (LM methods; the OpenCV ones take levels per call)."""
        return replace(self, lm=replace(self.lm, levels=levels)) if self.lm is not None else self


COVARIANCE_SCALES: Mapping[str, CovarianceScale] = MappingProxyType({
    "classical": CovarianceScale(3.22, "registry", 7.289e-4),
    "klt": CovarianceScale(19.78, "registry", 1.484e-3),
})
"""The fitted covariance calibrations (scale, floor in px^2) of the methods without a model, as ``python -m
nsflow_ros.evaluation.covariance fit`` prints them (the learned methods' are stored with their model)."""

METHODS: Mapping[str, MethodSpec] = MappingProxyType({
    "nsflow": MethodSpec(
        "nsflow", "NSFlow", "learned encoder + the LM solver (NumPy), finished on the image",
        EncoderSource.LEARNED, lm=DEPLOYED_LM, policy=SolvePolicy(), refine=IntensityRefinement(),
        check=CovarianceCheck(),
    ),
    "nsflow_lk": MethodSpec(
        "nsflow_lk", "NSFlow + OpenCV LK", "learned encoder as uint8 + OpenCV's pyramidal LK (VINS's calls)",
        EncoderSource.LEARNED, smoothed=False, klt=KLTConfig(), default_model="d4",
    ),
    "classical": MethodSpec(
        "classical", "LM (intensity)", "image intensity + the same LM solver", EncoderSource.INTENSITY,
        lm=DEPLOYED_LM, policy=SolvePolicy(), covariance_scale=COVARIANCE_SCALES["classical"],
    ),
    "klt": MethodSpec(
        "klt", "OpenCV KLT", "OpenCV calcOpticalFlowPyrLK on the gray image, as VINS-Fusion calls it",
        EncoderSource.NONE, klt=KLTConfig(), covariance_scale=COVARIANCE_SCALES["klt"],
    ),
})
"""The registry of tracking methods (learned methods first)."""

BASELINE = "klt"
"""The method every other is compared with: VINS-Fusion's own front-end."""


def _spec(method: str | MethodSpec) -> MethodSpec:
    if isinstance(method, MethodSpec):
        return method
    spec = METHODS.get(method)
    if spec is None:
        raise CoreError(f"method must be one of {tuple(METHODS)}, got {method!r}")
    return spec


def make_method(
    method: str | MethodSpec,
    *,
    solver: Solver | str = Solver.DEPLOYED,
    encoder: Encoder | None = None,
    model_path: str | None = None,
    threads: int | None = None,
    providers: ExecutionProviders | str | None = None,
) -> TrackingMethod:
    """Build a tracking method: ``make_method("nsflow")`` is exactly what the tracker runs.

    Args:
        method: a key of :data:`METHODS`, or a spec (``METHODS["nsflow"].with_levels(1)``), used as given.
        solver: for a registry name, the LM settings to give an LM method; ignored for a spec.
        encoder: encoder to use instead of the one the spec names; not for a method without one.
        model_path: ONNX encoder of the learned methods; None = the shipped model.
        threads: encoder threads; None = all usable cores.
        providers: onnxruntime execution providers of the learned encoder, best first; None = the CPU.

    Raises:
        CoreError: unknown name or solver, or an encoder given to a method without one.
        EncoderError: the learned model cannot be loaded.
    """
    spec = method if isinstance(method, MethodSpec) else _spec(method).with_solver(solver)
    if spec.encoder is EncoderSource.NONE:
        if encoder is not None:
            raise CoreError(
                f"method {spec.name!r} tracks the gray image with OpenCV; an encoder cannot be given"
            )
        return KLTMethod(spec)
    if encoder is None:
        encoder = method_encoder(spec, model_path, threads, providers)
    assert encoder is not None
    if spec.is_lm:
        return LMMethod(spec, encoder)
    return DescriptorKLTMethod(spec, encoder)


def method_encoder(
    method: str | MethodSpec, model_path: str | None = None, threads: int | None = None,
    providers: ExecutionProviders | str | None = None,
) -> Encoder | None:
    """The encoder :func:`make_method` gives a method when none is passed (None: OpenCV on the gray image).

    Raises:
        CoreError: unknown name.
        EncoderError: the learned model cannot be loaded.
    """
    spec = _spec(method)
    if spec.encoder is EncoderSource.NONE:
        return None
    if spec.encoder is EncoderSource.INTENSITY:
        return IntensityEncoder()
    smoothing = None if spec.smoothed else Smoothing()  # None: as the model declares
    model = spec.default_model if model_path is None else model_path
    return load_encoder(model, threads=threads, smoothing=smoothing, providers=providers)
