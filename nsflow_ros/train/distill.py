"""Distillation: train a narrower (cheaper) encoder to reproduce a trained encoder's descriptor maps.

Regression on the teacher's maps needs no solver in the loop, so it takes minutes instead of the hours of
end-to-end training. The loss matches what the solver reads from a map, its values (the residual) and
its x / y differences (the Jacobian); the teacher runs through the deployed onnxruntime path, so the
student learns exactly the maps the tracker uses.
"""

from __future__ import annotations

import os

import numpy as np
import torch

from nsflow_ros.core.encoder import OnnxEncoder
from nsflow_ros.core.errors import CoreError
from nsflow_ros.train.errors import TrainError

__all__ = ["Teacher", "distill_loss"]


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

