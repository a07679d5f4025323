"""Inference efficiency (the paper's Table II) and the whole tracker's per-frame time per method.

Parameters and FLOPs of the ONNX encoder are counted from its graph (:func:`onnx_complexity`), the
encoder is timed at 320x240 and 752x480 beside the intensity encoder, and the whole
:class:`~nsflow_ros.core.tracker.FeatureTracker` is timed stage by stage for every evaluated method on
frames of the sample sequence. Reading the graph needs the ``onnx`` package (a dependency of nsflow_ros
with no rosdep key).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from nsflow_ros.core.encoder import Encoder, IntensityEncoder
from nsflow_ros.core.errors import CoreError
from nsflow_ros.core.tracker import FeatureTracker, TrackerSettings
from nsflow_ros.evaluation import sequences
from nsflow_ros.evaluation.context import EvalContext, axis_label, new_figure, save_figure
from nsflow_ros.evaluation.errors import EvaluationError
from nsflow_ros.evaluation.methods import CLASSICAL, NSFLOW
from nsflow_ros.evaluation.section import HeadlineRow, Section
from nsflow_ros.evaluation.targets import headline_row
from nsflow_ros.evaluation.timing import time_encoder, timing_stats
from nsflow_ros.optional import require

__all__ = [
    "PAPER_TABLE_II",
    "ModelComplexity",
    "onnx_complexity",
    "run",
    "time_tracker",
]

KEY = "efficiency"
SIZES = ((320, 240), (752, 480))
PAPER_TABLE_II = {"parameters": 1010, "gflops": 0.27, "cpu_ms_320x240": 5.21, "gpu_ms_320x240": 0.84}
"""The paper's own Table II row (RGB input, d = 3, their hardware and image size convention)."""
_COUNTED = ("Conv", "Gemm", "MatMul")


@dataclass(frozen=True)
class ModelComplexity:
    """Size and cost of an ONNX model at one input size.

    Attributes:
        parameters: elements of the initializers feeding Conv / Gemm / MatMul nodes.
        macs: multiply-accumulates of those nodes at ``size``.
        size: (width, height) of the input.
        layers: per counted node: name, op type, output shape, MACs.
    """

    parameters: int
    macs: int
    size: tuple[int, int]
    layers: list[dict[str, Any]] = field(default_factory=list)

    @property
    def flops(self) -> int:
        """2 x MACs (one multiply and one add per multiply-accumulate)."""
        return 2 * self.macs


