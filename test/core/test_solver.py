"""Tests of the LM Lucas-Kanade solver (nsflow_ros.core.solver)."""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import pytest
from image_pairs import apply_h, rotation, texture, translation, warp_pair

from nsflow_ros import CoreError, IntensityEncoder, Jacobian, LMConfig, build_pyramid, detect_corners, track
from nsflow_ros.core import solver as solver_mod
from nsflow_ros.core.solver import sample_windows, window_centres

ENC = IntensityEncoder()


def _run(gray1, gray2, h, config=None, n=150):
    pts = detect_corners(gray1, n, min_distance=10)
    res = track(ENC(gray1), ENC(gray2), pts, config=config)
    err = np.linalg.norm(pts + res.flow - apply_h(h, pts), axis=1)
    return pts, res, err


@pytest.mark.parametrize("shift", [(0.37, -0.21), (2.3, -1.7), (7.6, 4.2)])
def test_recovers_subpixel_translations(textures, shift):
    h = translation(*shift)
    for gray in textures.values():
        a, b = warp_pair(gray, h)
        _, res, err = _run(a, b, h)
        assert res.status.mean() > 0.9
        assert np.median(err[res.status]) < 0.05


@pytest.mark.parametrize("deg", [-0.5, 0.4])
def test_recovers_small_rotation(textures, deg):
    # A translational window model: at 2 degrees the deformation inside an 11x11 window already costs
    # OpenCV and this solver alike ~0.09 px median, so "small" here means half a degree.
    gray = textures["astronaut"]
    h = rotation(deg, (376.0, 240.0))
    a, b = warp_pair(gray, h)
    _, res, err = _run(a, b, h)
    assert res.status.mean() > 0.9
    assert np.median(err[res.status]) < 0.05


def test_recovers_homography(textures):
    h = np.array([[1.01, 0.01, 2.0], [-0.008, 0.995, -1.5], [1.5e-5, -1e-5, 1.0]])
    for name in ("coffee", "chelsea"):
        a, b = warp_pair(textures[name], h)
        _, res, err = _run(a, b, h)
        assert res.status.mean() > 0.85
        assert np.median(err[res.status]) < 0.05


def test_multichannel_descriptors(textures):
    # Three channels (intensity, squared intensity, blurred intensity) run through the same solver.
    h = translation(1.3, -0.6)
    a, b = warp_pair(textures["coffee"], h)

    def desc(img):
        x = img.astype(np.float32) / 255.0
        return np.dstack([x, x * x, cv2.GaussianBlur(x, (5, 5), 1.0)])

    pts = detect_corners(a, 150, min_distance=10)
    res = track(desc(a), desc(b), pts)
    err = np.linalg.norm(pts + res.flow - apply_h(h, pts), axis=1)
    assert res.status.mean() > 0.9
    assert np.median(err[res.status]) < 0.05


def test_agrees_with_opencv_pyramidal_lk(textures):
    h = translation(3.4, 1.2)
    a, b = warp_pair(textures["astronaut"], h)
    pts = detect_corners(a, 150, min_distance=10)
    res = track(ENC(a), ENC(b), pts, config=LMConfig(window=21))
    cv_pts, cv_st, _ = cv2.calcOpticalFlowPyrLK(
        a, b, pts.astype(np.float32), None, winSize=(21, 21), maxLevel=2,
        criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 30, 0.01),
    )
    both = res.status & (cv_st[:, 0] == 1)
    assert both.mean() > 0.9
    diff = np.linalg.norm(pts[both] + res.flow[both] - cv_pts[both], axis=1)
    # Both solve the same 21x21 intensity problem; they differ by their stop rules and gradient filters.
    assert np.median(diff) < 0.05
    assert np.percentile(diff, 90) < 0.15


