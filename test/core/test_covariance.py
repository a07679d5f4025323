"""Tests of the per-feature covariance (nsflow_ros.core.covariance) and the solver's J^T J it starts from."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from nsflow_ros.core.covariance import (
    METADATA_KEY,
    CovarianceScale,
    klt_covariance,
    lm_covariance,
    max_sigma,
    read_scale,
    sidecar_path,
    window_covariance,
)
from nsflow_ros.core.errors import CoreError
from nsflow_ros.core.methods import SolveKind, klt_track_error, make_method
from nsflow_ros.core.solver import LMConfig, sample_windows, track

CFG = LMConfig(window=11, levels=1, eps=1e-4, max_iterations=30, margin=6)


def _smooth_texture(size: int = 160, seed: int = 0, blur: float = 4.0) -> np.ndarray:
    """A band-limited float texture in [0, 1] (smooth enough that Scharr is the exact derivative's peer)."""
    rng = np.random.default_rng(seed)
    img = cv2.GaussianBlur(rng.uniform(0, 1, (size, size)).astype(np.float32), (0, 0), blur)
    img = (img - img.min()) / (img.max() - img.min())
    return img


def _shifted(img: np.ndarray, dx: float, dy: float) -> np.ndarray:
    """``img`` moved by (dx, dy): out(x + d) = img(x), bilinear, replicated borders."""
    m = np.float32([[1, 0, dx], [0, 1, dy]])
    return cv2.warpAffine(img, m, img.shape[::-1], flags=cv2.INTER_CUBIC, borderMode=cv2.BORDER_REPLICATE)


def _cost(d1: np.ndarray, d2: np.ndarray, pts: np.ndarray, flow: np.ndarray, window: int) -> np.ndarray:
    """S(u) = 1/2 sum over the window of (D2(x + u) - D1(x))^2, sampled as the solver samples."""
    t = sample_windows(d1[:, :, None], pts, window).astype(np.float64)
    p = sample_windows(d2[:, :, None], pts + flow, window).astype(np.float64)
    return 0.5 * ((p - t) ** 2).sum(axis=(1, 2, 3))


def test_solver_jtj_is_the_finite_difference_hessian_of_its_cost():
    # Smooth enough that Scharr's derivative and the bilinear cost's own one agree to a few per cent.
    d1 = _smooth_texture(blur=8.0)
    d2 = _shifted(d1, 1.0, -2.0)
    pts = np.array([[40.0, 50.0], [80.0, 80.0], [110.0, 60.0], [60.0, 115.0]])
    res = track(d1[:, :, None], d2[:, :, None], pts, config=CFG)
    assert res.status.all() and res.hessian.shape == (4, 3)
    h = 0.05
    u = res.flow
    fd = np.zeros((4, 3))
    c0 = _cost(d1, d2, pts, u, CFG.window)
    for k, (a, b) in enumerate(((0, 0), (0, 1), (1, 1))):
        ea, eb = np.eye(2)[a] * h, np.eye(2)[b] * h
        if a == b:
            fd[:, k] = (_cost(d1, d2, pts, u + ea, 11) - 2 * c0 + _cost(d1, d2, pts, u - ea, 11)) / h**2
        else:
            cross = (_cost(d1, d2, pts, u + ea + eb, 11) - _cost(d1, d2, pts, u + ea - eb, 11)
                     - _cost(d1, d2, pts, u - ea + eb, 11) + _cost(d1, d2, pts, u - ea - eb, 11))
            fd[:, k] = cross / (4 * h * h)
    # At a near-perfect match the cost's Hessian is J^T J (the residual's own curvature term vanishes).
    scale = np.abs(fd).max(axis=1, keepdims=True)
    np.testing.assert_allclose(res.hessian / scale, fd / scale, atol=0.06)


def test_predicted_covariance_matches_the_spread_of_solutions_under_noise():
    d1 = _smooth_texture(220, seed=1)
    clean = _shifted(d1, 0.4, 0.25)
    g = np.arange(30, 191, 20, dtype=np.float64)
    pts = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2)  # 81 windows, 9 px apart: independent noise
    ref = track(d1[:, :, None], clean[:, :, None], pts, config=CFG).flow  # the noise-free solution
    rng = np.random.default_rng(7)
    d2s = []
    for _ in range(12):
        # White noise on the template, which is sampled on its pixel centres: the Gauss-Newton model
        # exactly (noise on frame 2, sampled between pixels, is correlated by the interpolation: one
        # reason real covariances need a fitted scale).
        noisy = d1 + rng.normal(0, 0.02, d1.shape).astype(np.float32)
        res = track(noisy[:, :, None], clean[:, :, None], pts, config=CFG)
        ok = res.status
        cov = lm_covariance(res.hessian[ok], res.cost[ok], CFG.window**2)
        e = res.flow[ok] - ref[ok]
        det = cov[:, 0] * cov[:, 2] - cov[:, 1] ** 2
        d2s.append((cov[:, 2] * e[:, 0] ** 2 - 2 * cov[:, 1] * e[:, 0] * e[:, 1] + cov[:, 0] * e[:, 1] ** 2)
                   / det)
    d2 = np.concatenate(d2s)
    assert d2.size > 900
    # d^2 is chi-square with 2 dof: mean 2 (a factor of 2 wrong in sigma_hat^2 or (J^T J)^-1 gives 1 or
    # 4), 68 % within 2.279.
    assert 1.6 < d2.mean() < 2.5, d2.mean()
    assert 0.6 < np.mean(d2 <= 2.279) < 0.76


