"""A calibrated 2x2 covariance per tracked feature, from the final Lucas-Kanade solve.

For a window cost S(u) = 1/2 sum ||r||^2 over n pixels and C channels, the Gauss-Newton covariance of the
solution is Sigma_raw = sigma_hat^2 (J^T J)^-1 with sigma_hat^2 = 2 S / (n C - 2), the residual variance
left after fitting the two unknowns (PNEC, CVPR 2022). Such covariances run optimistic (neighbouring
residuals are correlated, the model is not exactly a translation) and their range is wider than the
error's (a window of strong texture still has interpolation and quantisation error), so the published one
is Sigma = s * Sigma_raw + f * I: a scale ``s`` and a variance floor ``f`` (px^2), one pair per method and
model, fitted on training data (``python -m nsflow_ros.evaluation.covariance fit``, maximum likelihood)
and stored with the model: its ONNX metadata key :data:`METADATA_KEY`, else a JSON file beside it
(``<model stem>`` :data:`SIDECAR_SUFFIX`), both ``{"<method>": {"scale": s, "floor": f}, ...}`` (a bare
number, as older files hold, is a scale with floor 0); the methods without a model keep theirs in their
registry entry (:attr:`~nsflow_ros.core.methods.MethodSpec.covariance_scale`).

A solve's own sigma describes its local minimum, not the chance that it settled in a wrong one, which grows
with sigma: past a knee (the covariance check's limit, where tracks end) the published covariance is
inflated by ``(sigma / knee)^(2 power)`` (:meth:`CovarianceScale.expected`, ``"knee"`` and ``"power"`` in
the same entry, power fitted by maximum likelihood with the scale and floor held). The checks read the
calibration without it (:meth:`CovarianceScale.apply`), so a fitted tail changes no track.

The LM methods take J^T J and S from the solver's own last step
(:attr:`~nsflow_ros.core.solver.TrackResult.hessian`); OpenCV's LK keeps J^T J to itself, so
:func:`klt_covariance` reads it from the template's window once and takes sigma_hat^2 from OpenCV's own
per-point ``err`` (:func:`window_covariance`, which resamples both windows at the solution, is the
reference it is tested against). Covariances are [sigma_uu, sigma_uv, sigma_vv] in pixels^2 of the
full-resolution image.
"""

from __future__ import annotations

import hashlib
import json
import math
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.lib.stride_tricks import sliding_window_view

from nsflow_ros.core.errors import CoreError

__all__ = [
    "DETECTION_VARIANCE",
    "METADATA_KEY",
    "SIDECAR_SUFFIX",
    "CovarianceScale",
    "err_covariance",
    "klt_covariance",
    "lm_covariance",
    "max_sigma",
    "read_scale",
    "sidecar_path",
    "template_hessian",
    "window_covariance",
]

METADATA_KEY = "covariance_scale"
"""ONNX metadata key of a model's fitted calibrations: JSON ``{"<method>": {"scale": s, "floor": f}}`` (a
bare number is a scale with floor 0)."""
SIDECAR_SUFFIX = ".covariance.json"
"""Suffix of the JSON file beside a model that holds its fitted scales (when its metadata has none)."""
DETECTION_VARIANCE = 1.0 / 12.0
"""Variance (px^2, per axis) of a feature detected in this frame: GFTT returns whole pixels, whose
rounding error is uniform over one pixel."""