def test_every_iteration_follows_accept_reject_rule():
    # A single Gaussian blob far from its match: Gauss-Newton steps overshoot, so some are rejected.
    yy, xx = np.mgrid[0:64, 0:64].astype(np.float32)
    blob = lambda cx, cy: np.exp(-((xx - cx) ** 2 + (yy - cy) ** 2) / (2 * 2.0**2))  # noqa: E731
    d1, d2 = blob(32, 32)[..., None], blob(34.5, 31.0)[..., None]
    # a fixed lambda^(0) (no scaling with J^T J), so that the first steps are nearly Gauss-Newton
    cfg = LMConfig(levels=1, lambda_scale=0, eps=1e-6, max_iterations=40,
                   min_eigen=0)
    pts = np.array([[32.0, 32.0], [31.0, 33.0], [33.0, 31.5]])
    res = track(d1, d2, pts, flow0=np.array([[0.2, 0.1], [0.0, 0.0], [-0.3, 0.4]]), config=cfg, record=True)
    prev_flow = np.array([[0.2, 0.1], [0.0, 0.0], [-0.3, 0.4]])
    prev_lam = np.full(3, cfg.lambda_init)
    # cost before the first iteration, evaluated independently of the solver's loop
    pyr1, pyr2 = build_pyramid(d1, 1), build_pyramid(d2, 1)
    t = sample_windows(pyr1.levels[0], pts, 11)[..., :1]
    prev_cost = 0.5 * ((sample_windows(pyr2.levels[0], pts + prev_flow, 11)[..., :1] - t) ** 2).sum((1, 2, 3))
    rejected = 0
    for rec in res.history:
        for i in np.flatnonzero(rec.active):
            if rec.accepted[i]:
                assert rec.cost[i] < prev_cost[i]
                assert rec.lam[i] == pytest.approx(prev_lam[i] / cfg.nu)
            else:
                rejected += 1
                assert np.array_equal(rec.flow[i], prev_flow[i])
                assert rec.cost[i] == prev_cost[i]
                assert rec.lam[i] == pytest.approx(prev_lam[i] * cfg.nu)
        prev_flow, prev_lam, prev_cost = rec.flow.copy(), rec.lam.copy(), rec.cost.copy()
    assert rejected > 0, "the case was built to force uphill steps"
    # the blob's sampled derivatives are approximations, so the fixed point is within ~1e-3 px of the shift
    np.testing.assert_allclose(res.flow, np.tile([2.5, -1.0], (3, 1)), atol=5e-3)


@pytest.mark.parametrize("scale", [0.0, 0.1, 3.0])
def test_initial_damping_scales_with_the_hessian(textures, scale):
    a, b = warp_pair(textures["coffee"], translation(1.2, -0.7))
    pts = detect_corners(a, 40, min_distance=10)
    cfg = LMConfig(levels=1, lambda_scale=scale, max_iterations=1)
    res = track(ENC(a), ENC(b), pts, config=cfg, record=True)
    level = build_pyramid(ENC(a), 1).levels[0]
    terms = solver_mod._normal_equations(
        build_pyramid(ENC(b), 1).levels[0], pts, solver_mod._sample_level(level, pts, cfg.window), cfg.window
    )
    lam0 = np.maximum(cfg.lambda_init, scale * np.maximum(terms[:, 1], terms[:, 3]))
    if scale == 3.0:
        assert (lam0 > cfg.lambda_init).all()  # the floor is not what is being tested
    (rec,) = res.history
    np.testing.assert_allclose(rec.lam, np.where(rec.accepted, lam0 / cfg.nu, lam0 * cfg.nu), rtol=1e-9)


def test_stops_at_k_max_and_on_tolerance():
    img = texture("astronaut", (160, 120))
    a, b = warp_pair(img, translation(1.2, 0.7))
    pts = detect_corners(a, 30, min_distance=8)
    loose = track(ENC(a), ENC(b), pts, config=LMConfig(levels=1, eps=1e-1))
    tight = track(ENC(a), ENC(b), pts, config=LMConfig(levels=1, eps=1e-12, max_iterations=7))
    assert tight.iterations.max() == 7
    assert loose.iterations.mean() < tight.iterations.mean()


def test_tail_share_ends_a_level_once_few_points_are_left():
    img = texture("astronaut", (160, 120))
    a, b = warp_pair(img, translation(1.2, 0.7))
    pts = detect_corners(a, 40, min_distance=8)
    full = track(ENC(a), ENC(b), pts, config=LMConfig(levels=1, eps=1e-12, max_iterations=7))
    # every point would iterate to K_max: the cut-off cannot apply while they are all active
    assert (full.iterations == 7).all()
    same = track(ENC(a), ENC(b), pts, config=LMConfig(levels=1, eps=1e-12, max_iterations=7, tail_share=0.5))
    np.testing.assert_array_equal(same.flow, full.flow)
    # with most points converged early, the few left stop after tail_passes with the flow they have
    base = LMConfig(levels=1, max_iterations=30)
    alg1 = track(ENC(a), ENC(b), pts, config=base)
    slow = alg1.iterations > 8
    assert 0 < slow.sum() <= 0.4 * len(pts)
    cfg = LMConfig(levels=1, max_iterations=30, tail_share=0.4, tail_passes=8)
    cut = track(ENC(a), ENC(b), pts, config=cfg)
    assert cut.iterations.max() == 8
    np.testing.assert_array_equal(cut.flow[~slow], alg1.flow[~slow])
    assert np.abs(cut.flow - alg1.flow).max() < 0.5


