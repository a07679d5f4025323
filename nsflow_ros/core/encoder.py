"""Encoders: uint8 image in, (H, W, d) float32 descriptor map out.

:class:`OnnxEncoder` runs the exported NSFlow encoder with onnxruntime; :class:`IntensityEncoder` is the
classical mode, the gray image scaled to [0, 1]. ONNX contract, checked at load time: one float32 input
(1, 1|3, H, W) in [0, 1] and one float32 output (1, d, H, W); H and W may be dynamic.

On the CPU with several threads a local model runs on horizontal strips with a halo of its
receptive-field radius (measured at load time), one single-threaded, non-spinning session per thread: the
whole-frame result, in less wall time than one multi-threaded session. One thread (the tracker's default)
encodes the whole frame in one session: with nothing to run in parallel the halos would only cost; a
narrow model does so in its band layout where one ships beside it (:mod:`~nsflow_ros.core.bands`).
On an accelerator (:class:`ExecutionProviders`) one session encodes the whole frame, launch overhead
dominating there. A model may declare in its metadata key ``smoothing`` ("fine,coarse" sigmas,
:class:`~nsflow_ros.core.pyramid.Smoothing`) how its maps are smoothed: the encoder applies ``fine`` to
its output, the LM methods ``coarse`` to the pyramid's coarser levels. Its key ``gain_levels`` (an
integer, 0 when absent) asks the LM methods to compare windows up to a gain as well as an offset on that
many of the finest pyramid levels (:attr:`~nsflow_ros.core.solver.LMConfig.gain_levels`): a one-channel
map cannot carry the invariance to contrast that several channels can.
"""

from __future__ import annotations

import json
import logging
import math
import os
from collections.abc import Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from types import MappingProxyType
from typing import Any, Protocol, runtime_checkable

import cv2
import numpy as np

from nsflow_ros.core.bands import BandLayout, bands_file
from nsflow_ros.core.errors import CoreError, EncoderError
from nsflow_ros.core.pyramid import MAX_CHUNK, Smoothing, gaussian_kernel

__all__ = [
    "CPU_PROVIDER",
    "DEFAULT_MODEL",
    "PROVIDER_NAMES",
    "SHIPPED_MODELS",
    "Encoder",
    "ExecutionProviders",
    "IntensityEncoder",
    "OnnxEncoder",
    "encoder_provider",
    "load_encoder",
    "model_file",
    "to_gray",
]

DEFAULT_MODEL = "models/nsflow_encoder_fast.onnx"

SHIPPED_MODELS: Mapping[str, str] = MappingProxyType({
    "default": DEFAULT_MODEL,
    "fast": DEFAULT_MODEL,
    "d4": "models/nsflow_encoder.onnx",
})
"""The encoders shipped in models/, by the names :func:`load_encoder` (and the node's ``model_path``) takes
for them: ``default`` (also ``fast``, its earlier name), one channel from a narrow network whose LM solve
also fits a gain on the finest level (metadata ``gain_levels``), the model that keeps up beside an
estimator on a small computer; ``d4``, the paper's four-channel descriptors, about 1.6 times the CPU per
frame, for a GPU provider or many cores, and the model ``nsflow_lk`` loads (its descriptors are in
[0, 1]). models/README.md has both cards."""

# Pixels per strip of a tiled run: large enough to amortise the halo, small enough to stay in cache.
TILE_PIXELS = 60_000
# Receptive-field radii from this many rows on count as "not local" (the shipped model's is 2).
_MAX_HALO = 32

_log = logging.getLogger(__name__)

CPU_PROVIDER = "CPUExecutionProvider"
"""onnxruntime's CPU execution provider, in every build."""

PROVIDER_NAMES: Mapping[str, str] = {
    "cpu": CPU_PROVIDER,
    "cuda": "CUDAExecutionProvider",
    "tensorrt": "TensorrtExecutionProvider",
    "openvino": "OpenVINOExecutionProvider",
    "coreml": "CoreMLExecutionProvider",
    "rocm": "ROCMExecutionProvider",
    "migraphx": "MIGraphXExecutionProvider",
    "directml": "DmlExecutionProvider",
    "dnnl": "DnnlExecutionProvider",
    "qnn": "QNNExecutionProvider",
    "xnnpack": "XnnpackExecutionProvider",
}
"""Short provider names (what the ``providers`` setting takes) -> onnxruntime's names."""