@dataclass(frozen=True)
class CovarianceScale:
    """The calibration of a method's raw covariances, Sigma = scale * Sigma_raw + floor * I, its tail above
    a knee, and its source.

    The floor is a variance every feature has whatever its window says (px^2 per axis: interpolation,
    the uint8 quantisation, a model that is not exactly a translation), which a scale alone cannot give:
    without it the raw covariance's dynamic range is wider than the error's. The tail is the published
    covariance's growth above ``knee`` (:meth:`expected`): beyond it a solve's sigma no longer reaches
    its error (a wrong minimum's 1-2 px), which the checks already act on.

    Attributes:
        scale: s (> 0); 1.0 when no fitted value was found.
        source: "metadata", a sidecar file's name, "registry", or "uncalibrated" (with the reason when a
            sidecar's scale was fitted on another model file: its ``model_sha256`` differs).
        floor: f (px^2, >= 0); 0 for a scale fitted alone (an older sidecar) or none fitted.
        knee: sigma (px, > 0) above which the tail applies; inf = no tail.
        power: the tail's exponent (>= 0); 0 = no tail.
    """

    scale: float = 1.0
    source: str = "uncalibrated"
    floor: float = 0.0
    knee: float = math.inf
    power: float = 0.0

    def __post_init__(self) -> None:
        if not (math.isfinite(self.scale) and self.scale > 0):
            raise CoreError(f"covariance scale must be a finite number > 0, got {self.scale!r}")
        if not (math.isfinite(self.floor) and self.floor >= 0):
            raise CoreError(f"covariance floor must be a finite number >= 0 (px^2), got {self.floor!r}")
        if not (self.knee > 0 and not math.isnan(self.knee)):
            raise CoreError(f"covariance knee must be a number > 0 (px; inf = no tail), got {self.knee!r}")
        if not (math.isfinite(self.power) and self.power >= 0):
            raise CoreError(f"covariance power must be a finite number >= 0, got {self.power!r}")

    @property
    def calibrated(self) -> bool:
        """Whether the scale was fitted (else the raw Gauss-Newton covariance is used)."""
        return not self.source.startswith("uncalibrated")

    def apply(self, raw: np.ndarray) -> np.ndarray:
        """scale * raw + floor * I of (N, 3) [uu, uv, vv] covariances (a new array; inf stays inf)."""
        out = np.asarray(raw, dtype=np.float64) * self.scale
        out[:, 0] += self.floor
        out[:, 2] += self.floor
        return out

    @property
    def tail_text(self) -> str:
        """``", tail power p above k px"``, or ``""`` without a tail (for log lines)."""
        return f", tail power {self.power:.3g} above {self.knee:g} px" if self.power > 0 else ""

    def expected(self, cov: np.ndarray) -> np.ndarray:
        """The published covariances of (N, 3) calibrated ones (:meth:`apply`'s): each multiplied by
        ``max(1, sigma / knee)^(2 power)``, sigma its major axis (:func:`max_sigma`); a new array.

        Monotone in sigma and the identity below the knee, so it reorders no feature and moves none of
        the checks, which read :meth:`apply`'s covariance.
        """
        out = np.array(cov, dtype=np.float64)
        if self.power == 0 or not math.isfinite(self.knee) or out.size == 0:
            return out
        with np.errstate(invalid="ignore"):
            grow = np.maximum(1.0, max_sigma(out) / self.knee) ** (2.0 * self.power)
        return out * np.where(np.isfinite(grow), grow, 1.0)[:, None]  # inf / NaN covariances stay as they are

    def raw(self, cov: np.ndarray) -> np.ndarray:
        """The raw covariances that :meth:`apply` turns into ``cov`` (for a new fit)."""
        out = np.array(cov, dtype=np.float64)
        out[:, 0] -= self.floor
        out[:, 2] -= self.floor
        return out / self.scale


def sidecar_path(model: str | Path) -> Path:
    """The JSON file beside ``model`` that holds its fitted scales (``nsflow_encoder.covariance.json``)."""
    p = Path(model)
    return p.with_name(p.stem + SIDECAR_SUFFIX)


