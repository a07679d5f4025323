"""Torch twins of the solver's map operations: Scharr derivatives and exact bilinear window sampling.

Both mirror the NumPy core exactly (``nsflow_ros.core.pyramid.descriptor_gradients`` and
``nsflow_ros.core.solver.sample_windows``): normalised Scharr kernels with replicated borders, and
bilinear interpolation whose sample coordinates are clamped to [0, W-1] x [0, H-1] (= replicated border).
Every pixel of a window shares the centre's fractional offset, so a window is interpolated from one
(window+1)^2 integer patch; the result is differentiable w.r.t. the maps and (through the fractional
offset) w.r.t. the centres.
"""

from __future__ import annotations

import torch
from torch.nn import functional as F  # noqa: N812 - the usual torch alias

from nsflow_ros.train.errors import TrainError

__all__ = ["sample_windows", "scharr_gradients"]


def _scharr_kernels(dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    kx = torch.tensor([[-3.0, 0.0, 3.0], [-10.0, 0.0, 10.0], [-3.0, 0.0, 3.0]], dtype=dtype, device=device)
    kx = kx / 32.0
    return torch.stack([kx, kx.t()])[:, None]  # (2, 1, 3, 3): d/dx, d/dy (cross-correlation, like cv2)


def scharr_gradients(desc: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """x- and y-derivatives of a descriptor map (normalised Scharr, replicated border).

    Args:
        desc: descriptor map, channels first.

    Returns:
        (dx, dy), each shaped like ``desc``.

    Shape:
        desc: (C, H, W) float.
    """
    if desc.dim() != 3:
        raise TrainError(f"scharr_gradients expects a (C, H, W) map, got shape {tuple(desc.shape)}")
    c = desc.shape[0]
    padded = F.pad(desc[:, None], (1, 1, 1, 1), mode="replicate")  # (C, 1, H+2, W+2)
    out = F.conv2d(padded, _scharr_kernels(desc.dtype, desc.device))  # (C, 2, H, W)
    return out[:, 0].reshape(c, *desc.shape[1:]), out[:, 1].reshape(c, *desc.shape[1:])


def sample_windows(maps: torch.Tensor, centers: torch.Tensor, window: int) -> torch.Tensor:
    """Sample square windows of a multi-channel map with exact bilinear interpolation.

    Args:
        maps: the map to sample, replicated beyond its border.
        centers: window centres (x, y) in pixels.
        window: odd window side.

    Returns:
        the windows, channel first then rows then columns.

    Shape:
        maps: (K, H, W). centers: (M, 2). Returns (M, K, window, window).
    """
    if maps.dim() != 3:
        raise TrainError(f"sample_windows expects (K, H, W) maps, got shape {tuple(maps.shape)}")
    if centers.dim() != 2 or centers.shape[1] != 2:
        raise TrainError(f"centers must have shape (M, 2), got {tuple(centers.shape)}")
    k, h, w = maps.shape
    m = centers.shape[0]
    r = window // 2
    # Positions in the maps' dtype, like the NumPy solver's float32 remap coordinates.
    c = centers.to(maps.dtype)
    base = torch.floor(c.detach())
    frac = c - base  # differentiable w.r.t. the centres
    ib = base.to(torch.int64)
    off = torch.arange(-r, r + 2, device=maps.device)
    xs = (ib[:, 0, None] + off[None, :]).clamp(0, w - 1)  # (M, window+1)
    ys = (ib[:, 1, None] + off[None, :]).clamp(0, h - 1)
    flat = (ys[:, :, None] * w + xs[:, None, :]).reshape(-1)  # (M * (window+1)^2,)
    patch = maps.reshape(k, h * w)[:, flat].reshape(k, m, window + 1, window + 1).transpose(0, 1)
    a = frac[:, 0, None, None, None]
    b = frac[:, 1, None, None, None]
    horiz = patch[..., :-1] + a * (patch[..., 1:] - patch[..., :-1])  # (M, K, window+1, window)
    return horiz[..., :-1, :] + b * (horiz[..., 1:, :] - horiz[..., :-1, :])
