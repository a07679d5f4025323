"""Convergence curves: LM's recorded history and KLT's re-runs decrease on texture; guards."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from image_pairs import texture, warp_pair

from nsflow_ros.evaluation import convergence as cv
from nsflow_ros.evaluation.errors import EvaluationError
from nsflow_ros.evaluation.methods import CLASSICAL, default_methods
from nsflow_ros.evaluation.pairs import HomographyPair, inside, keypoints, true_flow

SHIFT = np.array([[1.0, 0.0, 1.3], [0.0, 1.0, 0.6], [0.0, 0.0, 1.0]])


@pytest.fixture(scope="module")
def setup():
    f1, f2 = warp_pair(texture("astronaut", (240, 180)), SHIFT)
    pair = HomographyPair("astronaut", "convergence", 1, f1, f2, SHIFT)
    pts = keypoints(f1, 120, 6.0)
    gt = true_flow(pts, SHIFT)
    pts, gt = pts[inside(pts + gt, 240, 180)], gt[inside(pts + gt, 240, 180)]
    ang = np.random.default_rng(0).uniform(0, 2 * np.pi, len(pts))
    flow0 = gt + 2.5 * np.stack([np.cos(ang), np.sin(ang)], 1)
    return default_methods(), pair, pts, flow0


def test_curves_start_at_the_initial_error_and_decrease_on_texture(setup):
    methods, pair, pts, flow0 = setup
    curves, final = cv.convergence_curves(methods, pair, pts, flow0, iterations=12, levels=1)
    for m in methods:
        c = curves[m.name].mean(axis=1)
        assert curves[m.name].shape == (13, len(pts))
        assert c[0] == pytest.approx(2.5)
        assert c[-1] < 0.3 * c[0], (m.name, c)
        assert c[3] < c[0], (m.name, c)
        assert np.median(final[m.name]) < 0.2, m.name
    # LM: once every point has stopped the curve is flat, and its end is the final flow of Algorithm 1
    # (the curves run without the tracker's straggler cut-off)
    lm = next(m for m in methods if m.name == CLASSICAL)
    res = lm.core.track_pair_result(lm.prepare(pair.image1), lm.prepare(pair.image2), pts, flow0,
                                    replace(lm.config, levels=1, max_iterations=12, tail_share=0.0))
    end = np.linalg.norm(res.flow - true_flow(pts, SHIFT), axis=1)
    np.testing.assert_allclose(curves[lm.name][-1], np.minimum(end, 10.0), atol=1e-9)


def test_capture_range_is_a_table_of_final_errors(setup):
    methods, pair, pts, _ = setup
    d = np.tile([1.0, 0.0], (len(pts), 1))
    out = cv.capture_range(methods, pair, pts, d, (1.0, 2.0), levels=3)
    assert set(out) == {1.0, 2.0}
    for per in out.values():
        assert set(per) == {m.name for m in methods}
        assert all(np.mean(e < 1.0) > 0.8 for e in per.values())


def test_guards(setup):
    methods, pair, pts, flow0 = setup
    with pytest.raises(EvaluationError, match=r"\(N, 2\)"):
        cv.convergence_curves(methods, pair, pts, flow0[:-1])
    with pytest.raises(EvaluationError, match="iterations"):
        cv.convergence_curves(methods, pair, pts, flow0, iterations=0)

    class Other:
        name, levels = "other", 1

    with pytest.raises(EvaluationError, match="LM or KLT"):
        cv.convergence_curves([Other()], pair, pts, flow0, iterations=2)


def test_quick_run_tables_the_basin_at_one_level_and_the_deployed_depth_and_one_fewer(tmp_path):
    from nsflow_ros.evaluation.context import EvalContext
    from nsflow_ros.evaluation.methods import KLT_CLAHE, NSFLOW

    ctx = EvalContext(methods=default_methods(), quick=True, out_dir=tmp_path, progress=False)
    sec = cv.run(ctx)
    # one level, then LM 6 and OpenCV LK 4 levels, each also one fewer
    assert {r["levels"] for r in sec.data["capture_within_1px"]} == {1, 3, 4, 5, 6}
    none, light = sec.headline
    assert none.target == "< LM (intensity)"
    assert light.target == f"< {CLASSICAL} and < {KLT_CLAHE}"
    mean = sec.data["mean_clipped"]["light"]
    assert light.met == (mean[NSFLOW][5] < mean[CLASSICAL][5] and mean[NSFLOW][5] < mean[KLT_CLAHE][5])
