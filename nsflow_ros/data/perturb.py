"""Perturbations of image streams (evaluation, replay, benchmark) and of image pairs (training).

Evaluation follows the NSFlow paper's EuRoC experiment: ``I'(t) = clip(a(t) * I + b(t), 0, 255)`` with a
gain ``a(t) = exp(g * s_a(t))`` and an offset ``b(t) = B * s_b(t)``, each ``s(t) = tanh(z(t))`` where
``z`` is a sum of four seeded sinusoids scaled to unit mean square: smooth, in (-1, 1), and a pure function
of ``(seed, t)``, so any frame can be perturbed on its own and replays are reproducible.

Levels (:data:`LEVELS`): ``small`` gain (0.78, 1.28) = exp(+-0.25), offset (-20, 20) gray levels,
sinusoids of 0.05 - 0.4 Hz; ``large`` gain (0.50, 2.01) = exp(+-0.7), offset (-60, 60), 0.1 - 0.6 Hz;
``none`` returns the image unchanged. For 16-bit images the offset is scaled by 257.

``dark`` (:class:`DarkPerturber`, :data:`DARK_SENSOR`) is low light on a real sensor: the exposure several
stops down, the photo-electrons drawn from a Poisson law (shot noise), Gaussian read noise added, the gain
raising the signal back by as many stops and the result quantised to the image's 8 (or 16) bits: the EMVA
1288 linear camera model. Its noise is a pure function of ``(seed, t, image)``.

:class:`ImageNoise` adds independent Gaussian sensor noise to every image, seeded like ``dark``:
``nsflow-scenes --draws`` tracks a scene on several such realisations, since the estimator's trajectory
moves more between two noise realisations of one scene than between front-ends (docs/scenes.md).

Every stream perturbation is chosen by name from :data:`PERTURBATIONS` (:func:`make_perturber`): the
replay, the benchmark and the evaluation take their choices from it.
"""

from __future__ import annotations

import zlib
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, replace
from typing import Any, Protocol

import cv2
import numpy as np

from nsflow_ros.data.errors import DataError
from nsflow_ros.data.records import ImageRecord, Record

__all__ = [
    "DARK_SENSOR",
    "LEVELS",
    "PERTURBATIONS",
    "DarkPerturber",
    "IlluminationPerturber",
    "ImageNoise",
    "PerturbLevel",
    "Perturber",
    "SensorModel",
    "make_perturber",
    "perturb_pair",
    "perturb_records",
]


@dataclass(frozen=True)
class PerturbLevel:
    """Parameters of one perturbation level.

    Attributes:
        name: level name.
        log_gain: g; the gain lies in (exp(-g), exp(g)).
        offset: B; the offset lies in (-B, B) gray levels (8-bit scale).
        freq: (low, high) range of the sinusoids' frequencies in Hz.
    """

    name: str
    log_gain: float
    offset: float
    freq: tuple[float, float]


LEVELS: dict[str, PerturbLevel] = {
    "none": PerturbLevel("none", 0.0, 0.0, (0.0, 0.0)),
    "small": PerturbLevel("small", 0.25, 20.0, (0.05, 0.4)),
    "large": PerturbLevel("large", 0.7, 60.0, (0.1, 0.6)),
}

_N_SINES = 4


def _check_image(image: Any, name: str = "image") -> np.ndarray:
    arr = np.asarray(image)
    if arr.ndim not in (2, 3) or arr.size == 0:
        raise DataError(f"{name}: expected shape (H, W) or (H, W, C), got {arr.shape}")
    if arr.dtype not in (np.uint8, np.uint16) and not np.issubdtype(arr.dtype, np.floating):
        raise DataError(f"{name}: expected dtype uint8, uint16 or float, got {arr.dtype}")
    return arr


def _full_scale(dtype: np.dtype) -> float:
    """Value of white: 255 for uint8, 65535 for uint16, 1 for floats (taken as [0, 1] images)."""
    if dtype == np.uint8:
        return 255.0
    if dtype == np.uint16:
        return 65535.0
    return 1.0


def _to_dtype(x: np.ndarray, dtype: np.dtype) -> np.ndarray:
    top = _full_scale(dtype)
    out = np.clip(x, 0.0, top)
    if np.issubdtype(dtype, np.integer):
        out = np.rint(out)
    return out.astype(dtype)


