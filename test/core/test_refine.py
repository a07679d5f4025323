"""The intensity step: smoke, exception and numeric cases, and its place in the LM method."""

from __future__ import annotations

import itertools
from dataclasses import replace

import cv2
import numpy as np
import pytest

from nsflow_ros.core.errors import CoreError
from nsflow_ros.core.methods import DEPLOYED_LM, METHODS, LMMethod, SolveKind, klt_track, make_method
from nsflow_ros.core.refine import IntensityRefinement, blurred_level, gray_level, refine, step_template

SHIFT = np.array([2.37, -1.61])


def _texture(seed: int = 0, size: tuple[int, int] = (120, 160)) -> np.ndarray:
    """A smooth random texture (float, 0-255), rendered at 4x and area-downsampled."""
    rng = np.random.default_rng(seed)
    big = cv2.GaussianBlur(rng.uniform(0, 255, (size[0] * 4, size[1] * 4)).astype(np.float32), (0, 0), 6)
    big = cv2.normalize(big, None, 20, 235, cv2.NORM_MINMAX)
    return cv2.resize(big, (size[1], size[0]), interpolation=cv2.INTER_AREA)


def _shifted(img: np.ndarray, shift: np.ndarray) -> np.ndarray:
    m = np.float32([[1, 0, shift[0]], [0, 1, shift[1]]])
    return cv2.warpAffine(img, m, (img.shape[1], img.shape[0]), flags=cv2.INTER_CUBIC,
                          borderMode=cv2.BORDER_REFLECT)


def _u8(img: np.ndarray) -> np.ndarray:
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)


@pytest.fixture
def pair() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    tex = _texture()
    pts = np.array([[40.0, 40.0], [80.5, 60.25], [120.0, 80.0], [60.0, 90.0]])
    return _u8(tex), _u8(_shifted(tex, SHIFT)), pts


@pytest.mark.parametrize("affine", [False, True])
def test_refines_to_the_true_shift_about_as_precisely_as_opencv_lk(
    pair: tuple[np.ndarray, ...], affine: bool
) -> None:
    g1, g2, pts = pair
    start = pts + SHIFT + np.array([0.3, -0.2])  # where the descriptor pyramid's level 1 leaves a point
    out = refine(gray_level(g1), gray_level(g2), pts, start, np.ones(len(pts), bool),
                 IntensityRefinement(affine=affine))
    assert out.kept.all()
    err = np.abs(out.positions - pts - SHIFT).max()
    # Bilinear sampling of a uint8 image leaves a few hundredths of a pixel, to OpenCV's LK as well; the
    # affine warp's four more unknowns in a 15 px window against LK's 21 px one cost a little on a pure shift.
    new, ok = klt_track(g1, g2, pts)
    assert ok.all()
    assert err < 0.05
    assert err < (1.5 if affine else 1.3) * np.abs(new - pts - SHIFT).max()


def test_the_affine_warp_follows_a_turning_scaling_window_where_a_translation_drifts() -> None:
    # A window that turns by 2 degrees and grows by 3 %: a translation fitted to it is pulled toward where
    # its texture lies, by a few hundredths of a pixel per point per frame, the same way every frame.
    tex = _texture(5, (160, 200))
    pts = np.array([[x, y] for x in range(40, 170, 22) for y in range(40, 130, 22)], float)
    m = cv2.getRotationMatrix2D((100.0, 80.0), 2.0, 1.03)
    m[:, 2] += (1.7, -0.9)
    warped = cv2.warpAffine(tex, m, (200, 160), flags=cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT)
    true = pts @ m[:, :2].T + m[:, 2]
    g1, g2 = gray_level(_u8(tex)), gray_level(_u8(warped))
    start = true + np.random.default_rng(2).normal(0.0, 0.2, true.shape)
    errors = {}
    for affine in (False, True):
        out = refine(g1, g2, pts, start, np.ones(len(pts), bool), IntensityRefinement(affine=affine))
        assert out.kept.all()
        errors[affine] = np.median(np.hypot(*(out.positions - true).T))
    lk, ok = klt_track(_u8(tex), _u8(warped), pts, true)
    assert ok.all()
    assert errors[True] < 0.05
    assert errors[True] < 0.6 * errors[False]
    assert errors[True] < 0.6 * np.median(np.hypot(*(lk - true).T))


