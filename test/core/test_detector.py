"""Tests of corner detection (nsflow_ros.core.detector)."""

from __future__ import annotations

import numpy as np
import pytest
from image_pairs import texture
from scipy.spatial.distance import pdist

from nsflow_ros import CoreError, detect_corners


def test_respects_count_distance_and_mask():
    img = texture("astronaut")
    pts = detect_corners(img, 100, min_distance=20)
    assert pts.shape == (100, 2)
    assert pdist(pts).min() >= 20 - 1e-6
    mask = np.zeros_like(img)
    mask[:, :376] = 255
    left = detect_corners(img, 50, min_distance=10, mask=mask)
    assert (left[:, 0] < 376).all()


def test_nothing_to_detect():
    assert detect_corners(np.full((50, 50), 9, np.uint8), 10).shape == (0, 2)
    assert detect_corners(texture("astronaut"), 0).shape == (0, 2)


def test_guards():
    with pytest.raises(CoreError, match="uint8"):
        detect_corners(np.zeros((5, 5), np.float32), 3)
    with pytest.raises(CoreError, match="mask"):
        detect_corners(np.zeros((5, 5), np.uint8), 3, mask=np.zeros((4, 5), np.uint8))