class IlluminationPerturber:
    """Time-varying gain and offset on a stream of images, deterministic in ``(seed, t)``.

    Args:
        level: a key of :data:`LEVELS` or a :class:`PerturbLevel`.
        seed: random seed of the two processes.

    Raises:
        DataError: for an unknown level name.

    Example:
        ``perturb = IlluminationPerturber("large", seed=3); out = perturb(image, stamp_ns * 1e-9)``
    """

    def __init__(self, level: str | PerturbLevel = "small", seed: int = 0) -> None:
        if isinstance(level, str):
            if level not in LEVELS:
                raise DataError(f"unknown illumination level {level!r}; expected one of {sorted(LEVELS)}")
            level = LEVELS[level]
        self.level = level
        self.seed = int(seed)
        rng = np.random.default_rng(np.random.SeedSequence([self.seed, 0x111]))
        lo, hi = level.freq
        # Two independent processes (gain, offset), each a weighted sum of sinusoids.
        self._freq = rng.uniform(lo, hi, (2, _N_SINES)) * 2.0 * np.pi
        self._phase = rng.uniform(0.0, 2.0 * np.pi, (2, _N_SINES))
        w = rng.uniform(0.5, 1.0, (2, _N_SINES))
        self._weight = w / np.sqrt((w * w).sum(axis=1, keepdims=True) / 2.0)  # unit mean square

    def params(self, t: float) -> tuple[float, float]:
        """Gain ``a(t)`` and offset ``b(t)`` (8-bit gray levels) at ``t`` seconds on any consistent clock."""
        if self.level.log_gain == 0.0 and self.level.offset == 0.0:
            return 1.0, 0.0
        z = (self._weight * np.sin(self._freq * float(t) + self._phase)).sum(axis=1)
        s = np.tanh(z)
        return float(np.exp(self.level.log_gain * s[0])), float(self.level.offset * s[1])

    def __call__(self, image: Any, t: float) -> np.ndarray:
        """Perturb one image taken at time ``t`` (seconds; see :meth:`params`).

        Args:
            image: (H, W) or (H, W, C) image, uint8, uint16 or float in [0, 1].

        Returns:
            The perturbed image, same shape and dtype; at level ``none`` the input array itself.

        Raises:
            DataError: on a bad shape or dtype.
        """
        img = _check_image(image)
        if self.level.name == "none":
            return img
        a, b = self.params(t)
        scale = _full_scale(img.dtype) / 255.0
        if img.dtype == np.uint8:
            # A lookup table is exact for 8 bit and much faster than float arithmetic per pixel.
            lut = _to_dtype(a * np.arange(256.0) + b, np.dtype(np.uint8))
            return cv2.LUT(img, lut) if img.ndim == 2 or img.shape[2] in (1, 3, 4) else lut[img]
        return _to_dtype(a * img.astype(np.float32) + np.float32(b * scale), img.dtype)


@dataclass(frozen=True)
class SensorModel:
    """A linear image sensor in low light (EMVA 1288's camera model), for :class:`DarkPerturber`.

    An image value ``I`` (full scale ``top``) is taken as linear in irradiance: at the normal exposure it
    collects ``I / top * full_well_e`` electrons; ``stops`` down it collects ``2**-stops`` of that.

    Attributes:
        name: what reports call it.
        full_well_e: electrons at white (saturation capacity).
        read_noise_e: standard deviation of the read (temporal dark) noise in electrons.
        stops: exposure reduction in stops (factor ``2**-stops`` on the collected light).
        gain: the factor the camera multiplies the dark signal by before quantisation (analogue gain of an
            auto-exposure at its exposure limit); None = ``2**stops``, the brightness of the normal exposure.
    """

    name: str
    full_well_e: float
    read_noise_e: float
    stops: float
    gain: float | None = None

    def __post_init__(self) -> None:
        if not (self.full_well_e > 0 and self.read_noise_e >= 0 and self.stops >= 0):
            raise DataError(
                f"sensor model {self.name!r}: full_well_e must be > 0, read_noise_e and stops >= 0; got "
                f"{self.full_well_e}, {self.read_noise_e}, {self.stops}"
            )
        if self.gain is not None and not self.gain > 0:
            raise DataError(f"sensor model {self.name!r}: gain must be > 0, got {self.gain}")

    @property
    def total_gain(self) -> float:
        """The gain applied to the dark signal (``2**stops`` unless given)."""
        return float(2.0**self.stops if self.gain is None else self.gain)