def _entry(table: Mapping[str, Any], method: str, where: str) -> tuple[float, float, float, float] | None:
    """A method's (scale, floor, knee, power) from a table of entries: a number (a scale alone, floor 0, as
    older files hold) or ``{"scale": s, "floor": f, "knee": k, "power": p}`` (knee and power optional: no
    tail); None when the method has none."""
    value = table.get(method)
    if value is None:
        return None
    if isinstance(value, dict):
        scale, floor = value.get("scale"), value.get("floor", 0.0)
        knee, power = value.get("knee", math.inf), value.get("power", 0.0)
    else:
        scale, floor, knee, power = value, 0.0, math.inf, 0.0
    for name, v, low_ok in (("scale", scale, False), ("floor", floor, True), ("knee", knee, False),
                            ("power", power, True)):
        bad = isinstance(v, bool) or not isinstance(v, int | float)
        absent_knee = name == "knee" and v == math.inf  # no tail stored
        if bad or not (math.isfinite(v) or absent_knee) or v < 0 or (v == 0 and not low_ok):
            need = "a finite number >= 0" if low_ok else "a finite number > 0"
            raise CoreError(f"{where}: covariance {name} of {method!r} must be {need}, got {v!r}")
    return float(scale), float(floor), float(knee), float(power)


def read_scale(method: str, metadata: Mapping[str, str] | None = None, model: str | Path | None = None,
               registry: CovarianceScale | float | None = None) -> CovarianceScale:
    """The fitted calibration of ``method``: from the model's metadata, else its sidecar file, else
    ``registry``.

    Args:
        method: the method's registry name (a model may carry a calibration per method).
        metadata: the model's ONNX metadata (``Encoder.metadata``); None = none.
        model: the model file, whose sidecar is read; None = none.
        registry: the method's own registry value (methods without a model; a number is a scale alone);
            None = none.

    Returns:
        the scale, floor, tail and source; ``CovarianceScale()`` (1.0, floor 0, no tail, uncalibrated) when
        none is found.

    Raises:
        CoreError: malformed JSON or a scale or knee that is not a number > 0 or a floor or power that is
            not a number >= 0 (naming the file or key).
    """
    if metadata and METADATA_KEY in metadata:
        where = f"model metadata {METADATA_KEY!r}"
        try:
            table = json.loads(metadata[METADATA_KEY])
        except (json.JSONDecodeError, TypeError) as err:
            raise CoreError(f"{where} is not JSON: {err}") from err
        if not isinstance(table, dict):
            raise CoreError(f"{where} must be a JSON object of scales by method, got {table!r}")
        found = _entry(table, method, where)
        if found is not None:
            return CovarianceScale(found[0], "metadata", *found[1:])
    if model is not None:
        side = sidecar_path(model)
        if side.is_file():
            try:
                table = json.loads(side.read_text())
            except (OSError, json.JSONDecodeError) as err:
                raise CoreError(f"cannot read the covariance scales {side}: {err}") from err
            scales = table.get("scales") if isinstance(table, dict) else None
            if not isinstance(scales, dict):
                raise CoreError(f"{side}: expected an object with 'scales' by method, got {table!r}")
            found = _entry(scales, method, str(side))
            fitted = table.get("model_sha256")
            if found is not None and fitted is not None and fitted != _sha256(Path(model)):
                # a model replaced under the same name: its calibration must be fitted again
                return CovarianceScale(1.0, f"uncalibrated ({side.name} was fitted on another model file)")
            if found is not None:
                return CovarianceScale(found[0], side.name, *found[1:])
    if isinstance(registry, CovarianceScale):
        return registry
    if registry is not None:
        return CovarianceScale(float(registry), "registry")
    return CovarianceScale()


def _sha256(path: Path) -> str:
    """The file's SHA-256 (models are kilobytes: a scale fitted on another file is caught at load)."""
    try:
        return hashlib.sha256(path.read_bytes()).hexdigest()
    except OSError as err:
        raise CoreError(f"cannot read the model {path}: {err}") from err