def test_window_covariance_of_opencv_lk_agrees_with_the_solver_s():
    d1 = _smooth_texture(seed=2)
    d2 = _shifted(d1, 0.3, -0.2) + np.random.default_rng(3).normal(0, 0.01, d1.shape).astype(np.float32)
    pts = np.array([[40.0, 50.0], [80.0, 80.0], [110.0, 60.0]])
    res = track(d1[:, :, None], d2[:, :, None], pts, config=CFG)
    lm = lm_covariance(res.hessian, res.cost, CFG.window**2)
    win = window_covariance(d1, d2, pts, pts + res.flow, CFG.window)
    np.testing.assert_allclose(win, lm, rtol=0.05, atol=1e-3 * np.abs(lm).max())


def test_klt_method_gives_covariances_where_tracked():
    rng = np.random.default_rng(4)
    img = cv2.GaussianBlur(rng.integers(0, 255, (120, 160)).astype(np.uint8), (0, 0), 1.5)
    img2 = np.roll(img, 1, axis=1)
    method = make_method("klt")
    pts = np.array([[60.0, 60.0], [100.0, 50.0], [-50.0, 10.0]])
    new, status, cov = method.solve_with_covariance(SolveKind.FORWARD, img, img2, pts)
    plain, plain_status = method.solve(SolveKind.FORWARD, img, img2, pts)
    np.testing.assert_array_equal(new, plain)  # the covariance does not change the track
    np.testing.assert_array_equal(status, plain_status)
    assert status[:2].all() and not status[2] and np.all(np.isnan(cov[~status]))
    # an exact match (OpenCV's err 0): the fitted floor alone, never a zero covariance
    floor = method.covariance_scale.floor
    assert floor > 0
    np.testing.assert_allclose(cov[status], [[floor, 0.0, floor]] * 2)
    noisy = np.clip(img2 + np.random.default_rng(5).normal(0, 4, img.shape), 0, 255).astype(np.uint8)
    _, status, cov = method.solve_with_covariance(SolveKind.FORWARD, img, noisy, pts)
    assert status[:2].all() and np.all(cov[status][:, [0, 2]] > floor)


def test_lm_method_covariance_leaves_the_track_bit_identical(textures):
    method = make_method("classical")
    gray = textures["coffee"]
    f1 = method.prepare(gray, gray)
    f2 = method.prepare(np.roll(gray, 2, axis=0), np.roll(gray, 2, axis=0))
    pts = np.array([[100.0, 100.0], [300.0, 200.0], [500.0, 300.0]])
    new, status = method.solve(SolveKind.FORWARD, f1, f2, pts)
    new_c, status_c, cov = method.solve_with_covariance(SolveKind.FORWARD, f1, f2, pts)
    np.testing.assert_array_equal(new, new_c)
    np.testing.assert_array_equal(status, status_c)
    assert cov.shape == (3, 3) and np.all(cov[status][:, 0] > 0)


def test_lm_covariance_inverts_the_normal_equations():
    hess = np.array([[4.0, 1.0, 2.0], [1.0, 0.0, 1.0], [1.0, 1.0, 1.0]])  # the last one singular
    cov = lm_covariance(hess, np.array([1.0, 2.0, 1.0]), 12, scale=2.0)
    var = 2.0 * 2.0 * np.array([1.0, 2.0]) / 10.0
    inv0 = np.linalg.inv([[4.0, 1.0], [1.0, 2.0]]) * var[0]
    np.testing.assert_allclose(cov[0], [inv0[0, 0], inv0[0, 1], inv0[1, 1]])
    np.testing.assert_allclose(cov[1], [var[1], 0.0, var[1]])
    assert np.isinf(cov[2, 0]) and np.isinf(max_sigma(cov[2:]))[0]
    with pytest.raises(CoreError, match="elements"):
        lm_covariance(hess, np.ones(3), 2)


