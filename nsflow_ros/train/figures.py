"""Training figures (PNG, matplotlib Agg): the loss curve and the per-epoch validation figure."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from nsflow_ros.optional import require

__all__ = ["plot_loss", "plot_validation"]


def _plt():
    require("matplotlib", "the training figures").use("Agg")
    return require("matplotlib.pyplot", "the training figures")


def plot_loss(
    losses: list[float], val_steps: list[int], val_within: list[float], path: str | os.PathLike[str]
) -> Path:
    """Training loss per step (raw and a 100-step running mean) and validation < 1 px share."""
    plt = _plt()
    fig, ax = plt.subplots(figsize=(6.4, 3.4), dpi=90)
    steps = np.arange(1, len(losses) + 1)
    ax.plot(steps, losses, color="0.8", lw=0.5, label="loss (per step)")
    if len(losses) >= 10:
        k = min(100, len(losses))
        smooth = np.convolve(losses, np.ones(k) / k, mode="valid")
        ax.plot(steps[k - 1 :], smooth, color="C0", lw=1.5, label=f"loss ({k}-step mean)")
    ax.set_xlabel("step")
    ax.set_ylabel("robust loss rho(EPE)")
    ax.set_yscale("log")
    if val_steps:
        ax2 = ax.twinx()
        ax2.plot(val_steps, val_within, "o-", color="C3", ms=3, label="val < 1 px (perturbed)")
        ax2.set_ylabel("val share < 1 px", color="C3")
        ax2.set_ylim(0, 1)
    ax.legend(loc="upper right", fontsize=7)
    fig.tight_layout()
    out = Path(path)
    fig.savefig(out)
    plt.close(fig)
    return out


def plot_validation(
    results: dict[str, tuple[np.ndarray, np.ndarray | None]], title: str, path: str | os.PathLike[str]
) -> Path:
    """Cumulative share of points within an error per label -> (errors, inf where lost; statuses or None).

    Labels containing "NSFlow" are drawn solid, others dashed, in pairs of colours.
    """
    plt = _plt()
    fig, ax = plt.subplots(figsize=(5.6, 3.4), dpi=90)
    grid = np.linspace(0, 5, 201)
    for k, (label, (err, _)) in enumerate(results.items()):
        share = [(err < t).mean() if err.size else 0.0 for t in grid]
        style = "-" if "NSFlow" in label else "--"
        ax.plot(grid, share, style, color=f"C{k // 2}", label=label)
    ax.axvline(1.0, color="0.6", lw=0.8)
    ax.set_xlabel("endpoint error threshold (px)")
    ax.set_ylabel("share of points (lost = fail)")
    ax.set_ylim(0, 1)
    ax.set_title(title, fontsize=9)
    ax.legend(fontsize=7, loc="lower right")
    fig.tight_layout()
    out = Path(path)
    fig.savefig(out)
    plt.close(fig)
    return out
