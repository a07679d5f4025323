"""Trackable-region ratio: a flat image has none, texture without offset is all, guards."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from image_pairs import texture, warp_pair

from nsflow_ros.core.methods import make_method
from nsflow_ros.evaluation import trackable as tr
from nsflow_ros.evaluation.errors import EvaluationError
from nsflow_ros.evaluation.methods import KLT, LMPairMethod, default_methods
from nsflow_ros.evaluation.pairs import HomographyPair

SHIFT = np.array([[1.0, 0.0, 1.5], [0.0, 1.0, -0.5], [0.0, 0.0, 1.0]])


@pytest.fixture(scope="module")
def methods():
    return default_methods()


def test_flat_image_has_no_trackable_region(methods):
    flat = np.full((60, 80), 128, np.uint8)
    pair = HomographyPair("flat", "trackable", 1, flat, flat.copy(), SHIFT)
    tm = tr.trackable_map(methods, pair, np.random.default_rng(0), stride=4)
    assert len(tm.points) > 20
    for name, r in tm.ratios().items():
        assert r[2] < 0.05, (name, r)


def test_textured_pair_without_offset_is_recovered_and_maps_to_the_grid(methods):
    f1, f2 = warp_pair(texture("astronaut", (120, 90)), SHIFT)
    pair = HomographyPair("astronaut", "trackable", 1, f1, f2, SHIFT)
    tm = tr.trackable_map(methods, pair, np.random.default_rng(0), stride=5, perturbation=0.0, chunk=17)
    r = tm.ratios()
    assert r[KLT][0] > 0.9, r
    for v in r.values():
        assert v[0] <= v[1] <= v[2]  # within 1 px implies within 2 and 3
    grid = tm.grid(KLT)
    assert grid.shape == tm.grid_shape
    assert np.isfinite(grid).sum() + np.isinf(grid).sum() == len(tm.points)


def test_map_does_not_depend_on_chunks_under_algorithm_1(methods):
    # Algorithm 1's per-point stops make a point's result independent of its batch; the tracker's
    # straggler cut-off (LMConfig.tail_share) does not, so this runs without it.
    exact = [LMPairMethod(m.name, make_method(replace(m.core.spec, lm=replace(m.config, tail_share=0.0)),
                                              encoder=m.encoder))
             if isinstance(m, LMPairMethod) else m for m in methods]
    f1, f2 = warp_pair(texture("astronaut", (120, 90)), SHIFT)
    pair = HomographyPair("astronaut", "trackable", 1, f1, f2, SHIFT)
    runs = [tr.trackable_map(exact, pair, np.random.default_rng(0), stride=5, perturbation=0.0, chunk=c)
            for c in (17, 10000)]
    for name in runs[0].errors:
        np.testing.assert_allclose(runs[1].errors[name], runs[0].errors[name], rtol=1e-9, atol=1e-9)


def test_clipped_windows_flag_saturation_in_either_frame():
    img = texture("astronaut", (80, 60))
    img = np.clip(img, 20, 230).astype(np.uint8)  # nothing clipped to begin with
    bright = img.copy()
    bright[:, 40:] = 255  # right half saturated in frame 2 only
    pts = np.array([[10.0, 30.0], [38.0, 30.0], [36.0, 30.0], [60.0, 30.0]])
    clipped = tr.clipped_windows(img, bright, pts, pts, 11)
    # 11 px windows: x = 38 covers 4 saturated columns (36 %), x = 36 two (18 %), x = 60 all of them
    np.testing.assert_array_equal(clipped, [False, True, False, True])
    np.testing.assert_array_equal(tr.clipped_windows(bright, img, pts, pts, 11), clipped)
    dark = np.where(np.arange(80)[None, :] < 40, 0, img).astype(np.uint8)
    assert tr.clipped_windows(dark, img, pts, pts, 11).tolist() == [True, True, True, False]
    assert not tr.clipped_windows(img, img, pts, pts, 11).any()


def test_ratios_among_unclipped_keypoints(methods):
    f1, f2 = warp_pair(texture("astronaut", (120, 90)), SHIFT)
    f2[:, :30] = 255  # a saturated strip in frame 2
    pair = HomographyPair("astronaut", "trackable", 1, f1, f2, SHIFT)
    tm = tr.trackable_map(methods, pair, np.random.default_rng(0), stride=5, perturbation=0.0)
    keep = ~tm.clipped
    assert 0.1 < np.mean(tm.clipped) < 0.5
    for name, r in tm.ratios(unclipped=True).items():
        assert r[0] == pytest.approx(np.mean(tm.errors[name][keep] < 1.0))


def test_guards():
    img = np.zeros((40, 40), np.uint8)
    pair = HomographyPair("x", "trackable", 1, img, img, np.eye(3))
    with pytest.raises(EvaluationError, match="stride"):
        tr.trackable_map([], pair, np.random.default_rng(0), stride=0)
    with pytest.raises(EvaluationError, match="perturbation"):
        tr.trackable_map([], pair, np.random.default_rng(0), perturbation=-1.0)
    bad = HomographyPair("x", "trackable", 1, img, np.zeros((40, 41), np.uint8), np.eye(3))
    with pytest.raises(EvaluationError, match=r"\(40, 40\) and \(40, 41\)"):
        tr.trackable_map([], bad, np.random.default_rng(0))


def test_quick_run_reports_the_deployed_depth_and_one_fewer_with_computed_targets(methods, tmp_path):
    from nsflow_ros.evaluation.context import EvalContext
    from nsflow_ros.evaluation.methods import BASELINES, NSFLOW

    ctx = EvalContext(methods=methods, quick=True, out_dir=tmp_path, progress=False)
    sec = tr.run(ctx)
    assert set(sec.data["levels"].values()) == {4, 6}
    med, fewer = sec.data["median"], sec.data["median_one_level_fewer"]
    rows = sec.headline
    assert [r.metric.endswith("(LM 6, OpenCV LK 4 levels)") for r in rows] == [True, True, True, False, False]
    assert "windows not clipped" in rows[2].metric and rows[2].target == "" and rows[2].met is None
    assert rows[2].values[NSFLOW] == f"{sec.data['median_unclipped']['light'][NSFLOW][0]:.1%}"
    assert rows[3].metric.endswith("(LM 5, OpenCV LK 3 levels: one fewer)")
    assert rows[3].target == "" and rows[3].met is None
    ns = med["none"][NSFLOW][0]
    assert rows[0].met == (ns > med["none"]["LM (intensity)"][0] and ns >= 0.85)
    best = max(med["light"][b][0] for b in BASELINES)
    assert rows[1].met == (med["light"][NSFLOW][0] >= 1.5 * best)
    assert rows[4].values[NSFLOW] == f"{fewer['light'][NSFLOW][0]:.1%}"
    assert set(sec.data["clipped_share"]) == set(sec.data["ratios"])
    assert "clipped windows" in sec.markdown
    with pytest.raises(EvaluationError, match="cannot be reduced"):
        tr.trackable_map(methods, tr.make_trackable_pairs(tr.QUICK)[0][1],
                         np.random.default_rng(0), stride=20, fewer_levels=4)  # fmt: skip