def test_max_sigma_is_the_major_axis():
    cov = np.array([[4.0, 0.0, 1.0], [2.0, 1.0, 2.0]])
    np.testing.assert_allclose(max_sigma(cov), [2.0, np.sqrt(3.0)])


def test_scale_comes_from_metadata_then_sidecar_then_registry(tmp_path):
    model = tmp_path / "enc.onnx"
    model.write_bytes(b"")
    assert read_scale("nsflow").scale == 1.0 and not read_scale("nsflow").calibrated
    assert read_scale("klt", registry=3.0).source == "registry"
    sidecar_path(model).write_text(json.dumps({"scales": {"nsflow": 5.0}}))
    got = read_scale("nsflow", {}, model)
    assert (got.scale, got.source) == (5.0, "enc.covariance.json")
    sidecar_path(model).write_text(json.dumps({"scales": {"nsflow": 5.0}, "model_sha256": "0" * 64}))
    stale = read_scale("nsflow", {}, model)  # fitted on another file: not used
    assert stale.scale == 1.0 and not stale.calibrated and "another model" in stale.source
    meta = {METADATA_KEY: json.dumps({"nsflow": 7.5})}
    assert read_scale("nsflow", meta, model).scale == 7.5
    assert read_scale("nsflow_lk", meta, model, registry=2.0).source == "registry"


@pytest.mark.parametrize("text, match", [
    ('{"nsflow": -1}', r"must be a finite number > 0"),
    ('{"nsflow": "x"}', r"must be a finite number > 0"),
    ("not json", "not JSON"),
    ("[1]", "JSON object"),
])
def test_bad_stored_scales_are_named(text, match):
    with pytest.raises(CoreError, match=match):
        read_scale("nsflow", {METADATA_KEY: text})


def test_bad_sidecar_is_named(tmp_path):
    model = tmp_path / "m.onnx"
    sidecar_path(model).write_text('{"nsflow": 2}')
    with pytest.raises(CoreError, match=r"m\.covariance\.json"):
        read_scale("nsflow", None, model)


def test_klt_covariance_from_opencv_s_err_agrees_with_the_window_sampled_one():
    # A smooth texture (central differences and Scharr agree there), shifted, with white noise of 3 grey
    # levels: the residual is nearly Gaussian, the case in which pi/2 err^2 is the residual variance.
    d1 = np.round(_smooth_texture(200, seed=5, blur=3.0) * 200 + 25).astype(np.uint8)
    rng = np.random.default_rng(6)
    d2 = np.clip(_shifted(d1.astype(np.float32), 0.4, -0.3) + rng.normal(0, 3.0, d1.shape), 0, 255)
    d2 = np.round(d2).astype(np.uint8)
    g = np.arange(30, 171, 20, dtype=np.float64)
    pts = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2) + 0.3  # off the pixel grid: rounded to read
    new, ok, err = klt_track_error(d1, d2, pts)
    assert ok.all() and np.all(err > 0)
    cheap = klt_covariance(d1, pts, err, 21)
    ref = window_covariance(d1, d2, pts, new, 21)
    # sigma along each axis within 10 %: the window's 441 residuals leave the mean-absolute-to-RMS ratio
    # a few per cent of spread, and J^T J is read at most half a pixel off the point on image 1 rather
    # than at the solution on image 2, a few per cent more on this texture.
    np.testing.assert_allclose(np.sqrt(cheap[:, [0, 2]]), np.sqrt(ref[:, [0, 2]]), rtol=0.10)
    corr = cheap[:, 1] / np.sqrt(cheap[:, 0] * cheap[:, 2])
    np.testing.assert_allclose(corr, ref[:, 1] / np.sqrt(ref[:, 0] * ref[:, 2]), atol=0.1)
    # and the whole: scale 2 doubles it; one channel of three identical ones is the same covariance
    np.testing.assert_allclose(klt_covariance(d1, pts, err, 21, scale=2.0), 2 * cheap)
    three = np.repeat(d1[:, :, None], 3, axis=2)
    # three channels: J^T J three times, the same per-element residual, 3 x 441 - 2 degrees of freedom
    dof = (3 * 441 / (3 * 441 - 2)) / (441 / (441 - 2))
    np.testing.assert_allclose(klt_covariance(three, pts, err, 21), cheap / 3 * dof, rtol=1e-6)


