"""Camera models of camodocal, the library VINS-Fusion and VINS-Mono load their cameras with.

``PINHOLE`` (radial-tangential distortion), ``KANNALA_BRANDT`` (equidistant fisheye, ``cv2.fisheye``'s
model) and ``MEI`` (unified omnidirectional, radial-tangential distortion), with camodocal's parameter
names and file layout, vectorised over N points in float64: ``lift_rays`` is camodocal's
``liftProjective``, ``lift`` divides its ray by z (the undistorted point the VINS trackers publish) and
``project`` is ``spaceToPlane``.

Undistortion follows camodocal step for step, so a tracker built on these models publishes the stock
tracker's numbers: PINHOLE and MEI run 8 fixed-point iterations (``undistort_iterations``), which do not
converge near the corners of a strongly distorted lens, as in VINS.
"""

from __future__ import annotations

import math
import numbers
import os
from abc import ABC, abstractmethod
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path
from typing import Any, ClassVar

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from nsflow_ros.core.errors import CoreError
from nsflow_ros.core.opencv_yaml import OpenCVYamlError, read_opencv_yaml

__all__ = [
    "CAMERA_MODELS",
    "CameraError",
    "CameraModel",
    "KannalaBrandtCamera",
    "MeiCamera",
    "PinholeCamera",
    "camera_from_dict",
    "load_camera",
    "radtan_distort",
]

_CAMODOCAL_ITERATIONS = 8  # PinholeCamera / CataCamera::liftProjective, "recursive distortion model"
_ROOT_TOL = 1e-10  # EquidistantCamera::backprojectSymmetric: imaginary-part and negativity tolerance

Float64Array = NDArray[np.float64]


class CameraError(CoreError):
    """A camera model cannot be built or used: bad parameters, bad file, bad input array."""


# ----------------------------------------------------------------------------------------------------------
# Guards and shared maths


def _as_points(values: ArrayLike, dim: int, name: str) -> Float64Array:
    """Return ``values`` as a float64 (N, dim) array, or raise naming expected and actual shape/dtype."""
    try:
        arr = np.asarray(values)
    except (ValueError, TypeError) as err:  # ragged nested lists
        raise CameraError(f"{name} must be an array of shape (N, {dim}): {err}") from err
    if arr.dtype.kind not in "iuf":
        raise CameraError(f"{name} must hold real numbers (integer or floating dtype), got dtype {arr.dtype}")
    if arr.ndim != 2 or arr.shape[1] != dim:
        raise CameraError(f"{name} must have shape (N, {dim}), got {arr.shape}")
    return arr.astype(np.float64, copy=False)


def _radtan_offset(
    x: Float64Array, y: Float64Array, k1: float, k2: float, p1: float, p2: float
) -> tuple[Float64Array, Float64Array]:
    """camodocal's ``distortion``: the offset d with distorted = undistorted + d (normalised plane)."""
    x2 = x * x
    y2 = y * y
    xy = x * y
    rho2 = x2 + y2
    radial = k1 * rho2 + k2 * rho2 * rho2
    dx = x * radial + 2.0 * p1 * xy + p2 * (rho2 + 2.0 * x2)
    dy = y * radial + 2.0 * p2 * xy + p1 * (rho2 + 2.0 * y2)
    return dx, dy


def _radtan_remove(
    xd: Float64Array, yd: Float64Array, coeffs: tuple[float, float, float, float], iterations: int
) -> tuple[Float64Array, Float64Array]:
    """camodocal's fixed-point undistortion: u <- d - offset(u), started from u = d - offset(d)."""
    if not any(coeffs):  # camodocal's m_noDistortion shortcut
        return xd.copy(), yd.copy()
    x, y = xd, yd
    for _ in range(iterations):
        dx, dy = _radtan_offset(x, y, *coeffs)
        x, y = xd - dx, yd - dy
    return x, y


def _radtan_apply(
    x: Float64Array, y: Float64Array, coeffs: tuple[float, float, float, float]
) -> tuple[Float64Array, Float64Array]:
    if not any(coeffs):
        return x, y
    dx, dy = _radtan_offset(x, y, *coeffs)
    return x + dx, y + dy


