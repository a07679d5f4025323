"""The tracker node's parameter table: the params file, --help and type checks come from it."""

from __future__ import annotations

from pathlib import Path

import pytest

from nsflow_ros.ros.errors import ParameterError
from nsflow_ros.ros.tracker_params import PARAMETERS, render_params_yaml, spec, usage

ROOT = Path(__file__).resolve().parents[2]


def test_shipped_params_file_is_the_table():
    # one source of truth: regenerate with render_params_yaml() after changing PARAMETERS
    assert (ROOT / "config" / "tracker_params.yaml").read_text() == render_params_yaml()


def test_params_file_parses_to_every_default():
    yaml = pytest.importorskip("yaml")
    params = yaml.safe_load(render_params_yaml())["nsflow_tracker"]["ros__parameters"]
    assert params == {p.name: p.default for p in PARAMETERS}
    assert all(type(params[p.name]) is type(p.default) for p in PARAMETERS)


def test_usage_lists_every_parameter_with_its_default():
    text = usage("nsflow-tracker")
    for p in PARAMETERS:
        assert f"  {p.name} ({p.kind}, default " in text
    flat = " ".join(text.split())
    assert "freq (integer, default -1)" in flat and "0 = 100 Hz, in effect every image" in flat
    assert "/diagnostics" in text and "qos_overrides" in text


def test_coerce_accepts_an_integer_for_a_number_and_names_slips():
    assert spec("F_threshold").coerce(1) == 1.0 and isinstance(spec("F_threshold").coerce(1), float)
    assert spec("max_cnt").coerce(20) == 20
    with pytest.raises(ParameterError, match=r"parameter max_cnt: got 'abc' \(string\), expected an integer"):
        spec("max_cnt").coerce("abc")
    with pytest.raises(ParameterError, match="parameter max_cnt: got True"):
        spec("max_cnt").coerce(True)
    with pytest.raises(ParameterError, match=r"parameter use_imu_prediction: got 1 .*expected a boolean"):
        spec("use_imu_prediction").coerce(1)
    with pytest.raises(ParameterError, match="unknown parameter"):
        spec("maxcnt")
    assert sum(not p.live for p in PARAMETERS) >= 5  # the topics and the config are read-only