def _from_normal_equations(hess: np.ndarray, variance: np.ndarray) -> np.ndarray:
    """variance * (J^T J)^-1 per point, [uu, uv, vv]; inf variances (0 covariance) where J^T J is singular."""
    h11, h12, h22 = hess[:, 0], hess[:, 1], hess[:, 2]
    det = h11 * h22 - h12 * h12
    good = det > 0
    out = np.empty((hess.shape[0], 3))
    out[:] = [np.inf, 0.0, np.inf]
    k = variance[good] / det[good]
    out[good, 0] = k * h22[good]
    out[good, 1] = -k * h12[good]
    out[good, 2] = k * h11[good]
    return out


def lm_covariance(hessian: np.ndarray, cost: np.ndarray, elements: int, scale: float = 1.0) -> np.ndarray:
    """Sigma = scale * sigma_hat^2 (J^T J)^-1 from the LM solver's final J^T J and cost S.

    Args:
        hessian: the solver's level-0 J^T J per point, [h11, h12, h22] (level-0 pixels = full resolution).
        cost: its final S = 1/2 sum r^2.
        elements: window pixels times channels (n C): sigma_hat^2 = 2 S / (n C - 2).
        scale: the method's fitted scale.

    Shape:
        hessian: (N, 3). cost: (N,). Returns (N, 3) [sigma_uu, sigma_uv, sigma_vv], px^2.
    """
    hess = np.asarray(hessian, dtype=np.float64)
    s = np.asarray(cost, dtype=np.float64)
    if hess.ndim != 2 or hess.shape[1] != 3 or s.shape != (hess.shape[0],):
        raise CoreError(f"hessian must be (N, 3) and cost (N,), got {hess.shape} and {s.shape}")
    if elements <= 2:
        raise CoreError(f"elements (window pixels x channels) must be > 2, got {elements}")
    return _from_normal_equations(hess, scale * 2.0 * s / (elements - 2))


def window_covariance(
    image1: np.ndarray, image2: np.ndarray, pts1: np.ndarray, pts2: np.ndarray, window: int,
    scale: float = 1.0,
) -> np.ndarray:
    """Sigma = scale * sigma_hat^2 (J^T J)^-1 of an LK solve that keeps neither (OpenCV's): J is the Scharr
    gradient of image 2 over the window at the solution, the residual the window difference.

    Args:
        image1, image2: the images (uint8 or float, 1-4 channels) the solve tracked ``pts1`` -> ``pts2`` on.
        window: the solve's window side (odd).
        scale: the method's fitted scale.

    Shape:
        image1, image2: (H, W) or (H, W, C). pts1, pts2: (N, 2). Returns (N, 3), px^2.
    """
    from nsflow_ros.core.solver import sample_windows  # the solver's exact bilinear sampler

    if window < 3 or window % 2 == 0:
        raise CoreError(f"window must be odd and >= 3, got {window}")
    a = np.asarray(pts1, dtype=np.float64)
    b = np.asarray(pts2, dtype=np.float64)
    if a.ndim != 2 or a.shape[1] != 2 or b.shape != a.shape:
        raise CoreError(f"pts1 and pts2 must both be (N, 2), got {a.shape} and {b.shape}")
    n = a.shape[0]
    if n == 0:
        return np.zeros((0, 3))

    def as_map(img: np.ndarray) -> np.ndarray:
        f = np.asarray(img, dtype=np.float32)
        return f[:, :, None] if f.ndim == 2 else f

    m1, m2 = as_map(image1), as_map(image2)
    if m1.shape != m2.shape:
        raise CoreError(f"image1 and image2 differ: {m1.shape} and {m2.shape}")
    b = np.where(np.isfinite(b), b, a)
    t = sample_windows(m1, a, window)  # (N, w, w, C)
    p = sample_windows(m2, b, window + 2)
    c = p.shape[3]
    flat = p.transpose(1, 0, 2, 3).reshape(window + 2, n * (window + 2), c)
    jx = cv2.Scharr(flat, cv2.CV_32F, 1, 0).reshape(window + 2, n, window + 2, c)[1:-1, :, 1:-1] / 32.0
    jy = cv2.Scharr(flat, cv2.CV_32F, 0, 1).reshape(window + 2, n, window + 2, c)[1:-1, :, 1:-1] / 32.0
    r = p[:, 1:-1, 1:-1].transpose(1, 0, 2, 3) - t.transpose(1, 0, 2, 3)
    hess = np.stack([np.einsum("imjk,imjk->m", jx, jx), np.einsum("imjk,imjk->m", jx, jy),
                     np.einsum("imjk,imjk->m", jy, jy)], axis=1).astype(np.float64)
    cost = 0.5 * np.einsum("imjk,imjk->m", r, r).astype(np.float64)
    return lm_covariance(hess, cost, window * window * c, scale)


