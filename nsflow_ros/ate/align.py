"""Least-squares alignment of an estimate onto a reference: Umeyama SE(3) / Sim(3), or none.

Umeyama's closed form maps the estimate's positions p to ``s R p + t`` minimising the squared distance to
the matched reference positions; R is always a proper rotation, never a reflection.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from nsflow_ros.ate.errors import ATEError
from nsflow_ros.ate.trajectory import Trajectory

__all__ = ["ALIGN_METHODS", "Alignment", "align_trajectory", "umeyama"]

ALIGN_METHODS: tuple[str, ...] = ("se3", "sim3", "none")
"""Accepted alignment names: rigid, similarity (with scale), identity."""

_MIN_POINTS = 3


@dataclass(frozen=True, eq=False)
class Alignment:
    """A similarity transform ``p' = scale * rotation @ p + translation`` (metres), the ``method`` of
    :data:`ALIGN_METHODS` it was fitted by, on ``n_points`` point pairs (0 for none).

    Shape:
        rotation (3, 3), translation (3,).
    """

    rotation: np.ndarray = field(default_factory=lambda: np.eye(3))
    translation: np.ndarray = field(default_factory=lambda: np.zeros(3))
    scale: float = 1.0
    method: str = "none"
    n_points: int = 0

    def matrix(self) -> np.ndarray:
        """The 4 x 4 homogeneous matrix ``[[s R, t], [0, 1]]``."""
        out = np.eye(4)
        out[:3, :3] = self.scale * np.asarray(self.rotation)
        out[:3, 3] = self.translation
        return out

    def apply(self, points: np.ndarray) -> np.ndarray:
        """Positions of the estimate's frame in the reference frame.

        Shape:
            points (N, 3) -> (N, 3).

        Raises:
            ATEError: when ``points`` is not (N, 3).
        """
        pts = np.asarray(points, dtype=np.float64)
        if pts.ndim != 2 or pts.shape[1] != 3:
            raise ATEError(f"points must have shape (N, 3), got {pts.shape}")
        return self.scale * pts @ np.asarray(self.rotation).T + np.asarray(self.translation)

    def as_dict(self) -> dict[str, object]:
        """The transform as JSON-ready lists and numbers."""
        return {
            "method": self.method,
            "scale": float(self.scale),
            "rotation": np.asarray(self.rotation).tolist(),
            "translation": np.asarray(self.translation).tolist(),
            "n_points": int(self.n_points),
        }


def _check_points(name: str, pts: np.ndarray) -> None:
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ATEError(f"{name} must have shape (N, 3), got {pts.shape}")
    if not np.all(np.isfinite(pts)):
        row = int(np.argwhere(~np.isfinite(pts))[0][0])
        raise ATEError(f"{name} contain NaN or inf (first at row {row}: {pts[row]})", reason="nan")


def umeyama(source: np.ndarray, target: np.ndarray, *, with_scale: bool = False) -> Alignment:
    """The similarity (Sim(3) ``with_scale``, else SE(3)) that best maps ``source`` onto ``target`` rows.

    Shape:
        source (N, 3), target (N, 3), N >= 3.

    Raises:
        ATEError: for mismatched shapes, NaNs, fewer than 3 pairs, or a degenerate source (all points equal
            or on one line, where the rotation about the line is undetermined).
    """
    src = np.asarray(source, dtype=np.float64)
    dst = np.asarray(target, dtype=np.float64)
    _check_points("source points", src)
    _check_points("target points", dst)
    if src.shape != dst.shape:
        raise ATEError(f"source and target must have the same shape, got {src.shape} and {dst.shape}")
    n = src.shape[0]
    if n < _MIN_POINTS:
        raise ATEError(f"alignment needs at least {_MIN_POINTS} point pairs, got {n}", reason="too_few")
    mu_src = src.mean(axis=0)
    mu_dst = dst.mean(axis=0)
    a = src - mu_src
    b = dst - mu_dst
    var_src = float(np.mean(np.sum(a * a, axis=1)))
    spread = np.linalg.svd(a, compute_uv=False)
    if var_src <= 0.0 or spread[1] <= 1e-9 * max(spread[0], 1e-300):
        raise ATEError(
            f"alignment is degenerate: the {n} estimate positions are all equal or collinear "
            f"(singular values {spread.tolist()})",
            reason="degenerate",
        )
    cov = b.T @ a / n
    u, d, vt = np.linalg.svd(cov)
    sign = np.ones(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0.0:
        sign[2] = -1.0
    rot = (u * sign) @ vt
    scale = float(np.sum(d * sign) / var_src) if with_scale else 1.0
    trans = mu_dst - scale * rot @ mu_src
    return Alignment(rot, trans, scale, "sim3" if with_scale else "se3", n)


def align_trajectory(
    est: Trajectory, ref: Trajectory, method: str = "se3", n_first: int | None = None
) -> tuple[Trajectory, Alignment]:
    """Align a matched estimate onto its matched reference: (the transformed estimate, the transform).

    Args:
        est: estimate poses, paired index by index with ``ref``.
        ref: reference poses.
        method: one of :data:`ALIGN_METHODS`.
        n_first: fit on the first N pairs only (``None``: all); the transform is applied to all poses.

    Raises:
        ATEError: for an unknown method, different lengths, an ``n_first`` outside [3, len], or any error
            of :func:`umeyama`.
    """
    if method not in ALIGN_METHODS:
        raise ATEError(f"unknown alignment {method!r}; expected one of {', '.join(ALIGN_METHODS)}")
    if len(est) != len(ref):
        raise ATEError(f"matched trajectories must have the same length, got {len(est)} and {len(ref)}")
    if method == "none":
        return est, Alignment()
    n = len(est)
    if n_first is not None:
        if not _MIN_POINTS <= n_first <= n:
            raise ATEError(f"n_first must be between {_MIN_POINTS} and the {n} matched poses, got {n_first}")
        n = n_first
    fit = umeyama(est.positions[:n], ref.positions[:n], with_scale=method == "sim3")
    return est.transformed(fit.rotation, fit.translation, fit.scale), fit
