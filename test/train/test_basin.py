"""Tests of the basin loss (nsflow_ros.train.basin)."""

from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from nsflow_ros import Jacobian, LMConfig  # noqa: E402
from nsflow_ros.train import TrainError, lk_track  # noqa: E402
from nsflow_ros.train.basin import basin_loss, first_step  # noqa: E402

SHIFT = np.array([2.6, -1.7])


def _maps(shift: np.ndarray) -> torch.Tensor:
    y, x = np.mgrid[0:64, 0:64].astype(np.float64)
    x, y = x - shift[0], y - shift[1]
    c0 = 0.5 + 0.25 * np.sin(0.35 * x + 0.2 * y) + 0.2 * np.cos(0.27 * y - 0.1 * x)
    c1 = 0.5 + 0.3 * np.sin(0.22 * x + 0.4) * np.cos(0.31 * y - 0.3)
    return torch.from_numpy(np.stack([c0, c1]))


POINTS = torch.tensor([[30.0, 30.0], [20.5, 40.2], [40.1, 22.7]], dtype=torch.float64)


@pytest.mark.parametrize("jacobian", list(Jacobian))
@pytest.mark.parametrize("lambda_scale", [0.0, 0.1])
def test_first_step_is_the_solvers_first_iteration(lambda_scale, jacobian):
    d1, d2 = _maps(np.zeros(2)), _maps(SHIFT)
    start = torch.from_numpy(SHIFT + np.array([[1.0, 0.5], [-0.8, 0.3], [0.2, -1.1]]))
    cfg = LMConfig(levels=1, max_iterations=1, lambda_scale=lambda_scale, jacobian=jacobian)
    du = first_step(d1, d2, POINTS, start, cfg)
    out = lk_track(d1, d2, POINTS, start, cfg)
    assert out.iterations.tolist() == [1, 1, 1]
    # Here every first step lowers the cost, so the solver accepts it.
    np.testing.assert_allclose((start + du).numpy(), out.flow.numpy(), atol=1e-6)
    assert (np.linalg.norm((start + du).numpy() - SHIFT, axis=1) < 0.2).all()


def test_basin_loss_is_small_for_a_wide_basin_and_reaches_both_maps():
    d1, d2 = _maps(np.zeros(2)).requires_grad_(True), _maps(SHIFT).requires_grad_(True)
    gt = torch.from_numpy(np.tile(SHIFT, (3, 1)))
    near = basin_loss(d1, d2, POINTS, gt, LMConfig(levels=2), 1.0, generator=torch.Generator().manual_seed(0))
    near.backward()
    assert float(d1.grad.abs().sum()) > 0 and float(d2.grad.abs().sum()) > 0
    far = basin_loss(d1, d2, POINTS, gt, LMConfig(levels=2), 12.0, generator=torch.Generator().manual_seed(0))
    # One step from within 1 px of a smooth map's answer lands close; from 12 px it does not.
    assert float(near.detach()) < 0.05 < float(far.detach())
    with pytest.raises(TrainError, match="radius must be >= 0"):
        basin_loss(d1, d2, POINTS, gt, LMConfig(levels=1), -1.0)
