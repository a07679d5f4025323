"""Contact sheets of debug images: tiles with captions and a legend of the VINS debug image's colours."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from nsflow_ros.errors import NSFlowError
from nsflow_ros.vins.draw import FULL_TRACK, track_colour

__all__ = ["contact_sheet", "track_legend", "write_png"]


def _label(tile: np.ndarray, text: str) -> None:
    """White text on a dark box in the tile's top-left corner: readable on any image."""
    font, scale = cv2.FONT_HERSHEY_SIMPLEX, 0.5
    (w, h), base = cv2.getTextSize(text, font, scale, 1)
    cv2.rectangle(tile, (0, 0), (w + 10, h + base + 8), (32, 32, 32), -1)
    cv2.putText(tile, text, (5, h + 4), font, scale, (255, 255, 255), 1, cv2.LINE_AA)


def track_legend(width: int) -> np.ndarray:
    """A legend strip for the VINS debug images: circle colour = track length, green arrow = motion."""
    strip = np.full((30, width, 3), 32, np.uint8)
    font = cv2.FONT_HERSHEY_SIMPLEX
    x = 8
    cv2.putText(strip, "track length:", (x, 20), font, 0.45, (255, 255, 255), 1, cv2.LINE_AA)
    x += 110
    for n in (1, 5, 10, 15, FULL_TRACK):
        cv2.circle(strip, (x, 15), 5, track_colour(n), -1)
        label = f"{n}+" if n == FULL_TRACK else str(n)
        cv2.putText(strip, label, (x + 9, 20), font, 0.45, (255, 255, 255), 1, cv2.LINE_AA)
        x += 45
    x += 15
    cv2.arrowedLine(strip, (x + 30, 15), (x, 15), (0, 255, 0), 1, cv2.LINE_AA, 0, 0.3)
    cv2.putText(strip, "to the previous position; green dots: right camera", (x + 38, 20), font, 0.45,
                (255, 255, 255), 1, cv2.LINE_AA)
    return strip


def contact_sheet(
    images: list[np.ndarray], cols: int = 3, width: int = 376, labels: list[str] | None = None,
    *, legend: bool = False,
) -> np.ndarray:
    """Tile BGR images (scaled to ``width`` px wide) into one sheet.

    Args:
        images: BGR uint8 images.
        cols: tiles per row.
        width: tile width in pixels.
        labels: one caption per image, white on a dark box.
        legend: add a strip explaining the VINS debug images' colours (:func:`track_legend`).
    """
    if not images:
        raise NSFlowError("contact_sheet needs at least one image")
    tiles = []
    for k, img in enumerate(images):
        h = round(img.shape[0] * width / img.shape[1])
        tile = cv2.resize(img, (width, h), interpolation=cv2.INTER_AREA)
        if labels:
            _label(tile, labels[k])
        tiles.append(tile)
    h = max(t.shape[0] for t in tiles)
    tiles = [cv2.copyMakeBorder(t, 0, h - t.shape[0], 0, 0, cv2.BORDER_CONSTANT) for t in tiles]
    while len(tiles) % cols:
        tiles.append(np.zeros_like(tiles[0]))
    rows = [np.hstack(tiles[i : i + cols]) for i in range(0, len(tiles), cols)]
    sheet = np.vstack(rows)
    if legend:
        sheet = np.vstack([sheet, track_legend(sheet.shape[1])])
    return sheet


def write_png(path: Path, img: np.ndarray) -> None:
    """Write a BGR or gray uint8 image as PNG; pair it with :func:`~nsflow_ros.files.atomic_write`.

    Raises:
        NSFlowError: the image cannot be encoded (naming the path).
    """
    ok, buf = cv2.imencode(".png", img)
    if not ok:
        raise NSFlowError(f"cannot encode {path} as PNG")
    path.write_bytes(buf.tobytes())