def test_a_still_camera_s_tracks_do_not_drift() -> None:
    # 40 frames of one still scene, each with its own sensor noise, each step started where the last ended:
    # a gain pulled by the noise moves a point the same way every frame, so its track drifts; without that
    # pull a frame's noise enters one step and leaves with the next, as in OpenCV's LK.
    tex = _texture(3)
    pts = np.array([[x, y] for x in range(25, 140, 18) for y in range(25, 100, 18)], float)
    rng = np.random.default_rng(1)
    frames = [_u8(tex + rng.normal(0.0, 1.0, tex.shape)) for _ in range(41)]
    levels = [gray_level(f) for f in frames]
    step, lk = pts.copy(), pts.copy()
    for a, b, la, lb in zip(frames, frames[1:], levels, levels[1:], strict=False):
        step = refine(la, lb, step, step.copy(), np.ones(len(pts), bool), IntensityRefinement()).positions
        lk, ok = klt_track(a, b, lk)
        assert ok.all()
    drift, lk_drift = (np.median(np.hypot(*(q - pts).T)) for q in (step, lk))
    # The step's window is 15 px to LK's 21: about 1.4x its noise per frame (a noise-pulled gain: 2.6x).
    assert drift < 1.7 * lk_drift


def test_gain_and_offset_cost_nothing(pair: tuple[np.ndarray, ...]) -> None:
    g1, _, pts = pair
    lit = _u8(0.7 * _shifted(_texture(), SHIFT) + 40.0)
    out = refine(gray_level(g1), gray_level(lit), pts, pts + SHIFT + 0.5, np.ones(len(pts), bool),
                 IntensityRefinement())
    assert out.kept.all()
    assert np.abs(out.positions - pts - SHIFT).max() < 0.05


def test_a_move_past_max_shift_is_not_kept(pair: tuple[np.ndarray, ...]) -> None:
    g1, g2, pts = pair
    start = pts + SHIFT + np.array([1.2, 0.0])
    out = refine(gray_level(g1), gray_level(g2), pts, start, np.ones(len(pts), bool),
                 IntensityRefinement(max_shift=0.5))
    assert not out.kept.any()
    np.testing.assert_array_equal(out.positions, start)


def test_other_content_is_not_kept(pair: tuple[np.ndarray, ...]) -> None:
    g1, _, pts = pair
    other = _u8(_texture(seed=7))  # the windows do not match at all: residual ratio about 1
    start = pts + SHIFT
    ones = np.ones(len(pts), bool)
    out = refine(gray_level(g1), gray_level(other), pts, start, ones, IntensityRefinement())
    assert not out.kept.any()
    np.testing.assert_array_equal(out.positions, start)


def test_a_noisy_frame_raises_the_residual_limit_to_its_ceiling() -> None:
    """Low contrast under sensor noise raises every window's residual ratio alike (here 0.24-0.35): the
    step is kept there, within its noise of the truth, and refused with the floor off; windows of other
    content (ratio about 1) stay refused whatever the floor."""
    tex = _texture()
    pts = np.array([[40.0, 40.0], [80.5, 60.25], [120.0, 80.0], [60.0, 90.0], [30.0, 70.0], [100.0, 30.0]])
    rng = np.random.default_rng(1)
    dim = [128 + 0.15 * (t - 128) for t in (tex, _shifted(tex, SHIFT))]
    g1, g2 = (gray_level(_u8(d + rng.normal(0, 2.0, d.shape))) for d in dim)
    start, ones = pts + SHIFT + 0.3, np.ones(len(pts), bool)
    out = refine(g1, g2, pts, start, ones, IntensityRefinement())
    ratio = 2 * out.cost / out.contrast
    assert (ratio > 0.2).all() and (ratio < 0.4).all()
    assert out.kept.all() and np.abs(out.positions - pts - SHIFT).max() < 0.25
    assert not refine(g1, g2, pts, start, ones, IntensityRefinement(residual_floor=0.0)).kept.any()
    other = gray_level(_u8(_texture(seed=7)))
    assert not refine(g1, other, pts, start, ones, IntensityRefinement(residual_floor=100.0)).kept.any()


