"""Tracking methods: the registry, each method's solve rules, and the solver paths they use."""

from __future__ import annotations

import ast
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import synthetic_sequences as syn
from onnx_models import conv_encoder

from nsflow_ros.core.encoder import IntensityEncoder, load_encoder, to_gray
from nsflow_ros.core.errors import CoreError
from nsflow_ros.core.methods import (
    CHECK_LEVELS,
    CLAHE,
    DEPLOYED_LM,
    METHODS,
    PAPER_LM,
    PREDICTED_LEVELS,
    DescriptorKLTMethod,
    EncoderSource,
    KLTConfig,
    KLTMethod,
    LMMethod,
    MethodSpec,
    SolveKind,
    SolvePolicy,
    declared_residual,
    klt_track,
    make_method,
    quantise_descriptors,
)
from nsflow_ros.core.pyramid import Smoothing, build_pyramid
from nsflow_ros.core.solver import Jacobian, LMConfig, track


@pytest.fixture(scope="module")
def pair():
    seq = syn.translating(2)  # 320x240, a known shift between the frames
    return seq, seq.frames[0], seq.frames[1]


def _corners(img, n=60):
    from nsflow_ros.core.detector import detect_corners

    return detect_corners(to_gray(img), n, min_distance=15)


def test_opencvs_lk_refuses_unbounded_descriptors_it_would_fold_into_uint8():
    folded = r"nsflow_lk quantises .*nsflow_encoder_fast\.onnx declares head 'none'"
    with pytest.raises(CoreError, match=folded):
        make_method("nsflow_lk", model_path="fast")
    assert isinstance(make_method("nsflow", model_path="fast"), LMMethod)  # the LM solver takes any range
    assert make_method("nsflow_lk").encoder.metadata["spec"]  # the default model declares its sigmoid head


def test_registry_builds_each_method_once_by_name(tmp_path):
    assert set(METHODS) == {"nsflow", "classical", "klt", "nsflow_lk"}
    assert isinstance(make_method("classical"), LMMethod)
    assert isinstance(make_method("klt"), KLTMethod) and make_method("klt").encoder is None
    enc = load_encoder(conv_encoder(tmp_path / "m.onnx", c_in=1, d=3))
    lk = make_method("nsflow_lk", encoder=enc)
    assert isinstance(lk, DescriptorKLTMethod) and lk.encoder is enc
    # the registry loads the shipped model smoothed for the LM method, unsmoothed for OpenCV's LK
    assert make_method("nsflow").encoder.smoothing.fine > 0
    assert make_method("nsflow_lk").encoder.smoothing == Smoothing()
    with pytest.raises(CoreError, match="nsflow_lk tracks unsmoothed descriptors"):
        make_method("nsflow_lk", encoder=load_encoder(enc.path, smoothing=Smoothing(1.0)))
    with pytest.raises(CoreError, match="method must be one of"):
        make_method("sift")
    with pytest.raises(CoreError, match="encoder cannot be given"):
        make_method("klt", encoder=IntensityEncoder())


def test_lm_methods_smooth_coarse_levels_as_the_encoder_declares(pair, tmp_path):
    _, img, _ = pair
    gray = to_gray(img)
    enc = load_encoder(conv_encoder(tmp_path / "m.onnx", c_in=1, d=3), smoothing=Smoothing(1.0, 0.5))
    nsflow = make_method("nsflow", encoder=enc)
    assert nsflow.pyramid_smoothing == Smoothing(coarse=0.5)  # the encoder applied the fine part
    got, want = nsflow.prepare(img, gray), build_pyramid(enc(img), nsflow.lm.levels, Smoothing(coarse=0.5))
    # 6 asked; a 1/32 level of this 320x240 image would be under 8 px
    assert got.num_levels == want.num_levels == 5
    for lev in range(got.num_levels):
        np.testing.assert_array_equal(got.level(lev), want.level(lev))
    plain = load_encoder(conv_encoder(tmp_path / "m.onnx", c_in=1, d=3))
    assert make_method("nsflow", encoder=plain).pyramid_smoothing is None
    classical = make_method("classical")
    assert classical.pyramid_smoothing is None
    np.testing.assert_allclose(classical.prepare(img, gray).level(0)[..., 0], gray / 255.0, atol=1e-6)


