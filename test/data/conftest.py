"""Shared fixtures of the data-layer tests: one short sample sequence for the whole session."""

from __future__ import annotations

import pytest

from nsflow_ros.data.sample import make_sample_sequence


@pytest.fixture(scope="session")
def sample_seq(tmp_path_factory):
    """0.5 s of stereo (10 frames per camera, 101 IMU samples) in all three formats."""
    root = tmp_path_factory.mktemp("data_sample") / "seq"
    return make_sample_sequence(root, seed=5, duration=0.5, progress=False)