def test_initial_flow_is_used(textures):
    h = translation(40.0, -25.0)
    a, b = warp_pair(textures["coffee"], h)
    pts = detect_corners(a, 100, min_distance=10)
    inner = (pts[:, 0] > 60) & (pts[:, 0] < 690) & (pts[:, 1] > 45) & (pts[:, 1] < 430)
    pts = pts[inner]
    guess = np.tile([39.0, -24.0], (len(pts), 1))
    res = track(ENC(a), ENC(b), pts, flow0=guess, config=LMConfig(levels=1))
    err = np.linalg.norm(res.flow - [40.0, -25.0], axis=1)
    assert res.status.mean() > 0.9 and np.median(err[res.status]) < 0.05
    blind = track(ENC(a), ENC(b), pts, config=LMConfig(levels=1))
    blind_err = np.linalg.norm(blind.flow - [40.0, -25.0], axis=1)
    assert np.median(blind_err) > 5.0


def test_border_points_get_status_false(textures):
    a, b = warp_pair(textures["astronaut"], translation(0.5, 0.5))
    inner = detect_corners(a[100:380, 100:650], 1)[0] + 100  # a strong corner well inside
    pts = np.array([[2.0, 200.0], [400.0, 1.0], [749.0, 300.0], [300.0, 478.5], inner])
    res = track(ENC(a), ENC(b), pts)
    assert res.status.tolist() == [False, False, False, False, True]
    # a flow that carries the window out of frame 2 is lost as well
    res = track(ENC(a), ENC(b), inner[None], flow0=np.array([[800.0, 0.0]]), config=LMConfig(levels=1))
    assert not res.status[0]


def test_window_centres_move_coarse_windows_inside_the_level():
    pts = np.array([[40.0, 30.0], [2.0, 30.0], [78.5, 1.0], [-3.0, 61.0]])
    got = window_centres(pts, (60, 80), 11)
    np.testing.assert_array_equal(got, [[40.0, 30.0], [5.0, 30.0], [74.0, 5.0], [5.0, 54.0]])
    # a level smaller than the window: its centre
    np.testing.assert_array_equal(window_centres(pts[:1], (8, 40), 11), [[34.0, 3.5]])


def test_coarse_levels_use_the_moved_windows(textures, monkeypatch):
    a, b = warp_pair(textures["astronaut"], translation(6.0, -4.0))
    pts = np.stack([np.full(9, 6.0), np.linspace(60, 420, 9)], 1)
    seen = []
    real = solver_mod._solve_level

    def spy(l1, l2, p, *args):
        seen.append((args[2], p.copy()))
        return real(l1, l2, p, *args)

    monkeypatch.setattr(solver_mod, "_solve_level", spy)
    track(ENC(a), ENC(b), pts, config=LMConfig(levels=3))
    by_level = dict(seen)
    np.testing.assert_array_equal(by_level[0], pts)  # level 0 keeps each point's own window
    for lev in (1, 2):
        shape = (480 // 2**lev, 752 // 2**lev)
        np.testing.assert_array_equal(by_level[lev], window_centres(pts / 2**lev, shape, 11))
        assert (by_level[lev][:, 0] == 5.0).all()  # moved right until the 11 px window fits


def test_textureless_and_saturated_windows_get_status_false(textures):
    img = textures["astronaut"].copy()
    img[100:200, 100:200] = 128  # flat
    img[300:400, 500:600] = 255  # saturated
    pts = np.array([[150.0, 150.0], [550.0, 350.0]])
    res = track(ENC(img), ENC(img), pts, flow0=np.array([[0.5, 0.5], [0.5, -0.5]]))
    assert not res.status.any()
    flat = np.full((64, 64), 77, np.uint8)
    res = track(ENC(flat), ENC(flat), np.array([[32.0, 32.0]]))
    assert not res.status[0]
    assert np.isfinite(res.flow).all()


def test_empty_point_set():
    d = np.zeros((32, 32, 1), np.float32)
    res = track(d, d, np.zeros((0, 2)))
    assert res.flow.shape == (0, 2) and res.status.shape == (0,)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"points": np.zeros((3, 3))}, r"points must have shape \(N, 2\)"),
        ({"flow0": np.zeros((2, 2))}, r"flow0 must have shape \(3, 2\)"),
        ({"points": np.full((3, 2), np.nan)}, "finite"),
        ({"desc2": np.zeros((16, 32, 1), np.float32)}, "descriptor maps differ"),
        ({"desc2": np.zeros((32, 32, 2), np.float32)}, "descriptor maps differ"),
        ({"desc1": np.zeros((32, 32, 1), np.int32)}, "floating point"),
        ({"desc1": [[0.0]]}, "DescriptorPyramid"),
    ],
)
def test_guards(kwargs, match):
    args = {"desc1": np.zeros((32, 32, 1), np.float32), "desc2": np.zeros((32, 32, 1), np.float32),
            "points": np.full((3, 2), 16.0), "flow0": None}
    args.update(kwargs)
    with pytest.raises(CoreError, match=match):
        track(args["desc1"], args["desc2"], args["points"], args["flow0"])


