"""The evaluated methods are the tracker's own method objects: same solves, same representations."""

from __future__ import annotations

import ast
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest
from image_pairs import texture, warp_pair

from nsflow_ros.core import methods as core
from nsflow_ros.core.encoder import load_encoder
from nsflow_ros.evaluation import methods as ev
from nsflow_ros.evaluation import sequences
from nsflow_ros.evaluation.errors import EvaluationError, MethodLeftOutError
from nsflow_ros.evaluation.pairs import endpoint_errors, inside, keypoints, true_flow

SHIFT = np.array([[1.0, 0.0, 3.2], [0.0, 1.0, -2.1], [0.0, 0.0, 1.0]])
PACKAGE = Path(ev.__file__).parent


@pytest.fixture(scope="module")
def methods():
    return ev.default_methods(threads=1)


@pytest.fixture(scope="module")
def pair():
    f1, f2 = warp_pair(texture("astronaut", (200, 150)), SHIFT)
    pts = keypoints(f1, 80, 6.0)
    gt = true_flow(pts, SHIFT)
    keep = inside(pts + gt, 200, 150)
    return f1, f2, pts[keep], gt[keep]


def test_no_solver_is_called_outside_the_core_methods():
    for path in sorted(PACKAGE.glob("*.py")):
        tree = ast.parse(path.read_text(), str(path))
        for node in ast.walk(tree):
            if isinstance(node, ast.Attribute):
                assert node.attr != "calcOpticalFlowPyrLK", f"{path.name}:{node.lineno}"
            if isinstance(node, ast.ImportFrom) and node.module == "nsflow_ros.core.solver":
                names = {a.name for a in node.names}
                assert "track" not in names, f"{path.name}:{node.lineno} imports the solver's track"


def test_every_method_at_the_deployed_depth_on_a_registry_object(methods):
    deployed = core.METHODS["nsflow"].lm
    assert [m.name for m in methods] == list(ev.METHOD_ORDER) == list(ev.VARIANTS)
    # each at the depth the tracker runs it: the LM solver's, OpenCV's maxLevel 3 as VINS calls it
    lm_depths = {m.levels for m in methods if isinstance(m, ev.LMPairMethod)}
    assert lm_depths == {deployed.levels} == {6}
    lk_depths = {m.levels for m in methods if not isinstance(m, ev.LMPairMethod)}
    assert lk_depths == {core.KLT_MAX_LEVEL + 1} == {4}
    # a stereo pair from zero flow at the depth of the tracker's first stereo solve
    assert {m.stereo_levels for m in methods} == {core.METHODS['nsflow'].policy.stereo_levels} == {4}
    for m in methods:
        variant = ev.VARIANTS[m.name]
        # the evaluated method is the registry entry the tracker deploys, equalised as the label says
        assert m.core.spec == core.METHODS[variant.method] and m.equalize == variant.equalize
        # the sequences analysis runs the tracker with the same method and equalisation
        assert sequences.TRACKER_METHODS[m.name] == {"method": m.core.name, "equalize": m.equalize}
    lm = {m.name: m for m in methods if isinstance(m, ev.LMPairMethod)}
    assert set(lm) == {ev.NSFLOW, ev.CLASSICAL}
    # NSFlow with its model's declared gain on the finest level, as the tracker binds it
    assert lm[ev.NSFLOW].config == replace(deployed, gain=True, gain_levels=1)
    assert lm[ev.CLASSICAL].config == deployed
    assert ev.BASELINES == (ev.CLASSICAL, ev.KLT, ev.KLT_CLAHE)
    # each learned method its registry's default model: NSFlow + OpenCV LK the four-channel one (OpenCV's
    # LK needs descriptors in [0, 1]), without the smoothing the LM solver gets
    assert methods[0].encoder.path == load_encoder().path
    assert methods[1].encoder.path == load_encoder("d4").path
    assert methods[0].encoder.smoothing.fine > 0 and methods[1].encoder.smoothing.fine == 0