def test_solve_policy_and_specs_reject_bad_values():
    with pytest.raises(CoreError, match="prior_levels"):
        SolvePolicy(prior_levels=-1)
    with pytest.raises(CoreError, match="fill_levels"):
        SolvePolicy(fill_levels=-1)
    with pytest.raises(CoreError, match="fill_neighbours must be >= 0, got -1"):
        SolvePolicy(fill_neighbours=-1)
    with pytest.raises(CoreError, match="stereo_levels"):
        SolvePolicy(stereo_levels=-1)
    with pytest.raises(CoreError, match="max_residual"):
        SolvePolicy(max_residual=0)
    with pytest.raises(CoreError, match="check_jacobian must be a Jacobian"):
        SolvePolicy(check_jacobian="forward")
    with pytest.raises(CoreError, match="check_eps must be > 0"):
        SolvePolicy(check_eps=0.0)
    with pytest.raises(CoreError, match=r"KLTConfig\.window"):
        KLTConfig(window=20)
    with pytest.raises(CoreError, match="not both"):
        MethodSpec("x", "X", "x", EncoderSource.INTENSITY, lm=DEPLOYED_LM, policy=SolvePolicy(),
                   klt=KLTConfig())
    with pytest.raises(CoreError, match="not both"):
        MethodSpec("x", "X", "x", EncoderSource.INTENSITY, lm=DEPLOYED_LM)
    with pytest.raises(CoreError, match="solver must be one of"):
        make_method("classical", solver="fast")


def test_make_method_is_the_registry_entry_it_names():
    for name, spec in METHODS.items():
        method = make_method(name)
        assert method.spec == spec and method.name == name
        if spec.is_lm:
            # the model's declaration (the default model: a gain on the finest level) is bound once here
            gain = replace(DEPLOYED_LM, gain=True, gain_levels=1) if spec.learned else DEPLOYED_LM
            assert method.lm == gain and spec.lm == DEPLOYED_LM
            assert method.policy == spec.policy == SolvePolicy()
        else:
            assert method.window == (spec.klt.window,) * 2 and method.criteria == spec.klt.criteria
        assert spec.clahe == CLAHE
    # a changed entry is used as given
    one = make_method(METHODS["classical"].with_levels(1))
    assert one.lm == replace(DEPLOYED_LM, levels=1)


def test_the_declared_gain_applies_to_the_zero_mean_residual_only():
    enc = load_encoder(threads=1)
    assert enc.gain_levels == 1
    assert declared_residual(DEPLOYED_LM, enc) == replace(DEPLOYED_LM, gain=True, gain_levels=1)
    assert declared_residual(PAPER_LM, enc) == PAPER_LM  # the paper's SSD has no offset to add a gain to
    assert declared_residual(DEPLOYED_LM, load_encoder("d4", threads=1)) == DEPLOYED_LM
    assert make_method("nsflow", solver="paper").lm == PAPER_LM
    # nsflow_lk takes the four-channel model by default: OpenCV's LK needs descriptors in [0, 1]
    assert METHODS["nsflow_lk"].default_model == "d4" and METHODS["nsflow"].default_model == "default"
    assert make_method("nsflow_lk").encoder.channels == 4


