"""Tests of descriptor pyramids (nsflow_ros.core.pyramid)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from nsflow_ros import CoreError, build_pyramid
from nsflow_ros.core.pyramid import descriptor_gradients, split_channels


def test_levels_halve_and_hold_the_map():
    rng = np.random.default_rng(0)
    desc = rng.random((120, 160, 3), dtype=np.float32)
    pyr = build_pyramid(desc, 3)
    assert pyr.num_levels == 3 and pyr.channels == 3 and pyr.shape == (120, 160)
    assert [pyr.level(i).shape for i in range(3)] == [(120, 160, 3), (60, 80, 3), (30, 40, 3)]
    assert all(c.flags.c_contiguous and c.dtype == np.float32 for lev in pyr.levels for c in lev)
    np.testing.assert_array_equal(pyr.level(0), desc)
    np.testing.assert_allclose(pyr.level(1), cv2.pyrDown(desc, borderType=cv2.BORDER_REPLICATE), atol=1e-7)


def test_more_than_four_channels_are_chunked_for_remap():
    desc = np.random.default_rng(1).random((40, 50, 9), dtype=np.float32)
    pyr = build_pyramid(desc, 2)
    assert [c.shape[2] for c in pyr.levels[0]] == [4, 4, 1] and pyr.channels == 9
    np.testing.assert_array_equal(pyr.level(0), desc)


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
