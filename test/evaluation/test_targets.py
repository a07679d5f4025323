"""Targets as data rows: the text a report prints and the verdict come from one row."""

from __future__ import annotations

import math

import pytest

from nsflow_ros.evaluation import capture, convergence, pairs, sequences, trackable
from nsflow_ros.evaluation.errors import EvaluationError
from nsflow_ros.evaluation.methods import CLASSICAL, KLT, KLT_CLAHE, NSFLOW
from nsflow_ros.evaluation.targets import Clause, Target, headline_row

ALL = {NSFLOW: 0.9, CLASSICAL: 0.6, KLT: 0.5, KLT_CLAHE: 0.8}


def test_a_bound_prints_with_its_unit_and_a_rival_with_its_scale():
    assert Clause(">=", bound=0.97, unit="%").text({}) == ">= 97 %"
    assert Clause("<=", bound=0.5, unit="px").text({}) == "<= 0.5 px"
    assert Clause("<=", (KLT,), 1.1).text({}) == f"<= 1.1x {KLT}"
    assert Clause("<", (KLT,), label="KLT").text({}) == "< KLT"


def test_a_bad_clause_is_refused():
    with pytest.raises(EvaluationError, match="'=>'"):
        Clause("=>", (KLT,))
    with pytest.raises(EvaluationError, match="rivals or a bound"):
        Clause(">=")


def test_verdict_is_none_without_the_subject_or_a_required_rival():
    t = Target("x", (Clause(">=", (KLT,)),))
    assert t.check({KLT: 0.5}) is None
    assert t.check({NSFLOW: 0.9}) is None
    assert t.check({NSFLOW: 0.9, KLT: None}) is None
    assert t.check({NSFLOW: 0.9, KLT: 0.5}) is True
    assert t.check({NSFLOW: 0.4, KLT: 0.5}) is False


def test_an_optional_clause_drops_out_of_text_and_verdict_without_its_rival():
    t = capture.TARGETS["light"]
    assert t.text(ALL) == f">= {KLT} and > {KLT_CLAHE}"
    assert t.check(ALL) is True
    assert t.check({**ALL, KLT_CLAHE: 0.95}) is False
    without = {NSFLOW: 0.9, KLT: 0.5}
    assert t.text(without) == f">= {KLT}"
    assert t.check(without) is True


def test_best_baseline_uses_the_rivals_evaluated_in_text_and_check():
    t = trackable.TARGETS["light"]
    assert t.text(ALL) == f">= 1.5x the best baseline ({CLASSICAL}, {KLT}, {KLT_CLAHE})"
    assert t.check(ALL) is False  # 0.9 < 1.5 x 0.8
    some = {NSFLOW: 0.9, KLT: 0.5}
    assert t.text(some) == f">= 1.5x the best baseline ({KLT})"
    assert t.check(some) is True
    assert t.check({NSFLOW: 0.9}) is None


def test_two_clauses_must_both_hold():
    t = trackable.TARGETS["none"]
    assert t.text(ALL) == f"> {CLASSICAL} and >= 85 %"
    assert t.check(ALL) is True
    assert t.check({**ALL, NSFLOW: 0.84}) is False  # above LM, under the floor
    assert t.check({**ALL, CLASSICAL: 0.95}) is False


def test_a_nan_figure_never_meets_a_target():
    assert pairs.TARGETS[("viewpoint", "within_1px")].check({**ALL, NSFLOW: math.nan}) is False
    assert pairs.TARGETS[("illumination", "median")].check({**ALL, KLT: math.nan}) is False


def test_stretch_target_names_the_reference_column():
    t = capture.stretch_target("4 levels", 0.179)
    assert t.text({}) == f"stretch: NSFlow here >= {KLT} at 4 levels (17.9%)"
    assert t.check({NSFLOW: 0.2, KLT: 0.179}) is True
    assert t.check({NSFLOW: 0.2}) is None


def test_every_analysis_target_prints_what_the_report_printed_before():
    assert pairs.TARGETS[("viewpoint", "median")].text(ALL) == "<= 1.2x KLT"
    assert pairs.TARGETS[("illumination", "within_1px")].text(ALL) == f">= 97 % and > {KLT_CLAHE}"
    assert convergence.TARGETS["light"].text(ALL) == f"< {CLASSICAL} and < {KLT_CLAHE}"
    assert convergence.TARGETS["none"].text(ALL) == f"< {CLASSICAL}"
    assert sequences.TARGETS[("large", "tracks_10_frames")].text(ALL) == f">= 2x {KLT}"
    assert sequences.TARGETS[("large", "error_median_px")].text(ALL) == "<= 0.5 px"
    assert sequences.TARGETS[("large", "tracks_10_frames")].check({NSFLOW: 40, KLT: 20}) is True
    assert sequences.TARGETS[("large", "tracks_10_frames")].check({NSFLOW: 39, KLT: 20}) is False


def test_row_carries_text_and_verdict():
    row = pairs.TARGETS[("viewpoint", "median")].row("m", {NSFLOW: "0.1"}, {NSFLOW: 0.1, KLT: 0.1})
    assert (row.metric, row.target, row.met) == ("m", "<= 1.2x KLT", True)


def test_headline_row_formats_each_figure_and_takes_text_and_verdict_from_the_target():
    figures = {NSFLOW: 0.25, KLT: 0.5}
    row = headline_row("m", figures, "{:.1%}".format, pairs.TARGETS[("viewpoint", "median")])
    assert row.values == {NSFLOW: "25.0%", KLT: "50.0%"}
    assert (row.metric, row.target, row.met) == ("m", "<= 1.2x KLT", True)
    plain = headline_row("m", figures, str)
    assert (plain.values, plain.target, plain.met) == ({NSFLOW: "0.25", KLT: "0.5"}, "", None)