def test_flat_window_and_lost_points_are_left_alone(pair: tuple[np.ndarray, ...]) -> None:
    g1, g2, pts = pair
    flat = np.full_like(g1, 128)
    start = pts + SHIFT + 0.3
    ones = np.ones(len(pts), bool)
    out = refine(gray_level(flat), gray_level(flat), pts, start, ones, IntensityRefinement())
    assert not out.kept.any()
    status = np.array([True, False, True, False])
    out = refine(gray_level(g1), gray_level(g2), pts, start, status, IntensityRefinement())
    np.testing.assert_array_equal(out.kept, status)
    np.testing.assert_array_equal(out.positions[~status], start[~status])


def test_window_moved_inside_near_the_border(pair: tuple[np.ndarray, ...]) -> None:
    g1, g2, _ = pair
    pts = np.array([[2.0, 60.0], [100.0, 3.0]])  # the 15 px window would reach 4-5 px past the edge
    out = refine(gray_level(g1), gray_level(g2), pts, pts + SHIFT + 0.4, np.ones(2, bool),
                 IntensityRefinement())
    assert out.kept.all()
    assert np.abs(out.positions - pts - SHIFT).max() < 0.05


def test_empty_input() -> None:
    img = gray_level(np.zeros((20, 20), np.uint8))
    out = refine(img, img, np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0, bool), IntensityRefinement())
    assert out.positions.shape == (0, 2) and out.kept.shape == (0,)


@pytest.mark.parametrize("kwargs", [{"window": 4}, {"window": 1}, {"iterations": 0}, {"max_shift": 0.0},
                                    {"temporal_max_shift": -1.0}, {"residual_floor": -1.0},
                                    {"residual_ceiling": 0.1},
                                    {"max_residual": -1.0}, {"min_eigen": -1.0}, {"coarse_eps": 0.0},
                                    {"noisy_window": 13}, {"noisy_window": 22}, {"noisy_ratio": 0.0},
                                    {"noisy_blur": -0.5}, {"noisy_blur_ratio": 0.0},
                                    {"noisy_blur_ratio": 1.5}])
def test_settings_out_of_range(kwargs: dict[str, float]) -> None:
    with pytest.raises(CoreError, match=next(iter(kwargs))):
        IntensityRefinement(**kwargs)


def test_blurred_level_is_a_gaussian_blur_of_the_gray_level() -> None:
    level = gray_level(_u8(_texture()))
    out = blurred_level(level, 0.7)
    assert out[0].shape == level[0].shape and out[0].dtype == np.float32
    np.testing.assert_array_equal(out[0][..., 0], cv2.GaussianBlur(level[0][..., 0], (0, 0), 0.7))
    assert 0 < np.abs(out[0] - level[0]).mean() < 0.01  # smooth texture: little changes


def test_gray_level_needs_uint8_gray() -> None:
    with pytest.raises(CoreError, match="uint8 gray"):
        gray_level(np.zeros((4, 4), np.float32))
    with pytest.raises(CoreError, match="uint8 gray"):
        gray_level(np.zeros((4, 4, 3), np.uint8))
    level = gray_level(np.full((4, 4), 255, np.uint8))
    assert level[0].shape == (4, 4, 1) and level[0].dtype == np.float32 and level[0].max() == 1.0


