"""Top-view trajectory plot coloured by error."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from nsflow_ros.ate import ATEError, Trajectory, evaluate_ape, plot_top_view


def test_png_written(tmp_path, gt):
    noisy = Trajectory(
        gt.stamps, gt.positions + np.random.default_rng(0).normal(0, 0.05, (600, 3)), gt.quaternions, "est"
    )
    result = evaluate_ape(gt, noisy)
    out = plot_top_view(result, tmp_path / "deep" / "top.png", title="test")
    data = out.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 10_000


def test_constant_error_and_guard(tmp_path, gt):
    result = evaluate_ape(gt, gt, align="none")  # zero error everywhere: the colour range must not collapse
    assert plot_top_view(result, tmp_path / "zero.png").is_file()
    tiny = evaluate_ape(gt, gt.take([0, 1, 2]).renamed("tiny"))
    tiny = type(tiny)(tiny.stats, tiny.errors[:1], tiny.alignment, tiny.ref.take([0]), tiny.est.take([0]))
    with pytest.raises(ATEError, match="at least 2 poses"):
        plot_top_view(tiny, tmp_path / "x.png")


def test_matplotlib_is_imported_lazily():
    code = "import sys, nsflow_ros.ate; print('matplotlib' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"