def onnx_complexity(path: str | Path, width: int = 320, height: int = 240) -> ModelComplexity:
    """Count the parameters and MACs of an ONNX model at a ``width`` x ``height`` input.

    Parameters are the elements of every initializer feeding a ``Conv``, ``Gemm`` or ``MatMul`` node;
    MACs are, for ``Conv``, output elements x (input channels / group) x kernel area, and for ``Gemm`` /
    ``MatMul`` with an initializer operand, output elements x the inner dimension; nothing else is
    counted (the convention of ``models/README.md``). Output sizes come from one onnxruntime run with
    the counted nodes' outputs exposed, so any padding scheme is measured, not assumed.

    Args:
        path: the .onnx file; its first input must be (1, C, H, W) with C fixed.
        width, height: input size.

    Raises:
        EvaluationError: missing file, an input that is not (N, C, H, W) with a fixed C, or a model
            onnxruntime cannot run.
        MissingExtraError: no onnx package (the ``eval`` extra).
    """
    import onnxruntime as ort

    onnx = require("onnx", "counting parameters and FLOPs (it reads the ONNX graph)")
    path = Path(path)
    if not path.is_file():
        raise EvaluationError(f"ONNX model not found: {path}")
    if width < 1 or height < 1:
        raise EvaluationError(f"input size must be positive, got {width}x{height}")
    try:
        model = onnx.load(str(path))
    except Exception as err:  # onnx raises DecodeError and others, no common base class
        raise EvaluationError(f"cannot read {path} as ONNX: {err}") from err
    graph = model.graph
    inits = {t.name: tuple(int(d) for d in t.dims) for t in graph.initializer}
    counted = [n for n in graph.node if n.op_type in _COUNTED]
    used = {name for n in counted for name in n.input if name in inits}
    parameters = int(sum(int(np.prod(inits[name])) for name in used))

    real_inputs = [i for i in graph.input if i.name not in inits]
    if not real_inputs:
        raise EvaluationError(f"{path}: the graph has no input")
    dims = real_inputs[0].type.tensor_type.shape.dim
    if len(dims) != 4 or not dims[1].dim_value:
        shape = [d.dim_value or d.dim_param for d in dims]
        raise EvaluationError(f"{path}: expected an (N, C, H, W) input with a fixed C, got {shape}")
    channels = int(dims[1].dim_value)
    have = {o.name for o in graph.output}
    for n in counted:
        if n.output[0] not in have:
            graph.output.append(onnx.helper.make_tensor_value_info(n.output[0], onnx.TensorProto.FLOAT, None))
    try:
        sess = ort.InferenceSession(model.SerializeToString(), providers=["CPUExecutionProvider"])
        names = [n.output[0] for n in counted]
        outs = sess.run(names, {real_inputs[0].name: np.zeros((1, channels, height, width), np.float32)})
    except Exception as err:  # onnxruntime's errors share no public base class
        raise EvaluationError(f"{path}: onnxruntime cannot run it at {width}x{height}: {err}") from err

    layers: list[dict[str, Any]] = []
    macs = 0
    for n, out in zip(counted, outs, strict=True):
        shape = tuple(int(d) for d in out.shape)
        if n.op_type == "Conv":
            w = inits.get(n.input[1])
            if w is None:
                raise EvaluationError(f"{path}: Conv {n.name!r} has no initializer weight; cannot count it")
            # weight (C_out, C_in / group, kh, kw): each output element costs C_in / group * kh * kw MACs
            node_macs = int(np.prod(shape)) * int(np.prod(w[1:]))
        else:
            b = inits.get(n.input[1])
            if b is None or len(b) != 2:
                continue  # activation x activation products are not a layer's cost here
            trans_b = n.op_type == "Gemm" and any(a.name == "transB" and a.i for a in n.attribute)
            inner = b[1] if trans_b else b[0]
            node_macs = int(np.prod(shape)) * int(inner)
        macs += node_macs
        layers.append({"name": n.name, "op": n.op_type, "output_shape": list(shape), "macs": node_macs})
    return ModelComplexity(parameters, macs, (width, height), layers)


def time_tracker(
    frames: list[np.ndarray],
    camera: Any,
    method: str,
    *,
    settings: TrackerSettings | None = None,
    encoder: Encoder | None = None,
    dt: float = 0.05,
) -> dict[str, dict[str, float]]:
    """Per-frame time of the whole tracker, stage by stage, over a frame sequence.

    Args:
        frames: uint8 images in order.
        camera: the tracker's camera model (its size must match the frames).
        method: tracker method (a key of :data:`nsflow_ros.core.methods.METHODS`), replacing the one of
            ``settings`` (None: the defaults).
        encoder: encoder of a method that has one (None: the tracker loads its own).
        dt: seconds between frames.

    Returns:
        stage (encode, track, detect, total) -> median / p90 ms, over every frame but the first (which
        has nothing to track).

    Raises:
        EvaluationError: fewer than 2 frames, or the tracker fails.
    """
    if len(frames) < 2:
        raise EvaluationError(f"timing the tracker needs at least 2 frames, got {len(frames)}")
    try:
        tracker = FeatureTracker(
            [camera], replace(settings or TrackerSettings(), method=method), encoder=encoder
        )
        timings = [tracker.process(k * dt, img).timings for k, img in enumerate(frames)]
    except CoreError as err:
        raise EvaluationError(f"tracker {method}: {err}") from err
    stages = ("encode", "track", "detect", "total")
    return {stage: timing_stats([t.get(stage, 0.0) for t in timings[1:]]) for stage in stages}