@pytest.mark.parametrize(
    ("field", "value"),
    [("window", 10), ("window", 1), ("levels", 0), ("max_iterations", 0), ("eps", 0.0), ("min_eigen", -1.0),
     ("tail_share", 1.0), ("tail_share", -0.1), ("tail_passes", 0), ("coarse_window", 14),
     ("coarse_window", 1), ("coarse_from", 0), ("jacobian", "esm")],
)
def test_config_validation(field, value):
    with pytest.raises(CoreError, match=field):
        LMConfig(**{field: value})


@pytest.mark.parametrize("channels", [1, 2, 3, 4, 6, 9])
def test_remap_sampler_is_exact_and_matches_numpy_fallback(channels):
    assert solver_mod._remap_is_exact(), "installed OpenCV quantises remap; the slow fallback would be used"
    rng = np.random.default_rng(3)
    level = rng.random((40, 50, channels), dtype=np.float32)
    centers = rng.uniform(-3, 52, (20, 2))
    slow = solver_mod._sample_numpy(level, centers, 7)
    # 2 channels too (OpenCV 5 samples an interleaved 2-channel map at 1/32 px: they are sampled padded)
    np.testing.assert_allclose(sample_windows(level, centers, 7), slow, atol=5e-6)  # 1/32 px: 1e-3
    pyramid_level = build_pyramid(level, 1).levels[0]
    np.testing.assert_allclose(sample_windows(pyramid_level, centers, 7), slow, atol=5e-6)
    # bilinear interpolation of a plane is exact
    yy, xx = np.mgrid[0:40, 0:50].astype(np.float32)
    plane = (0.3 * xx - 0.2 * yy + 1.0)[..., None]
    c = np.array([[20.37, 15.81]])
    win = sample_windows(plane, c, 3)[0, :, :, 0]
    off = np.array([-1, 0, 1])
    expect = 0.3 * (c[0, 0] + off)[None, :] - 0.2 * (c[0, 1] + off)[:, None] + 1
    np.testing.assert_allclose(win, expect, atol=1e-5)


@pytest.mark.parametrize("points", [0, 1, 5])
def test_scatter_maps_lay_square_grids_side_by_side(points):
    centers = np.random.default_rng(4).uniform(0, 30, (points, 2))
    mapx, mapy = solver_mod._scatter_maps(centers, 5)
    assert mapx.shape == mapy.shape == (5, points * 5) and mapx.dtype == mapy.dtype == np.float32
    off = np.arange(-2, 3, dtype=np.float32)
    c = centers.astype(np.float32)
    for i in range(points):
        grid = np.s_[:, 5 * i : 5 * i + 5]
        np.testing.assert_array_equal(mapx[grid], np.broadcast_to(c[i, 0] + off, (5, 5)))
        np.testing.assert_array_equal(mapy[grid], np.broadcast_to((c[i, 1] + off)[:, None], (5, 5)))


@pytest.mark.parametrize("channels", [1, 4, 6])
def test_patch_scharr_jacobian_equals_sampled_derivative_maps(channels):
    """J from the Scharr filter of a sampled patch = the Scharr maps sampled at x + u, wherever the window
    lies inside the image (also touching its border); beyond it J is that of the replicated map: 0."""
    from nsflow_ros.core.pyramid import build_pyramid, descriptor_gradients

    rng = np.random.default_rng(channels)
    desc = cv2.GaussianBlur(rng.random((40, 50, channels), dtype=np.float32), (0, 0), 1.5)
    desc = desc.reshape(40, 50, channels)
    # window (side 5) inside the image, some touching its border, all with sub-pixel offsets
    edge = [[2.3, 2.1], [46.7, 36.9], [2.0, 37.0]]
    centers = np.concatenate([rng.uniform([3, 3], [46, 36], (10, 2)), edge])
    level = build_pyramid(desc, 1).levels[0]
    template = solver_mod._sample_level(level, centers, 5)
    terms = solver_mod._normal_equations(level, centers, template, 5)
    cost, hess = terms[:, 0], terms[:, 1:4]
    dx, dy = descriptor_gradients(desc)
    jx = sample_windows(dx, centers, 5).reshape(len(centers), -1).astype(np.float64)
    jy = sample_windows(dy, centers, 5).reshape(len(centers), -1).astype(np.float64)
    # f = 0 at the template's own position, so compare H directly and J^T f against a shifted template
    np.testing.assert_allclose(cost, 0.0, atol=1e-10)
    expect = np.stack([(jx * jx).sum(1), (jx * jy).sum(1), (jy * jy).sum(1)], axis=1)
    np.testing.assert_allclose(hess, expect, rtol=1e-5, atol=1e-9)
    shifted = [t + 0.1 for t in template]
    g = solver_mod._normal_equations(level, centers, shifted, 5)[:, 4:]
    np.testing.assert_allclose(g, -0.1 * np.stack([jx.sum(1), jy.sum(1)], axis=1), rtol=1e-4, atol=1e-7)


