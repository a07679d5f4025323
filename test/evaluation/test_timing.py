"""Timing helpers shared by the benchmark and the evaluation."""

from __future__ import annotations

import numpy as np
import pytest

from nsflow_ros.core.encoder import IntensityEncoder
from nsflow_ros.evaluation.errors import EvaluationError
from nsflow_ros.evaluation.timing import make_frames, time_encoder, timing_stats


def test_timing_helpers():
    frames = make_frames(2, (64, 48))
    assert len(frames) == 2 and frames[0].shape == (48, 64, 3) and (frames[0] != frames[1]).any()
    assert timing_stats([1.0, 2.0, 3.0]) == {"median_ms": 2.0, "p90_ms": pytest.approx(2.8)}
    assert all(np.isnan(v) for v in timing_stats([]).values())
    st = time_encoder(IntensityEncoder(), (64, 48), 3)
    assert 0 < st["median_ms"] <= st["p90_ms"]
    with pytest.raises(EvaluationError, match="repeats"):
        time_encoder(IntensityEncoder(), (64, 48), 0)
