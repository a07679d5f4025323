"""The basin loss: where the solver's first step lands when it starts away from the answer.

The implicit backward of the LK layer moves the minimum the solver converged to but cannot see how wide
its basin is; this loss looks at the basin directly: for every point and pyramid level, start at the
ground truth plus a random offset (length uniform in [0, radius] level pixels), take the solver's first
LM step, and penalise the robust distance from where it lands to the ground truth.
"""

from __future__ import annotations

import torch

from nsflow_ros.core.pyramid import Smoothing
from nsflow_ros.core.solver import LMConfig
from nsflow_ros.train.data import inside
from nsflow_ros.train.errors import TrainError
from nsflow_ros.train.lk_layer import residual_and_jacobian, stack_level, template_windows
from nsflow_ros.train.loss import flow_loss
from nsflow_ros.train.ops import pyramid

__all__ = ["basin_loss", "first_step"]


def first_step(
    desc1: torch.Tensor, desc2: torch.Tensor, points: torch.Tensor, start: torch.Tensor, config: LMConfig
) -> torch.Tensor:
    """The solver's first LM step from ``start`` (accepted or not), differentiable w.r.t. both maps.

    Args:
        desc1: frame-1 map of one level.
        desc2: frame-2 map of the same level.
        points: keypoints in that level's pixels.
        start: starting flows in that level's pixels (no gradient).
        config: window, Jacobian and lambda^(0) rule.

    Returns:
        the step du, float64.

    Shape:
        desc1, desc2: (C, H, W). points, start: (N, 2). Returns (N, 2).
    """
    if desc1.shape != desc2.shape or desc1.dim() != 3:
        shapes = f"{tuple(desc1.shape)}, {tuple(desc2.shape)}"
        raise TrainError(f"first_step needs two equal (C, H, W) maps, got {shapes}")
    win = config.window
    template = template_windows(desc1, points, win, config.jacobian, config.zero_mean)
    f, jx, jy = residual_and_jacobian(stack_level(desc2), points + start.detach(), template, win)
    h11, h12, h22 = ((jx * jx).sum(1).double(), (jx * jy).sum(1).double(), (jy * jy).sum(1).double())
    g1, g2 = (jx * f).sum(1).double(), (jy * f).sum(1).double()
    lam = torch.full_like(h11, config.lambda_init)
    if config.lambda_scale > 0:
        lam = torch.maximum(lam, config.lambda_scale * torch.maximum(h11, h22))
    a11, a22 = h11 + lam, h22 + lam
    det = a11 * a22 - h12 * h12
    return -torch.stack([a22 * g1 - h12 * g2, a11 * g2 - h12 * g1], 1) / det[:, None]


def basin_loss(
    desc1: torch.Tensor,
    desc2: torch.Tensor,
    points: torch.Tensor,
    flow_gt: torch.Tensor,
    config: LMConfig,
    radius: float,
    delta: float = 1.0,
    rho: str = "cauchy",
    generator: torch.Generator | None = None,
    smoothing: Smoothing | None = None,
) -> torch.Tensor:
    """Mean over pyramid levels of the robust landing error of one step from a random start.

    Args:
        desc1: frame-1 full-resolution map.
        desc2: frame-2 full-resolution map.
        points: keypoints, level-0 pixels.
        flow_gt: ground-truth flow, level-0 pixels.
        config: levels, windows, Jacobian and lambda^(0) rule of the solver.
        radius: largest start offset in each level's own pixels.
        delta: robust scale, in each level's pixels.
        rho: robust penalty (:func:`~nsflow_ros.train.loss.flow_loss`).
        generator: torch random generator of the offsets (None = the global one).
        smoothing: the pyramid's Gaussian smoothing; None = none.

    Returns:
        the loss (a scalar with a graph; 0 when no point is usable).

    Raises:
        TrainError: on a negative radius or mismatched maps.

    Shape:
        desc1, desc2: (C, H, W). points, flow_gt: (N, 2).
    """
    if radius < 0:
        raise TrainError(f"radius must be >= 0, got {radius}")
    pyr1, pyr2 = pyramid(desc1, config.levels, smoothing), pyramid(desc2, config.levels, smoothing)
    pts = points.detach().to(torch.float64)
    gt = flow_gt.detach().to(torch.float64)
    n = pts.shape[0]
    total = desc1.new_zeros((), dtype=torch.float64)
    for lev, (m1, m2) in enumerate(zip(pyr1, pyr2, strict=True)):
        lcfg = config.at_level(lev)
        r = lcfg.window // 2
        s = 2.0**lev
        p_l, gt_l = pts / s, gt / s
        ang = torch.rand(n, generator=generator, dtype=torch.float64, device=pts.device) * (2 * torch.pi)
        length = torch.rand(n, generator=generator, dtype=torch.float64, device=pts.device) * radius
        start = gt_l + length[:, None] * torch.stack([torch.cos(ang), torch.sin(ang)], 1)
        h, w = m1.shape[1:]
        valid = inside(p_l, w, h, r) & inside(p_l + gt_l, w, h, r)
        if not bool(valid.any()):
            continue
        du = first_step(m1, m2, p_l[valid], start[valid], lcfg)
        total = total + flow_loss(start[valid] + du, gt_l[valid], torch.isfinite(du).all(1), delta, rho)[0]
    return total / len(pyr1)