def test_paper_preset_differs_from_the_deployed_one_in_the_documented_fields():
    documented = {"levels", "margin", "tail_share", "tail_passes", "jacobian", "zero_mean", "eps",
                  "coarse_window", "coarse_from"}
    differ = {k for k, v in DEPLOYED_LM.as_dict().items() if PAPER_LM.as_dict()[k] != v}
    assert differ == documented
    from nsflow_ros.core import methods

    for name in documented:  # each difference is named in the deployed settings' documentation
        assert f"``{name}``" in methods.__doc__ + _attr_doc(methods, "DEPLOYED_LM"), name
    paper = make_method("classical", solver="paper")
    assert paper.lm == PAPER_LM == LMConfig()
    policy = SolvePolicy.paper()
    assert paper.policy == policy and policy.prior_levels == 0 and policy.max_residual == float("inf")
    changed = {f for f in ("prior_levels", "fill_levels", "max_residual", "check_jacobian", "check_eps")
               if getattr(policy, f) != getattr(SolvePolicy(), f)}
    assert changed == {"prior_levels", "fill_levels", "max_residual"}
    assert make_method("klt", solver="paper").spec == METHODS["klt"]  # no LM settings to change


def _attr_doc(module, name: str) -> str:
    """The docstring written under a module-level constant (read from the source)."""
    import inspect

    src = inspect.getsource(module)
    start = src.index(f"\n{name} = ")
    doc = src.index('"""', start)
    return src[doc:src.index('"""', doc + 3)]


def test_first_level_solves_points_from_their_own_level(pair):
    seq, a, b = pair
    enc = IntensityEncoder()
    pa, pb = build_pyramid(enc(a), 4), build_pyramid(enc(b), 4)
    pts = _corners(a)
    truth = seq.truth(0, 1, pts)
    cfg = LMConfig(levels=4)
    full = track(pa, pb, pts, None, cfg)
    # a good start on one level gives the same answer as the full pyramid from zero
    first = np.zeros(len(pts), np.int64)
    near = track(pa, pb, pts, truth - pts + 0.7, cfg, first_level=first)
    both = full.status & near.status
    assert both.mean() > 0.8
    for res in (full, near):
        assert np.median(np.hypot(*(pts + res.flow - truth)[both].T)) < 0.1
    # ... at a fraction of the iterations, and a mixed call equals the two calls it replaces
    assert near.iterations.sum() < 0.5 * full.iterations.sum()
    mixed_first = np.where(np.arange(len(pts)) % 2 == 0, 0, 3)
    flow0 = np.where(mixed_first[:, None] == 0, truth - pts + 0.7, 0.0)
    mixed = track(pa, pb, pts, flow0, cfg, first_level=mixed_first)
    even, odd = mixed_first == 0, mixed_first == 3
    np.testing.assert_allclose(mixed.flow[even], near.flow[even], atol=1e-9)
    np.testing.assert_allclose(mixed.flow[odd], full.flow[odd], atol=1e-9)
    with pytest.raises(CoreError, match="first_level"):
        track(pa, pb, pts, None, cfg, first_level=np.zeros(3, np.int64))


def test_margin_keeps_points_whose_window_reaches_past_the_edge(pair):
    seq, a, b = pair
    enc = IntensityEncoder()
    pa, pb = build_pyramid(enc(a), 3), build_pyramid(enc(b), 3)
    # a column of points 4 px from the right edge (the frames move left, so they stay in the image)
    pts = np.stack([np.full(21, 315.0), np.linspace(20, 220, 21)], axis=1)
    truth = seq.truth(0, 1, pts)
    # from a start near the answer, as the tracker's priors give (from zero flow, the coarse levels
    # see mostly replicated border there, and the tracker's checks must catch what goes astray)
    start = truth - pts + 0.5
    inside = track(pa, pb, pts, start, LMConfig(levels=2))
    assert not inside.status.any()  # their windows reach past the edge
    edge = track(pa, pb, pts, start, LMConfig(levels=2, margin=1))
    np.testing.assert_allclose(edge.flow, inside.flow)  # same solve, only the status rule differs
    assert edge.status.sum() >= 5  # the textured ones (flat windows fail the eigenvalue test)
    # Where the template itself holds replicated border pixels the solve is biased (several px here):
    # the tracker's flow-back and residual tests are what drop those (test_tracker's occlusion and
    # sequence tests, and the benchmark's error figures, hold with margin 1).
    near = np.hypot(*(pts + edge.flow - truth).T) < 0.5
    assert (edge.status & near).sum() >= 4  # 5 (3 before the coarse windows were moved inside)
    with pytest.raises(CoreError, match="margin"):
        LMConfig(margin=-1)