def _figure(enc: dict[str, dict[str, dict[str, float]]], trk: dict[str, dict[str, dict[str, float]]],
            size: tuple[int, int], path: Path) -> Path:
    fig = new_figure(11, 4.2)
    ax1, ax2 = fig.subplots(1, 2)
    labels = list(next(iter(enc.values())))
    x = np.arange(len(labels))
    width = 0.8 / len(enc)
    for k, (name, per) in enumerate(enc.items()):
        med = [per[s]["median_ms"] for s in labels]
        err = [per[s]["p90_ms"] - per[s]["median_ms"] for s in labels]
        ax1.bar(x + (k - (len(enc) - 1) / 2) * width, med, width, yerr=[np.zeros(len(med)), err], capsize=3,
                label=name)
    ax1.set_xticks(x, labels)
    ax1.set_ylabel("ms (median, bar to p90)")
    ax1.set_title("encoder alone (onnxruntime, CPU)")
    ax1.legend(fontsize=8)
    ax1.grid(axis="y", alpha=0.3)
    names = [axis_label(n) for n in trk]
    bottom = np.zeros(len(names))
    for stage in ("encode", "track", "detect"):
        vals = np.array([trk[m][stage]["median_ms"] for m in trk])
        ax2.bar(names, vals, 0.6, bottom=bottom, label=stage)
        bottom += vals
    # the rest of the frame: gray conversion, undistortion, velocities, the mask
    other = np.maximum(np.array([trk[m]["total"]["median_ms"] for m in trk]) - bottom, 0.0)
    ax2.bar(names, other, 0.6, bottom=bottom, label="other", color="0.7")
    ax2.tick_params(axis="x", labelsize=8)
    ax2.set_ylabel("ms per frame (median per stage)")
    ax2.set_title(f"whole tracker per frame, {size[0]}x{size[1]}")
    ax2.legend(fontsize=8)
    ax2.grid(axis="y", alpha=0.3)
    fig.tight_layout()
    return save_figure(fig, path)


def run(ctx: EvalContext) -> Section:
    """The ``efficiency`` section: Table II (with the paper's row), the tracker's per-frame times, a figure.

    ``ctx.extra["efficiency"]`` may hold ``repeats`` (encoder runs) and ``frames`` (tracker frames).

    Raises:
        EvaluationError: no ONNX model, or a run that fails.
        MissingExtraError: no onnx package (the ``eval`` extra).
    """
    opts = dict(ctx.extra.get(KEY, {}))
    repeats = int(opts.get("repeats", 3 if ctx.quick else 50))
    warmup = 1 if ctx.quick else 5
    n_frames = int(opts.get("frames", 0 if ctx.quick else 40))  # 0: the whole (quick) sequence
    encoder = sequences.method_encoders(ctx, [NSFLOW])[NSFLOW]
    model_path = Path(encoder.path)  # type: ignore[attr-defined]
    counts = {f"{w}x{h}": onnx_complexity(model_path, w, h) for w, h in SIZES}
    enc_times = _time_encoders(ctx, {NSFLOW: encoder, "intensity": IntensityEncoder()}, repeats, warmup)
    setup = sequences.QUICK if ctx.quick else sequences.FULL
    source = sequences.load_source(ctx, setup)
    count = len(source) if n_frames <= 0 else min(n_frames, len(source))
    tracker_times = _time_trackers(ctx, source, count, setup)
    fig = _figure(enc_times, tracker_times, source.size, Path(ctx.out_dir) / f"{KEY}_times.png")
    size_txt = f"{source.size[0]}x{source.size[1]}"
    threads = "all usable cores" if ctx.threads is None else str(ctx.threads)
    quick = " Quick mode: few runs on tiny frames, the times are not meaningful." if ctx.quick else ""
    md = "\n\n".join([
        f"Encoder `{model_path.name}`; FLOPs = 2 x multiply-adds of the Conv/Gemm/MatMul nodes, counted from "
        "the ONNX graph (biases, activations and padding not counted); parameters = elements of their "
        f"initializers. Times: {repeats} runs after {warmup} warm-up, threads {threads}.{quick}",
        _encoder_table(encoder, counts, enc_times),
        f"Whole `FeatureTracker` per frame on {count - 1} frames of the sample sequence ({size_txt}, max_cnt "
        f"{setup.max_cnt}, flow-back on; first frame left out), every stage timed inside the tracker:",
        _tracker_table(tracker_times),
        f"![efficiency]({fig.name})",
    ])
    c320 = counts["320x240"]
    headline = [
        HeadlineRow("encoder parameters / GFLOPs at 320x240",
                    {NSFLOW: f"{c320.parameters:,} / {c320.flops / 1e9:.3f}"}),
        HeadlineRow("encoder CPU ms at 320x240 (median)",
                    {NSFLOW: f"{enc_times[NSFLOW]['320x240']['median_ms']:.2f}",
                     CLASSICAL: f"{enc_times['intensity']['320x240']['median_ms']:.2f}"}),
        headline_row(f"whole tracker ms per frame at {size_txt} (median)",
                     {name: st["total"]["median_ms"] for name, st in tracker_times.items()}, "{:.1f}".format),
    ]
    data = {
        "model": str(model_path),
        "complexity": {k: {"parameters": c.parameters, "macs": c.macs, "flops": c.flops, "layers": c.layers}
                       for k, c in counts.items()},
        "encoder_ms": enc_times,
        "tracker_ms": tracker_times,
        "setup": {"repeats": repeats, "warmup": warmup, "tracker_frames": count, "size": list(source.size),
                  "threads": ctx.threads, "quick": ctx.quick},
        "paper_table_ii": PAPER_TABLE_II,
    }
    return Section(KEY, "Inference efficiency (Table II) and per-frame time", md, [fig], headline, data)


