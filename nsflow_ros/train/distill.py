"""Distillation: train a smaller encoder to reproduce a trained encoder's descriptor maps.

The encoder's cost at deployment is its width (see :mod:`nsflow_ros.train.model`); what the LK layer
taught a wide encoder, a narrower one can learn by regression on the wide one's output, which needs no
solver in the loop and so takes minutes instead of the hours of end-to-end training. The loss matches
what the solver reads from a descriptor map: its values (the residual f) and its x / y differences (the
Jacobian J), both as mean squared differences over the whole image:

    L = mean (S - T)^2 + mean (dx S - dx T)^2 + mean (dy S - dy T)^2

with S the student's and T the teacher's (d, H, W) maps and dx, dy forward differences. The teacher runs
through the deployed onnxruntime path (:class:`~nsflow_ros.core.encoder.OnnxEncoder`), so the student
learns exactly the maps the tracker uses today.
"""

from __future__ import annotations

import os

import numpy as np
import torch

from nsflow_ros.core.encoder import OnnxEncoder
from nsflow_ros.core.errors import CoreError
from nsflow_ros.train.data import Pair
from nsflow_ros.train.errors import TrainError
from nsflow_ros.train.model import Encoder

__all__ = ["Teacher", "distill_loss", "distill_step"]


class Teacher:
    """A trained ONNX encoder whose descriptor maps a student learns.

    Args:
        path: the teacher's ONNX file.
        channels: descriptor channels the student outputs (must equal the teacher's).
        in_channels: the student's input channels (must equal the teacher's).

    Raises:
        TrainError: the file cannot be loaded, or its channels differ from the student's.
    """

    def __init__(self, path: str | os.PathLike[str], channels: int, in_channels: int) -> None:
        try:
            self.encoder = OnnxEncoder(path, threads=1)
        except CoreError as err:
            raise TrainError(f"teacher {path}: {err}") from err
        if self.encoder.channels != channels or self.encoder.input_channels != in_channels:
            raise TrainError(
                f"teacher {path} maps {self.encoder.input_channels} -> {self.encoder.channels} channels, "
                f"the student {in_channels} -> {channels}"
            )

    def __call__(self, image: np.ndarray) -> torch.Tensor:
        """The teacher's (d, H, W) descriptor map of one uint8 image."""
        return torch.from_numpy(self.encoder(image)).permute(2, 0, 1)


def distill_loss(student: torch.Tensor, teacher: torch.Tensor) -> torch.Tensor:
    """Mean squared difference of two descriptor maps, of their x and of their y differences.

    Args:
        student: the student's maps.
        teacher: the teacher's maps (no gradient needed).

    Returns:
        the scalar loss.

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


def distill_step(model: Encoder, opt: torch.optim.Optimizer, pair: Pair, teacher: Teacher) -> float:
    """One optimisation step on both frames of a pair; returns the loss."""
    frames = (pair.image1, pair.image2)
    x = torch.from_numpy(np.stack(frames).astype(np.float32) / 255.0)[:, None]
    if model.spec.in_channels == 3:
        x = x.expand(-1, 3, -1, -1).contiguous()
    target = torch.stack([teacher(f) for f in frames])
    loss = distill_loss(model(x), target)
    opt.zero_grad()
    loss.backward()
    opt.step()
    return float(loss.item())
