"""Fixtures of the training tests."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import skimage.data


@pytest.fixture(scope="session")
def textures32():
    """A real-photo pair (float32 in [0, 1], 240x320) with a known shift, GFTT points and noisy flow0."""
    img = cv2.resize(skimage.data.camera(), (320, 240), interpolation=cv2.INTER_AREA)
    shift = np.array([1.7, -0.8])
    m = np.float32([[1, 0, shift[0]], [0, 1, shift[1]]])
    img2 = cv2.warpAffine(img.astype(np.float32), m, (320, 240), borderMode=cv2.BORDER_REFLECT)
    pts = cv2.goodFeaturesToTrack(img, 150, 0.01, 7).reshape(-1, 2).astype(np.float64)
    rng = np.random.default_rng(0)
    flow0 = shift + rng.normal(0.0, 1.5, (len(pts), 2))
    return img.astype(np.float32) / 255.0, img2 / 255.0, pts, flow0


@pytest.fixture(scope="session")
def tartanair(tmp_path_factory):
    root = tmp_path_factory.mktemp("tartanair")
    from train_sources_data import write_tartanair

    return root, write_tartanair(root)
