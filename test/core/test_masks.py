"""Feature masks: conventions, size checks, the tracking resolution, intersections."""

from __future__ import annotations

import numpy as np
import pytest

from nsflow_ros.core.errors import CoreError
from nsflow_ros.core.masks import (
    MASK_CONVENTIONS,
    binarize,
    check_mask,
    combine,
    usable_at,
)


def test_binarize_reads_both_conventions_with_jpeg_noise():
    raw = np.array([[0, 3, 126, 128, 250, 255]], np.uint8)
    np.testing.assert_array_equal(binarize(raw, "vins"), [[0, 0, 0, 255, 255, 255]])
    np.testing.assert_array_equal(binarize(raw, "openvins"), [[255, 255, 255, 0, 0, 0]])
    assert set(MASK_CONVENTIONS) == {"vins", "openvins"}
    with pytest.raises(CoreError, match=r"mask convention must be one of \('vins', 'openvins'\), got 'x'"):
        binarize(raw, "x")
    with pytest.raises(CoreError, match="2-D uint8"):
        binarize(np.zeros((2, 2, 3), np.uint8))
    with pytest.raises(CoreError, match="uint8"):
        binarize(np.zeros((2, 2), np.uint16))


def test_check_mask_names_both_sizes():
    with pytest.raises(CoreError, match=r"mask1 is 4x3 but camera 1 \(cam1\) is 5x3"):
        check_mask(np.zeros((3, 4), np.uint8), (5, 3), "mask1", "camera 1 (cam1)")
    out = check_mask(np.array([[200, 20]], np.uint8), (2, 1))
    np.testing.assert_array_equal(out, [[255, 0]])


def test_combine_intersects_and_ignores_none():
    a = np.array([[255, 255, 0]], np.uint8)
    b = np.array([[255, 0, 255]], np.uint8)
    assert combine(None, None) is None
    assert combine(a, None) is a
    np.testing.assert_array_equal(combine(a, b), [[255, 0, 0]])


def test_usable_at_rounds_and_treats_the_outside_and_nan_as_unusable():
    mask = np.zeros((3, 4), np.uint8)
    mask[1, 2] = 255
    pts = np.array([[2.4, 0.6], [1.6, 1.0], [2.0, 3.2], [-0.6, 1.0], [np.nan, 1.0]])
    assert usable_at(mask, pts).tolist() == [True, True, False, False, False]