def test_residual_test_drops_a_point_tracked_onto_something_else(pair):
    seq, a, b = pair
    method = make_method("classical")
    fa = method.prepare(a, to_gray(a))
    fb = method.prepare(b, to_gray(b))
    pts = _corners(a, 40)
    truth = seq.truth(0, 1, pts)
    # The true match leaves only noise; an unrelated window keeps a residual of its own contrast.
    good = method.track_pair_result(fa, fb, pts, truth - pts, LMConfig(levels=1, max_iterations=1))
    ratio_good = method.residual_ratio(good)
    other = np.roll(truth, 7, axis=0)
    bad = method.track_pair_result(fa, fb, pts, other - pts, LMConfig(levels=1, max_iterations=1))
    ratio_bad = method.residual_ratio(bad)
    assert np.median(ratio_good) < 0.1 and np.median(ratio_bad) > 0.5
    # started next to other corners on the finest levels, most points stay there and must be dropped
    new, ok = method.solve(SolveKind.FORWARD, fa, fb, pts, prior=other)
    wrong = np.hypot(*(new - truth).T) > 1
    spec = method.spec
    untested = make_method(replace(spec, policy=replace(spec.policy, max_residual=float("inf"))))
    _, ok_untested = untested.solve(SolveKind.FORWARD, fa, fb, pts, prior=other)
    assert (ok_untested & wrong).sum() > 5 * max(1, (ok & wrong).sum())


def test_fill_prior_takes_the_nearest_known_flows():
    from nsflow_ros.core.methods import _fill_prior

    # the left half of the image moves 10 px right, the right half 4 px down (a depth step, a turn)
    rng = np.random.default_rng(3)
    pts = rng.uniform([0, 0], [640, 480], size=(60, 2))
    left = pts[:, 0] < 320
    flow = np.where(left[:, None], [10.0, 0.0], [0.0, 4.0])
    prior = pts + flow
    known = np.ones(60, bool)
    known[::6] = False  # new points: no prior of their own
    prior[~known] = np.nan
    near = _fill_prior(pts, prior, known, neighbours=5)
    np.testing.assert_allclose(near[known], flow[known])  # a prior stays as it is
    far = ~known & (np.abs(pts[:, 0] - 320) > 80)  # new points well inside their half
    np.testing.assert_allclose(near[far], flow[far])
    # 0 neighbours: every new point takes the median of all, whichever half it is in
    every = _fill_prior(pts, prior, known, neighbours=0)
    np.testing.assert_array_equal(every[~known], np.broadcast_to(np.median(flow[known], axis=0), (10, 2)))
    assert (np.hypot(*(every[far] - flow[far]).T) > 4).any()
    # fewer known points than neighbours: the median of all of them
    few = np.zeros(60, bool)
    few[1:4] = True
    np.testing.assert_array_equal(_fill_prior(pts, prior, few, neighbours=5)[~few],
                                  np.broadcast_to(np.median(flow[1:4], axis=0), (57, 2)))


