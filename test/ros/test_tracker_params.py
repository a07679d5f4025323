"""The tracker node's parameter table: the params file, --help and type checks come from it."""

from __future__ import annotations

from pathlib import Path

import pytest

from nsflow_ros.ros.errors import ParameterError
from nsflow_ros.ros.tracker_params import PARAMETERS, coerce, render_params_yaml, spec, usage
from nsflow_ros.vins.settings import SESSION_SETTINGS, SETTINGS, VINS_KEYS, Mode

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
        unit = f", {p.unit}" if p.unit else ""
        assert f"  {p.name} ({p.kind}{unit}, default " in text
        assert " ".join(p.full_description.split()) in " ".join(text.split())
    flat = " ".join(text.split())
    assert "freq (integer, Hz, default -1)" in flat and "0 = 100 Hz, in effect every image" in flat
    assert "/diagnostics" in text and "qos_overrides" in text


def test_coerce_accepts_an_integer_for_a_number_and_names_slips():
    assert coerce(spec("F_threshold"), 1) == 1.0 and isinstance(coerce(spec("F_threshold"), 1), float)
    assert coerce(spec("max_cnt"), 20) == 20
    with pytest.raises(ParameterError, match=r"parameter max_cnt: got 'abc' \(string\), expected an integer"):
        coerce(spec("max_cnt"), "abc")
    with pytest.raises(ParameterError, match="parameter max_cnt: got True"):
        coerce(spec("max_cnt"), True)
    with pytest.raises(ParameterError, match=r"parameter use_imu_prediction: got 1 .*expected a boolean"):
        coerce(spec("use_imu_prediction"), 1)
    with pytest.raises(ParameterError, match=r"parameter queue_size: got 0, expected an integer >= 1"):
        coerce(spec("queue_size"), 0)
    with pytest.raises(ParameterError, match=r"parameter status_period: got -1.0, expected a number >= 0"):
        coerce(spec("status_period"), -1.0)
    with pytest.raises(ParameterError, match="unknown parameter"):
        spec("maxcnt")
    assert sum(p.mode is Mode.READ_ONLY for p in PARAMETERS) >= 5  # the topics and the config are read-only


def test_the_node_parameters_are_the_settings_table():
    # every derived view names the same settings: node parameters, VINS overrides, session settings
    assert PARAMETERS is SETTINGS
    assert all(spec(k).vins_key == k for k in VINS_KEYS)
    assert set(SESSION_SETTINGS) <= {p.name for p in PARAMETERS}
    rebuild = {"method", "model_path", "num_threads", "equalize", "providers", "tensorrt_fp16",
               "tensorrt_cache", "downsample"}
    assert {p.name for p in PARAMETERS if p.mode is Mode.REBUILD} == rebuild
    text = render_params_yaml()
    for p in PARAMETERS:  # the mode reaches the params file's comments
        assert " ".join(p.full_description.split()) in " ".join(text.replace("#", " ").split())


def test_opencv_threads_is_a_read_only_node_setting_checked_at_start_up():
    p = spec("opencv_threads")
    assert p.default == 1 and p.mode is Mode.READ_ONLY and not p.session and not p.tracker
    assert coerce(p, 0) == 0 and coerce(p, 4) == 4  # 0 = OpenCV's default pool
    with pytest.raises(ParameterError, match=r"parameter opencv_threads: got -1, expected an integer >= 0"):
        coerce(p, -1)
    assert SETTINGS[-1] is p  # the last row of the table, as in the params file


@pytest.mark.parametrize(("name", "value", "said"), [
    ("downsample", -1, "downsample must be one of 1, 2, 4, got -1"),
    ("downsample", 0, "downsample must be one of 1, 2, 4, got 0"),
    ("max_sigma", -1.0, "parameter max_sigma: got -1.0, expected a number >= 0"),
    ("publish_covariance", 2, r"parameter publish_covariance: got 2, expected 0 or 1 \(or -1: the default\)"),
    ("publish_covariance", 5, "publish_covariance: got 5, expected 0 or 1"),
    ("publish_covariance", -2, "publish_covariance: got -2, expected 0 or 1"),
    ("max_cnt", 0, r"parameter max_cnt: got 0, expected an integer >= 1 \(or -1: the default\)"),
    ("mask_wait_ms", 1e9, r"parameter mask_wait_ms: got 1000000000.0, expected a number in \[0, 1000\]"),
    ("degraded_features", 1.5, r"degraded_features: got 1.5, expected a number in \[0, 1\]"),
    ("num_threads", -1, "parameter num_threads: got -1, expected an integer >= 0"),
])
def test_out_of_range_values_are_refused_with_the_range_including_the_keep_value(name, value, said):
    # the node's one rule, at start-up and at run time: -1 only where it is the default
    with pytest.raises(ParameterError, match=said):
        coerce(spec(name), value)


def test_the_keep_value_and_the_range_ends_are_accepted_where_they_mean_something():
    assert coerce(spec("publish_covariance"), -1) == -1 and coerce(spec("publish_covariance"), 1) == 1
    assert coerce(spec("max_cnt"), -1) == -1 and coerce(spec("publish_rate"), -1) == -1.0
    assert coerce(spec("downsample"), 4) == 4 and coerce(spec("mask_wait_ms"), 1000) == 1000.0
    assert coerce(spec("max_sigma"), 0.0) == 0.0 and coerce(spec("lost_carried"), 1.0) == 1.0
    assert all(p.keeps == (p.default == -1 and not isinstance(p.default, bool)) for p in PARAMETERS)
