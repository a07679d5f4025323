"""The core is importable without ROS or torch."""

from __future__ import annotations

import subprocess
import sys


def test_import_pulls_in_neither_rclpy_nor_torch():
    code = "import sys, nsflow_ros; print(sorted(m for m in ('rclpy', 'torch') if m in sys.modules))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"


def test_public_api_is_documented():
    import nsflow_ros

    for name in nsflow_ros.__all__:
        obj = getattr(nsflow_ros, name)
        assert obj.__doc__, f"nsflow_ros.{name} has no docstring"
