"""Tests of nsflow_ros.allocator (glibc malloc settings)."""

from __future__ import annotations

import platform

import numpy as np
import pytest

import nsflow_ros.allocator as allocator


@pytest.mark.skipif(platform.libc_ver()[0] != "glibc", reason="mallopt is glibc's")
def test_glibc_accepts_the_settings_and_memory_still_works():
    assert allocator.keep_large_buffers()
    assert allocator.keep_large_buffers()  # idempotent
    # a few frames' worth of large buffers, allocated and freed, still hold what was written
    for k in range(3):
        buf = np.full((480, 752, 4), k, np.float32)
        assert float(buf.sum()) == k * buf.size


def test_other_c_libraries_are_left_alone(monkeypatch):
    monkeypatch.setattr(allocator.platform, "libc_ver", lambda: ("", ""))
    assert allocator.keep_large_buffers() is False
    monkeypatch.setattr(allocator.platform, "libc_ver", lambda: ("glibc", "2.36"))
    monkeypatch.setattr(allocator.ctypes.util, "find_library", lambda name: None)
    assert allocator.keep_large_buffers() is False