def test_forward_prior_and_checks_use_fewer_levels_than_a_blind_solve(pair, monkeypatch):
    seq, a, b = pair
    method = make_method("classical")
    fa, fb = method.prepare(a, to_gray(a)), method.prepare(b, to_gray(b))
    pts = _corners(a)
    truth = seq.truth(0, 1, pts)
    calls = []
    real = LMMethod.track_pair_result

    def spy(self, *args, **kw):
        calls.append((kw.get("first_level"), args[4].levels if len(args) > 4 else None))
        return real(self, *args, **kw)

    monkeypatch.setattr(LMMethod, "track_pair_result", spy)
    prior = truth.copy()
    prior[::3] = np.nan  # ids new to the previous frame have no prior
    new, ok = method.solve(SolveKind.FORWARD, fa, fb, pts, prior=prior)
    first, _ = calls[-1]
    # 2 levels with a prior, 3 from the median of the others' flows without one
    assert (first[1::3] == 1).all() and (first[::3] == 2).all()
    assert ok.mean() > 0.8 and np.median(np.hypot(*(new - truth).T)[ok]) < 0.1
    # with no prior at all, the whole pyramid from zero flow; fill_levels 0 = the whole pyramid too
    method.solve(SolveKind.FORWARD, fa, fb, pts, prior=np.full_like(prior, np.nan))
    assert calls[-1] == (None, method.lm.levels)
    # a stereo solve without any prior (a first frame's matches) on the policy's fewer levels
    method.solve(SolveKind.STEREO, fa, fb, pts)
    assert calls[-1] == (None, method.policy.stereo_levels) and method.policy.stereo_levels < method.lm.levels
    spec = method.spec
    make_method(replace(spec, policy=replace(spec.policy, fill_levels=0))).solve(
        SolveKind.FORWARD, fa, fb, pts, prior=prior
    )
    assert (calls[-1][0][::3] == method.lm.levels - 1).all() and (calls[-1][0][1::3] == 1).all()
    back, back_ok = method.solve(SolveKind.FLOW_BACK, fb, fa, new[ok], pts[ok])
    assert calls[-1][1] == 2  # the check starts at its answer on two levels
    assert np.hypot(*(back - pts[ok]).T)[back_ok].max() < 0.5


def _record_configs(monkeypatch, attr: str) -> list:
    """Record ``attr`` of the solver config of every ``LMMethod.track_pair_result`` call from now on."""
    used = []
    real = LMMethod.track_pair_result

    def spy(self, *args, **kw):
        used.append(getattr(args[4], attr))
        return real(self, *args, **kw)

    monkeypatch.setattr(LMMethod, "track_pair_result", spy)
    return used


def test_only_solves_from_zero_flow_use_the_coarse_window(pair, monkeypatch):
    _, a, b = pair
    method = make_method("classical")  # deployed: 21 px from level 2
    fa, fb = method.prepare(a, to_gray(a)), method.prepare(b, to_gray(b))
    pts = _corners(a, 20)
    used = _record_configs(monkeypatch, "coarse_window")
    prior = pts + 1.0
    prior[::2] = np.nan
    method.solve(SolveKind.FORWARD, fa, fb, pts, prior=prior)  # every point near its start
    method.solve(SolveKind.FORWARD, fa, fb, pts, prior=np.full_like(pts, np.nan))  # none
    method.solve(SolveKind.STEREO, fa, fb, pts)
    assert used == [None, 21, 21]


def test_checks_use_the_forward_jacobian_whatever_the_solves_use(pair, monkeypatch):
    _, a, b = pair
    method = make_method("classical")  # deployed: ESM solves
    assert method.lm.jacobian is Jacobian.ESM and method.policy.check_jacobian is Jacobian.FORWARD
    fa, fb = method.prepare(a, to_gray(a)), method.prepare(b, to_gray(b))
    pts = _corners(a)
    used = _record_configs(monkeypatch, "jacobian")
    new, ok = method.solve(SolveKind.STEREO, fa, fb, pts)
    back, back_ok = method.solve(SolveKind.STEREO_BACK, fb, fa, new[ok], pts[ok])
    assert used == [Jacobian.ESM, Jacobian.FORWARD]
    assert back_ok.mean() > 0.9 and np.median(np.hypot(*(back - pts[ok]).T)[back_ok]) < 0.1