def test_method_refines_forward_and_stereo(pair: tuple[np.ndarray, ...]) -> None:
    g1, g2, pts = pair
    method = make_method("nsflow")
    assert method.refinement == IntensityRefinement()  # the default finishes on the image
    f1, f2 = method.prepare(g1, g1), method.prepare(g2, g2)
    for kind in (SolveKind.FORWARD, SolveKind.STEREO):
        new, status = method.solve(kind, f1, f2, pts)
        assert status.all()
        assert np.abs(new - pts - SHIFT).max() < 0.05


def test_checks_stay_on_the_descriptors_by_default(pair: tuple[np.ndarray, ...]) -> None:
    g1, g2, pts = pair
    method = make_method("nsflow")
    plain = make_method(replace(METHODS["nsflow"], refine=None))
    f1, f2 = method.prepare(g1, g1), method.prepare(g2, g2)
    back, ok = method.solve(SolveKind.FLOW_BACK, f2, f1, pts + SHIFT, pts)
    p1, p2 = plain.prepare(g1, g1), plain.prepare(g2, g2)
    back0, ok0 = plain.solve(SolveKind.FLOW_BACK, p2, p1, pts + SHIFT, pts)
    np.testing.assert_array_equal(back, back0)
    np.testing.assert_array_equal(ok, ok0)


def test_checks_can_end_on_the_image_too(pair: tuple[np.ndarray, ...]) -> None:
    g1, g2, pts = pair
    method = make_method(replace(METHODS["nsflow"], refine=IntensityRefinement(checks=True)))
    f1, f2 = method.prepare(g1, g1), method.prepare(g2, g2)
    back, ok = method.solve(SolveKind.FLOW_BACK, f2, f1, pts + SHIFT, pts)
    assert ok.all() and np.abs(back - pts).max() < 0.05
    # a planted wrong match (3 px off) does not come back to where it started: the tracker drops it
    back, ok = method.solve(SolveKind.FLOW_BACK, f2, f1, pts + SHIFT + np.array([3.0, 0.0]), pts)
    assert (~ok | (np.hypot(*(back - pts).T) > 0.5)).all()


@pytest.mark.parametrize(("kind", "retrack"), [(SolveKind.STEREO, False), (SolveKind.FORWARD, True)])
def test_points_the_step_rejects_get_the_descriptors_last_level(
    pair: tuple[np.ndarray, ...], kind: SolveKind, retrack: bool
) -> None:
    """No point kept: the coarse levels (at the plain solve's tolerance), then the last level on its own, are
    the plain method's solve (a stereo match always, a temporal point with ``retrack_refused``)."""
    g1, g2, pts = pair
    step = IntensityRefinement(max_residual=1e-30, residual_floor=0.0, coarse_eps=DEPLOYED_LM.eps,
                               retrack_refused=retrack)
    never = make_method(replace(METHODS["nsflow"], refine=step))
    plain = make_method(replace(METHODS["nsflow"], refine=None))
    a = never.solve_with_covariance(kind, never.prepare(g1, g1), never.prepare(g2, g2), pts)
    b = plain.solve_with_covariance(kind, plain.prepare(g1, g1), plain.prepare(g2, g2), pts)
    for x, y in zip(a, b, strict=True):
        np.testing.assert_allclose(x, y, rtol=1e-12, atol=1e-12)


def test_a_temporal_point_the_step_refuses_ends_its_track(pair: tuple[np.ndarray, ...]) -> None:
    """By default a temporal point the step refuses is lost (the detector replaces it), whatever the
    descriptors would say; the stereo solve of the same pair keeps every point."""
    g1, g2, pts = pair
    step = IntensityRefinement(max_residual=1e-30, residual_floor=0.0)
    never = make_method(replace(METHODS["nsflow"], refine=step))
    f1, f2 = never.prepare(g1, g1), never.prepare(g2, g2)
    _, status = never.solve(SolveKind.FORWARD, f1, f2, pts)
    assert not status.any()
    new, status = never.solve(SolveKind.STEREO, f1, f2, pts)
    assert status.all() and np.abs(new - pts - SHIFT).max() < 0.1


