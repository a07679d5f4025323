"""Front-end metrics on the sample sequences: the geometry steps on exact data, guards, a quick run."""

from __future__ import annotations

import numpy as np
import pytest

from nsflow_ros.core.imu import so3_exp
from nsflow_ros.core.tracker import TrackerSettings
from nsflow_ros.evaluation import sequences as sq
from nsflow_ros.evaluation.context import EvalContext
from nsflow_ros.evaluation.errors import EvaluationError
from nsflow_ros.evaluation.methods import KLT, METHOD_ORDER, NSFLOW, default_methods


def _two_views(n: int = 60, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Normalised points of n random 3-D points in two views; returns (x1, x2, R) with X2 = R X1 + t."""
    rng = np.random.default_rng(seed)
    pts = np.c_[rng.uniform(-2, 2, (n, 2)), rng.uniform(3, 8, n)]
    r = so3_exp(np.array([0.02, -0.05, 0.01]))
    t = np.array([0.3, 0.05, 0.1])
    p2 = pts @ r.T + t
    return pts[:, :2] / pts[:, 2:], p2[:, :2] / p2[:, 2:], r


def test_rotation_error_of_exact_matches_is_zero_and_measures_a_wrong_truth():
    x1, x2, r = _two_views()
    err = sq.relative_rotation_error(x1, x2, r, threshold=1e-3)
    assert err is not None and err < 1e-3
    off = so3_exp(np.array([0.0, 0.0, np.radians(2.0)]))
    assert sq.relative_rotation_error(x1, x2, off @ r, threshold=1e-3) == pytest.approx(2.0, abs=1e-3)


def test_rotation_error_guards():
    x1, x2, r = _two_views()
    assert sq.relative_rotation_error(x1[:5], x2[:5], r, 1e-3) is None  # too few to estimate
    with pytest.raises(EvaluationError, match=r"\(N, 2\)"):
        sq.relative_rotation_error(x1, x2[:-1], r, 1e-3)
    with pytest.raises(EvaluationError, match="threshold"):
        sq.relative_rotation_error(x1, x2, r, 0.0)
    with pytest.raises(EvaluationError, match="r_true"):
        sq.relative_rotation_error(x1, x2, np.eye(4), 1e-3)


def test_epipolar_distance_of_a_horizontal_translation_is_the_vertical_offset():
    f = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])  # [t]x for t = (1, 0, 0)
    p1 = np.array([[10.0, 20.0], [50.0, 5.0]])
    p2 = np.array([[30.0, 23.0], [7.0, 4.5]])
    np.testing.assert_allclose(sq.epipolar_distances(f, p1, p2), [3.0, 0.5])


def test_fundamental_inliers_count_lost_tracks_against_the_rate():
    x1, x2, _ = _two_views(80)
    k = np.array([400.0, 400.0])
    p1, p2 = x1 * k + 300, x2 * k + 200
    p2[:8] += np.array([15.0, -12.0])  # 8 gross outliers
    rate, err = sq.fundamental_inliers(p1, p2, n_first=100, threshold=1.0)
    assert rate == pytest.approx(72 / 100, abs=0.02)  # 72 good matches of 100 first-frame features
    assert err < 0.05
    assert sq.fundamental_inliers(p1[:7], p2[:7], 7) is None
    with pytest.raises(EvaluationError, match="n_first"):
        sq.fundamental_inliers(p1, p2, n_first=10)


@pytest.fixture(scope="module")
def quick_ctx(tmp_path_factory) -> EvalContext:
    root = tmp_path_factory.mktemp("seq")
    (root / "report").mkdir()
    methods = default_methods(threads=1)
    return EvalContext(methods=methods, quick=True, out_dir=root / "report", progress=False, threads=1,
                       extra={"sequences": {"cache_dir": str(root / "cache")}})


@pytest.fixture(scope="module")
def quick_section(quick_ctx):
    return sq.run(quick_ctx)


def test_quick_run_writes_figures_table_and_computed_headline(quick_section, quick_ctx):
    sec = quick_section
    assert sec.key == "sequences"
    assert [p.name for p in sec.figures] == ["sequences_metrics.png", "sequences_track_lengths.png"]
    for p in sec.figures:
        assert p.is_file() and p.stat().st_size > 5000 and p.parent == quick_ctx.out_dir
        assert f"]({p.name})" in sec.markdown
    res = sec.data["results"]
    assert set(res) == {"none", "small", "large", "dark"} and set(res["none"]) == set(METHOD_ORDER)
    assert f"| dark | {KLT} |" in sec.markdown and "5 stops under-exposed" in sec.markdown
    # the dark rows come from noisy images: every method's figures differ from the unperturbed ones
    assert all(res["dark"][m]["error_median_px"] != res["none"][m]["error_median_px"] for m in res["none"])
    targets = [r for r in sec.headline if r.target]
    assert len(targets) == 4 and all(isinstance(r.met, bool) for r in targets)
    # met is computed from the figures, not fixed
    ten = res["large"]
    assert targets[0].met == (ten[NSFLOW]["tracks_10_frames"] >= 2 * ten[KLT]["tracks_10_frames"])
    assert targets[2].met == (ten[NSFLOW]["error_median_px"] <= 0.5)
    verdict = "met" if targets[0].met else "**not met**"
    assert f"target >= 2x OpenCV KLT: {verdict}" in sec.markdown
    assert 0 <= res["none"][KLT]["lost_near_border_share"] <= 1


def test_every_method_tracks_most_features_with_subpixel_error_unperturbed(quick_section):
    for method, f in quick_section.data["results"]["none"].items():
        assert f["tracked_share"] > 0.8, f"{method}: {f}"
        assert f["error_median_px"] < 0.3 and f["error_p90_px"] < 1.0, f"{method}: {f}"
        assert f["rotation_error_median_deg"] < 1.0 and f["rotation_failures"] == 0, f"{method}: {f}"
        assert f["f_inlier_rate"] > 0.7 and f["f_epipolar_error_px"] < 0.5, f"{method}: {f}"


def test_bad_methods_and_levels_are_clear_errors(quick_ctx):
    source = sq.load_source(quick_ctx, sq.QUICK)
    settings = TrackerSettings(max_cnt=30, min_dist=12)
    with pytest.raises(EvaluationError, match="unknown method"):
        sq.track_sequence(source, "ORB", "none", settings=settings)
    with pytest.raises(EvaluationError, match="unknown perturbation 'huge'"):
        sq.track_sequence(source, KLT, "huge", settings=settings)
    with pytest.raises(EvaluationError, match="no methods"):
        sq.evaluate_sequences(source, [], settings=settings)
    ctx = EvalContext(methods=[], quick=True, out_dir=quick_ctx.out_dir, progress=False)
    with pytest.raises(EvaluationError, match="none of the run's methods"):
        sq.run(ctx)
    with pytest.raises(EvaluationError, match="scale"):
        sq.SequenceSetup(duration=1.0, scale=2.0)


def test_learned_encoder_names_the_missing_model(tmp_path):
    missing = tmp_path / "absent.onnx"
    with pytest.raises(EvaluationError, match=r"absent\.onnx"):
        sq.learned_encoder(NSFLOW, str(missing), 1)
    assert sq.learned_encoder(NSFLOW, None, 1) is not None  # the shipped model