_TENSORRT = PROVIDER_NAMES["tensorrt"]


@dataclass(frozen=True)
class ExecutionProviders:
    """Where the encoder runs: onnxruntime execution providers in order of preference, and their options.

    Attributes:
        names: onnxruntime provider names, best first.
        tensorrt_fp16: let TensorRT build half-precision engines.
        tensorrt_cache: folder where TensorRT keeps its engines between runs; None = no cache.

    Raises:
        EncoderError: an empty list or a name that is not an onnxruntime provider name.
    """

    names: tuple[str, ...] = (CPU_PROVIDER,)
    tensorrt_fp16: bool = False
    tensorrt_cache: str | None = None

    def __post_init__(self) -> None:
        if not self.names:
            raise EncoderError("the execution provider list is empty; give at least one, e.g. 'cpu'")
        for name in self.names:
            if not (isinstance(name, str) and name.endswith("ExecutionProvider")):
                raise EncoderError(f"{name!r} is not an onnxruntime execution provider name")

    @classmethod
    def parse(
        cls,
        providers: str | Sequence[str] | ExecutionProviders | None,
        *,
        tensorrt_fp16: bool = False,
        tensorrt_cache: str | None = None,
    ) -> ExecutionProviders:
        """Read a provider list: ``"tensorrt,cuda,cpu"``, ``["cuda", "CPUExecutionProvider"]``.

        Args:
            providers: short names (:data:`PROVIDER_NAMES`, any case) or onnxruntime names, as
                comma-separated text or a sequence; returned as it is if parsed already; None or "" = CPU.

        Raises:
            EncoderError: an unknown short name (the known ones are listed) or an empty list.
        """
        if isinstance(providers, ExecutionProviders):
            return providers
        if providers is None or (isinstance(providers, str) and not providers.strip()):
            items: list[str] = ["cpu"]
        elif isinstance(providers, str):
            items = [p.strip() for p in providers.split(",")]
        else:
            items = [str(p).strip() for p in providers]
        names: list[str] = []
        for item in items:
            if not item:
                raise EncoderError(f"empty name in the execution provider list {providers!r}")
            name = item if item.endswith("ExecutionProvider") else PROVIDER_NAMES.get(item.lower())
            if name is None:
                raise EncoderError(
                    f"unknown execution provider {item!r}; short names: {', '.join(PROVIDER_NAMES)}, "
                    "or onnxruntime's full names (e.g. CUDAExecutionProvider)"
                )
            if name not in names:
                names.append(name)
        return cls(tuple(names), tensorrt_fp16=bool(tensorrt_fp16), tensorrt_cache=tensorrt_cache or None)

    def available(self) -> tuple[str, ...]:
        """The requested providers this onnxruntime has, in order; warns of the others.

        Raises:
            EncoderError: none of them is installed (one line naming the installed ones).
        """
        import onnxruntime as ort

        installed = ort.get_available_providers()
        usable = tuple(n for n in self.names if n in installed)
        if not usable:
            raise EncoderError(
                f"none of the execution providers {', '.join(self.names)} is in this onnxruntime "
                f"(installed: {', '.join(installed)})"
            )
        missing = [n for n in self.names if n not in installed]
        if missing:
            _log.warning(
                "execution provider(s) %s not in this onnxruntime (installed: %s); using %s",
                ", ".join(missing), ", ".join(installed), usable[0],
            )
        return usable

    def session_providers(self, usable: Sequence[str]) -> list[Any]:
        """onnxruntime's ``providers`` argument for ``usable``: names, with TensorRT's options attached."""
        out: list[Any] = []
        for name in usable:
            if name == _TENSORRT:
                options = {"trt_fp16_enable": str(self.tensorrt_fp16)}
                if self.tensorrt_cache:
                    options["trt_engine_cache_enable"] = "True"
                    options["trt_engine_cache_path"] = self.tensorrt_cache
                out.append((name, options))
            else:
                out.append(name)
        return out