def radtan_distort(points: ArrayLike, coeffs: ArrayLike) -> Float64Array:
    """Apply radial-tangential distortion ``coeffs`` (k1, k2, p1, p2) to normalised points (x/z, y/z).

    Shape:
        points: (N, 2) -> (N, 2) float64.

    Raises:
        CameraError: ``points`` is not (N, 2) or ``coeffs`` does not hold four numbers.
    """
    p = _as_points(points, 2, "points")
    c = np.asarray(coeffs, dtype=np.float64).ravel()
    if c.shape != (4,):
        raise CameraError(f"radtan coefficients must be (k1, k2, p1, p2), got shape {c.shape}")
    x, y = _radtan_apply(p[:, 0], p[:, 1], (float(c[0]), float(c[1]), float(c[2]), float(c[3])))
    return np.stack([x, y], axis=1)


def _check_real(
    owner: str, key: str, value: Any, *, positive: bool = False, non_negative: bool = False
) -> float:
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise CameraError(f"{owner}: {key} must be a real number, got {type(value).__name__} {value!r}")
    out = float(value)
    if not math.isfinite(out):
        raise CameraError(f"{owner}: {key} must be finite, got {out}")
    if positive and out <= 0.0:
        raise CameraError(f"{owner}: {key} must be > 0, got {out}")
    if non_negative and out < 0.0:
        raise CameraError(f"{owner}: {key} must be >= 0, got {out}")
    return out


def _check_int(owner: str, key: str, value: Any, minimum: int) -> int:
    if isinstance(value, bool) or not isinstance(value, numbers.Integral):
        raise CameraError(f"{owner}: {key} must be an integer, got {type(value).__name__} {value!r}")
    if int(value) < minimum:
        raise CameraError(f"{owner}: {key} must be >= {minimum}, got {int(value)}")
    return int(value)


# ----------------------------------------------------------------------------------------------------------
# Models


