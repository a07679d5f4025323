"""Tests of the per-feature covariance (nsflow_ros.core.covariance) and the solver's J^T J it starts from."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from nsflow_ros.core.covariance import (
    METADATA_KEY,
    lm_covariance,
    max_sigma,
    read_scale,
    sidecar_path,
    window_covariance,
)
from nsflow_ros.core.errors import CoreError
from nsflow_ros.core.methods import SolveKind, make_method
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
    assert status[:2].all() and not status[2]
    assert np.all(cov[status, 0] > 0) and np.all(np.isnan(cov[~status]))


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