@runtime_checkable
class Encoder(Protocol):
    """What the tracker needs from an encoder."""

    name: str
    channels: int
    smoothing: Smoothing  # the fine part is already applied to the returned map
    gain_levels: int  # finest levels on which the LM methods also fit a gain (0 = none)

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
    """The classical mode: image intensity / 255 as a (H, W, 1) float32 descriptor map."""

    name = "classical"
    channels = 1
    input_channels = 1
    smoothing = Smoothing()  # intensity is tracked as it is
    gain_levels = 0  # the deployed zero-mean residual, as the classical mode has always been measured
    provider = "none"  # NumPy, no onnxruntime session

    def __call__(self, image: np.ndarray) -> np.ndarray:
        gray = to_gray(image)
        return (gray.astype(np.float32) * (1.0 / 255.0))[..., None]


def _output(h: int, w: int, d: int) -> np.ndarray:
    """The C-contiguous block an encoder output is merged into: (h, w, d), or (h, w, 4) for 2-3 channels,
    which the descriptor pyramid samples padded (:func:`~nsflow_ros.core.pyramid.sampling_source`)."""
    return np.empty((h, w, MAX_CHUNK if 1 < d < MAX_CHUNK else d), np.float32)


def _merge_into(planes: list[np.ndarray], dst: np.ndarray) -> None:
    """Interleave d (h, w) planes into the C-contiguous (h, w, d) block ``dst`` in one pass; a 4-channel
    ``dst`` of 2-3 planes gets copies of the leading planes as its padding."""
    if len(planes) == 1:
        dst[..., 0] = planes[0]
        return
    planes = (planes * 2)[: dst.shape[2]]
    if not np.shares_memory(cv2.merge(planes, dst=dst), dst):  # cv2 wrote elsewhere: copy
        dst[...] = cv2.merge(planes)