def test_each_method_solves_through_its_core_track_pair(methods, pair):
    f1, f2, pts, gt = pair
    flow0 = np.tile([1.0, -1.0], (len(pts), 1))
    frames = ev.prepare_pair(methods, f1, f2)
    for m in methods:
        res = m.track(*frames[m.name], pts, flow0)
        new, status = m.core.track_pair(*frames[m.name], pts, pts + flow0, m.levels)
        np.testing.assert_array_equal(res.status, status)
        np.testing.assert_allclose(res.flow, new - pts, atol=1e-12)
        assert np.median(endpoint_errors(res, gt)) < 0.1, m.name


def test_klt_is_vins_call_with_the_evaluations_criteria(methods, pair):
    f1, f2, pts, gt = pair
    klt = next(m for m in methods if m.name == ev.KLT)
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 30, 0.01)
    want, ok = core.klt_track(f1, f2, pts, None, 3, window=(21, 21), criteria=crit)
    frames = (klt.prepare(f1), klt.prepare(f2))
    res = klt.track(*frames, pts)
    np.testing.assert_array_equal(res.status, ok)
    np.testing.assert_allclose(res.flow, want - pts)
    # one iteration per level from a 5 px start ends further off than thirty on a single level
    start = gt + np.tile([5.0, 0.0], (len(pts), 1))
    one = klt.with_iterations(1)
    assert one.name == klt.name and one.levels == klt.levels
    e1 = endpoint_errors(one.track(*frames, pts, start, 1), gt)
    e30 = endpoint_errors(klt.track(*frames, pts, start, 1), gt)
    assert np.median(e30) < 0.1 < np.median(e1)


def test_clahe_and_descriptor_lk_prepare_what_the_tracker_tracks(methods, pair):
    f1 = pair[0]
    by = {m.name: m for m in methods}
    eq = cv2.createCLAHE(clipLimit=3.0, tileGridSize=(8, 8)).apply(f1)  # VINS-Mono's, the tracker's
    np.testing.assert_array_equal(by[ev.KLT_CLAHE].prepare(f1), eq)
    np.testing.assert_array_equal(by[ev.KLT].prepare(f1), f1)
    lk = by[ev.NSFLOW_LK]
    desc = lk.prepare(f1)
    assert desc.dtype == np.uint8 and desc.shape == (*f1.shape, lk.encoder.channels)
    np.testing.assert_array_equal(desc, core.quantise_descriptors(lk.encoder(f1)))


def test_guards(methods, pair):
    f1, f2, pts, _ = pair
    frames = ev.prepare_pair(methods, f1, f2)
    with pytest.raises(EvaluationError, match=r"levels must be in 1\.\.6, got 7"):
        methods[0].track(*frames[methods[0].name], pts, None, 7)
    with pytest.raises(EvaluationError, match=r"\(N, 2\)"):
        methods[3].track(*frames[methods[3].name], pts[:, 0])
    with pytest.raises(EvaluationError, match="cannot be reduced by 6"):
        methods[0].levels_fewer(6)
    assert methods[0].levels_fewer(1) == 5
    with pytest.raises(EvaluationError, match="levels"):
        ev.default_methods(levels=0)
    klt = next(m for m in methods if m.name == ev.KLT)
    with pytest.raises(EvaluationError, match="max_iterations"):
        klt.with_iterations(0)
    with pytest.raises(EvaluationError, match="unknown method"):
        ev.eval_method("SIFT")


def test_usable_methods_leave_out_only_what_cannot_take_the_model():
    methods, left_out = ev.usable_methods(threads=1)
    assert [m.name for m in methods] == list(ev.METHOD_ORDER) and left_out == {}
    methods, left_out = ev.usable_methods("fast", threads=1)
    assert [m.name for m in methods] == [n for n in ev.METHOD_ORDER if n != ev.NSFLOW_LK]
    assert set(left_out) == {ev.NSFLOW_LK} and "unbounded descriptors" in left_out[ev.NSFLOW_LK]
    with pytest.raises(MethodLeftOutError, match="NSFlow \\+ OpenCV LK: nsflow_lk quantises"):
        ev.eval_method(ev.NSFLOW_LK, model="fast")