@pytest.mark.parametrize("args, match", [
    ({"err": np.array([1.0, -1.0])}, r"err must be finite and >= 0, got -1\.0 at point 1"),
    ({"err": np.array([np.nan, 1.0])}, r"err must be finite and >= 0, got nan at point 0"),
    ({"err": np.ones(3)}, r"pts must be \(N, 2\) and err \(N,\), got \(2, 2\) and \(3,\)"),
    ({"pts": np.array([[10.0, np.inf], [20.0, 20.0]])}, r"pts must be finite, got \[10\.0, inf\] at point 0"),
    ({"window": 20}, "window must be odd"),
    ({"image": np.zeros((20, 40), np.uint8)}, r"image 40x20 is smaller than the 23x23 window"),
])
def test_klt_covariance_names_bad_input(args, match):
    kw = {"image": np.zeros((60, 60), np.uint8), "pts": np.array([[10.0, 10.0], [20.0, 20.0]]),
          "err": np.ones(2), "window": 21, **args}
    with pytest.raises(CoreError, match=match):
        klt_covariance(**kw)


def test_klt_covariance_of_a_border_point_reads_a_window_inside_the_image():
    img = np.round(_smooth_texture(80, seed=8, blur=2.0) * 255).astype(np.uint8)
    pts = np.array([[0.0, 0.0], [11.0, 11.0], [79.0, 40.0]])
    cov = klt_covariance(img, pts, np.ones(3), 21)
    np.testing.assert_allclose(cov[0], cov[1])  # moved inside: the same window as the corner one
    assert np.isfinite(cov).all() and np.all(cov[:, 0] > 0)


def test_calibration_applies_scale_and_floor_and_inverts():
    cal = CovarianceScale(4.0, "registry", 0.01)
    raw = np.array([[1.0, 0.5, 2.0], [np.inf, 0.0, np.inf]])
    got = cal.apply(raw)
    np.testing.assert_allclose(got[0], [4.01, 2.0, 8.01])
    assert np.isinf(got[1, 0]) and got[1, 1] == 0.0  # a singular J^T J stays unbounded
    np.testing.assert_allclose(cal.raw(got)[0], raw[0])
    with pytest.raises(CoreError, match=r"floor must be a finite number >= 0 \(px\^2\), got -0\.1"):
        CovarianceScale(1.0, "registry", -0.1)
    with pytest.raises(CoreError, match="scale must be a finite number > 0, got nan"):
        CovarianceScale(float("nan"))


def test_the_tail_grows_the_published_covariance_above_the_knee_only():
    cal = CovarianceScale(1.0, "registry", 0.0, knee=0.15, power=0.5)
    cov = np.array([[0.01, 0.0, 0.01], [0.04, 0.0, 0.01], [0.09, 0.03, 0.09], [np.inf, 0.0, np.inf],
                    [np.nan, np.nan, np.nan]])
    got = cal.expected(cov)
    np.testing.assert_array_equal(got[0], cov[0])  # sigma 0.1: below the knee, as calibrated
    # sigma 0.2 along x: the whole covariance times (0.2 / 0.15)^(2 * 0.5), its shape kept
    np.testing.assert_allclose(got[1], cov[1] * 0.2 / 0.15)
    np.testing.assert_allclose(max_sigma(got[2:3]), max_sigma(cov[2:3]) ** 1.5 / 0.15**0.5)
    assert np.isinf(got[3, 0]) and np.isnan(got[4]).all()  # unbounded and unknown stay so
    order = np.argsort(max_sigma(cov[:3]))
    np.testing.assert_array_equal(np.argsort(max_sigma(got[:3])), order)  # monotone: no feature reordered
    for plain in (CovarianceScale(2.0, "registry", 0.1), CovarianceScale(knee=0.15)):
        np.testing.assert_array_equal(plain.expected(cov[:3]), cov[:3])  # no tail: the identity
    assert cal.expected(np.zeros((0, 3))).shape == (0, 3)
    with pytest.raises(CoreError, match="knee must be a number > 0"):
        CovarianceScale(knee=0.0)
    with pytest.raises(CoreError, match="power must be a finite number >= 0, got -1"):
        CovarianceScale(power=-1.0)


