"""Encoders: uint8 image in, (H, W, d) float32 descriptor map out.

Two kinds share one interface (callable on an image, with ``channels`` and ``name``):

* :class:`OnnxEncoder` runs the project's exported NSFlow encoder with onnxruntime;
* :class:`IntensityEncoder` is the classical mode: the gray image scaled to [0, 1] as a 1-channel map.
  It runs through the same solver and is the baseline of every accuracy figure.

ONNX contract (checked at load time): one float32 input of shape (1, c_in, H, W) with c_in 1 (gray) or
3 (RGB), values in [0, 1]; one float32 output of shape (1, d, H, W). Height and width may be dynamic.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Protocol, runtime_checkable

import cv2
import numpy as np

from nsflow_ros.core.errors import EncoderError

__all__ = ["DEFAULT_MODEL", "Encoder", "IntensityEncoder", "OnnxEncoder", "load_encoder", "to_gray"]

DEFAULT_MODEL = "models/nsflow_encoder.onnx"


@runtime_checkable
class Encoder(Protocol):
    """What the tracker needs from an encoder."""

    name: str
    channels: int

    def __call__(self, image: np.ndarray) -> np.ndarray: ...


def _check_image(image: np.ndarray) -> np.ndarray:
    if not isinstance(image, np.ndarray):
        raise EncoderError(f"image must be a numpy array, got {type(image).__name__}")
    if image.dtype != np.uint8:
        raise EncoderError(f"image must be uint8, got dtype {image.dtype}")
    if image.ndim == 3 and image.shape[2] == 1:
        image = image[..., 0]
    if not (image.ndim == 2 or (image.ndim == 3 and image.shape[2] == 3)):
        raise EncoderError(f"image must be (H, W) mono or (H, W, 3) BGR, got shape {image.shape}")
    if image.shape[0] < 2 or image.shape[1] < 2:
        raise EncoderError(f"image is empty or too small: shape {image.shape}")
    return image


def to_gray(image: np.ndarray) -> np.ndarray:
    """Return the (H, W) uint8 gray version of a mono or BGR uint8 image."""
    image = _check_image(image)
    return image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)


class IntensityEncoder:
    """The classical mode: image intensity / 255 as a 1-channel descriptor map."""

    name = "classical"
    channels = 1

    def __call__(self, image: np.ndarray) -> np.ndarray:
        """Encode an image.

        Args:
            image: uint8, (H, W) mono or (H, W, 3) BGR.

        Returns:
            (H, W, 1) float32 in [0, 1].
        """
        gray = to_gray(image)
        return (gray.astype(np.float32) * (1.0 / 255.0))[..., None]


class OnnxEncoder:
    """The NSFlow encoder exported to ONNX, run with onnxruntime on the CPU.

    Args:
        path: the .onnx file.
        threads: intra-op threads (None = onnxruntime's default, all cores).

    Raises:
        EncoderError: when the file is missing, is not a loadable model, or its signature is not
            (1, 1|3, H, W) float32 -> (1, d, H, W) float32.
    """

    def __init__(self, path: str | os.PathLike[str], threads: int | None = None) -> None:
        import onnxruntime as ort  # heavy import; only when an ONNX model is used

        self.path = Path(path)
        if not self.path.is_file():
            raise EncoderError(f"encoder model not found: {self.path}")
        opts = ort.SessionOptions()
        # EXTENDED beat ALL here: the NCHWc layout rewrite of ALL costs more than it saves on this
        # 1k-parameter net (752x480 gray, 2 threads: 7.1 ms vs 8.3 ms median).
        opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_EXTENDED
        if threads is not None:
            if threads < 1:
                raise EncoderError(f"threads must be >= 1, got {threads}")
            opts.intra_op_num_threads = threads
            opts.inter_op_num_threads = 1
        try:
            self._session = ort.InferenceSession(
                str(self.path), sess_options=opts, providers=["CPUExecutionProvider"]
            )
        except Exception as err:  # onnxruntime raises several unrelated types for a bad file
            raise EncoderError(f"cannot load encoder model {self.path}: {err}") from err
        inputs = self._session.get_inputs()
        outputs = self._session.get_outputs()
        expected = "one input (1, 1|3, H, W) float32 and one output (1, d, H, W) float32"
        found = (
            f"inputs {[(i.name, i.shape, i.type) for i in inputs]}, "
            f"outputs {[(o.name, o.shape, o.type) for o in outputs]}"
        )
        if len(inputs) != 1 or len(outputs) != 1:
            raise EncoderError(f"{self.path}: expected {expected}; found {found}")
        inp, out = inputs[0], outputs[0]
        if (
            inp.type != "tensor(float)"
            or out.type != "tensor(float)"
            or len(inp.shape) != 4
            or len(out.shape) != 4
            or inp.shape[1] not in (1, 3)
            or not isinstance(out.shape[1], int)
        ):
            raise EncoderError(f"{self.path}: expected {expected}; found {found}")
        self._input = inp.name
        self.input_channels = int(inp.shape[1])
        self.channels = int(out.shape[1])
        meta = self._session.get_modelmeta().custom_metadata_map
        self.name = meta.get("name", self.path.stem)
        self.metadata = dict(meta)

    def __call__(self, image: np.ndarray) -> np.ndarray:
        """Encode an image.

        Args:
            image: uint8, (H, W) mono or (H, W, 3) BGR. Mono input to an RGB model is replicated to
                three channels; colour input to a gray model is converted to gray.

        Returns:
            (H, W, d) float32 descriptor map, C-contiguous.
        """
        image = _check_image(image)
        if self.input_channels == 1:
            x = to_gray(image)[None, None].astype(np.float32)
        elif image.ndim == 2:
            x = np.broadcast_to(image[None, None], (1, 3, *image.shape)).astype(np.float32)
        else:
            x = cv2.cvtColor(image, cv2.COLOR_BGR2RGB).transpose(2, 0, 1)[None].astype(np.float32)
        x *= 1.0 / 255.0
        (out,) = self._session.run(None, {self._input: x})
        return np.ascontiguousarray(out[0].transpose(1, 2, 0))


def load_encoder(path: str | os.PathLike[str] | None = None, threads: int | None = None) -> OnnxEncoder:
    """Load an ONNX encoder; ``path=None`` means the shipped model in models/.

    Args:
        path: an .onnx file, or None for ``models/nsflow_encoder.onnx`` of the install or checkout.
        threads: onnxruntime intra-op threads (None = all cores).

    Returns:
        the encoder.

    Raises:
        EncoderError: naming the path when the model is missing or has the wrong signature.
    """
    if path is None:
        from nsflow_ros.resources import ResourceError, share_file

        try:
            path = share_file(DEFAULT_MODEL)
        except ResourceError as err:
            raise EncoderError(f"the shipped encoder {DEFAULT_MODEL} is missing: {err}") from err
    return OnnxEncoder(path, threads=threads)
