"""Torch twins of the solver's map operations: Scharr derivatives, exact bilinear window sampling and
the pyramid's downsampling.

All mirror the NumPy core exactly (``nsflow_ros.core.pyramid.descriptor_gradients``,
``nsflow_ros.core.solver.sample_windows`` and ``nsflow_ros.core.pyramid.build_pyramid``): normalised Scharr
kernels with replicated borders, ``cv2.pyrDown`` with ``BORDER_REPLICATE`` (the border the core passes,
not OpenCV's default reflect-101), and bilinear interpolation whose sample coordinates are clamped to
[0, W-1] x [0, H-1] (= replicated border).
Every pixel of a window shares the centre's fractional offset, so a window is interpolated from one
(window+1)^2 integer patch; the result is differentiable w.r.t. the maps and (through the fractional
offset) w.r.t. the centres.
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


def pyr_down(desc: torch.Tensor) -> torch.Tensor:
    """One coarser pyramid level: ``cv2.pyrDown(desc, borderType=cv2.BORDER_REPLICATE)`` per channel.

    The 5x5 Gaussian [1 4 6 4 1] / 16 (separable), borders replicated, then every second row and
    column from the first: output size ((H + 1) // 2, (W + 1) // 2), as OpenCV's.

    Args:
        desc: the finer level.

    Returns:
        the coarser level, differentiable w.r.t. ``desc`` (the filter is linear).

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
    """Separable Gaussian smoothing with replicated borders, as the core's pyramid smoothing.

    Args:
        desc: the map.
        sigma: standard deviation in pixels, > 0 (the taps of ``nsflow_ros.core.pyramid.gaussian_kernel``).

    Returns:
        the smoothed map, differentiable w.r.t. ``desc``.

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
        levels: levels wanted; as in the core, a level whose smaller side would drop below
            :data:`MIN_LEVEL_SIZE` is not built, so the result may have fewer.
        smoothing: Gaussian smoothing, as in the core: level 0 before the coarser levels are made
            from it, each coarser level after; None = none.

    Returns:
        the maps, level 0 first (``desc`` itself unless level 0 is smoothed).

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
