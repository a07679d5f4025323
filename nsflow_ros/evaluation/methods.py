"""The methods every analysis compares: a view over the tracker's method registry.

Each evaluated method is a :class:`Variant` (an entry of :data:`nsflow_ros.core.methods.METHODS` under
its label, with or without the tracker's CLAHE) built by :func:`~nsflow_ros.core.methods.make_method`
and wrapped in :class:`EvalMethod`, so that what is evaluated is the code and configuration deployed.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from types import MappingProxyType
from typing import Any

import numpy as np

from nsflow_ros.core.encoder import Encoder, to_gray
from nsflow_ros.core.errors import CoreError, UnsupportedEncoderError
from nsflow_ros.core.methods import (
    DEPLOYED_LM,
    KLT_MAX_LEVEL,
    METHODS,
    KLTMethod,
    LMMethod,
    MethodSpec,
    TrackingMethod,
    make_method,
    method_encoder,
)
from nsflow_ros.core.solver import LMConfig
from nsflow_ros.evaluation.errors import EvaluationError, MethodLeftOutError

__all__ = [
    "BASELINES",
    "CLASSICAL",
    "KLT",
    "KLT_CLAHE",
    "METHOD_ORDER",
    "NSFLOW",
    "NSFLOW_LK",
    "VARIANTS",
    "EvalMethod",
    "KLTPairMethod",
    "LMPairMethod",
    "PairResult",
    "Variant",
    "default_methods",
    "eval_method",
    "prepare_pair",
    "usable_methods",
]

NSFLOW = METHODS["nsflow"].label
NSFLOW_LK = METHODS["nsflow_lk"].label
CLASSICAL = METHODS["classical"].label
KLT = METHODS["klt"].label
KLT_CLAHE = f"{KLT} + CLAHE"


@dataclass(frozen=True)
class Variant:
    """An evaluated method: a registry entry, on equalised images or not.

    Attributes:
        label: name in tables and plots.
        method: the key of :data:`~nsflow_ros.core.methods.METHODS`.
        equalize: CLAHE the gray image first, as the tracker does with ``equalize`` on.
    """

    label: str
    method: str
    equalize: bool = False

    @property
    def spec(self) -> MethodSpec:
        """The registry entry."""
        return METHODS[self.method]

    @property
    def tracker_overrides(self) -> dict[str, Any]:
        """The :class:`~nsflow_ros.core.tracker.TrackerSettings` fields that make the tracker run this."""
        return {"method": self.method, "equalize": self.equalize}


VARIANTS: Mapping[str, Variant] = MappingProxyType({
    v.label: v for v in (
        Variant(NSFLOW, "nsflow"), Variant(NSFLOW_LK, "nsflow_lk"), Variant(CLASSICAL, "classical"),
        Variant(KLT, "klt"), Variant(KLT_CLAHE, "klt", equalize=True),
    )
})
"""Every evaluated method by label, in table order (the learned descriptors first)."""
METHOD_ORDER = tuple(VARIANTS)
"""Every evaluated method's label, in table order."""
BASELINES = tuple(label for label, v in VARIANTS.items() if not v.spec.learned)
"""The classical baselines (the methods without the learned descriptors)."""