def test_a_temporal_solve_takes_its_own_shift_limit(pair: tuple[np.ndarray, ...]) -> None:
    """From a start 1.5 px off, a temporal step is kept under ``temporal_max_shift`` and refused over it;
    ``max_shift`` does not apply to it."""
    g1, g2, pts = pair
    im1, im2 = gray_level(g1), gray_level(g2)
    start = pts + SHIFT + np.array([1.5, 0.0])
    ones = np.ones(len(pts), bool)
    wide = IntensityRefinement(max_shift=1.0)
    assert refine(im1, im2, pts, start, ones, replace(wide, max_shift=wide.temporal_max_shift)).kept.all()
    assert not refine(im1, im2, pts, start, ones, wide).kept.any()
    method = make_method("nsflow")
    # the noise floor serves temporal solves only: a refused stereo match gets the descriptors' levels
    assert method._steps[True, False].residual_floor > 0 and method._steps[False, False].residual_floor == 0
    for limit, kept in ((4.0, True), (1.0, False)):
        method = make_method(replace(METHODS["nsflow"], refine=IntensityRefinement(temporal_max_shift=limit)))
        assert method._steps[True, False].max_shift == method._steps[True, True].max_shift == limit
        out = refine(im1, im2, pts, start, ones, method._steps[True, False])
        assert out.kept.all() if kept else not out.kept.any()


def _noisy(img: np.ndarray, sigma: float, seed: int) -> np.ndarray:
    return _u8(img + np.random.default_rng(seed).normal(0.0, sigma, img.shape))


def test_a_wider_window_is_more_precise_on_noisy_images() -> None:
    """Where sensor noise limits the step, the noisy window's more pixels average it: on a pure shift with
    8 gray levels of noise its median error is below the plain window's."""
    tex = _texture(3, (160, 200))
    pts = np.array([[x, y] for x in range(30, 175, 12) for y in range(30, 135, 12)], float)
    g1, g2 = gray_level(_noisy(tex, 8.0, 1)), gray_level(_noisy(_shifted(tex, SHIFT), 8.0, 2))
    start = pts + SHIFT + np.random.default_rng(4).normal(0.0, 0.3, pts.shape)
    err = {}
    for window in (15, 21):
        out = refine(g1, g2, pts, start, np.ones(len(pts), bool),
                     IntensityRefinement(window=window, noisy_window=window, max_residual=0.4))
        assert out.kept.mean() > 0.9
        err[window] = np.median(np.hypot(*(out.positions - pts - SHIFT)[out.kept].T))
    assert err[21] < 0.85 * err[15]


@pytest.mark.parametrize("noisy_temporal", [False, True])
@pytest.mark.parametrize(("sigma", "noisy"), [(0.0, False), (10.0, True)])
def test_the_images_noise_chooses_the_next_steps_images_and_window(
    pair: tuple[np.ndarray, ...], monkeypatch: pytest.MonkeyPatch, sigma: float, noisy: bool,
    noisy_temporal: bool,
) -> None:
    """A temporal step measures the images' noise (its median residual ratio); after one over
    ``noisy_ratio`` the stream's next steps compare blurred images, the stereo step in ``noisy_window``
    (the temporal step too with ``noisy_temporal``); after a clean one the plain images in ``window``; a
    solve from another frame the plain images in ``window`` whatever came before. A blurred step's noise
    reads in the plain images' units."""
    import nsflow_ros.core.methods as methods_mod

    g1, g2, pts = pair
    g1, g2 = (_noisy(g.astype(np.float64), sigma, k) if sigma else g for k, g in enumerate((g1, g2)))
    base = make_method("nsflow")
    assert base.spec.refine is not None and not base.spec.refine.noisy_temporal  # the default
    refine_cfg = replace(base.spec.refine, noisy_temporal=noisy_temporal, noisy_window=21)
    method = LMMethod(replace(base.spec, refine=refine_cfg), base.encoder)
    f1, f2, other = method.prepare(g1, g1), method.prepare(g2, g2), method.prepare(g1, g1)
    plain = [f.image[0] for f in (f1, f2, other) if f.image is not None]
    reads: list[tuple[int, bool]] = []

    def spy(image: tuple[np.ndarray, ...], *a: object) -> object:
        reads.append((int(a[1]), not any(image[0] is p for p in plain)))  # (window, blurred)
        return step_template(image, *a)  # type: ignore[arg-type]

    monkeypatch.setattr(methods_mod, "step_template", spy)
    assert method.noise == 0.0 and not method.noisy
    method.solve(SolveKind.FORWARD, f1, f2, pts)
    step = method.refinement
    first = method.noise
    assert step is not None and method.noisy == noisy == (first > step.noisy_ratio)
    method.solve(SolveKind.STEREO, f2, f1, pts + 1.0)  # the frame's stereo step
    method.solve(SolveKind.FORWARD, f2, f1, pts + 2.0)  # the stream's next temporal step
    method.solve(SolveKind.STEREO, other, f2, pts + 3.0)  # an unrelated pair
    wide = 21 if noisy else 15
    assert reads == [(15, False), (wide, noisy), (wide if noisy_temporal else 15, noisy), (15, False)]
    assert 0.5 < method.noise / first < 2.0  # blurred or not, the same units