DARK_SENSOR = SensorModel("dark", full_well_e=32_000.0, read_noise_e=7.0, stops=5.0)
"""The ``dark`` perturbation: a Sony Pregius-class global-shutter sensor (IMX249: SNR 45.1 dB = sqrt of a
32,400 e- saturation capacity, dynamic range 73 dB = saturation over a 7.2 e- read noise, as its camera's
EMVA 1288 figures give them) five stops (1/32) under the normal exposure, gained back by 32: mid-gray gets
~500 electrons (shot-noise SNR ~21, about 6 gray levels of noise after the gain)."""


class Perturber(Protocol):
    """A stream perturbation: ``perturber(image, t)`` -> the perturbed image, same shape and dtype."""

    def __call__(self, image: Any, t: float) -> np.ndarray: ...


def _image_rng(seed: int, kind: int, image: np.ndarray, t: float) -> np.random.Generator:
    """A noise generator seeded by ``(seed, kind, t in ns, CRC-32 of the image)``: reproducible frame by
    frame in any order, independent between the images of a stereo pair (same stamp, other content) and
    between the kinds of noise."""
    t_ns = round(float(t) * 1e9) % (1 << 63)
    crc = zlib.crc32(np.ascontiguousarray(image).data)
    return np.random.default_rng(np.random.SeedSequence([seed & 0xFFFFFFFF, kind, t_ns, crc]))


class DarkPerturber:
    """Low light on a real sensor: fewer photo-electrons, shot and read noise, gain, quantisation.

    Per pixel: ``e ~ Poisson(I / top * full_well * 2**-stops) + N(0, read_noise^2)`` electrons, then
    ``I' = clip(round(e * gain / full_well * top), 0, top)`` (:class:`SensorModel`). The noise is drawn
    from a generator seeded by ``(seed, t in ns, CRC-32 of the image)``: reproducible frame by frame in any
    order, and independent between the two images of a stereo pair (same stamp, other content).

    Args:
        sensor: the sensor model (default :data:`DARK_SENSOR`).
        seed: random seed.
    """

    def __init__(self, sensor: SensorModel = DARK_SENSOR, seed: int = 0) -> None:
        self.sensor = sensor
        self.seed = int(seed)

    def rng(self, image: np.ndarray, t: float) -> np.random.Generator:
        """The noise generator of one image at ``t`` seconds."""
        return _image_rng(self.seed, 0xDA4C, image, t)

    def __call__(self, image: Any, t: float) -> np.ndarray:
        """Perturb one image taken at time ``t`` (seconds).

        Args:
            image: (H, W) or (H, W, C) image, uint8, uint16 or float in [0, 1].

        Returns:
            The dark, noisy image, same shape and dtype.

        Raises:
            DataError: on a bad shape or dtype.
        """
        img = _check_image(image)
        s = self.sensor
        top = _full_scale(img.dtype)
        rng = self.rng(img, t)
        electrons = img.astype(np.float64) * (s.full_well_e * 2.0**-s.stops / top)
        signal = rng.poisson(electrons).astype(np.float32)
        if s.read_noise_e > 0:
            signal += rng.standard_normal(img.shape, dtype=np.float32) * np.float32(s.read_noise_e)
        return _to_dtype(signal * np.float32(s.total_gain * top / s.full_well_e), img.dtype)


class ImageNoise:
    """Another realisation of a sensor's noise: ``I' = clip(round(I + N(0, sigma^2)), 0, top)`` per pixel.

    The noise is drawn, as :class:`DarkPerturber`'s, from a generator seeded by ``(seed, t in ns, CRC-32 of
    the image)``: reproducible frame by frame, independent between the images of a stereo pair.

    Args:
        sigma: standard deviation in gray levels of the 8-bit scale (scaled by 257 for 16-bit images).
        seed: random seed (one per realisation).

    Raises:
        DataError: a negative sigma.
    """

    def __init__(self, sigma: float = 1.0, seed: int = 0) -> None:
        if not sigma >= 0:
            raise DataError(f"image noise sigma must be >= 0 gray levels, got {sigma}")
        self.sigma = float(sigma)
        self.seed = int(seed)

    def __call__(self, image: Any, t: float) -> np.ndarray:
        """The image taken at ``t`` (seconds) with the noise added; same shape and dtype.

        Raises:
            DataError: on a bad shape or dtype.
        """
        img = _check_image(image)
        rng = _image_rng(self.seed, 0x1A0E, img, t)
        top = _full_scale(img.dtype)
        noise = rng.standard_normal(img.shape, dtype=np.float32) * np.float32(self.sigma * top / 255.0)
        return _to_dtype(img.astype(np.float32) + noise, img.dtype)