@dataclass(frozen=True, kw_only=True)
class CameraModel(ABC):
    """Base of the camodocal camera models: image ``width`` and ``height`` in pixels, ``name``, and the
    class attribute ``model_type`` ("PINHOLE", "KANNALA_BRANDT" or "MEI").

    The geometry methods take (N, 2) pixels or (N, 3) points of any real dtype and raise
    :class:`CameraError` on other input.
    """

    width: int
    height: int
    name: str = "camera"

    model_type: ClassVar[str]
    # camodocal file layout: (map name, parameter names in file order), in file order.
    PARAMETER_GROUPS: ClassVar[tuple[tuple[str, tuple[str, ...]], ...]]
    # parameters that must be > 0 / >= 0.
    _POSITIVE: ClassVar[frozenset[str]] = frozenset()
    _NON_NEGATIVE: ClassVar[frozenset[str]] = frozenset()

    def __post_init__(self) -> None:
        owner = type(self).__name__
        object.__setattr__(self, "width", _check_int(owner, "width", self.width, 1))
        object.__setattr__(self, "height", _check_int(owner, "height", self.height, 1))
        if not isinstance(self.name, str):
            raise CameraError(f"{owner}: name must be a string, got {type(self.name).__name__} {self.name!r}")
        for key in self.parameter_names():
            value = _check_real(
                owner,
                key,
                getattr(self, key),
                positive=key in self._POSITIVE,
                non_negative=key in self._NON_NEGATIVE,
            )
            object.__setattr__(self, key, value)
        iterations = getattr(self, "undistort_iterations", None)
        if iterations is not None:
            iterations = _check_int(owner, "undistort_iterations", iterations, 1)
            object.__setattr__(self, "undistort_iterations", iterations)

    # -- parameters ------------------------------------------------------------------------------------

    @classmethod
    def parameter_names(cls) -> tuple[str, ...]:
        """Return the model's parameter names in camodocal file order."""
        return tuple(key for _, keys in cls.PARAMETER_GROUPS for key in keys)

    @property
    def parameters(self) -> dict[str, float]:
        """The model's parameters by camodocal name, in file order."""
        return {key: getattr(self, key) for key in self.parameter_names()}

    def to_dict(self) -> dict[str, Any]:
        """The camodocal file layout as a dict (the inverse of :func:`camera_from_dict`)."""
        out: dict[str, Any] = {
            "model_type": self.model_type,
            "camera_name": self.name,
            "image_width": self.width,
            "image_height": self.height,
        }
        for group, keys in self.PARAMETER_GROUPS:
            out[group] = {key: getattr(self, key) for key in keys}
        return out

    def save_yaml(self, path: str | os.PathLike[str]) -> None:
        """Write the camera as a camodocal YAML file (``%YAML:1.0``, 17 significant digits).

        Raises:
            CameraError: when the file cannot be written.
        """
        storage = cv2.FileStorage(
            "camera.yaml", cv2.FILE_STORAGE_WRITE | cv2.FILE_STORAGE_MEMORY | cv2.FILE_STORAGE_FORMAT_YAML
        )
        for key, value in self.to_dict().items():
            if isinstance(value, dict):
                storage.startWriteStruct(key, cv2.FileNode_MAP)
                for sub, number in value.items():
                    storage.write(sub, float(number))
                storage.endWriteStruct()
            else:
                storage.write(key, value)
        text = storage.releaseAndGetString()
        # OpenCV 5 writes "%YAML 1.2"; camodocal-era readers expect the OpenCV 3/4 header.
        body = text.split("\n", 1)[1] if text.startswith("%YAML") else text
        try:
            Path(path).write_text("%YAML:1.0\n" + body, encoding="utf-8")
        except OSError as err:
            raise CameraError(f"cannot write camera file {path}: {err.strerror or err}") from err

    @classmethod
    def from_yaml(cls, path: str | os.PathLike[str]) -> CameraModel:
        """Read a camodocal camera file (:func:`load_camera`); on a subclass, of that subclass's model_type.

        Raises:
            CameraError: naming the file and the key at fault.
        """
        camera = load_camera(path)
        if cls is not CameraModel and not isinstance(camera, cls):
            raise CameraError(f"{path}: model_type is {camera.model_type}, expected {cls.model_type}")
        return camera

    # -- geometry --------------------------------------------------------------------------------------

    @abstractmethod
    def lift_rays(self, pixels: ArrayLike) -> Float64Array:
        """Lift distorted pixels (u, v) to (N, 3) camera-frame rays, as camodocal's ``liftProjective``."""

    @abstractmethod
    def project(self, points: ArrayLike) -> Float64Array:
        """Project points (X, Y, Z) in the camera frame to (N, 2) distorted pixels (``spaceToPlane``).

        As in camodocal there is no visibility test: a point with no valid projection gives inf / nan or a
        mirrored pixel.
        """

    def lift(self, pixels: ArrayLike) -> Float64Array:
        """Lift distorted pixels (u, v) to the undistorted normalised plane (x/z, y/z) that VINS publishes.

        Pixels whose ray has z <= 0 give inf or mirrored values, as in VINS.
        """
        rays = self.lift_rays(pixels)
        with np.errstate(divide="ignore", invalid="ignore"):
            return rays[:, :2] / rays[:, 2:3]