def test_patch_jacobian_beyond_the_image_is_that_of_the_replicated_map():
    desc = np.tile(np.linspace(0, 1, 30, dtype=np.float32), (20, 1))[..., None]  # ramp along x
    level = build_pyramid(desc, 1).levels[0]
    far = np.array([[40.5, 10.0], [-9.5, 10.0]])  # whole window right / left of the image
    hess = solver_mod._normal_equations(level, far, solver_mod._sample_level(level, far, 5), 5)[:, 1:4]
    np.testing.assert_allclose(hess, 0.0, atol=1e-12)


def test_jacobian_terms_only_for_candidates_below_the_current_cost():
    rng = np.random.default_rng(5)
    desc = cv2.GaussianBlur(rng.random((40, 50, 4), dtype=np.float32), (0, 0), 1.5)
    level = build_pyramid(desc, 1).levels[0]
    centers = rng.uniform(8, 30, (12, 2))
    template = solver_mod._sample_level(level, centers + 0.4, 7)
    full = solver_mod._normal_equations(level, centers, template, 7)
    below = np.where(np.arange(12) % 2 == 0, full[:, 0] + 1.0, full[:, 0] - 1e-9)  # even rows "accepted"
    part = solver_mod._normal_equations(level, centers, template, 7, below=below)
    np.testing.assert_array_equal(part[:, 0], full[:, 0])
    even, odd = np.arange(0, 12, 2), np.arange(1, 12, 2)
    np.testing.assert_allclose(part[even, 1:], full[even, 1:], rtol=1e-12)
    assert not part[odd, 1:].any()


def test_many_points_in_one_call():
    # 3000 windows of side 13 need more map columns than one cv2.remap call accepts (32767)
    img = texture("astronaut", (160, 120))
    a, b = warp_pair(img, translation(0.6, -0.4))
    yy, xx = np.mgrid[20:100:1.6, 20:140:2.0]
    pts = np.stack([xx.ravel(), yy.ravel()], axis=1)[:3000]
    assert len(pts) == 3000
    res = track(ENC(a), ENC(b), pts, config=LMConfig(levels=1, min_eigen=0))
    ok = res.status
    assert ok.mean() > 0.9
    assert np.median(np.hypot(*(res.flow[ok] - [0.6, -0.4]).T)) < 0.1


def test_window_at_gives_the_coarse_window_above_level_0():
    assert [LMConfig(window=11).window_at(lev) for lev in range(3)] == [11, 11, 11]
    assert [LMConfig(window=11, coarse_window=21).window_at(lev) for lev in range(3)] == [11, 21, 21]
    cfg = LMConfig(window=11, coarse_window=21, coarse_from=2)
    assert [cfg.window_at(lev) for lev in range(4)] == [11, 11, 21, 21]
    assert cfg.at_level(1) == LMConfig(window=11) and cfg.at_level(3) == LMConfig(window=21)


def test_coarse_window_changes_only_the_coarse_levels(textures):
    gray = textures["astronaut"]
    a, b = warp_pair(gray, translation(0.6, -0.4))
    pts = detect_corners(a, 80, min_distance=10)
    one = [track(ENC(a), ENC(b), pts, config=LMConfig(levels=1, coarse_window=w)) for w in (None, 21)]
    np.testing.assert_array_equal(one[0].flow, one[1].flow)  # a single level is level 0
    h = translation(9.5, -6.0)
    a, b = warp_pair(gray, h)
    cfgs = [LMConfig(levels=3, coarse_window=w) for w in (None, 21)]
    runs = [track(ENC(a), ENC(b), pts, config=c, record=True) for c in cfgs]
    coarse = [[r for r in run.history if r.level > 0] for run in runs]
    assert not np.array_equal(coarse[0][0].flow, coarse[1][0].flow)
    for run in runs:
        err = np.linalg.norm(pts + run.flow - apply_h(h, pts), axis=1)
        assert run.status.mean() > 0.9 and np.median(err[run.status]) < 0.05


def _normal_sums(f, jx, jy):
    """Columns [S, h11, h12, h22, g1, g2] of (N, window, window, C) residuals and derivatives."""
    axes = (1, 2, 3)
    terms = [0.5 * f * f, jx * jx, jx * jy, jy * jy, jx * f, jy * f]
    return np.stack([t.sum(axes) for t in terms], axis=1)