PERTURBATIONS: dict[str, Callable[[int], Perturber]] = {
    **{name: (lambda seed, name=name: IlluminationPerturber(name, seed)) for name in LEVELS},
    "dark": lambda seed: DarkPerturber(DARK_SENSOR, seed),
}
"""Stream perturbations by name -> a factory taking the seed: ``none``, the paper's illumination levels
``small`` and ``large``, and ``dark`` (low light with sensor noise)."""


def make_perturber(name: str, seed: int = 0) -> Perturber:
    """The stream perturbation ``name`` of :data:`PERTURBATIONS`, seeded.

    Raises:
        DataError: for an unknown name, listing the known ones.
    """
    try:
        factory = PERTURBATIONS[name]
    except KeyError:
        known = ", ".join(PERTURBATIONS)
        raise DataError(f"unknown perturbation {name!r}; expected one of {known}") from None
    return factory(seed)


def perturb_records(records: Iterable[Record], perturber: Perturber) -> Iterator[Record]:
    """Perturb the images of a record stream at ``t = stamp_ns * 1e-9``; IMU records pass unchanged.

    The stamp is the clock so that both images of a stereo pair see the same illumination.
    """
    for rec in records:
        if isinstance(rec, ImageRecord):
            yield replace(rec, image=perturber(rec.image, rec.stamp_ns * 1e-9))
        else:
            yield rec


def perturb_pair(img1: Any, img2: Any, rng: np.random.Generator, strength: float = 1.0
                 ) -> tuple[np.ndarray, np.ndarray]:
    """Independent random illumination changes on the two images of a training pair.

    Each image gets, with ``s = strength`` in [0, 1] and ``U`` uniform on (-1, 1):

    * local shading: multiply by ``1 + 0.35 s F`` where ``F`` is a smooth random field in (-1, 1)
      (a bicubic upsampling of a random 4x4 grid), i.e. uneven lighting;
    * gamma ``exp(0.35 s U)`` on the normalised image (0.70 - 1.42 at s = 1);
    * gain ``exp(0.5 s U)`` (0.61 - 1.65) and offset ``40 s U`` gray levels (8-bit scale);
    * Gaussian noise with standard deviation uniform in (0, 3 s) gray levels.

    Args:
        img1, img2: (H, W) or (H, W, C) images, uint8, uint16 or float in [0, 1].
        rng: random generator (the caller owns reproducibility).
        strength: 0 leaves the images unchanged, 1 is the full range above.

    Returns:
        The two perturbed images with their inputs' shapes and dtypes.

    Raises:
        DataError: on a bad shape or dtype, or a strength outside [0, 1].
    """
    if not 0.0 <= strength <= 1.0:
        raise DataError(f"perturbation strength must be in [0, 1], got {strength}")
    a, b = _check_image(img1, "img1"), _check_image(img2, "img2")
    return _perturb_one(a, rng, strength), _perturb_one(b, rng, strength)


def _perturb_one(img: np.ndarray, rng: np.random.Generator, s: float) -> np.ndarray:
    top = _full_scale(img.dtype)
    x = img.astype(np.float32) / np.float32(top)
    h, w = img.shape[:2]
    grid = rng.uniform(-1.0, 1.0, (4, 4)).astype(np.float32)
    field = np.clip(cv2.resize(grid, (w, h), interpolation=cv2.INTER_CUBIC), -1.0, 1.0)
    if x.ndim == 3:
        field = field[:, :, None]
    gamma = float(np.exp(0.35 * s * rng.uniform(-1, 1)))
    gain = float(np.exp(0.5 * s * rng.uniform(-1, 1)))
    offset = 40.0 / 255.0 * s * float(rng.uniform(-1, 1))
    sigma = 3.0 / 255.0 * s * float(rng.uniform(0, 1))
    x = x * (1.0 + 0.35 * s * field)
    x = np.power(np.clip(x, 0.0, 1.0), gamma)
    x = gain * x + offset
    if sigma > 0:
        x = x + rng.standard_normal(x.shape, dtype=np.float32) * np.float32(sigma)
    return _to_dtype(x * top, img.dtype)
