"""Command-line value types shared by the tools."""

from __future__ import annotations

import argparse

import pytest

from nsflow_ros.argtypes import method_variant, method_variants


def test_a_method_variant_is_its_name_and_settings_as_yaml_scalars():
    assert method_variant("klt") == ("klt", {})
    assert method_variant("nsflow:reverse_checks=1:max_cnt=200:model_path=d4") == (
        "nsflow", {"reverse_checks": 1, "max_cnt": 200, "model_path": "d4"})
    assert method_variant("nsflow:max_sigma=0.4:equalize=true") == (
        "nsflow", {"max_sigma": 0.4, "equalize": True})


@pytest.mark.parametrize("text", ["nsflow:reverse_checks", "nsflow:=1", "nsflow,klt:x"])
def test_a_setting_without_key_and_value_is_refused_naming_it(text):
    with pytest.raises(argparse.ArgumentTypeError, match="name:key=value"):
        method_variants(text)


def test_method_variants_keeps_the_entries_as_typed():
    assert method_variants(" nsflow , nsflow:reverse_checks=1,") == ["nsflow", "nsflow:reverse_checks=1"]