def test_esm_template_is_the_inner_window_of_its_patch():
    rng = np.random.default_rng(3)
    desc = cv2.GaussianBlur(rng.random((40, 50, 6), dtype=np.float32), (0, 0), 1.5)
    level = build_pyramid(desc, 1).levels[0]
    centers = rng.uniform(8, 30, (6, 2))
    plain, none = solver_mod._templates(level, centers, 7, Jacobian.FORWARD)
    esm, patches = solver_mod._templates(level, centers, 7, Jacobian.ESM)
    assert none is None and [p.shape for p in patches] == [(9, 6, 9, 4), (9, 6, 9, 2)]
    for a, b in zip(plain, esm, strict=True):
        np.testing.assert_array_equal(a, b)


def test_esm_normal_equations_use_the_mean_jacobian():
    rng = np.random.default_rng(4)
    desc = cv2.GaussianBlur(rng.random((40, 50, 2), dtype=np.float32), (0, 0), 1.5)
    level = build_pyramid(desc, 1).levels[0]
    centers = rng.uniform(8, 30, (5, 2))
    shifted = centers + np.array([0.7, -0.3])
    template, tpatch = solver_mod._templates(level, centers, 7, Jacobian.ESM)
    got = solver_mod._normal_equations(level, shifted, template, 7, template_patch=tpatch)
    below = np.where(np.arange(5) % 2 == 0, got[:, 0] + 1.0, got[:, 0] - 1e-9)  # even rows "accepted"
    part = solver_mod._normal_equations(level, shifted, template, 7, below, tpatch)
    np.testing.assert_allclose(part[::2], got[::2], rtol=1e-12)
    d2 = sample_windows(desc, shifted, 7).astype(np.float64)
    f = d2 - sample_windows(desc, centers, 7)
    border = cv2.BORDER_REPLICATE
    dmaps = [cv2.Scharr(desc, cv2.CV_32F, *o, scale=1 / 32, borderType=border) for o in ((1, 0), (0, 1))]
    jx2, jy2 = (sample_windows(m, shifted, 7) for m in dmaps)
    jx1, jy1 = (sample_windows(m, centers, 7) for m in dmaps)
    jx, jy = 0.5 * (jx1 + jx2), 0.5 * (jy1 + jy2)
    np.testing.assert_allclose(got, _normal_sums(f, jx, jy), rtol=1e-4, atol=1e-6)


@pytest.mark.parametrize("jacobian", list(Jacobian))
def test_zero_mean_normal_equations_centre_every_factor(jacobian):
    rng = np.random.default_rng(5)
    desc = cv2.GaussianBlur(rng.random((40, 50, 5), dtype=np.float32), (0, 0), 1.5)  # chunks of 4 and 1
    level = build_pyramid(desc, 1).levels[0]
    centers = rng.uniform(8, 30, (6, 2))
    shifted = centers + np.array([0.6, -0.4])
    template, tpatch = solver_mod._templates(level, centers, 7, jacobian)
    tsums = solver_mod._template_sums(template, tpatch)
    got = solver_mod._normal_equations(level, shifted, template, 7, None, tpatch, tsums)
    below = np.where(np.arange(6) % 2 == 0, got[:, 0] + 1.0, got[:, 0] - 1e-9)
    part = solver_mod._normal_equations(level, shifted, template, 7, below, tpatch, tsums)
    np.testing.assert_allclose(part[::2], got[::2], rtol=1e-12)
    assert not part[1::2, 1:].any()
    border = cv2.BORDER_REPLICATE
    dmaps = [cv2.Scharr(desc, cv2.CV_32F, *o, scale=1 / 32, borderType=border) for o in ((1, 0), (0, 1))]
    jx, jy = (sample_windows(m, shifted, 7).astype(np.float64) for m in dmaps)
    if jacobian is Jacobian.ESM:
        jx, jy = (0.5 * (j + sample_windows(m, centers, 7)) for j, m in zip((jx, jy), dmaps, strict=True))
    f = sample_windows(desc, shifted, 7).astype(np.float64) - sample_windows(desc, centers, 7)

    def centred(a):
        return a - a.mean(axis=(1, 2), keepdims=True)

    f, jx, jy = centred(f), centred(jx), centred(jy)
    np.testing.assert_allclose(got, _normal_sums(f, jx, jy), rtol=1e-4, atol=1e-6)