@dataclass(frozen=True, kw_only=True)
class PinholeCamera(CameraModel):
    """camodocal ``PINHOLE``: pinhole projection with radial-tangential distortion.

    Projection: x = X/Z, y = Y/Z; distorted = (x, y) + radtan offset; u = fx x_d + cx, v = fy y_d + cy.
    ``lift_rays`` returns (x, y, 1).

    Attributes:
        fx, fy, cx, cy: projection parameters (pixels); fx, fy > 0.
        k1, k2, p1, p2: distortion parameters (default 0: no distortion).
        undistort_iterations: fixed-point iterations of the undistortion (camodocal: 8).
    """

    fx: float
    fy: float
    cx: float
    cy: float
    k1: float = 0.0
    k2: float = 0.0
    p1: float = 0.0
    p2: float = 0.0
    undistort_iterations: int = _CAMODOCAL_ITERATIONS

    model_type: ClassVar[str] = "PINHOLE"
    PARAMETER_GROUPS: ClassVar[tuple[tuple[str, tuple[str, ...]], ...]] = (
        ("distortion_parameters", ("k1", "k2", "p1", "p2")),
        ("projection_parameters", ("fx", "fy", "cx", "cy")),
    )
    _POSITIVE: ClassVar[frozenset[str]] = frozenset({"fx", "fy"})

    @property
    def camera_matrix(self) -> Float64Array:
        """The 3x3 intrinsic matrix K, as OpenCV expects it."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def dist_coeffs(self) -> Float64Array:
        """OpenCV distortion coefficients (k1, k2, p1, p2): the same model as camodocal's."""
        return np.array([self.k1, self.k2, self.p1, self.p2])

    def lift_rays(self, pixels: ArrayLike) -> Float64Array:
        p = _as_points(pixels, 2, "pixels")
        # camodocal's inverse-K terms, kept in its form so results match it to the last bit.
        xd = (1.0 / self.fx) * p[:, 0] + (-self.cx / self.fx)
        yd = (1.0 / self.fy) * p[:, 1] + (-self.cy / self.fy)
        x, y = _radtan_remove(xd, yd, (self.k1, self.k2, self.p1, self.p2), self.undistort_iterations)
        return np.stack([x, y, np.ones_like(x)], axis=1)

    def project(self, points: ArrayLike) -> Float64Array:
        q = _as_points(points, 3, "points")
        with np.errstate(divide="ignore", invalid="ignore"):
            x = q[:, 0] / q[:, 2]
            y = q[:, 1] / q[:, 2]
            xd, yd = _radtan_apply(x, y, (self.k1, self.k2, self.p1, self.p2))
            return np.stack([self.fx * xd + self.cx, self.fy * yd + self.cy], axis=1)


