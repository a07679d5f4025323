"""Encoders: uint8 image in, (H, W, d) float32 descriptor map out.

Two kinds share one interface (callable on an image, with ``channels`` and ``name``):

* :class:`OnnxEncoder` runs the project's exported NSFlow encoder with onnxruntime;
* :class:`IntensityEncoder` is the classical mode: the gray image scaled to [0, 1] as a 1-channel map.
  It runs through the same solver and is the baseline of every accuracy figure.

ONNX contract (checked at load time): one float32 input of shape (1, c_in, H, W) with c_in 1 (gray) or
3 (RGB), values in [0, 1]; one float32 output of shape (1, d, H, W). Height and width may be dynamic.

Speed (measured at 752x480, 2 threads, the shipped d=4 model; ``nsflow-bench`` times it):

* Strips. A fully convolutional encoder is run on horizontal strips of about ``TILE_PIXELS`` pixels,
  each with ``halo`` extra rows above and below (its receptive-field radius), and only the strip's own
  rows are kept. Every kept pixel sees exactly the inputs it sees in a whole-frame run, so the result
  is the same (tested bit for bit on the shipped model), while the 8- and 16-channel intermediate maps
  of one strip stay in cache: 9.1 -> 7.8 ms per frame in the tracking pipeline. The halo is measured
  at load time, model-agnostically: flip one row of a random image and see which output rows change.
  A model whose output depends on far-away rows (pooling over the image, normalisation, attention) is
  run whole-frame; so is one whose tiled and whole runs of a second random image disagree.
* No spinning. onnxruntime's worker threads busy-wait after a run by default; on a 2-core robot computer
  that steals the CPU from the solver that runs next (solver 10.8 -> 8.6 ms per frame in the pipeline).
* The (1, d, H, W) output becomes (H, W, d) with ``cv2.merge`` (0.13 ms) instead of a NumPy transpose
  copy (1.0 ms).
"""

from __future__ import annotations

import math
import os
from pathlib import Path
from typing import Protocol, runtime_checkable

import cv2
import numpy as np

from nsflow_ros.core.errors import EncoderError

__all__ = [
    "DEFAULT_MODEL",
    "Encoder",
    "IntensityEncoder",
    "OnnxEncoder",
    "load_encoder",
    "to_gray",
]

DEFAULT_MODEL = "models/nsflow_encoder.onnx"

# Pixels per strip of a tiled run. In the tracking pipeline at 752x480 (2 threads, no spinning) 120-row
# strips were fastest: 7.8 ms against 9.1 whole-frame, 8.3 at 88 rows and 8.9 at 240. At 320x240 one
# strip (the whole frame) is best, which this size also gives.
TILE_PIXELS = 90_000
# Receptive-field radii from this many rows on count as "not local" (the shipped model's is 2).
_MAX_HALO = 32

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
        tile_rows: rows per strip of a tiled run (see the module docstring); None = about
            ``TILE_PIXELS`` pixels per strip, 0 = always run the whole frame at once. Tiling applies
            only to graphs that pass the locality check at load time (``tiled`` says whether it does).

    Raises:
        EncoderError: when the file is missing, is not a loadable model, or its signature is not
            (1, 1|3, H, W) float32 -> (1, d, H, W) float32.
    """

    def __init__(
        self, path: str | os.PathLike[str], threads: int | None = None, tile_rows: int | None = None
    ) -> None:
        import onnxruntime as ort  # heavy import; only when an ONNX model is used

        self.path = Path(path)
        if not self.path.is_file():
            raise EncoderError(f"encoder model not found: {self.path}")
        if tile_rows is not None and tile_rows < 0:
            raise EncoderError(f"tile_rows must be >= 0 or None, got {tile_rows}")
        opts = ort.SessionOptions()
        # Busy-waiting workers would compete with the solver for the robot's few cores.
        opts.add_session_config_entry("session.intra_op.allow_spinning", "0")
        # EXTENDED beat ALL and BASIC here: the NCHWc layout rewrite of ALL costs more than it saves
        # on this 1k-parameter net (752x480 gray, 2 threads: 8.4 ms vs 14.2 (ALL) and 9.6 (BASIC)).
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
        self._tile_rows = tile_rows
        self.halo: int | None = None if tile_rows == 0 else self._local_halo()

    @property
    def tiled(self) -> bool:
        """Whether frames are encoded in strips (identical results, faster; module docstring)."""
        return self.halo is not None

    def _local_halo(self) -> int | None:
        """The receptive-field radius in rows, measured; None when tiling would change the output."""
        rng = np.random.default_rng(0)
        probe, row = 2 * _MAX_HALO + 1, _MAX_HALO
        x = rng.random((1, self.input_channels, probe, 16), dtype=np.float32)
        flipped = x.copy()
        flipped[:, :, row] = 1.0 - flipped[:, :, row]
        try:
            base, moved = self._run(x), self._run(flipped)
        except Exception:  # e.g. a model that needs a minimum size: run it as it comes
            return None
        if base.shape[2:] != x.shape[2:]:
            return None
        changed = np.flatnonzero((base != moved).any(axis=(0, 1, 3)))
        halo = int(np.abs(changed - row).max()) if changed.size else 0
        if halo >= _MAX_HALO:  # the whole probe changed: not a local model
            return None
        # Cross-check on another random image cut into strips of a few rows.
        rows = 2 * halo + 3
        x = rng.random((1, self.input_channels, 3 * rows + 1, 16), dtype=np.float32)
        if not np.allclose(self._run(x), self._run_tiled(x, halo, rows), rtol=0.0, atol=1e-5):
            return None
        return halo

    def _run(self, x: np.ndarray) -> np.ndarray:
        (out,) = self._session.run(None, {self._input: x})
        return out

    def _run_tiled(self, x: np.ndarray, halo: int, rows: int) -> np.ndarray:
        h = x.shape[2]
        out: np.ndarray | None = None
        for r0 in range(0, h, rows):
            r1 = min(r0 + rows, h)
            a, b = max(r0 - halo, 0), min(r1 + halo, h)
            part = self._run(np.ascontiguousarray(x[:, :, a:b]))
            if out is None:
                out = np.empty((1, part.shape[1], h, x.shape[3]), np.float32)
            out[:, :, r0:r1] = part[:, :, r0 - a : r1 - a]
        assert out is not None
        return out

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
        h, w = x.shape[2:]
        rows = self._tile_rows or max(1, math.ceil(TILE_PIXELS / w))
        halo = self.halo
        out = self._run(x) if halo is None or rows >= h else self._run_tiled(x, halo, rows)
        # cv2.merge interleaves the planes in one fast pass; it drops a single channel's axis.
        desc = cv2.merge(list(out[0]))
        return desc if desc.ndim == 3 else desc[..., None]


def load_encoder(
    path: str | os.PathLike[str] | None = None, threads: int | None = None, tile_rows: int | None = None
) -> OnnxEncoder:
    """Load an ONNX encoder; ``path=None`` means the shipped model in models/.

    Args:
        path: an .onnx file, or None for ``models/nsflow_encoder.onnx`` of the install or checkout.
        threads: onnxruntime intra-op threads (None = all cores).
        tile_rows: rows per strip (None = automatic, 0 = whole frame); see :class:`OnnxEncoder`.

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
    return OnnxEncoder(path, threads=threads, tile_rows=tile_rows)
