"""The data package: pure Python (no rclpy, no torch) and its re-exported public API."""

from __future__ import annotations

import subprocess
import sys

import nsflow_ros.data as data


def test_import_pulls_in_neither_rclpy_nor_torch():
    code = "import sys, nsflow_ros.data; print(sorted(m for m in ('rclpy', 'torch') if m in sys.modules))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"


def test_public_api_is_exported_and_documented():
    assert len(set(data.__all__)) == len(data.__all__)
    for name in data.__all__:
        obj = getattr(data, name)
        if callable(obj):
            assert obj.__doc__, f"nsflow_ros.data.{name} has no docstring"
    assert issubclass(data.DataError, __import__("nsflow_ros").NSFlowError)