def max_sigma(cov: np.ndarray) -> np.ndarray:
    """The standard deviation along each covariance's major axis (sqrt of its largest eigenvalue), px.

    Shape:
        cov: (N, 3) [uu, uv, vv]. Returns (N,).
    """
    c = np.asarray(cov, dtype=np.float64)
    tr = c[:, 0] + c[:, 2]
    with np.errstate(invalid="ignore"):
        diff = c[:, 0] - c[:, 2]
        out = np.sqrt(np.maximum(0.5 * (tr + np.sqrt(diff * diff + 4.0 * c[:, 1] ** 2)), 0.0))
    return np.where(np.isinf(tr), np.inf, out)  # a singular J^T J: no bound at all


def template_hessian(image: np.ndarray, pts: np.ndarray, window: int) -> np.ndarray:
    """J^T J of an OpenCV LK solve's template: the structure tensor of ``image`` over the window at each
    rounded point (the matrix OpenCV's own inverse-compositional step inverts).

    The windows are read at whole pixels, at most half a pixel from the point, once: no resampling.
    Central differences: OpenCV's Scharr without its cross smoothing, which the fitted scale absorbs.

    Args:
        image: the solve's first image (uint8 or float, 1-4 channels, at least window + 2 pixels a side).
        pts: the points it tracked (in ``image``); windows reaching past the border are moved inside.
        window: the solve's window side (odd).

    Shape:
        image: (H, W) or (H, W, C). pts: (N, 2). Returns (N, 3) [h11, h12, h22], summed over channels.

    Raises:
        CoreError: a window that is not odd and >= 3, points that are not (N, 2) and finite, an image that
            is not (H, W[, 1-4]) or is smaller than the window.
    """
    if window < 3 or window % 2 == 0:
        raise CoreError(f"window must be odd and >= 3, got {window}")
    a = np.asarray(pts, dtype=np.float64)
    if a.ndim != 2 or a.shape[1] != 2:
        raise CoreError(f"pts must be (N, 2), got {a.shape}")
    if not np.isfinite(a).all():
        i = int(np.flatnonzero(~np.isfinite(a).all(axis=1))[0])
        raise CoreError(f"pts must be finite, got {a[i].tolist()} at point {i}")
    img = np.asarray(image)
    if img.ndim not in (2, 3) or (img.ndim == 3 and not 1 <= img.shape[2] <= 4):
        raise CoreError(f"image must be (H, W) or (H, W, 1-4), got {img.shape}")
    side = window + 2  # one more pixel each way for the derivative
    height, width = img.shape[:2]
    if height < side or width < side:
        raise CoreError(f"image {width}x{height} is smaller than the {side}x{side} window of its derivative")
    n = a.shape[0]
    if n == 0:
        return np.zeros((0, 3))
    half = side // 2
    cx = np.clip(np.rint(a[:, 0]).astype(np.intp), half, width - 1 - half) - half
    cy = np.clip(np.rint(a[:, 1]).astype(np.intp), half, height - 1 - half) - half
    # one gather of every point's window (a view per top-left corner: no per-point call), flattened
    patch = sliding_window_view(img, (side, side), axis=(0, 1))[cy, cx]
    if patch.ndim == 3:
        patch = patch[:, None]  # (N, C, side, side)
    channels = patch.shape[1]
    flat = patch.reshape(n * channels, side * side).astype(np.float32)
    # the derivatives at every flattened position of rows 1..side-2; the weights keep columns 1..side-2
    lo, hi = side + 1, side * side - side - 1
    jx = flat[:, lo + 1:hi + 1] - flat[:, lo - 1:hi - 1]
    jy = flat[:, lo + side:hi + side] - flat[:, lo - side:hi - side]
    col = np.arange(lo, hi) % side
    inside = ((col >= 1) & (col <= side - 2)).astype(np.float32)
    hess = np.stack([(jx * jx) @ inside, (jx * jy) @ inside, (jy * jy) @ inside], axis=1)
    return hess.reshape(n, channels, 3).sum(axis=1, dtype=np.float64) / 4.0