def test_checks_keep_their_own_stop_tolerance(pair, monkeypatch):
    _, a, b = pair
    spec = METHODS["classical"]
    method = make_method(replace(spec, lm=replace(spec.lm, eps=0.03)))
    assert method.policy.check_eps == 0.01
    fa, fb = method.prepare(a, to_gray(a)), method.prepare(b, to_gray(b))
    pts = _corners(a)
    used = _record_configs(monkeypatch, "eps")
    new, ok = method.solve(SolveKind.FORWARD, fa, fb, pts)
    method.solve(SolveKind.FLOW_BACK, fb, fa, new[ok], pts[ok])
    assert used == [0.03, 0.01]


def test_klt_method_makes_vins_calls(pair):
    seq, a, b = pair
    method = KLTMethod()
    ga, gb = to_gray(a), to_gray(b)
    pts = _corners(a)
    truth = seq.truth(0, 1, pts)
    new, ok = method.solve(SolveKind.FORWARD, ga, gb, pts)
    ref, _ = klt_track(ga, gb, pts)  # VINS: maxLevel 3 from the point itself
    np.testing.assert_array_equal(new, ref)
    assert ok.mean() > 0.9 and np.median(np.hypot(*(new - truth).T)[ok]) < 0.1
    # a prior is not a VINS input: ignored
    np.testing.assert_array_equal(method.solve(SolveKind.FORWARD, ga, gb, pts, prior=truth + 3)[0], ref)


def test_nsflow_lk_tracks_quantised_descriptors(pair, tmp_path):
    seq, a, b = pair
    enc = load_encoder(conv_encoder(tmp_path / "m.onnx", c_in=1, d=4))
    method = make_method("nsflow_lk", encoder=enc)
    fa, fb = method.prepare(a, to_gray(a)), method.prepare(b, to_gray(b))
    assert fa.dtype == np.uint8 and fa.shape == (240, 320, 4)
    pts = _corners(a)
    truth = seq.truth(0, 1, pts)
    new, ok = method.solve(SolveKind.FORWARD, fa, fb, pts)
    assert ok.mean() > 0.8 and np.median(np.hypot(*(new - truth).T)[ok]) < 0.2
    q = quantise_descriptors(np.array([[[0.0, 0.5, 1.0, 2.0]]], np.float32))
    np.testing.assert_array_equal(q, [[[0, 128, 255, 255]]])
    with pytest.raises(CoreError, match="1-4 descriptor channels"):
        quantise_descriptors(np.zeros((4, 4, 5), np.float32))


PACKAGE = Path(__file__).resolve().parents[2] / "nsflow_ros"
ENCODER_TYPES = {"IntensityEncoder", "OnnxEncoder"}


def _names_a_method(source: str, filename: str = "<snippet>") -> list[str]:
    """Where ``source`` branches on a method's name (a comparison with a registry key as a string
    literal, ``x == "klt"``, ``x in ("klt", ...)``) or on an encoder's type (``isinstance(e,
    IntensityEncoder)``): the choices only the registry may make."""
    found = []
    for node in ast.walk(ast.parse(source, filename)):
        if isinstance(node, ast.Compare):
            for operand in (node.left, *node.comparators):
                items = operand.elts if isinstance(operand, (ast.Tuple, ast.List, ast.Set)) else [operand]
                if any(isinstance(i, ast.Constant) and i.value in METHODS for i in items):
                    found.append(f"{filename}:{node.lineno} compares with a method name")
        if isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id == "isinstance":
            kinds = node.args[1].elts if isinstance(node.args[1], ast.Tuple) else [node.args[1]]
            if any(isinstance(k, ast.Name) and k.id in ENCODER_TYPES for k in kinds):
                found.append(f"{filename}:{node.lineno} branches on an encoder's type")
    return found


