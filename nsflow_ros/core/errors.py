"""Errors of the tracking core."""

from __future__ import annotations

from nsflow_ros.errors import NSFlowError

__all__ = ["CoreError", "EncoderError", "UnsupportedEncoderError"]


class CoreError(NSFlowError):
    """Bad input to the tracking core (shapes, dtypes, settings)."""


class EncoderError(CoreError):
    """An encoder model cannot be loaded or run (missing file, wrong ONNX signature, bad image)."""


class UnsupportedEncoderError(CoreError):
    """A tracking method cannot track a (valid) encoder's descriptors, e.g. OpenCV's LK unbounded ones."""