def test_sidecar_with_a_floor_and_an_older_one_without(tmp_path):
    model = tmp_path / "enc.onnx"
    model.write_bytes(b"model")
    import hashlib

    sha = hashlib.sha256(b"model").hexdigest()
    side = sidecar_path(model)
    side.write_text(json.dumps({"scales": {"nsflow": 5.0}, "model_sha256": sha}))  # an older sidecar
    old = read_scale("nsflow", {}, model)
    assert (old.scale, old.floor, old.calibrated) == (5.0, 0.0, True)
    side.write_text(json.dumps({"scales": {"nsflow": {"scale": 4.0, "floor": 0.002}}, "model_sha256": sha}))
    new = read_scale("nsflow", {}, model)
    assert (new.scale, new.floor, new.source) == (4.0, 0.002, "enc.covariance.json")
    model.write_bytes(b"another model")  # replaced under the same name: the stale check still holds
    stale = read_scale("nsflow", {}, model)
    assert (stale.scale, stale.floor, stale.calibrated) == (1.0, 0.0, False)
    meta = {METADATA_KEY: json.dumps({"nsflow": {"scale": 3.0, "floor": 0.5}})}
    assert read_scale("nsflow", meta).floor == 0.5
    assert read_scale("nsflow", meta).expected(np.array([[9.0, 0.0, 9.0]]))[0, 0] == 9.0  # no tail stored
    meta = {METADATA_KEY: json.dumps({"nsflow": {"scale": 3.0, "floor": 0.5, "knee": 0.15, "power": 0.4}})}
    tail = read_scale("nsflow", meta)
    assert (tail.knee, tail.power) == (0.15, 0.4)
    reg = CovarianceScale(2.0, "registry", 0.1)
    assert read_scale("klt", registry=reg) is reg


@pytest.mark.parametrize("entry, match", [
    ({"scale": 2.0, "floor": -1}, r"covariance floor of 'nsflow' must be a finite number >= 0, got -1"),
    ({"scale": 2.0, "floor": "x"}, r"covariance floor of 'nsflow' must be a finite number >= 0, got 'x'"),
    ({"floor": 0.1}, r"covariance scale of 'nsflow' must be a finite number > 0, got None"),
    ({"scale": 0, "floor": 0.1}, r"covariance scale of 'nsflow' must be a finite number > 0, got 0"),
    ({"scale": 2.0, "knee": 0, "power": 0.5},
     r"covariance knee of 'nsflow' must be a finite number > 0, got 0"),
    ({"scale": 2.0, "knee": 0.15, "power": -0.5},
     r"covariance power of 'nsflow' must be a finite number >= 0, got -0\.5"),
    ({"scale": 2.0, "knee": 0.15, "power": True}, r"covariance power of 'nsflow' must be"),
])
def test_bad_stored_floors_are_named(entry, match):
    with pytest.raises(CoreError, match=match):
        read_scale("nsflow", {METADATA_KEY: json.dumps({"nsflow": entry})})


def test_klt_template_hessian_is_read_once_for_a_stereo_then_temporal_solve_and_never_stale():
    rng = np.random.default_rng(9)
    left = cv2.GaussianBlur(rng.integers(0, 255, (120, 160)).astype(np.uint8), (0, 0), 1.5)
    right = np.roll(left, -3, axis=1)
    nxt = np.clip(np.roll(left, 1, axis=0) + rng.normal(0, 3, left.shape), 0, 255).astype(np.uint8)
    pts = np.array([[60.0, 60.0], [100.5, 50.2], [40.3, 80.0]])
    method, fresh = make_method("klt"), make_method("klt")
    method.solve_with_covariance(SolveKind.STEREO, left, right, pts)
    # the next frame's temporal solve from the same left image and points: the windows are not read again
    hess = method._hessian_memo[2]
    _, status, cov = method.solve_with_covariance(SolveKind.FORWARD, left, nxt, pts)
    assert method._hessian_memo[2] is hess and status.all()
    np.testing.assert_array_equal(cov, fresh.solve_with_covariance(SolveKind.FORWARD, left, nxt, pts)[2])
    # another image or other points: read again
    _, _, other = method.solve_with_covariance(SolveKind.FORWARD, nxt, left, pts)
    np.testing.assert_array_equal(other, fresh.solve_with_covariance(SolveKind.FORWARD, nxt, left, pts)[2])
    moved = pts + 5.0
    _, _, cov2 = method.solve_with_covariance(SolveKind.FORWARD, nxt, left, moved)
    np.testing.assert_array_equal(cov2, fresh.solve_with_covariance(SolveKind.FORWARD, nxt, left, moved)[2])