def test_a_noisy_stream_stays_noisy_down_to_half_the_limit(
    pair: tuple[np.ndarray, ...], monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Once noisy a stream stays so while its noise is over half of ``noisy_ratio`` (a blurred step's
    ratio divided by ``noisy_blur_ratio``), so that a dark stream's frames near the limit do not switch
    the images back and forth; under half it is clean again, and a clean stream becomes noisy only over
    the limit."""
    import nsflow_ros.core.methods as methods_mod

    g1, g2, pts = pair
    method = make_method("nsflow")
    step = method.refinement
    assert step is not None
    limit, k = step.noisy_ratio, step.noisy_blur_ratio
    # the ratio each temporal step reports (in the units of the images it compared)
    reported = iter([1.2 * limit, 0.6 * limit * k, 0.4 * limit * k, 0.8 * limit, 1.2 * limit])
    real = methods_mod.refine
    monkeypatch.setattr(methods_mod, "refine",
                        lambda *a, **kw: replace(real(*a, **kw), median_ratio=next(reported)))
    frames = [method.prepare(g, g) for g in (g1, g2, g1, g2, g1, g2)]
    states = []
    for f_a, f_b in itertools.pairwise(frames):
        method.solve(SolveKind.FORWARD, f_a, f_b, pts)
        states.append(method.noisy)
    assert states == [True, True, False, False, True]
    assert method.noise == pytest.approx(1.2 * limit)


def test_the_light_perturbations_are_not_noise(pair: tuple[np.ndarray, ...]) -> None:
    """A gain and an offset between the frames (the illumination perturbations) leave the step's residual
    ratio far under ``noisy_ratio``: only sensor noise widens the stereo window."""
    g1, g2, pts = pair
    method = make_method("nsflow")
    lit = _u8(0.6 * g2.astype(np.float64) + 40.0)
    method.solve(SolveKind.FORWARD, method.prepare(g1, g1), method.prepare(lit, lit), pts)
    assert method.refinement is not None and 0 < method.noise < 0.5 * method.refinement.noisy_ratio


def test_kept_points_carry_the_steps_covariance(pair: tuple[np.ndarray, ...]) -> None:
    g1, g2, pts = pair
    method = make_method("nsflow")
    f1, f2 = method.prepare(g1, g1), method.prepare(g2, g2)
    new, status, cov = method.solve_with_covariance(SolveKind.FORWARD, f1, f2, pts)
    assert status.all() and np.isfinite(cov).all()
    step = refine(f1.image, f2.image, pts, new, status, method.refinement)
    # the covariance is the step's own: smaller along the better-textured axis, positive definite
    assert (cov[:, 0] > 0).all() and (cov[:, 0] * cov[:, 2] - cov[:, 1] ** 2 > 0).all()
    assert step.kept.all()


def test_a_template_read_once_serves_every_subset(pair: tuple[np.ndarray, ...]) -> None:
    """Each point's template rows depend on that point only: a subset of a template read at all points is
    the template of the subset, its rows bit for bit and its window sums to float32 rounding (a BLAS
    product rounds by how many rows it multiplies, differently per CPU), and refining with it is refining
    without it to that rounding."""
    g1, g2, pts = pair
    im1, im2 = gray_level(g1), gray_level(g2)
    pts = np.vstack([pts, [[2.0, 3.0]]])  # one near the corner: its window is moved inward
    whole = step_template(im1, pts, 15)
    sel = np.array([True, False, True, True, True])
    part = step_template(im1, pts[sel], 15)
    taken = whole[sel]
    for name in ("centres", "rows"):
        np.testing.assert_array_equal(getattr(taken, name), getattr(part, name))
    np.testing.assert_allclose(taken.gram, part.gram, rtol=1e-6, atol=1e-9)
    start = pts + SHIFT + 0.3
    given = refine(im1, im2, pts, start, sel, IntensityRefinement(), whole)
    read = refine(im1, im2, pts, start, sel, IntensityRefinement())
    np.testing.assert_array_equal(given.kept, read.kept)
    np.testing.assert_allclose(given.positions, read.positions, rtol=0, atol=1e-5)  # px
    for name in ("hessian", "cost", "contrast"):
        np.testing.assert_allclose(getattr(given, name), getattr(read, name), rtol=1e-5, atol=1e-9)


def test_the_method_reads_a_stereo_template_once_for_the_next_temporal_step(
    pair: tuple[np.ndarray, ...], monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A stereo solve's template (this frame's left image at its features) is the next frame's temporal
    one: the method reads it once, and solves as it would reading it each time."""
    import nsflow_ros.core.methods as methods_mod

    g1, g2, pts = pair
    reads = []
    monkeypatch.setattr(methods_mod, "step_template",
                        lambda *a: reads.append(len(a[1])) or step_template(*a))
    method = make_method("nsflow")
    left, right, nxt = (method.prepare(g, g) for g in (g1, _u8(_shifted(_texture(), -SHIFT)), g2))
    stereo = method.solve_with_covariance(SolveKind.STEREO, left, right, pts)
    temporal = method.solve_with_covariance(SolveKind.FORWARD, left, nxt, pts.copy())
    assert reads == [len(pts)]
    want_stereo = make_method("nsflow").solve_with_covariance(SolveKind.STEREO, left, right, pts)
    want_temporal = make_method("nsflow").solve_with_covariance(SolveKind.FORWARD, left, nxt, pts)
    for got, want in ((stereo, want_stereo), (temporal, want_temporal)):
        for a, b in zip(got, want, strict=True):
            np.testing.assert_array_equal(a, b)
    # another image at the same points is read anew
    method.solve_with_covariance(SolveKind.FORWARD, nxt, left, pts)
    assert reads == [len(pts), len(pts), len(pts), len(pts)]


def test_a_template_s_kept_affine_system_gives_the_answer_of_one_formed_in_the_call(
    pair: tuple[np.ndarray, ...],
) -> None:
    # The stereo solve's template is the next frame's temporal one: its normal equations are formed once.
    g1, g2, pts = pair
    l1, l2 = gray_level(g1), gray_level(g2)
    start, ok = pts + SHIFT + 0.3, np.ones(len(pts), bool)
    kept = step_template(l1, pts, 15)
    bare = step_template(l1, pts, 15, affine=False)
    assert kept.system is not None and bare.system is None
    assert kept[np.array([0, 2])].system[1].shape == (2, 6, 6)
    a = refine(l1, l2, pts, start, ok, IntensityRefinement(), kept)
    b = refine(l1, l2, pts, start, ok, IntensityRefinement(), bare)
    np.testing.assert_array_equal(a.positions, b.positions)
    np.testing.assert_array_equal(a.kept, b.kept)
