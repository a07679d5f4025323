"""Tests of the scene-rendered training pairs (nsflow_ros.train.scenes)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

torch = pytest.importorskip("torch")

from nsflow_ros.train import TrainError  # noqa: E402
from nsflow_ros.train.data import PairConfig  # noqa: E402
from nsflow_ros.train.scenes import ScenePool, make_scene_pair  # noqa: E402


@pytest.fixture(scope="module")
def pool(tmp_path_factory):
    return ScenePool(tmp_path_factory.mktemp("scenes"), seeds=(1,), frames=2, duration=1.0, points=300)


def _sample(img: np.ndarray, q: np.ndarray) -> np.ndarray:
    f = img.astype(np.float32)
    return cv2.remap(f, q[:, :1].astype(np.float32), q[:, 1:].astype(np.float32), cv2.INTER_LINEAR)[:, 0]


def test_pool_holds_stereo_and_temporal_pairs_with_visible_flow(pool):
    assert [p.kind for p in pool.pairs] == ["stereo", "temporal"]
    stereo = pool.pairs[0]
    assert len(stereo.points) > 100 and np.isfinite(stereo.flow).all()
    # EuRoC-baseline stereo: disparities of several pixels, not zero.
    assert 3.0 < np.median(np.linalg.norm(stereo.flow, axis=1)) < 40.0


def test_scene_pair_crops_keep_the_flow_exact(pool):
    cfg = PairConfig(init_mode="zero")
    rng = np.random.default_rng(0)
    pair = make_scene_pair(pool, rng, cfg, strength=0.0)
    while len(pair.points) < 20:
        pair = make_scene_pair(pool, rng, cfg, strength=0.0)
    assert pair.image1.shape == (cfg.height, cfg.width) and pair.image2.shape == (cfg.height, cfg.width)
    assert np.array_equal(pair.flow0, np.zeros_like(pair.flow_gt))
    r = cfg.window // 2
    for q in (pair.points, pair.points + pair.flow_gt):
        assert (q >= r).all()
        assert (q[:, 0] <= cfg.width - 1 - r).all() and (q[:, 1] <= cfg.height - 1 - r).all()
    a = _sample(pair.image1, pair.points)
    b = _sample(pair.image2, pair.points + pair.flow_gt)
    off = _sample(pair.image2, pair.points + pair.flow_gt + 3.0)
    # Corners seen in both views match in intensity (rendering noise aside); 3 px off they do not.
    assert np.median(np.abs(a - b)) < 6.0
    assert np.median(np.abs(a - off)) > 2 * np.median(np.abs(a - b))


def test_scene_pair_refuses_a_crop_larger_than_the_frames(pool):
    with pytest.raises(TrainError, match="larger than the rendered frames"):
        make_scene_pair(pool, np.random.default_rng(0), PairConfig(width=800, height=240))