@pytest.mark.parametrize("window", [3, 7, 11])
def test_patch_sums_telescope_to_the_window_sums(window):
    rng = np.random.default_rng(window)
    patches = rng.random((window + 2, 9, window + 2, 4), dtype=np.float32)
    jx, jy = solver_mod._scharr_xy(patches)
    want = np.stack([solver_mod._window_sums(a) for a in (patches[1:-1, :, 1:-1], jx, jy)])
    got = solver_mod._patch_sums(patches)
    assert got.shape == (3, 9, 4)
    np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-4)
    # a point's sums do not depend on its batch (bit for bit), one-point batches included
    for part in (slice(0, 1), slice(3, 4), slice(2, 7)):
        assert np.array_equal(solver_mod._patch_sums(np.ascontiguousarray(patches[:, part])), got[:, part])


def test_zero_mean_ignores_a_constant_offset_between_the_frames(textures):
    h = translation(1.3, -0.7)
    for gray in textures.values():
        a, b = warp_pair(gray, h)
        pts = detect_corners(a, 100, min_distance=10)
        d1, d2 = IntensityEncoder()(a), IntensityEncoder()(b)
        cfg = LMConfig(zero_mean=True, jacobian=Jacobian.ESM)
        same = track(d1, d2, pts, config=cfg)
        brighter = track(d1, d2 + 0.2, pts, config=cfg)
        plain = track(d1, d2 + 0.2, pts, config=LMConfig(jacobian=Jacobian.ESM))
        truth = apply_h(h, pts) - pts
        err = [np.linalg.norm(r.flow - truth, axis=1) for r in (same, brighter, plain)]
        assert np.mean(err[0] < 0.5) > 0.9 and np.mean(err[1] < 0.5) > 0.9
        assert np.median(np.abs(same.flow - brighter.flow)) < 1e-3
        assert np.mean(err[2] < 0.5) < np.mean(err[1] < 0.5)  # the plain SSD is thrown by the offset
    with pytest.raises(CoreError, match="zero_mean must be a bool"):
        LMConfig(zero_mean=1)


@pytest.mark.parametrize("shift", [(0.37, -0.21), (2.3, -1.7)])
def test_esm_is_as_accurate_as_the_forward_jacobian(textures, shift):
    h = translation(*shift)
    for gray in textures.values():
        a, b = warp_pair(gray, h)
        _, fwd, err_f = _run(a, b, h)
        _, esm, err_e = _run(a, b, h, LMConfig(jacobian=Jacobian.ESM))
        assert esm.status.mean() > 0.9
        assert np.median(err_e[esm.status]) < max(0.05, 1.2 * np.median(err_f[fwd.status]))


def test_esm_captures_more_from_far_starts(textures):
    # One level from starts 4-6 px off: the template's derivative keeps the step pointing home.
    rng = np.random.default_rng(0)
    shares = {jac: [] for jac in Jacobian}
    for gray in textures.values():
        a, b = warp_pair(gray, translation(0.4, -0.2))
        pts = detect_corners(a, 150, min_distance=10)
        ang = rng.uniform(0, 2 * np.pi, len(pts))
        offset = rng.uniform(4, 6, len(pts))[:, None] * np.stack([np.cos(ang), np.sin(ang)], 1)
        start = np.array([0.4, -0.2]) + offset
        for jac in Jacobian:
            res = track(ENC(a), ENC(b), pts, start, LMConfig(levels=1, max_iterations=30, jacobian=jac))
            shares[jac].append(np.mean(res.status & (np.hypot(*(res.flow - [0.4, -0.2]).T) < 0.5)))
    # Measured: 0.53-0.87 forward, 0.57-0.93 ESM per texture (+5 to +7 points on each).
    forward, esm = np.array(shares[Jacobian.FORWARD]), np.array(shares[Jacobian.ESM])
    assert (esm > forward).all() and esm.mean() > forward.mean() + 0.03, (forward, esm)


def test_as_dict_is_plain_values():
    d = LMConfig(jacobian=Jacobian.ESM, coarse_window=15).as_dict()
    assert d["jacobian"] == "esm" and d["coarse_window"] == 15 and d["window"] == 11
    assert set(d) == {f.name for f in dataclasses.fields(LMConfig)}
    assert "lambda_init" not in d and "nu" not in d  # Algorithm 1's constants, not settings


