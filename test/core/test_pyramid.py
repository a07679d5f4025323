"""Tests of descriptor pyramids (nsflow_ros.core.pyramid)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from nsflow_ros import CoreError, Smoothing, build_pyramid
from nsflow_ros.core.pyramid import descriptor_gradients, gaussian_kernel, sampling_source, split_channels


def test_levels_halve_and_hold_the_map():
    rng = np.random.default_rng(0)
    desc = rng.random((120, 160, 3), dtype=np.float32)
    pyr = build_pyramid(desc, 3)
    assert pyr.num_levels == 3 and pyr.channels == 3 and pyr.shape == (120, 160)
    assert [pyr.level(i).shape for i in range(3)] == [(120, 160, 3), (60, 80, 3), (30, 40, 3)]
    # 3 channels are held as the leading ones of a zero-padded 4-channel buffer, which remap samples
    for lev in pyr.levels:
        (c,) = lev
        src = sampling_source(c)
        assert src.shape == (*c.shape[:2], 4) and src.flags.c_contiguous and src.dtype == np.float32
    np.testing.assert_array_equal(pyr.level(0), desc)
    np.testing.assert_allclose(pyr.level(1), cv2.pyrDown(desc, borderType=cv2.BORDER_REPLICATE), atol=1e-7)


def test_one_and_four_channel_chunks_are_sampled_as_they_are():
    for k in (1, 4):
        (c,) = build_pyramid(np.random.default_rng(k).random((20, 30, k), dtype=np.float32), 1).levels[0]
        assert c.flags.c_contiguous and sampling_source(c) is c
    # a user's channel slice is not mistaken for a padded chunk
    four = np.random.default_rng(2).random((20, 30, 4), dtype=np.float32)
    assert sampling_source(four[..., 1:3]) is not four


def test_more_than_four_channels_are_chunked_for_remap():
    desc = np.random.default_rng(1).random((40, 50, 9), dtype=np.float32)
    pyr = build_pyramid(desc, 2)
    assert [c.shape[2] for c in pyr.levels[0]] == [4, 4, 1] and pyr.channels == 9
    np.testing.assert_array_equal(pyr.level(0), desc)
    six = build_pyramid(desc[..., :6], 1).levels[0]
    assert [c.shape[2] for c in six] == [4, 2] and sampling_source(six[1]).shape[2] == 4


def test_gradients_of_a_ramp_are_its_slopes():
    yy, xx = np.mgrid[0:30, 0:40].astype(np.float32)
    ramp = (0.25 * xx - 0.5 * yy)[..., None]
    dx, dy = descriptor_gradients(ramp)
    np.testing.assert_allclose(dx[2:-2, 2:-2], 0.25, atol=1e-6)
    np.testing.assert_allclose(dy[2:-2, 2:-2], -0.5, atol=1e-6)


def test_small_maps_get_fewer_levels():
    assert build_pyramid(np.zeros((20, 20), np.float32), 4).num_levels == 2


def test_split_channels_keeps_order():
    x = np.arange(2 * 3 * 9, dtype=np.float32).reshape(2, 3, 9)
    parts = split_channels(x)
    assert [p.shape[2] for p in parts] == [4, 4, 1]
    np.testing.assert_array_equal(np.concatenate(parts, axis=2), x)


@pytest.mark.parametrize(
    ("desc", "levels", "match"),
    [
        (np.zeros((10, 10, 1), np.float32), 0, "levels"),
        (np.zeros((10,), np.float32), 1, r"\(H, W, C\)"),
        (np.zeros((1, 10, 1), np.float32), 1, "degenerate"),
        (np.zeros((10, 10, 1), np.uint8), 1, "floating"),
    ],
)
def test_guards(desc, levels, match):
    with pytest.raises(CoreError, match=match):
        build_pyramid(desc, levels)


@pytest.mark.parametrize(("sigma", "taps"), [(0.5, 3), (1.0, 5), (1.3, 7)])
def test_gaussian_kernel_taps_and_spread(sigma, taps):
    k = gaussian_kernel(sigma)
    assert k.shape == (taps,) and k.dtype == np.float32
    np.testing.assert_allclose(k.sum(), 1.0, atol=1e-6)
    np.testing.assert_array_equal(k, k[::-1])
    x = np.arange(taps) - taps // 2
    # truncated at 2 sigma, so a little narrower than sigma
    assert 0.8 * sigma**2 < float((k * x**2).sum()) < sigma**2


def test_fine_smoothing_comes_before_the_coarse_levels_and_coarse_smoothing_after():
    desc = np.random.default_rng(4).random((64, 80, 4), dtype=np.float32)
    r = cv2.BORDER_REPLICATE

    def blur(m, sigma):
        k = gaussian_kernel(sigma)
        return cv2.sepFilter2D(m, cv2.CV_32F, k, k, borderType=r)

    smooth = build_pyramid(desc, 3, Smoothing(fine=1.0, coarse=0.5))
    level0 = blur(desc, 1.0)
    level1 = cv2.pyrDown(level0, borderType=r)
    level2 = cv2.pyrDown(level1, borderType=r)  # made from the level above before its own smoothing
    np.testing.assert_allclose(smooth.level(0), level0, atol=1e-6)
    np.testing.assert_allclose(smooth.level(1), blur(level1, 0.5), atol=1e-6)
    np.testing.assert_allclose(smooth.level(2), blur(level2, 0.5), atol=1e-6)
    # smoothing lowers the map's variation (what widens the solver's basin); level 0 is a new array
    assert np.abs(np.diff(smooth.level(0), axis=1)).mean() < 0.6 * np.abs(np.diff(desc, axis=1)).mean()
    assert not np.shares_memory(smooth.levels[0][0], desc)
    # the encoder applies the fine part itself: coarse only leaves level 0 as it is
    plain = build_pyramid(desc, 3)
    only_coarse = build_pyramid(desc, 3, Smoothing(coarse=0.5))
    np.testing.assert_array_equal(only_coarse.level(0), desc)
    np.testing.assert_allclose(only_coarse.level(1), blur(plain.level(1), 0.5), atol=1e-6)
    np.testing.assert_array_equal(build_pyramid(desc, 2, Smoothing()).level(1), plain.level(1))


def test_smoothing_keeps_a_single_channel_map_three_dimensional():
    pyr = build_pyramid(np.random.default_rng(5).random((30, 40), dtype=np.float32), 2, Smoothing(1.0, 0.5))
    assert [pyr.level(i).shape for i in range(2)] == [(30, 40, 1), (15, 20, 1)]


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [({"fine": -1.0}, "fine"), ({"coarse": float("nan")}, "coarse"), ({"fine": "1"}, "fine")],
)
def test_smoothing_guards(kwargs, match):
    with pytest.raises(CoreError, match=match):
        Smoothing(**kwargs)


def test_smoothing_argument_and_kernel_guards():
    with pytest.raises(CoreError, match="Smoothing or None"):
        build_pyramid(np.zeros((10, 10, 1), np.float32), 1, (1.0, 0.5))  # type: ignore[arg-type]
    with pytest.raises(CoreError, match="sigma"):
        gaussian_kernel(0.0)