@dataclass(frozen=True, kw_only=True)
class KannalaBrandtCamera(CameraModel):
    """camodocal ``KANNALA_BRANDT``: equidistant fisheye (OpenCV ``cv2.fisheye`` model).

    Projection: theta = angle from the optical axis, phi = atan2(Y, X);
    r = theta + k2 theta^3 + k3 theta^5 + k4 theta^7 + k5 theta^9; u = mu r cos(phi) + u0,
    v = mv r sin(phi) + v0. ``lift_rays`` returns the unit ray (sin theta cos phi, sin theta sin phi,
    cos theta), theta being the smallest non-negative real root of r(theta) = |p| (theta = |p| when there
    is none). Valid beyond 90 degrees: ``project`` uses acos, not atan.

    The polynomial's degree is set by its highest non-zero coefficient: camodocal's count of zeros
    divides by zero when a zero precedes a non-zero one, and agrees otherwise.

    Attributes:
        k2, k3, k4, k5: polynomial coefficients (default 0).
        mu, mv, u0, v0: projection parameters (pixels); mu, mv > 0.
    """

    mu: float
    mv: float
    u0: float
    v0: float
    k2: float = 0.0
    k3: float = 0.0
    k4: float = 0.0
    k5: float = 0.0

    model_type: ClassVar[str] = "KANNALA_BRANDT"
    PARAMETER_GROUPS: ClassVar[tuple[tuple[str, tuple[str, ...]], ...]] = (
        ("projection_parameters", ("k2", "k3", "k4", "k5", "mu", "mv", "u0", "v0")),
    )
    _POSITIVE: ClassVar[frozenset[str]] = frozenset({"mu", "mv"})

    @property
    def camera_matrix(self) -> Float64Array:
        """The 3x3 intrinsic matrix K, as ``cv2.fisheye`` expects it."""
        return np.array([[self.mu, 0.0, self.u0], [0.0, self.mv, self.v0], [0.0, 0.0, 1.0]])

    @property
    def dist_coeffs(self) -> Float64Array:
        """``cv2.fisheye`` distortion coefficients (k1, k2, k3, k4) = camodocal (k2, k3, k4, k5)."""
        return np.array([self.k2, self.k3, self.k4, self.k5])

    def radius(self, theta: ArrayLike) -> Float64Array:
        """r(theta) = theta + k2 theta^3 + k3 theta^5 + k4 theta^7 + k5 theta^9 (elementwise)."""
        t = np.asarray(theta, dtype=np.float64)
        t2 = t * t
        t3 = t2 * t
        t5 = t3 * t2
        t7 = t5 * t2
        t9 = t7 * t2
        return t + self.k2 * t3 + self.k3 * t5 + self.k4 * t7 + self.k5 * t9

    def _radius_slope(self, theta: Float64Array) -> Float64Array:
        t2 = theta * theta
        return 1.0 + t2 * (3.0 * self.k2 + t2 * (5.0 * self.k3 + t2 * (7.0 * self.k4 + t2 * 9.0 * self.k5)))

    @cached_property
    def _monotonic_limit(self) -> float:
        """First theta > 0 where dr/dtheta = 0 (inf if none): r is increasing on [0, this limit]."""
        # dr/dtheta = 1 + 3 k2 s + 5 k3 s^2 + 7 k4 s^3 + 9 k5 s^4 with s = theta^2.
        slope = np.array([9.0 * self.k5, 7.0 * self.k4, 5.0 * self.k3, 3.0 * self.k2, 1.0])
        slope = np.trim_zeros(slope, "f")
        if slope.size < 2:
            return math.inf
        roots = np.roots(slope)
        # Count near-real roots as real: a limit that is too small only sends more points to the fallback.
        real = roots[np.abs(roots.imag) <= 1e-8 * np.maximum(1.0, np.abs(roots))].real
        positive = real[real > 0.0]
        return float(np.sqrt(positive.min())) if positive.size else math.inf

    def _theta(self, rho: Float64Array) -> Float64Array:
        """Smallest non-negative real root of r(theta) = rho (rho itself if there is none), camodocal's pick.

        Where r increases on [0, limit] and rho <= r(limit) that root is unique and safeguarded Newton finds
        it fast; elsewhere camodocal's companion-matrix eigenvalues decide.
        """
        if not any((self.k2, self.k3, self.k4, self.k5)) or rho.size == 0:
            return rho.copy()
        limit = self._monotonic_limit
        reach = math.inf if math.isinf(limit) else float(self.radius(limit))
        inside = rho <= reach
        theta = np.empty_like(rho)
        theta[inside] = self._theta_newton(rho[inside], limit)
        if not inside.all():
            theta[~inside] = self._theta_companion(rho[~inside])
        return theta

    def _theta_newton(self, rho: Float64Array, limit: float) -> Float64Array:
        lo = np.zeros_like(rho)
        if math.isinf(limit):  # r increasing everywhere: grow a bracket until r(hi) >= rho
            hi = np.maximum(rho, 1.0)
            for _ in range(64):
                short = self.radius(hi) < rho
                if not short.any():
                    break
                hi = np.where(short, 2.0 * hi, hi)
        else:
            hi = np.full_like(rho, limit)
        theta = np.clip(rho, lo, hi)
        for _ in range(100):
            f = self.radius(theta) - rho
            lo = np.where(f < 0.0, theta, lo)
            hi = np.where(f > 0.0, theta, hi)
            with np.errstate(divide="ignore", invalid="ignore"):
                step = theta - f / self._radius_slope(theta)
            inside = (step > lo) & (step < hi)
            step = np.where(inside, step, 0.5 * (lo + hi))
            step = np.where(f == 0.0, theta, step)
            done = np.abs(step - theta) <= 4.0 * np.finfo(np.float64).eps * np.maximum(theta, 1e-300)
            theta = step
            if done.all():
                break
        return theta

    def _theta_companion(self, rho: Float64Array) -> Float64Array:
        """camodocal's way: eigenvalues of the companion matrix, smallest real root >= 0 (tolerance 1e-10)."""
        coeffs = (self.k2, self.k3, self.k4, self.k5)
        top = max((i for i, c in enumerate(coeffs) if c != 0.0), default=-1)
        if top < 0 or rho.size == 0:
            return rho.copy()
        degree = 2 * top + 3
        lead = coeffs[top]
        # Companion matrix of  -rho + theta + k2 theta^3 + ... + lead theta^degree  (monic after / lead).
        poly = np.zeros(degree)
        poly[1] = 1.0
        for i, c in enumerate(coeffs[:top]):
            poly[2 * i + 3] = c
        companion = np.zeros((degree, degree))
        companion[np.arange(1, degree), np.arange(degree - 1)] = 1.0
        companion[:, degree - 1] = -poly / lead
        batch = np.broadcast_to(companion, (rho.size, degree, degree)).copy()
        batch[:, 0, degree - 1] = rho / lead
        roots = np.linalg.eigvals(batch)
        real = roots.real
        valid = (np.abs(roots.imag) <= _ROOT_TOL) & (real >= -_ROOT_TOL)
        candidates = np.where(valid, np.maximum(real, 0.0), np.inf)
        theta = candidates.min(axis=1)
        return np.where(np.isfinite(theta), theta, rho)

    def lift_rays(self, pixels: ArrayLike) -> Float64Array:
        p = _as_points(pixels, 2, "pixels")
        x = (1.0 / self.mu) * p[:, 0] + (-self.u0 / self.mu)
        y = (1.0 / self.mv) * p[:, 1] + (-self.v0 / self.mv)
        rho = np.sqrt(x * x + y * y)
        phi = np.where(rho < 1e-10, 0.0, np.arctan2(y, x))
        theta = self._theta(rho)
        sin_t = np.sin(theta)
        return np.stack([sin_t * np.cos(phi), sin_t * np.sin(phi), np.cos(theta)], axis=1)

    def project(self, points: ArrayLike) -> Float64Array:
        q = _as_points(points, 3, "points")
        with np.errstate(divide="ignore", invalid="ignore"):
            norm = np.sqrt(np.sum(q * q, axis=1))
            theta = np.arccos(q[:, 2] / norm)
            phi = np.arctan2(q[:, 1], q[:, 0])
            r = self.radius(theta)
            return np.stack(
                [self.mu * r * np.cos(phi) + self.u0, self.mv * r * np.sin(phi) + self.v0], axis=1
            )


