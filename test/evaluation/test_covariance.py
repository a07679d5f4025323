"""The covariance analysis: its metrics on known distributions, the weighted rotation, a quick run."""

from __future__ import annotations

import numpy as np
import pytest

from nsflow_ros.evaluation import covariance as cv
from nsflow_ros.evaluation.context import EvalContext
from nsflow_ros.evaluation.methods import KLT, NSFLOW, eval_method
from nsflow_ros.evaluation.registry import ANALYSES


def _gaussian(n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Errors drawn from per-point covariances (sigmas 0.05-0.5 px, random orientation)."""
    rng = np.random.default_rng(seed)
    s1, s2 = rng.uniform(0.05, 0.5, n), rng.uniform(0.05, 0.5, n)
    th = rng.uniform(0, np.pi, n)
    c, s = np.cos(th), np.sin(th)
    cov = np.c_[c * c * s1**2 + s * s * s2**2, c * s * (s1**2 - s2**2), s * s * s1**2 + c * c * s2**2]
    z = rng.normal(size=(n, 2))
    err = np.c_[c * s1 * z[:, 0] - s * s2 * z[:, 1], s * s1 * z[:, 0] + c * s2 * z[:, 1]]
    return err, cov


def test_a_true_covariance_is_calibrated_and_its_scale_is_one():
    err, cov = _gaussian(20000)
    cal = cv.calibration(err, cov)
    assert abs(cal["inside_68"] - 0.68) < 0.015 and abs(cal["inside_95"] - 0.95) < 0.01
    assert 0.9 < cal["decile_ratio_min"] <= cal["decile_ratio_max"] < 1.1
    assert cal["nll_gain"] > 0.15  # per-point sigmas beat the best single one
    assert cv.fit_scale(err, cov) == pytest.approx(1.0, abs=0.03)
    assert cv.fit_scale(err, cov / 9.0) == pytest.approx(9.0, rel=0.03)  # a 3x optimistic sigma


def test_fit_calibration_recovers_a_scale_and_a_floor():
    err, cov = _gaussian(8000, seed=1)
    # Errors whose covariance is cov / 4 x 4 + 0.01 I: the raw covariance (cov / 4) is too small and its
    # range too wide (sigmas up to 0.5 px: the 2 px inlier cut leaves the Gaussian whole).
    rng = np.random.default_rng(2)
    noisy = err + rng.normal(0, 0.1, err.shape)
    s, f = cv.fit_calibration(noisy, cov / 4.0)
    assert s == pytest.approx(4.0, rel=0.05) and f == pytest.approx(0.01, rel=0.15)
    # Without a floor in the data the fit finds (nearly) none and the scale alone, as fit_scale does.
    s0, f0 = cv.fit_calibration(err, cov / 9.0)
    assert s0 == pytest.approx(9.0, rel=0.05) and f0 < 1e-3
    cal = cv.calibration(noisy, cov / 4.0 * s + np.array([f, 0.0, f]))
    assert 0.66 < cal["inside_68"] < 0.70 and 0.9 < cal["decile_ratio_min"] <= cal["decile_ratio_max"] < 1.1
    with pytest.raises(cv.EvaluationError, match="no inlier"):
        cv.fit_calibration(np.full((3, 2), 5.0), cov[:3])


def test_fit_tail_recovers_the_power_of_errors_that_outgrow_their_sigma():
    err, cov = _gaussian(20000, seed=3)
    # errors drawn with sigma^1.5 / 0.15^0.5 above a 0.15 px knee: the true tail has power 0.5
    truth = cv.CovarianceScale(knee=0.15, power=0.5)
    grow = np.sqrt(truth.expected(cov)[:, 0] / cov[:, 0])
    p = cv.fit_tail(err * grow[:, None], cov, 0.15)
    assert p == pytest.approx(0.5, abs=0.05)
    assert cv.fit_tail(err, cov, 0.15) < 0.03  # Gaussian errors under their own covariance: (almost) none
    big = cv.calibration(err * grow[:, None], cov)
    fitted = cv.calibration(err * grow[:, None], cv.CovarianceScale(knee=0.15, power=p).expected(cov))
    assert big["decile_ratio_max"] > 1.3 and fitted["decile_ratio_max"] < 1.1  # the top deciles mended
    with pytest.raises(cv.EvaluationError, match="no inlier"):
        cv.fit_tail(np.full((3, 2), 5.0), cov[:3], 0.15)


def test_ranking_metrics_on_known_orders():
    err = np.linspace(0, 3, 301)
    bad = err > 1.0
    assert cv.auroc(err, bad) == 1.0 and cv.auroc(-err, bad) == 0.0
    assert cv.auroc(np.zeros_like(err), bad) == 0.5  # ties count half
    assert np.isnan(cv.auroc(err, np.zeros_like(bad)))
    ratio, curve, oracle = cv.ause_ratio(err, err)
    assert ratio == 0.0 and np.array_equal(curve, oracle)
    rand, _, _ = cv.ause_ratio(np.random.default_rng(0).permutation(err), err)
    assert 0.8 < rand < 1.2
    assert cv.auroc(np.array([1.0, np.inf]), np.array([False, True])) == 1.0  # lost check = most uncertain


def test_weighting_by_the_true_covariance_lowers_the_rotation_error():
    rng = np.random.default_rng(3)
    pts = np.c_[rng.uniform(-4, 4, (200, 2)), rng.uniform(4, 12, 200)]
    r_true, _ = np.linalg.qr(np.eye(3) + 0.02 * rng.normal(size=(3, 3)))
    r_true *= np.sign(np.linalg.det(r_true))
    t = np.array([0.3, 0.05, 0.02])
    x1 = pts[:, :2] / pts[:, 2:]
    cam2 = pts @ r_true.T + t
    x2 = cam2[:, :2] / cam2[:, 2:]
    f = 400.0
    sig = np.where(rng.uniform(size=200) < 0.3, 2.0, 0.1) / f  # a third of the points noisy
    x2n = x2 + rng.normal(size=(200, 2)) * sig[:, None]
    cov = np.c_[sig**2, np.zeros(200), sig**2]
    iso, wtd = cv.weighted_rotation_error(x1, x2n, cov, r_true, threshold=6.0 / f)
    assert wtd < iso


@pytest.fixture(scope="module")
def ctx(tmp_path_factory):
    root = tmp_path_factory.mktemp("covariance")
    (root / "report").mkdir()
    methods = [eval_method(NSFLOW, threads=1), eval_method(KLT)]
    return EvalContext(methods=methods, quick=True, out_dir=root / "report", progress=False, threads=1,
                       extra={"covariance": {"cache_dir": str(root / "cache")}})


def test_the_published_row_keeps_what_the_track_check_passed():
    err, cov = _gaussian(300)
    passed = np.arange(300) % 3 != 0
    s = cv.Samples([err], [cov], [np.zeros(300)], [np.zeros(300)], [np.zeros(300)], [passed])
    rows = cv._pools({"sequence none": s})
    assert set(rows) == {"sequence none", "all", "published"}
    np.testing.assert_array_equal(rows["published"]["error"], err[passed])
    np.testing.assert_array_equal(rows["published"]["cov"], cov[passed])
    s.published = [np.zeros(300, bool)]  # nothing passed: no row rather than an empty one
    assert "published" not in cv._pools({"sequence none": s})


def test_quick_run_reports_every_metric_per_method(ctx):
    assert "covariance" in [a.key for a in ANALYSES]
    sec = cv.run(ctx)
    assert sec.key == "covariance" and sec.figures[0].is_file()
    for name in (NSFLOW, KLT):
        pooled = sec.data["results"][name]["all"]
        assert pooled["points"] > 100 and pooled["calibration"]["inliers"] > 100
        assert set(pooled["ranking"]) == set(cv.SIGNALS)
        assert 0.0 <= pooled["calibration"]["inside_68"] <= pooled["calibration"]["inside_95"] <= 1.0
        assert sec.data["rotation"][name]  # weighted and isotropic rotation errors per level
        assert 0 < sec.data["results"][name]["published"]["points"] <= pooled["points"]
    assert "AUROC" in sec.markdown and "Quick mode" in sec.markdown
    scale, source, floor, knee, power = sec.data["scales"][NSFLOW]
    assert scale > 1 and source.endswith(".covariance.json")  # the shipped model's fitted scale
    assert floor > 0  # every method's calibration has a variance floor
    assert knee == 0.15 and power > 0  # and the default's a tail above its covariance check's limit


def test_fit_command_prints_each_method_s_scale(tmp_path, capsys):
    assert cv.main(["fit", "--quick", "--no-write", "--out", str(tmp_path), "--threads", "1"]) == 0
    out = capsys.readouterr().out
    for name in ("nsflow", "nsflow_lk", "classical", "klt"):
        assert f"{name}: scale" in out and "floor" in out


def test_fit_keep_scale_refuses_a_method_without_a_fitted_scale(tmp_path):
    from dataclasses import replace

    from nsflow_ros.core.covariance import CovarianceScale

    m = eval_method(KLT)
    m.core._covariance_scale = CovarianceScale()  # as a model without its sidecar loads
    ctx = EvalContext(methods=[m], quick=True, out_dir=tmp_path, progress=False, threads=1)
    with pytest.raises(cv.EvaluationError, match=r"--keep-scale: OpenCV KLT has no fitted scale"):
        cv.fit(ctx, replace(cv.QUICK, photos=("x",)), keep_scale=True)
