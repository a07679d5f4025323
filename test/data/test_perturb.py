"""Illumination perturbation: identity at 'none', seeded determinism, documented ranges, strength order."""

from __future__ import annotations

import numpy as np
import pytest

from nsflow_ros.data.errors import DataError
from nsflow_ros.data.perturb import LEVELS, IlluminationPerturber, perturb_pair, perturb_records
from nsflow_ros.data.records import ImageRecord, ImuRecord


@pytest.fixture(scope="module")
def image():
    rng = np.random.default_rng(0)
    # A textured gradient covering most of the 8-bit range.
    base = np.linspace(30, 220, 160)[None, :] + rng.normal(0, 12, (120, 160))
    return np.clip(base, 0, 255).astype(np.uint8)


TIMES = np.linspace(0.0, 30.0, 61)


def _mean_change(level: str, image: np.ndarray, seed: int = 0) -> float:
    p = IlluminationPerturber(level, seed)
    return float(np.mean([np.abs(p(image, t).astype(float) - image).mean() for t in TIMES]))


def test_none_is_the_identity(image):
    p = IlluminationPerturber("none", seed=3)
    for t in (0.0, 1.7, 1e9):
        assert np.array_equal(p(image, t), image)
    assert p.params(5.0) == (1.0, 0.0)


def test_same_seed_same_output_any_access_order(image):
    a, b = IlluminationPerturber("large", 7), IlluminationPerturber("large", 7)
    forward = [a(image, t) for t in TIMES]
    backward = [b(image, t) for t in TIMES[::-1]][::-1]
    assert all(np.array_equal(x, y) for x, y in zip(forward, backward, strict=True))
    other = IlluminationPerturber("large", 8)
    assert any(not np.array_equal(other(image, t), x) for t, x in zip(TIMES, forward, strict=True))


def test_parameters_stay_in_the_documented_ranges_and_vary_smoothly():
    for name in ("small", "large"):
        lvl = LEVELS[name]
        p = IlluminationPerturber(name, 1)
        ts = np.linspace(0, 200, 4001)
        ab = np.array([p.params(t) for t in ts])
        assert np.all(ab[:, 0] > np.exp(-lvl.log_gain)) and np.all(ab[:, 0] < np.exp(lvl.log_gain))
        assert np.all(np.abs(ab[:, 1]) < lvl.offset)
        # It does use its range, and changes little between 20 Hz frames.
        assert np.ptp(np.log(ab[:, 0])) > lvl.log_gain and np.ptp(ab[:, 1]) > lvl.offset
        frames = np.array([p.params(t) for t in np.arange(0, 60, 0.05)])
        assert np.abs(np.diff(np.log(frames[:, 0]))).max() < 0.25 * lvl.log_gain
        assert np.abs(np.diff(frames[:, 1])).max() < 0.35 * lvl.offset


def test_large_changes_images_more_than_small(image):
    small = np.mean([_mean_change("small", image, s) for s in range(3)])
    large = np.mean([_mean_change("large", image, s) for s in range(3)])
    assert 2.0 < small < large / 1.8