def err_covariance(hessian: np.ndarray, err: np.ndarray, elements: int, scale: float = 1.0) -> np.ndarray:
    """Sigma = scale * sigma_hat^2 (J^T J)^-1 with sigma_hat^2 from OpenCV's per-point ``err``.

    ``err`` is the mean absolute window difference at the solution; for Gaussian residuals the RMS is
    sqrt(pi / 2) times it, so sigma_hat^2 = pi / 2 err^2 nC / (nC - 2) (the degrees of freedom of
    :func:`lm_covariance`; the fitted scale absorbs the rest).

    Args:
        hessian: J^T J per point (:func:`template_hessian`), [h11, h12, h22].
        err: OpenCV's ``err`` per point (``calcOpticalFlowPyrLK`` without
            ``OPTFLOW_LK_GET_MIN_EIGENVALS``).
        elements: window pixels times channels (n C).
        scale: the method's fitted scale.

    Shape:
        hessian: (N, 3). err: (N,). Returns (N, 3) [sigma_uu, sigma_uv, sigma_vv], px^2.

    Raises:
        CoreError: shapes that do not match, elements <= 2, or an ``err`` that is not finite and >= 0
            (naming the first one).
    """
    hess = np.asarray(hessian, dtype=np.float64)
    e = np.asarray(err, dtype=np.float64).reshape(-1)
    if hess.ndim != 2 or hess.shape[1] != 3 or e.shape != (hess.shape[0],):
        raise CoreError(f"hessian must be (N, 3) and err (N,), got {hess.shape} and {np.shape(err)}")
    if elements <= 2:
        raise CoreError(f"elements (window pixels x channels) must be > 2, got {elements}")
    bad = ~(np.isfinite(e) & (e >= 0))
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise CoreError(f"err must be finite and >= 0, got {float(e[i])!r} at point {i}")
    return _from_normal_equations(hess, scale * (0.5 * math.pi) * e * e * elements / (elements - 2))


def klt_covariance(image: np.ndarray, pts: np.ndarray, err: np.ndarray, window: int,
                   scale: float = 1.0) -> np.ndarray:
    """Sigma = scale * sigma_hat^2 (J^T J)^-1 of an OpenCV LK solve from what the solve already has:
    :func:`template_hessian` of its first image and :func:`err_covariance` of OpenCV's ``err``.

    Shape:
        image: (H, W) or (H, W, C). pts: (N, 2). err: (N,). Returns (N, 3) [sigma_uu, sigma_uv, sigma_vv],
        px^2.

    Raises:
        CoreError: as :func:`template_hessian` and :func:`err_covariance`.
    """
    e = np.asarray(err)
    a = np.asarray(pts)
    if e.reshape(-1).shape[0] != (a.shape[0] if a.ndim == 2 else -1):
        raise CoreError(f"pts must be (N, 2) and err (N,), got {a.shape} and {e.shape}")
    channels = 1 if np.ndim(image) == 2 else np.shape(image)[2]
    hess = template_hessian(image, pts, window)
    return err_covariance(hess, err, window * window * channels, scale)