@dataclass(frozen=True)
class PairResult:
    """Flow of N points from image 1 to image 2.

    Attributes:
        flow: (N, 2) float64, new position = points + flow (meaningless where status is False).
        status: (N,) bool, the method's own tracked flag.
    """

    flow: np.ndarray
    status: np.ndarray


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
        core: the tracking method (:func:`nsflow_ros.core.methods.make_method`).
        levels: pyramid levels of every solve (OpenCV ``maxLevel`` = levels - 1).
        equalize: CLAHE the gray image first, with the method's CLAHE, as the tracker does.
    """

    def __init__(self, name: str, core: TrackingMethod, levels: int, *, equalize: bool = False) -> None:
        if levels < 1:
            raise EvaluationError(f"levels must be >= 1, got {levels}")
        self.name = name
        self.core = core
        self.levels = int(levels)
        self.equalize = bool(equalize)
        self._clahe = core.spec.clahe.create() if equalize else None

    @property
    def encoder(self) -> Encoder | None:
        """The core method's descriptor encoder (None for OpenCV's KLT on the gray image)."""
        return self.core.encoder

    @property
    def stereo_levels(self) -> int:
        """The depth of the tracker's stereo solve from zero flow (a first frame's matches): :attr:`levels`
        unless the method's solve policy says fewer."""
        return self.levels

    def levels_fewer(self, fewer: int, stereo: bool = False) -> int:
        """:attr:`levels` (``stereo``: :attr:`stereo_levels`) less ``fewer``.

        Raises:
            EvaluationError: no level would be left.
        """
        depth = self.stereo_levels if stereo else self.levels
        if depth - fewer < 1:
            raise EvaluationError(f"{self.name}: {depth} levels cannot be reduced by {fewer}")
        return depth - fewer

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

    def track(
        self, frame1: Any, frame2: Any, points: np.ndarray, flow0: np.ndarray | None = None,
        levels: int | None = None,
    ) -> PairResult:
        """Track ``points`` between two frames from :meth:`prepare` (the core method's ``track_pair``).

        Args:
            frame1, frame2: representations of the two images.
            points: (N, 2) points in image 1.
            flow0: (N, 2) initial flow; None = zero.
            levels: pyramid levels of this solve, 1..:attr:`levels`; None = :attr:`levels`.

        Raises:
            EvaluationError: bad shapes or levels, or a solve that fails.
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

    def iterate(
        self, frame1: Any, frame2: Any, points: np.ndarray, flow0: np.ndarray, levels: int, iterations: int
    ) -> tuple[list[np.ndarray], PairResult]:
        """The flow after each iteration k = 1..``iterations`` on ``levels`` levels, and the final result.

        Raises:
            EvaluationError: a method that cannot report its iterations.
        """
        raise EvaluationError(f"{self.name}: this method cannot report its iterations")


class LMPairMethod(EvalMethod):
    """An LM method of the registry (core ``nsflow`` / ``classical``); its ``lm.levels`` is the depth."""

    core: LMMethod

    def __init__(self, name: str, core: LMMethod) -> None:
        super().__init__(name, core, core.lm.levels)

    @property
    def stereo_levels(self) -> int:
        return min(self.core.policy.stereo_levels or self.levels, self.levels)

    @property
    def config(self) -> LMConfig:
        """The solver settings of the core method."""
        return self.core.lm

    def iterate(
        self, frame1: Any, frame2: Any, points: np.ndarray, flow0: np.ndarray, levels: int, iterations: int
    ) -> tuple[list[np.ndarray], PairResult]:
        # Algorithm 1's per-iteration flow, read from the solver's history: no straggler cut-off.
        pts, flow0 = _check_points(points, flow0)
        cfg = replace(self.config, levels=levels, max_iterations=iterations, tail_share=0.0)
        try:
            res = self.core.track_pair_result(frame1, frame2, pts, flow0, cfg, record=True)
        except CoreError as err:
            raise EvaluationError(f"{self.name}: {err}") from err
        flows = [rec.flow for rec in res.history]
        flows += [res.flow] * (iterations - len(flows))  # every point had stopped: flows stay
        return flows[:iterations], PairResult(res.flow, res.status)


class KLTPairMethod(EvalMethod):
    """An OpenCV LK method of the registry (core ``klt``, ``nsflow_lk``)."""

    core: KLTMethod

    def with_iterations(self, max_iterations: int) -> KLTPairMethod:
        """A copy limited to ``max_iterations`` per level; same representation.

        Raises:
            EvaluationError: max_iterations < 1.
        """
        spec = self.core.spec
        try:
            spec = replace(spec, klt=replace(spec.klt, max_iterations=max_iterations))
        except CoreError as err:
            raise EvaluationError(f"{self.name}: {err}") from err
        core = make_method(spec, encoder=self.encoder)
        return KLTPairMethod(self.name, core, self.levels, equalize=self.equalize)

    def iterate(
        self, frame1: Any, frame2: Any, points: np.ndarray, flow0: np.ndarray, levels: int, iterations: int
    ) -> tuple[list[np.ndarray], PairResult]:
        # OpenCV keeps no history: run again with max_iterations = k, on the same representations.
        results = [self.with_iterations(k).track(frame1, frame2, points, flow0, levels)
                   for k in range(1, iterations + 1)]
        return [r.flow for r in results], results[-1]


def prepare_pair(
    methods: Sequence[EvalMethod], image1: np.ndarray, image2: np.ndarray
) -> dict[str, tuple[Any, Any]]:
    """Each method's representations of two images, by name, for any number of solves on them.

    Raises:
        EvaluationError: an object that is not an :class:`EvalMethod`, or an image a method cannot take.
    """
    out = {}
    for m in methods:
        if not isinstance(m, EvalMethod):
            raise EvaluationError(f"expected LM or KLT evaluation methods, got {type(m).__name__} {m.name!r}")
        out[m.name] = (m.prepare(image1), m.prepare(image2))
    return out


def eval_method(
    label: str, *, encoder: Encoder | None = None, levels: int | None = None, model: str | None = None,
    threads: int | None = None, providers: str = "cpu",
) -> EvalMethod:
    """Build the evaluated method ``label`` (a key of :data:`VARIANTS`) from its registry entry.

    Args:
        label: the method's label.
        encoder: encoder to use instead of the one the registry loads (a method without one: ignored).
        levels: pyramid levels; None = the depth the tracker runs the method at (the LM solver's 6, or
            OpenCV's maxLevel 3 + 1 as VINS calls it).
        model: ONNX encoder of the learned methods when ``encoder`` is None; None = the shipped one.
        threads: encoder threads (None = all usable cores).
        providers: onnxruntime execution providers of the learned encoder, best first.

    Raises:
        EvaluationError: an unknown label, bad levels, or a model that cannot be loaded.
        MethodLeftOutError: the method cannot track this model's descriptors.
    """
    variant = VARIANTS.get(label)
    if variant is None:
        raise EvaluationError(f"unknown method {label!r}; expected one of {list(VARIANTS)}")
    # each at the depth the tracker runs it: the LM solver's, or OpenCV's maxLevel as VINS calls it
    lev = (DEPLOYED_LM.levels if variant.spec.is_lm else KLT_MAX_LEVEL + 1) if levels is None else levels
    if lev < 1:
        raise EvaluationError(f"levels must be >= 1, got {lev}")
    spec = variant.spec.with_levels(lev)
    try:
        enc = encoder if encoder is not None else method_encoder(spec, model, threads, providers)
        core = make_method(spec, encoder=enc)
    except UnsupportedEncoderError as err:
        raise MethodLeftOutError(f"{label}: {err}") from err
    except CoreError as err:
        raise EvaluationError(f"{label}: {err}") from err
    if spec.is_lm:
        return LMPairMethod(label, core)  # type: ignore[arg-type]
    return KLTPairMethod(label, core, lev, equalize=variant.equalize)


def default_methods(
    model: str | None = None, levels: int | None = None, threads: int | None = None, providers: str = "cpu"
) -> list[EvalMethod]:
    """Every evaluated method (:data:`METHOD_ORDER`), each built by :func:`eval_method` with these settings.

    Raises:
        EvaluationError: bad levels, or the model cannot be loaded.
        MethodLeftOutError: a method cannot track this model's descriptors.
    """
    methods, left_out = usable_methods(model, levels, threads, providers)
    if left_out:
        raise MethodLeftOutError(next(iter(left_out.values())))
    return methods


def usable_methods(
    model: str | None = None, levels: int | None = None, threads: int | None = None, providers: str = "cpu"
) -> tuple[list[EvalMethod], dict[str, str]]:
    """:func:`default_methods` less those that cannot track ``model``'s descriptors (OpenCV's LK and a
    model of unbounded descriptors), and why each was left out, by label.

    Raises:
        EvaluationError: bad levels, or the model cannot be loaded.
    """
    methods: list[EvalMethod] = []
    left_out: dict[str, str] = {}
    for label in METHOD_ORDER:
        try:
            method = eval_method(label, levels=levels, model=model, threads=threads, providers=providers)
        except MethodLeftOutError as err:
            left_out[label] = str(err)
            continue
        methods.append(method)
    return methods, left_out
