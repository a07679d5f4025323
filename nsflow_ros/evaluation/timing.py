"""Timing helpers shared by the benchmark command and the evaluation: a camera-like test sequence, the
median / p90 summary of millisecond samples, and one encoder call timed on a real-photo frame."""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from typing import Any

import cv2
import numpy as np

from nsflow_ros.core.encoder import Encoder
from nsflow_ros.evaluation.errors import EvaluationError
from nsflow_ros.optional import require

__all__ = ["make_frames", "time_encoder", "timed", "timing_stats"]


def make_frames(count: int, size: tuple[int, int] = (752, 480), seed: int = 0) -> list[np.ndarray]:
    """``count`` BGR uint8 frames of ``size`` (width, height): a smooth camera-like motion over a real
    photo (small rotations, zoom and translation per frame, seeded by ``seed``)."""
    skdata = require("skimage.data", "the benchmark's frames (a scikit-image photo)")
    w, h = size
    base = cv2.resize(cv2.cvtColor(skdata.astronaut(), cv2.COLOR_RGB2BGR), (w + 80, h + 80))
    rng = np.random.default_rng(seed)
    frames = []
    for i in range(count):
        ang = 1.5 * np.sin(0.2 * i + rng.uniform(0, 0.1))
        scale = 1.0 + 0.02 * np.sin(0.13 * i)
        m = cv2.getRotationMatrix2D(((w + 80) / 2, (h + 80) / 2), ang, scale)
        m[:, 2] += [3.0 * np.sin(0.1 * i) - 40, 2.0 * np.cos(0.17 * i) - 40]
        frames.append(cv2.warpAffine(base, m, (w, h), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT))
    return frames


def timing_stats(samples: Sequence[float]) -> dict[str, float]:
    """``{"median_ms", "p90_ms"}`` of millisecond samples (NaN for none)."""
    arr = np.asarray(samples, dtype=np.float64)
    if arr.size == 0:
        return {"median_ms": float("nan"), "p90_ms": float("nan")}
    return {"median_ms": float(np.median(arr)), "p90_ms": float(np.percentile(arr, 90))}


def timed(fn: Callable[[], Any]) -> tuple[Any, float]:
    """``fn()`` and its wall time in milliseconds."""
    t0 = time.perf_counter()
    out = fn()
    return out, (time.perf_counter() - t0) * 1e3


def time_encoder(
    encoder: Encoder, size: tuple[int, int], repeats: int, warmup: int = 1
) -> dict[str, float]:
    """``{"median_ms", "p90_ms"}`` of ``repeats`` encoder calls on a real-photo frame of ``size`` (width,
    height), after ``warmup`` untimed calls (onnxruntime allocates its buffers on the first run).

    Raises:
        EvaluationError: repeats < 1 or warmup < 0.
    """
    if repeats < 1 or warmup < 0:
        raise EvaluationError(f"repeats must be >= 1 and warmup >= 0, got {repeats} and {warmup}")
    frame = make_frames(1, size)[0]
    for _ in range(warmup):
        encoder(frame)
    return timing_stats([timed(lambda: encoder(frame))[1] for _ in range(repeats)])