@dataclass(frozen=True, kw_only=True)
class MeiCamera(CameraModel):
    """camodocal ``MEI``: unified omnidirectional model (Mei and Rives) with radial-tangential distortion.

    Projection: z' = Z + xi |P|; (x, y) = (X, Y) / z'; distorted = (x, y) + radtan offset;
    u = gamma1 x_d + u0, v = gamma2 y_d + v0. ``lift_rays`` undistorts like PINHOLE and returns
    (x, y, 1 - xi (rho^2 + 1) / (xi + sqrt(1 + (1 - xi^2) rho^2))), rho^2 = x^2 + y^2, or
    (x, y, (1 - rho^2) / 2) when xi == 1; this ray is not unit length. For xi > 1 pixels outside the
    model's image circle lift to nan.

    Attributes:
        xi: mirror parameter, >= 0.
        k1, k2, p1, p2: distortion parameters (default 0).
        gamma1, gamma2, u0, v0: generalised projection parameters (pixels); gamma1, gamma2 > 0.
        undistort_iterations: fixed-point iterations of the undistortion (camodocal: 8).
    """

    xi: float
    gamma1: float
    gamma2: float
    u0: float
    v0: float
    k1: float = 0.0
    k2: float = 0.0
    p1: float = 0.0
    p2: float = 0.0
    undistort_iterations: int = _CAMODOCAL_ITERATIONS

    model_type: ClassVar[str] = "MEI"
    PARAMETER_GROUPS: ClassVar[tuple[tuple[str, tuple[str, ...]], ...]] = (
        ("mirror_parameters", ("xi",)),
        ("distortion_parameters", ("k1", "k2", "p1", "p2")),
        ("projection_parameters", ("gamma1", "gamma2", "u0", "v0")),
    )
    _POSITIVE: ClassVar[frozenset[str]] = frozenset({"gamma1", "gamma2"})
    _NON_NEGATIVE: ClassVar[frozenset[str]] = frozenset({"xi"})

    def lift_rays(self, pixels: ArrayLike) -> Float64Array:
        p = _as_points(pixels, 2, "pixels")
        xd = (1.0 / self.gamma1) * p[:, 0] + (-self.u0 / self.gamma1)
        yd = (1.0 / self.gamma2) * p[:, 1] + (-self.v0 / self.gamma2)
        x, y = _radtan_remove(xd, yd, (self.k1, self.k2, self.p1, self.p2), self.undistort_iterations)
        rho2 = x * x + y * y
        xi = self.xi
        if xi == 1.0:
            z = (1.0 - rho2) / 2.0
        else:
            with np.errstate(invalid="ignore"):
                z = 1.0 - xi * (rho2 + 1.0) / (xi + np.sqrt(1.0 + (1.0 - xi * xi) * rho2))
        return np.stack([x, y, z], axis=1)

    def project(self, points: ArrayLike) -> Float64Array:
        q = _as_points(points, 3, "points")
        with np.errstate(divide="ignore", invalid="ignore"):
            z = q[:, 2] + self.xi * np.sqrt(np.sum(q * q, axis=1))
            x = q[:, 0] / z
            y = q[:, 1] / z
            xd, yd = _radtan_apply(x, y, (self.k1, self.k2, self.p1, self.p2))
            return np.stack([self.gamma1 * xd + self.u0, self.gamma2 * yd + self.v0], axis=1)


