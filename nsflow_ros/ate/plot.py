"""Top-view (x-y) trajectory plot coloured by the position error, written as PNG.

matplotlib is imported on use and drawn through its Agg canvas, so no global backend is switched.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from nsflow_ros.ate.errors import ATEError
from nsflow_ros.ate.metrics import APEResult
from nsflow_ros.optional import require

__all__ = ["plot_top_view"]


def plot_top_view(result: APEResult, path: str | Path, title: str | None = None, dpi: int = 120) -> Path:
    """Draw the aligned estimate over the reference, seen from above, coloured by APE; returns the path.

    Args:
        result: an :func:`~nsflow_ros.ate.evaluate_ape` result.
        path: PNG file to write (parent folders are created).
        title: first title line (default: the last parts of the estimate's path); the second gives the
            RMSE, the number of poses and the alignment.
        dpi: resolution.

    Raises:
        ATEError: when the result holds fewer than two poses or the file cannot be written.
        MissingExtraError: no matplotlib (the ``eval`` extra).
    """
    agg = require("matplotlib.backends.backend_agg", "the ATE plot")
    collections = require("matplotlib.collections", "the ATE plot")
    figure = require("matplotlib.figure", "the ATE plot")

    ref = result.ref.positions
    est = result.est.positions
    err = np.asarray(result.errors, dtype=np.float64)
    if len(est) < 2:
        raise ATEError(f"a trajectory plot needs at least 2 poses, got {len(est)}")
    fig = figure.Figure(figsize=(7.0, 6.0))
    agg.FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 1, 1)
    ax.plot(ref[:, 0], ref[:, 1], color="0.6", linestyle="--", linewidth=1.2, label="ground truth")
    segments = np.stack([est[:-1, :2], est[1:, :2]], axis=1)
    lines = collections.LineCollection(segments, cmap="jet", linewidths=2.0)
    lines.set_array(0.5 * (err[:-1] + err[1:]))
    lines.set_clim(float(err.min()), float(err.max()) if err.max() > err.min() else float(err.min()) + 1e-9)
    ax.add_collection(lines)
    ax.plot(est[0, 0], est[0, 1], "o", color="black", label="start")
    ax.plot(est[-1, 0], est[-1, 1], "s", color="black", label="end")
    fig.colorbar(lines, ax=ax, label="APE [m]")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_aspect("equal", adjustable="datalim")
    ax.autoscale_view()
    ax.grid(True, linewidth=0.3)
    ax.legend(loc="best", fontsize="small")
    s = result.stats
    label = "/".join(Path(result.est.name).parts[-4:])
    summary = f"APE rmse {s.rmse:.3f} m, n {s.n}, {result.alignment.method}"
    ax.set_title(f"{title or label}\n{summary}", fontsize="medium")
    out = Path(path)
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        fig.savefig(out, dpi=dpi, format="png")
    except OSError as exc:
        raise ATEError(f"{out}: cannot write the plot ({exc.strerror})") from exc
    return out