def test_the_detector_catches_a_branch_on_a_method():
    assert len(_names_a_method('if settings.method == "klt":\n    pass\n')) == 1
    assert len(_names_a_method('ok = name in ("nsflow", "nsflow_lk")\n')) == 1
    assert len(_names_a_method('ok = isinstance(enc, (OnnxEncoder, str))\n')) == 1
    assert _names_a_method('spec = METHODS["klt"]\nok = spec.encoder is EncoderSource.NONE\n') == []


def test_no_module_but_the_registry_names_a_method():
    registry = PACKAGE / "core" / "methods.py"
    found = []
    for path in sorted(PACKAGE.rglob("*.py")):
        if path != registry:
            found += _names_a_method(path.read_text(), str(path.relative_to(PACKAGE)))
    assert found == []


def test_the_registry_deploys_what_the_tracker_deployed_before_the_registry_existed():
    """The settings the tracker ran before they moved into the registry, spelled out as they were then
    (``TrackerSettings.lm``'s default, ``LMMethod``'s keyword defaults, the tracker's VINS constants):
    the move kept the tracker's output bit for bit only if each of them is still what runs."""
    from nsflow_ros.core import tracker as tr

    spec = METHODS["nsflow"]
    assert spec.lm == LMConfig(
        levels=6, margin=1, tail_share=0.4, tail_passes=2, jacobian=Jacobian.ESM, eps=0.05, zero_mean=True,
        coarse_window=21, coarse_from=2,
    )
    assert METHODS["classical"].lm == spec.lm
    assert spec.policy == SolvePolicy(prior_levels=2, fill_levels=3, fill_neighbours=5, stereo_levels=4,
                                      max_residual=0.5, check_jacobian=Jacobian.FORWARD, check_eps=0.01)
    assert (CHECK_LEVELS, PREDICTED_LEVELS) == (2, 1)
    vins = (tr.GFTT_QUALITY, tr.FLOW_BACK_THRESHOLD_PX, tr.BORDER_PX, tr.PREDICTION_MIN_TRACKED)
    assert vins == (0.01, 0.5, 1, 10)
    assert (LMConfig().lambda_init, LMConfig().nu) == (1e-2, 10.0)
    klt = METHODS["klt"].klt
    assert (klt.window, klt.max_iterations, klt.eps) == (21, 30, 0.01)
    assert (CLAHE.clip, CLAHE.tiles) == (3.0, (8, 8))


def test_a_solve_from_zero_flow_captures_the_first_pair_of_a_flight_at_10_hz(tmp_path):
    # Scene 3 in flight from its first frame at 10 Hz: the first pair's corners move 30-50 px. The learned
    # map's coarse levels carry little; on 4 levels none of the kept tracks was right (0 of 57).
    from nsflow_ros.core.detector import detect_corners
    from nsflow_ros.data.sample import make_sample_sequence

    seq = make_sample_sequence(tmp_path / "s", seed=3, duration=0.2, rate_hz=10.0, stereo=False,
                               formats=("asl",), progress=False)  # fmt: skip
    a, b = seq.image(0, 0), seq.image(1, 0)
    pts = detect_corners(a, 150, quality=0.01, min_distance=30)
    flow, visible = seq.flow(0, 1, pts)
    assert np.median(np.hypot(*flow.T)) > 30

    def right_share(method):
        fa, fb = method.prepare(a, a), method.prepare(b, b)
        new, ok = method.solve(SolveKind.FORWARD, fa, fb, pts)
        right = np.hypot(*(new - pts - flow).T) < 1.0
        return np.mean(right[ok & visible]) if (ok & visible).any() else 0.0, np.mean(ok & visible & right)

    nsflow = make_method("nsflow")
    assert nsflow.lm.levels == 6
    kept_right, right = right_share(nsflow)
    assert kept_right > 0.95 and right > 0.8
    four, _ = right_share(make_method(METHODS["nsflow"].with_levels(4)))
    assert four < 0.2
