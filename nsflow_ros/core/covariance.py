"""A calibrated 2x2 covariance per tracked feature, from the final Lucas-Kanade solve.

For a window cost S(u) = 1/2 sum ||r||^2 over n pixels and C channels, the Gauss-Newton covariance of the
solution is Sigma = s * sigma_hat^2 (J^T J)^-1 with sigma_hat^2 = 2 S / (n C - 2), the residual variance
left after fitting the two unknowns (PNEC, CVPR 2022). Such covariances run optimistic (neighbouring
residuals are correlated, the model is not exactly a translation), so ``s``, one scale per method and
model, is fitted on training data (``python -m nsflow_ros.evaluation.covariance fit``) and stored with
the model: its ONNX metadata key :data:`METADATA_KEY`, else a JSON file beside it (``<model stem>``
:data:`SIDECAR_SUFFIX`), both ``{"<method>": scale, ...}``; the methods without a model keep theirs in
their registry entry (:attr:`~nsflow_ros.core.methods.MethodSpec.covariance_scale`).

The LM methods take J^T J and S from the solver's own last step
(:attr:`~nsflow_ros.core.solver.TrackResult.hessian`); OpenCV's LK keeps neither, so
:func:`window_covariance` forms them from the image windows at the solution.
Covariances are [sigma_uu, sigma_uv, sigma_vv] in pixels^2 of the full-resolution image.
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

from nsflow_ros.core.errors import CoreError

__all__ = [
    "DETECTION_VARIANCE",
    "METADATA_KEY",
    "SIDECAR_SUFFIX",
    "CovarianceScale",
    "lm_covariance",
    "max_sigma",
    "read_scale",
    "sidecar_path",
    "window_covariance",
]

METADATA_KEY = "covariance_scale"
"""ONNX metadata key of a model's fitted scales: JSON ``{"<method>": scale}``."""
SIDECAR_SUFFIX = ".covariance.json"
"""Suffix of the JSON file beside a model that holds its fitted scales (when its metadata has none)."""
DETECTION_VARIANCE = 1.0 / 12.0
"""Variance (px^2, per axis) of a feature detected in this frame: GFTT returns whole pixels, whose
rounding error is uniform over one pixel."""


@dataclass(frozen=True)
class CovarianceScale:
    """The scale ``s`` a method's covariances are multiplied by, and where it came from.

    Attributes:
        scale: s (> 0); 1.0 when no fitted value was found.
        source: "metadata", a sidecar file's name, "registry", or "uncalibrated" (with the reason when a
            sidecar's scale was fitted on another model file: its ``model_sha256`` differs).
    """

    scale: float = 1.0
    source: str = "uncalibrated"

    @property
    def calibrated(self) -> bool:
        """Whether the scale was fitted (else the raw Gauss-Newton covariance is used)."""
        return not self.source.startswith("uncalibrated")


def sidecar_path(model: str | Path) -> Path:
    """The JSON file beside ``model`` that holds its fitted scales (``nsflow_encoder.covariance.json``)."""
    p = Path(model)
    return p.with_name(p.stem + SIDECAR_SUFFIX)


def _scale_of(table: Mapping[str, Any], method: str, where: str) -> float | None:
    value = table.get(method)
    if value is None:
        return None
    bad = isinstance(value, bool) or not isinstance(value, int | float)
    if bad or not math.isfinite(value) or value <= 0:
        raise CoreError(f"{where}: covariance scale of {method!r} must be a finite number > 0, got {value!r}")
    return float(value)


def read_scale(method: str, metadata: Mapping[str, str] | None = None, model: str | Path | None = None,
               registry: float | None = None) -> CovarianceScale:
    """The fitted scale of ``method``: from the model's metadata, else its sidecar file, else ``registry``.

    Args:
        method: the method's registry name (a model may carry a scale per method).
        metadata: the model's ONNX metadata (``Encoder.metadata``); None = none.
        model: the model file, whose sidecar is read; None = none.
        registry: the method's own registry value (methods without a model); None = none.

    Returns:
        the scale and its source; ``CovarianceScale()`` (1.0, uncalibrated) when none is found.

    Raises:
        CoreError: malformed JSON or a scale that is not a number > 0 (naming the file or key).
    """
    if metadata and METADATA_KEY in metadata:
        where = f"model metadata {METADATA_KEY!r}"
        try:
            table = json.loads(metadata[METADATA_KEY])
        except (json.JSONDecodeError, TypeError) as err:
            raise CoreError(f"{where} is not JSON: {err}") from err
        if not isinstance(table, dict):
            raise CoreError(f"{where} must be a JSON object of scales by method, got {table!r}")
        found = _scale_of(table, method, where)
        if found is not None:
            return CovarianceScale(found, "metadata")
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
            found = _scale_of(scales, method, str(side))
            fitted = table.get("model_sha256")
            if found is not None and fitted is not None and fitted != _sha256(Path(model)):
                # a model replaced under the same name: its scale must be fitted again
                return CovarianceScale(1.0, f"uncalibrated ({side.name} was fitted on another model file)")
            if found is not None:
                return CovarianceScale(found, side.name)
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