def test_dtypes_and_shapes_are_kept(image):
    p = IlluminationPerturber("large", 2)
    color = np.repeat(image[:, :, None], 3, axis=2)
    out = p(color, 1.0)
    assert out.shape == color.shape and out.dtype == np.uint8
    assert np.array_equal(out[:, :, 0], p(image, 1.0))
    wide = image.astype(np.uint16) * 257
    out16 = p(wide, 1.0)
    assert out16.dtype == np.uint16 and np.abs(out16 // 257 - p(image, 1.0).astype(int)).max() <= 1
    with pytest.raises(DataError, match="unknown illumination level 'huge'"):
        IlluminationPerturber("huge")
    with pytest.raises(DataError, match=r"expected shape \(H, W\) or \(H, W, C\), got \(5,\)"):
        p(np.zeros(5, np.uint8), 0.0)


def test_perturb_pair_for_training(image):
    a, b = perturb_pair(image, image, np.random.default_rng(1), 1.0)
    c, d = perturb_pair(image, image, np.random.default_rng(1), 1.0)
    assert np.array_equal(a, c) and np.array_equal(b, d)
    assert not np.array_equal(a, b)  # independent changes: a relative change between the two frames
    assert a.dtype == np.uint8 and a.shape == image.shape
    same = perturb_pair(image, image, np.random.default_rng(1), 0.0)
    assert all(np.array_equal(x, image) for x in same)
    f = image.astype(np.float32) / 255.0
    fa, _ = perturb_pair(f, f, np.random.default_rng(2), 0.5)
    assert fa.dtype == np.float32 and fa.min() >= 0.0 and fa.max() <= 1.0
    def change(strength: float) -> float:
        outs = [perturb_pair(image, image, np.random.default_rng(s), strength)[0] for s in range(5)]
        return float(np.mean([np.abs(o.astype(float) - image).mean() for o in outs]))

    assert change(0.2) < change(1.0)
    with pytest.raises(DataError, match="strength must be in"):
        perturb_pair(image, image, np.random.default_rng(0), 1.5)


def test_perturb_records_changes_images_only(image):
    recs = [ImageRecord("/cam0/image_raw", 1_000_000_000, image, "mono8", "cam0"),
            ImuRecord("/imu0", 1_000_000_000, np.zeros(3), np.ones(3))]
    p = IlluminationPerturber("large", 0)
    out = list(perturb_records(recs, p))
    assert np.array_equal(out[0].image, p(image, 1.0)) and out[0].frame_id == "cam0"
    assert out[1] is recs[1]


def test_dark_follows_the_sensor_model(image):
    from nsflow_ros.data.perturb import DARK_SENSOR, PERTURBATIONS, DarkPerturber, SensorModel, make_perturber

    assert set(PERTURBATIONS) == {"none", "small", "large", "dark"}
    p = make_perturber("dark", 4)
    assert isinstance(p, DarkPerturber) and p.sensor is DARK_SENSOR
    flat = np.full((200, 200), 128, np.uint8)
    out = p(flat, 2.0).astype(float)
    s = DARK_SENSOR
    electrons = 128 / 255 * s.full_well_e / s.total_gain  # mean photo-electrons of the dark exposure
    expected_sd = np.sqrt(electrons + s.read_noise_e**2) * s.total_gain / s.full_well_e * 255
    assert abs(out.mean() - 128) < 0.2  # the gain restores the brightness
    assert 0.9 * expected_sd < out.std() < 1.1 * expected_sd  # shot + read noise, after the gain
    # no noise, no loss of light: the identity up to rounding; more stops: more noise
    assert np.array_equal(DarkPerturber(SensorModel("x", 1e12, 0.0, 0.0))(image, 0.0), image)
    darker = DarkPerturber(SensorModel("x", s.full_well_e, s.read_noise_e, s.stops + 2), 4)
    assert darker(flat, 2.0).std() > 1.5 * out.std()
    with pytest.raises(DataError, match="unknown perturbation 'night'; expected one of none, small"):
        make_perturber("night")
    with pytest.raises(DataError, match="full_well_e must be > 0"):
        SensorModel("bad", 0.0, 1.0, 3.0)


def test_dark_is_reproducible_and_independent_per_image(image):
    from nsflow_ros.data.perturb import make_perturber

    a, b = make_perturber("dark", 1), make_perturber("dark", 1)
    first = [a(image, t) for t in TIMES[:5]]
    assert all(np.array_equal(x, b(image, t)) for x, t in zip(first[::-1], TIMES[:5][::-1], strict=True))
    assert not np.array_equal(first[0], first[1])  # another frame time: other noise
    assert not np.array_equal(first[0], make_perturber("dark", 2)(image, TIMES[0]))
    # the right image of a stereo pair (same stamp, other content) gets its own noise
    shifted = np.roll(image, 3, axis=1)
    assert not np.array_equal(np.roll(first[0], 3, axis=1), a(shifted, TIMES[0]))
    assert a(image.astype(np.uint16) * 257, 0.0).dtype == np.uint16


def test_image_noise_is_a_seeded_realisation_of_the_given_sigma(image):
    from nsflow_ros.data.perturb import ImageNoise

    flat = np.full((200, 200), 128, np.uint8)
    noisy = ImageNoise(2.0, seed=1)(flat, 0.5)
    assert noisy.dtype == np.uint8 and noisy.shape == flat.shape
    assert abs(float(np.mean(noisy)) - 128) < 0.05 and abs(float(np.std(noisy.astype(float))) - 2.0) < 0.05
    assert np.array_equal(noisy, ImageNoise(2.0, seed=1)(flat, 0.5))
    assert not np.array_equal(noisy, ImageNoise(2.0, seed=2)(flat, 0.5))  # another draw
    assert not np.array_equal(noisy, ImageNoise(2.0, seed=1)(flat, 0.55))  # another frame
    assert np.array_equal(ImageNoise(0.0, seed=1)(image, 0.5), image)
    wide = ImageNoise(1.0, seed=1)(flat.astype(np.uint16) * 257, 0.5)
    # 1 gray level of the 8-bit scale is 257 of 16 bit
    assert wide.dtype == np.uint16 and 200 < float(np.std(wide.astype(float))) < 314
    with pytest.raises(DataError, match="-1"):
        ImageNoise(-1.0)
