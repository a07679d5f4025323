"""Distillation: train a narrower (cheaper) encoder to reproduce a trained encoder's descriptor maps.

Regression on the teacher's maps needs no solver in the loop, so it takes minutes instead of the hours of
end-to-end training. The loss matches what the solver reads from a map, its values (the residual) and
its x / y differences (the Jacobian); the teacher runs through the deployed onnxruntime path, so the
student learns exactly the maps the tracker uses. A student with fewer channels than its teacher learns
the teacher's leading principal components: the solver's cost grows with the channels it compares, and
the components keep as much of the maps' variation as so few channels can.
"""

from __future__ import annotations

import os
from collections.abc import Sequence

import numpy as np
import torch

from nsflow_ros.core.encoder import OnnxEncoder
from nsflow_ros.core.errors import CoreError
from nsflow_ros.core.pyramid import Smoothing
from nsflow_ros.train.errors import TrainError

__all__ = ["Teacher", "distill_loss", "principal_components"]


def principal_components(maps: Sequence[np.ndarray], k: int) -> tuple[np.ndarray, np.ndarray]:
    """The ``k`` leading principal directions of the pixels of descriptor maps, and their mean.

    Each direction's sign is chosen so that its largest weight is positive (a reproducible choice).

    Shape:
        maps: (H, W, d) each. Returns (k, d) orthonormal rows and (d,).
    """
    pixels = np.concatenate([np.asarray(m, np.float64).reshape(-1, m.shape[-1]) for m in maps])
    if not 1 <= k <= pixels.shape[1]:
        raise TrainError(f"principal_components: k must be in [1, {pixels.shape[1]}], got {k}")
    mean = pixels.mean(axis=0)
    values, vectors = np.linalg.eigh(np.cov(pixels - mean, rowvar=False))
    top = vectors[:, np.argsort(values)[::-1][:k]].T
    top *= np.sign(top[np.arange(k), np.abs(top).argmax(axis=1)])[:, None]
    return top, mean


class Teacher:
    """A trained ONNX encoder whose descriptor maps a student learns.

    The maps are the network's own, without the smoothing the model may declare: the student declares
    its smoothing itself (``nsflow-train --smoothing``).

    Args:
        path: the teacher's ONNX file.
        channels: descriptor channels the student outputs: the teacher's, or fewer, then the teacher's
            ``channels`` leading principal components (centred) over ``fit_images``.
        in_channels: the student's input channels (must equal the teacher's).
        fit_images: uint8 images whose teacher maps fix the principal components (needed when
            ``channels`` is below the teacher's).

    Raises:
        TrainError: the file cannot be loaded, the student has other input channels or more channels, or
            fewer channels without ``fit_images``.
    """

    def __init__(
        self, path: str | os.PathLike[str], channels: int, in_channels: int,
        fit_images: Sequence[np.ndarray] = (),
    ) -> None:
        try:
            self.encoder = OnnxEncoder(path, threads=1, smoothing=Smoothing())
        except CoreError as err:
            raise TrainError(f"teacher {path}: {err}") from err
        d = self.encoder.channels
        if channels > d or self.encoder.input_channels != in_channels:
            raise TrainError(
                f"teacher {path} maps {self.encoder.input_channels} -> {d} channels, "
                f"the student {in_channels} -> {channels}"
            )
        self.projection: tuple[np.ndarray, np.ndarray] | None = None
        if channels < d:
            if not fit_images:
                raise TrainError(
                    f"a student of {channels} channels learns the principal components of teacher {path} "
                    f"({d} channels): images to fit them are needed"
                )
            self.projection = principal_components([self.encoder(im) for im in fit_images], channels)

    def __call__(self, image: np.ndarray) -> torch.Tensor:
        """The teacher's (d, H, W) descriptor map of one uint8 image (projected for a narrower student)."""
        desc = self.encoder(image)
        if self.projection is not None:
            top, mean = self.projection
            desc = ((desc - mean) @ top.T).astype(np.float32)
        return torch.from_numpy(np.ascontiguousarray(desc)).permute(2, 0, 1)


def distill_loss(student: torch.Tensor, teacher: torch.Tensor) -> torch.Tensor:
    """mean (S - T)^2 + mean (dx S - dx T)^2 + mean (dy S - dy T)^2 of student S and teacher T maps.

    Shape:
        student, teacher: (B, d, H, W) with H, W >= 2.
    """
    if student.shape != teacher.shape or student.dim() != 4:
        raise TrainError(
            f"distill_loss expects two (B, d, H, W) maps of one shape, got {tuple(student.shape)} and "
            f"{tuple(teacher.shape)}"
        )
    diff = student - teacher
    dx = diff[..., :, 1:] - diff[..., :, :-1]
    dy = diff[..., 1:, :] - diff[..., :-1, :]
    return (diff * diff).mean() + (dx * dx).mean() + (dy * dy).mean()

