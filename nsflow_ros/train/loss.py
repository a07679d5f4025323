"""The training loss: mean robust penalty of the endpoint error over valid points (paper, Algorithm 2)."""

from __future__ import annotations

import torch

from nsflow_ros.train.errors import TrainError

__all__ = ["RHOS", "endpoint_error", "flow_loss"]

RHOS = ("huber", "cauchy", "charbonnier")


def endpoint_error(flow: torch.Tensor, flow_gt: torch.Tensor) -> torch.Tensor:
    """||u_hat - u_gt|| per point, smoothed at zero so its gradient exists everywhere.

    Shape:
        flow, flow_gt: (N, 2). Returns (N,).
    """
    if flow.shape != flow_gt.shape or flow.dim() != 2 or flow.shape[1] != 2:
        raise TrainError(
            f"flow and flow_gt must both be (N, 2), got {tuple(flow.shape)} and {tuple(flow_gt.shape)}"
        )
    diff = flow - flow_gt.to(flow.dtype)
    return torch.sqrt((diff * diff).sum(1) + 1e-12)


def flow_loss(
    flow: torch.Tensor, flow_gt: torch.Tensor, valid: torch.Tensor, delta: float = 1.0, rho: str = "huber"
) -> tuple[torch.Tensor, int]:
    """Mean robust penalty rho of the endpoint error over the valid points.

    Args:
        flow: estimated flow.
        flow_gt: ground-truth flow.
        valid: solver status; non-finite estimates are masked as well.
        delta: scale of rho in pixels.
        rho: "huber", "cauchy" (its gradient falls off beyond delta, so points stuck in a wrong minimum
            far away barely pull) or "charbonnier".

    Returns:
        (loss, number of points used); the loss is 0 (with a graph) when no point is valid.

    Shape:
        flow, flow_gt: (N, 2). valid: (N,) bool.
    """
    if valid.shape != flow.shape[:1]:
        raise TrainError(f"valid must have shape ({flow.shape[0]},), got {tuple(valid.shape)}")
    mask = valid & torch.isfinite(flow).all(1)
    count = int(mask.sum())
    if count == 0:
        return flow.sum() * 0.0 if torch.isfinite(flow).all() else flow.new_zeros(()), 0
    epe = endpoint_error(flow[mask], flow_gt[mask])
    if rho == "huber":
        pen = torch.where(epe < delta, 0.5 * epe * epe, delta * (epe - 0.5 * delta))
    elif rho == "cauchy":
        pen = 0.5 * delta * delta * torch.log1p((epe / delta) ** 2)
    elif rho == "charbonnier":
        pen = torch.sqrt(epe * epe + delta * delta) - delta
    else:
        raise TrainError(f"rho must be one of {RHOS}, got {rho!r}")
    return pen.mean(), count