class OnnxEncoder:
    """The NSFlow encoder exported to ONNX, run with onnxruntime (on the CPU unless told otherwise).

    Args:
        path: the .onnx file.
        threads: CPU threads (None = the cores this process may use): one session per thread for a
            tiled model, else one session with that many intra-op threads.
        tile_rows: rows per strip; None = about ``TILE_PIXELS`` pixels with several CPU threads, else the
            whole frame; 0 = the whole frame at once. Only models that pass the locality check at load
            time are tiled (``tiled``).
        smoothing: None = what the model's metadata declares; ``Smoothing()`` turns it off.
        providers: execution providers, best first (:meth:`ExecutionProviders.parse`); None = the CPU.
            ``provider`` is the one in use.
        bands: run whole frames on the CPU in the model's band layout where one ships beside it
            (:mod:`~nsflow_ros.core.bands`; the same output, in less time); False = the model's own graph.

    Raises:
        EncoderError: a missing or unloadable file, a wrong signature, malformed ``smoothing`` or
            ``gain_levels`` metadata, or none of the providers installed.
    """

    def __init__(
        self, path: str | os.PathLike[str], threads: int | None = None, tile_rows: int | None = None,
        smoothing: Smoothing | None = None, providers: ExecutionProviders | str | Sequence[str] | None = None,
        bands: bool = True,
    ) -> None:
        self.path = Path(path)
        if not self.path.is_file():
            raise EncoderError(f"encoder model not found: {self.path}")
        if threads is not None and threads < 1:
            raise EncoderError(f"threads must be >= 1, got {threads}")
        if tile_rows is not None and tile_rows < 0:
            raise EncoderError(f"tile_rows must be >= 0 or None, got {tile_rows}")
        self.threads = threads or _usable_cores()
        self.providers = ExecutionProviders.parse(providers)
        self._sessions = [self._start_session(self.providers.available())]
        self.provider: str = self._sessions[0].get_providers()[0]
        if tile_rows is None and (self.provider != CPU_PROVIDER or self.threads == 1):
            tile_rows = 0  # whole frame on an accelerator or on one thread (module docstring)
        self._tile_rows = tile_rows
        self._pool: ThreadPoolExecutor | None = None
        self._check_signature()
        if smoothing is not None and not isinstance(smoothing, Smoothing):
            raise EncoderError(f"smoothing must be a Smoothing or None, got {smoothing!r}")
        self.smoothing = self._declared_smoothing() if smoothing is None else smoothing
        # The last layer's activation (nsflow-train's metadata 'spec'); None when undeclared.
        self.head: str | None = self._declared_head()
        self.gain_levels: int = self._declared_gain_levels()
        fine = self.smoothing.fine
        self._kernel = gaussian_kernel(fine) if fine > 0 else None
        self.halo: int | None = None if tile_rows == 0 else self._local_halo()
        if self.threads > 1 and self.provider == CPU_PROVIDER:
            if self.halo is None:
                self._sessions = [self._new_session(self.threads)]
            else:
                self._sessions += [self._new_session(1) for _ in range(self.threads - 1)]
                # the calling thread encodes its own share of strips; the pool runs the others
                self._pool = ThreadPoolExecutor(self.threads - 1, thread_name_prefix="nsflow-encoder")
        # A one-channel model encoding whole frames on the CPU runs in its band layout where one ships.
        self._bands: BandLayout | None = None
        if bands and self.provider == CPU_PROVIDER and self.halo is None and self.input_channels == 1:
            self._bands = self._load_bands()

    def _start_session(self, usable: Sequence[str]) -> Any:
        """The first session: one CPU thread on the CPU, else the best usable provider with ``threads``
        threads, back to the CPU when it cannot start."""
        self._session_providers: list[Any] = [CPU_PROVIDER]
        if usable[0] == CPU_PROVIDER:
            return self._new_session(1)
        self._session_providers = self.providers.session_providers(usable)
        session = self._new_session(self.threads)
        used = session.get_providers()[0]
        if used != usable[0]:  # installed but could not start (no GPU, driver): onnxruntime fell back
            _log.warning("execution provider %s could not start; using %s", usable[0], used)
        if used == CPU_PROVIDER:
            self._session_providers = [CPU_PROVIDER]
            return self._new_session(1)
        return session

    def _new_session(self, threads: int, path: Path | None = None, blocked: bool = False) -> Any:
        """An onnxruntime session of ``path`` (None = the model) with ``threads`` intra-op threads.

        ``blocked`` allows onnxruntime's blocked-channel (NCHWc) rewrite: it pays on the band layout's
        many channels, and costs more than it saves on the one-channel original.
        """
        import onnxruntime as ort  # heavy import; only when an ONNX model is used

        path = path or self.path
        opts = ort.SessionOptions()
        # Busy-waiting workers would compete with the solver for the robot's few cores.
        opts.add_session_config_entry("session.intra_op.allow_spinning", "0")
        level = ort.GraphOptimizationLevel
        opts.graph_optimization_level = level.ORT_ENABLE_ALL if blocked else level.ORT_ENABLE_EXTENDED
        opts.intra_op_num_threads = threads
        opts.inter_op_num_threads = 1
        try:
            return ort.InferenceSession(str(path), sess_options=opts, providers=self._session_providers)
        except Exception as err:  # onnxruntime raises several unrelated types for a bad file
            raise EncoderError(f"cannot load encoder model {path}: {err}") from err

    def _load_bands(self) -> BandLayout | None:
        """The model's band layout (:mod:`~nsflow_ros.core.bands`) when its sibling file exists and
        reproduces the model on a probe image; None otherwise (a mismatch is logged)."""
        path = bands_file(self.path)
        if not path.is_file():
            return None
        try:
            layout = BandLayout(self._new_session(self.threads, path, blocked=True), self.channels, self._run)
        except EncoderError as err:
            _log.warning("ignoring the band layout %s: %s", path, err)
            return None
        # A height that is no multiple of the bands, so that the last band's border is probed too.
        probe = np.random.default_rng(0).integers(0, 256, (4 * layout.bands + 5, 24), dtype=np.uint8)
        x = probe[None, None].astype(np.float32) * np.float32(1.0 / 255.0)
        if not np.allclose(layout(probe), self._run(x), rtol=1e-5, atol=1e-5):
            _log.warning("ignoring the band layout %s: it does not reproduce %s", path, self.path.name)
            return None
        return layout

    @property
    def layout(self) -> str:
        """How frames are encoded: "bands" (:mod:`~nsflow_ros.core.bands`), "strips" (one session per
        thread) or "whole frame"."""
        if self._bands is not None:
            return "bands"
        return "strips" if self.tiled else "whole frame"

    def _check_signature(self) -> None:
        session = self._sessions[0]
        inputs = session.get_inputs()
        outputs = session.get_outputs()
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
        meta = session.get_modelmeta().custom_metadata_map
        self.name = meta.get("name", self.path.stem)
        self.metadata = dict(meta)

    def _declared_smoothing(self) -> Smoothing:
        text = self.metadata.get("smoothing")
        if text is None:
            return Smoothing()
        try:
            fine, coarse = (float(v) for v in text.split(","))
            return Smoothing(fine, coarse)
        except (ValueError, CoreError) as err:
            msg = f"{self.path}: metadata 'smoothing' must be 'fine,coarse' (two sigmas >= 0), got {text!r}"
            raise EncoderError(msg) from err

    def _declared_gain_levels(self) -> int:
        text = self.metadata.get("gain_levels", "0")
        try:
            levels = int(text)
        except ValueError:
            levels = -1
        if levels < 0:
            raise EncoderError(f"{self.path}: metadata 'gain_levels' must be an integer >= 0, got {text!r}")
        return levels

    def _declared_head(self) -> str | None:
        try:
            head = json.loads(self.metadata["spec"]).get("head")
        except (KeyError, ValueError, AttributeError):
            return None
        return head if isinstance(head, str) else None

    def _planes(self, out: np.ndarray, rows: slice) -> list[np.ndarray]:
        """The (h, w) planes of an encoder output (1, d, h, w), smoothed as declared, cut to ``rows``."""
        k = self._kernel
        if k is None:
            return [p[rows] for p in out[0]]
        return [cv2.sepFilter2D(p, cv2.CV_32F, k, k, borderType=cv2.BORDER_REPLICATE)[rows] for p in out[0]]

    def _write(self, out: np.ndarray, dst: np.ndarray) -> None:
        """A whole encoder output (1, d, h, w), smoothed as declared, into the output block ``dst``; one
        smoothed plane is filtered straight into its place (no copy of the plane)."""
        k = self._kernel
        if k is None or out.shape[1] != 1:
            _merge_into(self._planes(out, slice(None)), dst)
            return
        plane = dst[..., 0]
        done = cv2.sepFilter2D(out[0, 0], cv2.CV_32F, k, k, dst=plane, borderType=cv2.BORDER_REPLICATE)
        if not np.shares_memory(done, plane):  # cv2 wrote elsewhere
            plane[...] = done

    @property
    def tiled(self) -> bool:
        """Whether frames are encoded in strips."""
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
        whole = self._run(x)[0].transpose(1, 2, 0)
        if not np.allclose(whole, self._run_tiled(x, halo, rows), rtol=0.0, atol=1e-5):
            return None
        return halo

    def _run(self, x: np.ndarray, worker: int = 0) -> np.ndarray:
        (out,) = self._sessions[worker].run(None, {self._input: x})
        return out

    def _run_tiled(self, x: np.ndarray, halo: int, rows: int, smooth: bool = False) -> np.ndarray:
        """Encode (1, c, H, W) in strips of ``rows`` rows with ``halo`` rows of context: (H, W, d).

        With ``smooth`` each strip is smoothed before it is cut; ``halo`` must include the kernel's radius.
        """
        h, w = x.shape[2:]
        out = _output(h, w, self.channels)
        starts = range(0, h, rows)

        def strips(worker: int) -> None:
            for r0 in starts[worker :: len(self._sessions)]:
                r1 = min(r0 + rows, h)
                a, b = max(r0 - halo, 0), min(r1 + halo, h)
                part = self._run(np.ascontiguousarray(x[:, :, a:b]), worker)
                rows_kept = slice(r0 - a, r1 - a)
                planes = self._planes(part, rows_kept) if smooth else [p[rows_kept] for p in part[0]]
                _merge_into(planes, out[r0:r1])

        # onnxruntime releases the GIL, so the workers' strips run in parallel with the caller's.
        pool = self._pool
        jobs = [] if pool is None else [pool.submit(strips, k) for k in range(1, len(self._sessions))]
        strips(0)
        for job in jobs:
            job.result()
        return out[..., : self.channels]

    def __call__(self, image: np.ndarray) -> np.ndarray:
        """Encode a uint8 (H, W) mono or (H, W, 3) BGR image into an (H, W, d) float32 map: C-contiguous for
        1 or 4 channels, else the leading channels of a C-contiguous 4-channel block (the pyramid's
        padded layout, sampled without a copy).

        Mono input to an RGB model is replicated to three channels; colour input to a gray model is grayed.
        """
        image = _check_image(image)
        if self._bands is not None:
            gray = to_gray(image)
            if self._bands.fits(*gray.shape):
                out = _output(*gray.shape, self.channels)
                self._write(self._bands(gray), out)
                return out[..., : self.channels]
        if self.input_channels == 1:
            x = to_gray(image)[None, None].astype(np.float32)
        elif image.ndim == 2:
            x = np.broadcast_to(image[None, None], (1, 3, *image.shape)).astype(np.float32)
        else:
            x = cv2.cvtColor(image, cv2.COLOR_BGR2RGB).transpose(2, 0, 1)[None].astype(np.float32)
        x *= 1.0 / 255.0
        h, w = x.shape[2:]
        halo = self.halo
        if halo is None:
            out = _output(h, w, self.channels)
            self._write(self._run(x), out)
            return out[..., : self.channels]
        # Strips of about TILE_PIXELS, and at least one per worker.
        rows = self._tile_rows or max(1, min(math.ceil(TILE_PIXELS / w), math.ceil(h / self.threads)))
        k = self._kernel
        if k is None:
            return self._run_tiled(x, halo, rows)
        return self._run_tiled(x, halo + len(k) // 2, rows, smooth=True)


def _usable_cores() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


def encoder_provider(encoder: Encoder | None) -> str:
    """The onnxruntime execution provider an encoder runs on ("none": no onnxruntime session, no encoder)."""
    return "none" if encoder is None else str(getattr(encoder, "provider", "none"))


def load_encoder(
    path: str | os.PathLike[str] | None = None, threads: int | None = None, tile_rows: int | None = None,
    smoothing: Smoothing | None = None, providers: ExecutionProviders | str | Sequence[str] | None = None,
    bands: bool = True,
) -> OnnxEncoder:
    """Load an ONNX encoder (:class:`OnnxEncoder`): a file, or a shipped model by its name in
    :data:`SHIPPED_MODELS`; ``path=None`` means the default one.

    Raises:
        EncoderError: naming the path when the model is missing or has the wrong signature, or naming
            the installed providers when none of ``providers`` is.
    """
    return OnnxEncoder(
        model_file(path), threads=threads, tile_rows=tile_rows, smoothing=smoothing, providers=providers,
        bands=bands,
    )


def model_file(path: str | os.PathLike[str] | None = None) -> Path:
    """The file of an encoder: a shipped model's by its name in :data:`SHIPPED_MODELS` (None = the
    default), else ``path`` itself.

    Raises:
        EncoderError: a shipped model whose file is missing from the install.
    """
    shipped = DEFAULT_MODEL if path is None else SHIPPED_MODELS.get(os.fspath(path))
    if shipped is None:
        return Path(path)  # type: ignore[arg-type]
    from nsflow_ros.resources import ResourceError, share_file

    try:
        return share_file(shipped)
    except ResourceError as err:
        raise EncoderError(f"the shipped encoder {shipped} is missing: {err}") from err
