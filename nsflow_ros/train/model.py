"""The NSFlow encoder CNN: image in [0, 1] -> full-resolution d-channel descriptor map.

Architecture (the paper's at width w = 8): 3x3 conv c_in -> w, 3x3 conv w -> w, 1x1 conv w -> 2w, 1x1
conv 2w -> d, with biases and a ReLU after each of the first three convs, then the head: ``"relu"`` as in
the paper, ``"sigmoid"`` as in the authors' code (descriptors in (0, 1) like the intensity baseline the
solver's thresholds assume), or ``"none"``. The 3x3 convs pad with replicated borders, the solver's
border rule, so no artificial edge appears at the image border. No BatchNorm.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import asdict, dataclass

import torch
from torch import nn

from nsflow_ros.train.errors import TrainError

__all__ = ["HEADS", "Encoder", "EncoderSpec", "count_flops", "count_parameters"]

_HEAD_FUNCTIONS: dict[str, Callable[[torch.Tensor], torch.Tensor]] = {
    "sigmoid": torch.sigmoid,
    "relu": torch.relu,
    "none": lambda x: x,
}
HEADS = tuple(_HEAD_FUNCTIONS)


@dataclass(frozen=True)
class EncoderSpec:
    """Shape of the encoder.

    Attributes:
        d: descriptor channels.
        in_channels: 1 (gray) or 3 (RGB).
        head: nonlinearity after the last conv, one of :data:`HEADS`.
        width: channels of the two 3x3 convs (twice as many in the 1x1 hidden layer); it sets the
            encoder's run time at deployment.
    """

    d: int = 4
    in_channels: int = 1
    head: str = "sigmoid"
    width: int = 8

    def __post_init__(self) -> None:
        if self.d < 1:
            raise TrainError(f"EncoderSpec.d must be >= 1, got {self.d}")
        if self.in_channels not in (1, 3):
            raise TrainError(f"EncoderSpec.in_channels must be 1 or 3, got {self.in_channels}")
        if self.head not in HEADS:
            raise TrainError(f"EncoderSpec.head must be one of {HEADS}, got {self.head!r}")
        if self.width < 1:
            raise TrainError(f"EncoderSpec.width must be >= 1, got {self.width}")

    def as_dict(self) -> dict[str, object]:
        return asdict(self)


class Encoder(nn.Module):
    """The descriptor CNN.

    Args:
        spec: channels and head.

    Shape:
        forward: (1, c_in, H, W) float in [0, 1] -> (1, d, H, W), same H and W.
    """

    def __init__(self, spec: EncoderSpec | None = None) -> None:
        super().__init__()
        self.spec = spec or EncoderSpec()
        c, w = self.spec.in_channels, self.spec.width
        self.conv1 = nn.Conv2d(c, w, 3, padding=1, padding_mode="replicate")
        self.conv2 = nn.Conv2d(w, w, 3, padding=1, padding_mode="replicate")
        self.conv3 = nn.Conv2d(w, 2 * w, 1)
        self.conv4 = nn.Conv2d(2 * w, self.spec.d, 1)
        self.reset_parameters()

    def reset_parameters(self) -> None:
        """He-normal weights and zero biases, the head's weights doubled.

        PyTorch's default init gives an almost constant map on which LM stops at once and training never
        starts; this one gives random local filters that LK can already track.
        """
        for conv in (self.conv1, self.conv2, self.conv3, self.conv4):
            nn.init.kaiming_normal_(conv.weight, nonlinearity="relu")
            nn.init.zeros_(conv.bias)
        with torch.no_grad():
            self.conv4.weight.mul_(2.0)

    def forward(self, image: torch.Tensor) -> torch.Tensor:
        """Descriptor maps of images scaled to [0, 1].

        Shape:
            image: (B, c_in, H, W). Returns (B, d, H, W).
        """
        if image.dim() != 4 or image.shape[1] != self.spec.in_channels:
            raise TrainError(
                f"encoder expects (B, {self.spec.in_channels}, H, W) input, got {tuple(image.shape)}"
            )
        x = torch.relu(self.conv1(image))
        x = torch.relu(self.conv2(x))
        x = torch.relu(self.conv3(x))
        return _HEAD_FUNCTIONS[self.spec.head](self.conv4(x))


def count_parameters(model: nn.Module) -> int:
    """Number of trainable parameters."""
    return sum(p.numel() for p in model.parameters() if p.requires_grad)


def count_flops(spec: EncoderSpec, height: int = 240, width: int = 320) -> int:
    """Floating-point operations of one forward pass (2 per multiply-add, conv layers only)."""
    w = spec.width
    macs = (spec.in_channels * 9 * w + w * 9 * w + w * 2 * w + 2 * w * spec.d) * height * width
    return 2 * macs
