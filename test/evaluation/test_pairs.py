"""HPatches-style homography pairs: exact geometry, honest error accounting, guards."""

from __future__ import annotations

import numpy as np
import pytest
from image_pairs import texture, warp_pair

from nsflow_ros.evaluation import pairs as pr
from nsflow_ros.evaluation.errors import EvaluationError
from nsflow_ros.evaluation.methods import PairResult, default_methods


@pytest.fixture(scope="module")
def methods():
    return default_methods()


def test_known_subpixel_translation_is_tracked_below_a_tenth_of_a_pixel_by_every_method(methods):
    h = np.array([[1.0, 0.0, 2.4], [0.0, 1.0, -1.7], [0.0, 0.0, 1.0]])
    f1, f2 = warp_pair(texture("astronaut", (240, 180)), h)
    pts = pr.keypoints(f1, 200, 6.0)
    gt = pr.true_flow(pts, h)
    keep = pr.inside(pts + gt, 240, 180)
    pts, gt = pts[keep], gt[keep]
    assert len(pts) > 50
    np.testing.assert_allclose(gt, np.tile([2.4, -1.7], (len(gt), 1)), atol=1e-9)
    for m in methods:
        err = pr.endpoint_errors(m.track(m.prepare(f1), m.prepare(f2), pts), gt)
        assert np.median(err) < 0.1, (m.name, np.median(err))


def test_homography_strength_grows_with_level_and_level_zero_is_identity():
    rng = np.random.default_rng(0)
    np.testing.assert_allclose(pr.random_homography(rng, 480, 360, 0.0), np.eye(3), atol=1e-9)
    corners = np.array([[0.0, 0.0], [479, 0], [479, 359], [0, 359]])
    shift = []
    for level in (1, 5):
        hs = [pr.random_homography(np.random.default_rng(s), 480, 360, level) for s in range(20)]
        moves = [np.abs(pr.true_flow(corners, h)).max() for h in hs]
        shift.append(np.mean(moves))
    assert shift[0] < 8.0 < shift[1] < 40.0, shift


def test_pairs_are_reproducible_and_subsets_differ_only_as_described():
    cfg = pr.QUICK
    a = pr.make_pairs("viewpoint", cfg, seed=3)
    b = pr.make_pairs("viewpoint", cfg, seed=3)
    assert len(a) == len(cfg.photos) * cfg.levels * cfg.per_level
    for p, q in zip(a, b, strict=True):
        np.testing.assert_array_equal(p.image1, q.image1)
        np.testing.assert_array_equal(p.homography, q.homography)
        assert p.image1.shape == (cfg.height, cfg.width) and p.image1.dtype == np.uint8
    light = pr.make_pairs("illumination", cfg, seed=3)
    assert {p.subset for p in light} == {"illumination"}
    # strongest illumination level: the two frames' brightness statistics no longer match
    top = next(p for p in light if p.level == cfg.levels)
    assert (
        abs(float(top.image1.mean()) - float(top.image2.mean())) > 1.0
        or abs(float(top.image1.std()) - float(top.image2.std())) > 1.0
    )
    with pytest.raises(EvaluationError, match="subset"):
        pr.make_pairs("blur", cfg)


def test_lost_points_count_as_infinite_error_in_every_statistic():
    gt = np.zeros((4, 2))
    flow = np.array([[0.5, 0.0], [0.0, 2.5], [0.0, 0.0], [np.nan, 0.0]])
    res = PairResult(flow, np.array([1, 1, 0, 1], bool))
    err = pr.endpoint_errors(res, gt)
    np.testing.assert_allclose(err[:2], [0.5, 2.5])
    assert np.isinf(err[2:]).all()
    s = pr.error_summary(err)
    assert s["tracked"] == 0.5 and s["within_1px"] == 0.25 and s["within_3px"] == 0.5
    assert np.isinf(s["median"]) and s["median_tracked"] == pytest.approx(1.5)
    assert pr.error_summary(np.zeros(0))["points"] == 0
    with pytest.raises(EvaluationError, match=r"\(4, 2\)"):
        pr.endpoint_errors(res, np.zeros((3, 2)))


def test_guards_name_expected_and_actual_shapes():
    with pytest.raises(EvaluationError, match=r"\(N, 2\), got \(5,\)"):
        pr.true_flow(np.zeros(5), np.eye(3))
    with pytest.raises(EvaluationError, match="uint8"):
        pr.render_pair(np.zeros((50, 50), np.float32), np.random.default_rng(0), 20, 20, np.eye(3))
    with pytest.raises(EvaluationError, match=r"\(3, 3\)"):
        pr.render_pair(np.zeros((50, 50), np.uint8), np.random.default_rng(0), 20, 20, np.eye(2))
    with pytest.raises(EvaluationError, match="uint8"):
        pr.keypoints(np.zeros((20, 20), np.float64))