CAMERA_MODELS: dict[str, type[CameraModel]] = {
    cls.model_type: cls for cls in (PinholeCamera, KannalaBrandtCamera, MeiCamera)
}
"""The supported models by camodocal ``model_type`` (matched case-insensitively, as camodocal does)."""


# ----------------------------------------------------------------------------------------------------------
# Construction from files


def camera_from_dict(data: dict[str, Any], *, source: str = "<dict>") -> CameraModel:
    """Build a camera from camodocal's file layout in a dict (other keys, as a VINS-Mono config's, ignored).

    Unlike camodocal, a missing model_type or parameter is an error rather than MEI / zero.

    Args:
        data: model_type, image_width, image_height, optionally camera_name and the model's parameter maps.
        source: what to name in error messages (the file the dict came from).

    Raises:
        CameraError: naming ``source`` and the key missing, of the wrong type or out of range.
    """
    model = data.get("model_type")
    if model is None:
        raise CameraError(f"{source}: missing key 'model_type' (one of {', '.join(CAMERA_MODELS)})")
    if not isinstance(model, str):
        raise CameraError(f"{source}: key 'model_type' must be a string, got {model!r}")
    cls = CAMERA_MODELS.get(model.upper())
    if cls is None:
        supported = ", ".join(CAMERA_MODELS)
        raise CameraError(f"{source}: key 'model_type': unsupported model {model!r} (supported: {supported})")

    kwargs: dict[str, Any] = {}
    for key, arg in (("image_width", "width"), ("image_height", "height")):
        value = data.get(key)
        if value is None:
            raise CameraError(f"{source}: missing key '{key}'")
        if isinstance(value, bool) or not isinstance(value, int) or value < 1:
            raise CameraError(f"{source}: key '{key}' must be a positive integer, got {value!r}")
        kwargs[arg] = value
    name = data.get("camera_name", "camera")
    if not isinstance(name, str):
        raise CameraError(f"{source}: key 'camera_name' must be a string, got {name!r}")
    kwargs["name"] = name

    for group, keys in cls.PARAMETER_GROUPS:
        block = data.get(group)
        if block is None:
            raise CameraError(f"{source}: missing key '{group}' (needed by model {cls.model_type})")
        if not isinstance(block, dict):
            raise CameraError(f"{source}: key '{group}' must be a map of {', '.join(keys)}, got {block!r}")
        for key in keys:
            value = block.get(key)
            where = f"{group}/{key}"
            if value is None:
                raise CameraError(f"{source}: missing key '{where}'")
            if isinstance(value, bool) or not isinstance(value, int | float):
                raise CameraError(f"{source}: key '{where}' must be a number, got {value!r}")
            kwargs[key] = value
    try:
        return cls(**kwargs)
    except CameraError as err:
        raise CameraError(f"{source}: {err}") from err


def load_camera(path: str | os.PathLike[str]) -> CameraModel:
    """Read a camodocal camera file (OpenCV FileStorage YAML) or a VINS-Mono config (the same keys inline).

    Raises:
        CameraError: the file is missing or malformed, or a key is missing or invalid; the message names
            the file and the key.
    """
    try:
        data = read_opencv_yaml(path)
    except OpenCVYamlError as err:
        raise CameraError(f"camera file {err}") from err
    return camera_from_dict(data, source=str(path))