def _time_encoders(ctx: EvalContext, encoders: dict[str, Encoder], repeats: int,
                   warmup: int) -> dict[str, dict[str, dict[str, float]]]:  # fmt: skip
    """Each encoder's time per size: name -> "WxH" -> median / p90 ms."""
    enc_times: dict[str, dict[str, dict[str, float]]] = {name: {} for name in encoders}
    jobs = [(name, size) for size in SIZES for name in encoders]
    for name, (w, h) in ctx.bar(jobs, desc="efficiency: encoders", unit="size"):
        try:
            enc_times[name][f"{w}x{h}"] = time_encoder(encoders[name], (w, h), repeats, warmup)
        except CoreError as err:
            raise EvaluationError(f"{name} encoder at {w}x{h}: {err}") from err
    return enc_times


def _time_trackers(
    ctx: EvalContext, source: sequences.FrameSource, count: int, setup: sequences.SequenceSetup
) -> dict[str, dict[str, dict[str, float]]]:
    """The whole tracker's stage times on the first ``count`` frames, per compared method."""
    frames = [source.image(i) for i in range(count)]
    settings = setup.tracker_settings(ctx)
    known = sequences.TRACKER_METHODS
    kinds = {m.name: known[m.name] for m in ctx.methods if m.name in known}
    encoders = sequences.method_encoders(ctx, list(kinds))
    tracker_times: dict[str, dict[str, dict[str, float]]] = {}
    for name in ctx.bar(list(kinds), desc="efficiency: tracker", unit="method"):
        per = settings.with_overrides(kinds[name])
        tracker_times[name] = time_tracker(frames, source.camera, per.method, settings=per,
                                           encoder=encoders.get(name))  # fmt: skip
    return tracker_times


def _ms(st: dict[str, float]) -> str:
    """Median / p90 ms as a table cell."""
    return f"{st['median_ms']:.2f} / {st['p90_ms']:.2f}"


def _encoder_table(encoder: Encoder, counts: dict[str, ModelComplexity], enc_times: dict) -> str:
    """Table II: NSFlow's and the intensity encoder's size, cost and time, with the paper's row."""
    c320 = counts["320x240"]
    return "\n".join([
        "| encoder | parameters | GFLOPs 320x240 | GFLOPs 752x480 | CPU ms 320x240 (median / p90) "
        "| CPU ms 752x480 (median / p90) |",
        "|---|---|---|---|---|---|",
        f"| NSFlow ({encoder.name}, d={encoder.channels}) | {c320.parameters:,} | {c320.flops / 1e9:.3f} "
        f"| {counts['752x480'].flops / 1e9:.3f} | {_ms(enc_times[NSFLOW]['320x240'])} "
        f"| {_ms(enc_times[NSFLOW]['752x480'])} |",
        f"| intensity (classical baseline) | 0 | 0 | 0 | {_ms(enc_times['intensity']['320x240'])} "
        f"| {_ms(enc_times['intensity']['752x480'])} |",
        f"| paper, Table II (RGB, d=3, their CPU) | {PAPER_TABLE_II['parameters']:,} "
        f"| {PAPER_TABLE_II['gflops']} | - | {PAPER_TABLE_II['cpu_ms_320x240']} | - |",
    ])


def _tracker_table(tracker_times: dict[str, dict[str, dict[str, float]]]) -> str:
    """Each method's median time per tracker stage."""
    rows = [
        "| method | encode ms | track + flow-back ms | detect ms | total ms (median / p90; the rest is gray "
        "conversion, undistortion, mask) |",
        "|---|---|---|---|---|",
    ]
    for name, st in tracker_times.items():
        rows.append(f"| {name} | {st['encode']['median_ms']:.2f} | {st['track']['median_ms']:.2f} "
                    f"| {st['detect']['median_ms']:.2f} | {_ms(st['total'])} |")  # fmt: skip
    return "\n".join(rows)
