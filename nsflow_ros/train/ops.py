"""Torch twins of the solver's map operations: Scharr derivatives, exact bilinear window sampling and
the descriptor pyramid.

Each mirrors the NumPy core exactly (``nsflow_ros.core.pyramid.descriptor_gradients``,
``nsflow_ros.core.solver.sample_windows``, ``nsflow_ros.core.pyramid.build_pyramid``), replicated borders
included, and is differentiable w.r.t. the maps (sampling also w.r.t. the centres).
"""

from __future__ import annotations

import torch
from torch.nn import functional as F  # noqa: N812 - the usual torch alias

from nsflow_ros.core.pyramid import Smoothing, gaussian_kernel
from nsflow_ros.train.errors import TrainError

__all__ = ["MIN_LEVEL_SIZE", "gaussian_smooth", "pyr_down", "pyramid", "sample_windows", "scharr_gradients"]

# build_pyramid stops before a level whose smaller side would be below this many pixels.
MIN_LEVEL_SIZE = 8


def _scharr_kernels(dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    kx = torch.tensor([[-3.0, 0.0, 3.0], [-10.0, 0.0, 10.0], [-3.0, 0.0, 3.0]], dtype=dtype, device=device)
    kx = kx / 32.0
    return torch.stack([kx, kx.t()])[:, None]  # (2, 1, 3, 3): d/dx, d/dy (cross-correlation, like cv2)


def scharr_gradients(desc: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(dx, dy) of a descriptor map (normalised Scharr, replicated border), each shaped like it.

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

    Every pixel of a window shares the centre's fractional offset, so a window is interpolated from one
    (window + 1)^2 integer patch with coordinates clamped to the map (= replicated border).

    Args:
        maps: the map to sample.
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


def pyr_down(desc: torch.Tensor) -> torch.Tensor:
    """One coarser pyramid level: ``cv2.pyrDown(desc, borderType=cv2.BORDER_REPLICATE)`` per channel.

    Shape:
        desc: (C, H, W). Returns (C, (H + 1) // 2, (W + 1) // 2).
    """
    if desc.dim() != 3:
        raise TrainError(f"pyr_down expects a (C, H, W) map, got shape {tuple(desc.shape)}")
    c, h, w = desc.shape
    k = torch.tensor([1.0, 4.0, 6.0, 4.0, 1.0], dtype=desc.dtype, device=desc.device) / 16.0
    padded = F.pad(desc[:, None], (2, 2, 2, 2), mode="replicate")  # (C, 1, H+4, W+4)
    rows = F.conv2d(padded, k.reshape(1, 1, 5, 1), stride=(2, 1))
    out = F.conv2d(rows, k.reshape(1, 1, 1, 5), stride=(1, 2))
    return out.reshape(c, (h + 1) // 2, (w + 1) // 2)


def gaussian_smooth(desc: torch.Tensor, sigma: float) -> torch.Tensor:
    """Separable Gaussian smoothing with replicated borders (``nsflow_ros.core.pyramid.gaussian_kernel``).

    Args:
        desc: the map.
        sigma: standard deviation in pixels, > 0.

    Shape:
        desc: (C, H, W). Returns (C, H, W).
    """
    if desc.dim() != 3:
        raise TrainError(f"gaussian_smooth expects a (C, H, W) map, got shape {tuple(desc.shape)}")
    k = torch.as_tensor(gaussian_kernel(sigma), dtype=desc.dtype, device=desc.device)
    r = k.numel() // 2
    c, h, w = desc.shape
    padded = F.pad(desc[:, None], (r, r, r, r), mode="replicate")
    rows = F.conv2d(padded, k.reshape(1, 1, -1, 1))
    return F.conv2d(rows, k.reshape(1, 1, 1, -1)).reshape(c, h, w)


def pyramid(desc: torch.Tensor, levels: int, smoothing: Smoothing | None = None) -> list[torch.Tensor]:
    """The solver's descriptor pyramid in torch, level 0 first (``nsflow_ros.core.pyramid.build_pyramid``).

    Args:
        desc: the full-resolution map.
        levels: levels wanted; fewer when a level's smaller side would drop below :data:`MIN_LEVEL_SIZE`.
        smoothing: Gaussian smoothing as in the core (level 0 before the coarser levels are made from
            it, each coarser level after); None = none.

    Shape:
        desc: (C, H, W).
    """
    if levels < 1:
        raise TrainError(f"levels must be >= 1, got {levels}")
    if smoothing is not None and smoothing.fine > 0:
        desc = gaussian_smooth(desc, smoothing.fine)
    out = [desc]
    for _ in range(1, levels):
        h, w = out[-1].shape[1:]
        if min(h, w) // 2 < MIN_LEVEL_SIZE:
            break
        out.append(pyr_down(out[-1]))
    if smoothing is not None and smoothing.coarse > 0:
        out = out[:1] + [gaussian_smooth(m, smoothing.coarse) for m in out[1:]]
    return out
