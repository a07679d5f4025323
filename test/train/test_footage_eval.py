"""Tests of the footage evaluation (nsflow_ros.train.footage_eval)."""

from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from nsflow_ros.core.encoder import IntensityEncoder  # noqa: E402
from nsflow_ros.core.solver import LMConfig  # noqa: E402
from nsflow_ros.train.data import load_image  # noqa: E402
from nsflow_ros.train.errors import TrainError  # noqa: E402
from nsflow_ros.train.footage_eval import evaluate_footage, footage_pairs, format_footage_table  # noqa: E402


def test_pairs_share_their_geometry_across_lighting():
    frames = [load_image("coffee")]
    lit, plain = footage_pairs(frames, 2, 1.0), footage_pairs(frames, 2, 0.0)
    assert len(lit) == 2
    assert all(np.array_equal(a.homography, b.homography) for a, b in zip(lit, plain, strict=True))
    assert not np.array_equal(lit[0].image1, plain[0].image1)
    err = np.linalg.norm(lit[0].flow0 - lit[0].flow_gt, axis=1)
    np.testing.assert_allclose(err, 5.0)
    with pytest.raises(TrainError, match="no held-out footage frame"):
        footage_pairs([], 1, 1.0)


def test_rows_hold_every_model_then_the_classical_mode():
    # the intensity encoder as "a model": its rows must equal the classical rows
    rows = evaluate_footage({"a": IntensityEncoder()}, [load_image("coffee")], 1, LMConfig(levels=1))
    assert [(r.pairs, r.mode) for r in rows] == [
        ("lighting change", "a"), ("lighting change", "classical"), ("same lighting", "a"),
        ("same lighting", "classical"),
    ]
    assert rows[0].metrics == rows[1].metrics and rows[0].metrics.points > 10
    assert "| same lighting | classical |" in format_footage_table(rows)