def test_gain_ignores_a_gain_and_an_offset_between_the_frames(textures):
    h = translation(1.3, -0.7)
    for gray in textures.values():
        a, b = warp_pair(gray, h)
        pts = detect_corners(a, 100, min_distance=10)
        d1, d2 = IntensityEncoder()(a), IntensityEncoder()(b)
        gain = LMConfig(zero_mean=True, gain=True, jacobian=Jacobian.ESM)
        same = track(d1, d2, pts, config=gain)
        relit = track(d1, 1.8 * d2 + 0.1, pts, config=gain)
        offset_only = track(d1, 1.8 * d2 + 0.1, pts, config=LMConfig(zero_mean=True, jacobian=Jacobian.ESM))
        truth = apply_h(h, pts) - pts
        err = [np.linalg.norm(r.flow - truth, axis=1) for r in (same, relit, offset_only)]
        assert np.mean(err[0] < 0.5) > 0.9 and np.mean(err[1] < 0.5) > 0.9
        assert np.median(np.abs(same.flow - relit.flow)) < 1e-3
        # the cost stays in the template's units: a gain leaves it (and the residual test) unchanged
        np.testing.assert_allclose(np.median(relit.cost), np.median(same.cost), rtol=0.05)
        assert np.median(offset_only.cost) > 2 * np.median(relit.cost)
    with pytest.raises(CoreError, match="gain needs zero_mean"):
        LMConfig(gain=True)
    with pytest.raises(CoreError, match="gain_levels must be >= 1 or None"):
        LMConfig(zero_mean=True, gain=True, gain_levels=0)
    with pytest.raises(CoreError, match="gain must be a bool"):
        LMConfig(zero_mean=True, gain=1)


def test_gain_levels_limit_the_gain_to_the_finest_levels(textures, monkeypatch):
    cfg = LMConfig(zero_mean=True, gain=True, gain_levels=1, levels=3)
    assert [cfg.gain_at(lev) for lev in range(3)] == [True, False, False]
    assert [LMConfig(zero_mean=True, gain=True).gain_at(lev) for lev in range(3)] == [True] * 3
    assert not LMConfig(zero_mean=True, gain_levels=1).gain_at(0)  # no gain asked for
    # a level's settings on their own (training's per-level solves) carry the level's residual
    assert cfg.at_level(0).gain and not cfg.at_level(1).gain and cfg.at_level(0).gain_levels is None
    seen = []
    real = solver_mod._gain_equations

    def spy(level, *args):
        seen.append(level[0].shape)
        return real(level, *args)

    monkeypatch.setattr(solver_mod, "_gain_equations", spy)
    gray = next(iter(textures.values()))
    desc = IntensityEncoder()(gray)
    pyr = build_pyramid(desc, 3)
    track(pyr, pyr, detect_corners(gray, 20, min_distance=10), config=cfg)
    assert seen and set(seen) == {pyr.levels[0][0].shape}  # only level 0 used the gain's equations


@pytest.mark.parametrize("jacobian", list(Jacobian))
def test_gain_normal_equations(jacobian):
    rng = np.random.default_rng(6)
    desc = cv2.GaussianBlur(rng.random((40, 50, 5), dtype=np.float32), (0, 0), 1.5)  # chunks of 4 and 1
    level = build_pyramid(desc, 1).levels[0]
    centers = rng.uniform(8, 30, (6, 2))
    shifted = centers + np.array([0.6, -0.4])
    template, tpatch = solver_mod._templates(level, centers, 7, jacobian)
    gain_template = solver_mod._gain_templates(template, tpatch)
    got = solver_mod._gain_equations(level, shifted, gain_template, 7)
    below = np.where(np.arange(6) % 2 == 0, got[:, 0] + 1.0, got[:, 0] - 1e-9)
    part = solver_mod._gain_equations(level, shifted, gain_template, 7, below)
    np.testing.assert_allclose(part[::2], got[::2], rtol=1e-6)
    assert not part[1::2, 1:].any()

    def centred(a):
        return a - a.mean(axis=(1, 2), keepdims=True)

    border = cv2.BORDER_REPLICATE
    dmaps = [cv2.Scharr(desc, cv2.CV_32F, *o, scale=1 / 32, borderType=border) for o in ((1, 0), (0, 1))]
    w = centred(sample_windows(desc, shifted, 7).astype(np.float64))
    t = centred(sample_windows(desc, centers, 7).astype(np.float64))
    g = np.clip((w * t).sum(axis=(1, 2)) / (w * w).sum(axis=(1, 2)), 0.25, 4.0)[:, None, None, :]
    f = g * w - t
    jx, jy = (g * sample_windows(m, shifted, 7) for m in dmaps)
    if jacobian is Jacobian.ESM:
        jx, jy = (0.5 * (j + sample_windows(m, centers, 7)) for j, m in zip((jx, jy), dmaps, strict=True))
    jx, jy = centred(jx), centred(jy)
    want = _normal_sums(f, jx, jy)
    # Kaufman: the Gauss-Newton matrix is that of J projected off the centred window, per channel
    qx, qy = ((w * j).sum(axis=(1, 2)) for j in (jx, jy))
    ww = (w * w).sum(axis=(1, 2))
    want[:, 1] -= (qx * qx / ww).sum(axis=1)
    want[:, 2] -= (qx * qy / ww).sum(axis=1)
    want[:, 3] -= (qy * qy / ww).sum(axis=1)
    np.testing.assert_allclose(got, want, rtol=1e-4, atol=1e-6)
