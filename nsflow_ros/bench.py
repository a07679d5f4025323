"""Speed benchmark of the tracking core, with OpenCV's pyramidal KLT measured side by side.

``nsflow-bench`` (or ``ros2 run nsflow_ros bench``) times, per frame of a 752x480 real-texture sequence
with 150 fresh GFTT points: the encoder, the LM solver (pyramid build + the tracker's solve from zero
flow) and GFTT detection, for the registry's ``nsflow`` and ``classical`` methods exactly as the tracker
builds them (:func:`nsflow_ros.core.methods.make_method`), and in the same run the registry's ``klt``
(OpenCV's ``calcOpticalFlowPyrLK`` as VINS-Fusion calls it) plus GFTT. The methods take turns frame by
frame, so a drifting machine load hits them alike. It also times the encoder alone at 320x240 and
752x480 (the paper's Table II sizes). Medians and 90th percentiles in milliseconds; with ``--json`` the
figures are printed as one JSON object. First of all it runs the whole VINS-style tracker per frame,
mono and stereo, every tracking method interleaved with ``klt``, and reports time, ratio to ``klt`` and
track quality (:mod:`nsflow_ros.tracker_bench`). A solver cost model (:func:`solver_cost_model`) splits
each LM method's solver time into passes x a fixed price per pass and point evaluations x a price per
point, fitted on the same frames: where the time goes, and so what any optimisation can save."""

from __future__ import annotations

import argparse
import functools
import json
import os
import platform
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from nsflow_ros.allocator import keep_large_buffers
from nsflow_ros.argtypes import (
    method_variants,
    names,
    non_negative_float,
    non_negative_int,
    positive_int,
    program_name,
)
from nsflow_ros.core import detect_corners, load_encoder, to_gray
from nsflow_ros.core.methods import LMMethod, SolveKind, make_method
from nsflow_ros.core.tracker import GFTT_QUALITY
from nsflow_ros.data.perturb import PERTURBATIONS
from nsflow_ros.errors import NSFlowError
from nsflow_ros.evaluation.timing import make_frames, time_encoder, timing_stats
from nsflow_ros.evaluation.timing import timed as _timed
from nsflow_ros.optional import require
from nsflow_ros.results import command_line, run_header, table, write_tables
from nsflow_ros.tracker_bench import format_tracker_table, run_tracker_benchmark
from nsflow_ros.vins.settings import setting

__all__ = [
    "main",
    "paper_encoder_onnx",
    "run_benchmark",
    "solver_cost_model",
]

WIDTH, HEIGHT = 752, 480
# Frames whose solver work the cost model counts (it also builds their pyramids).
COST_MODEL_FRAMES = 21


def paper_encoder_onnx(path: Path, c_in: int = 3, d: int = 3, seed: int = 0) -> Path:
    """Write the paper's encoder architecture with random weights (1,003 parameters for RGB, d=3).

    3x3 conv -> 8, 3x3 8 -> 8, 1x1 8 -> 16, 1x1 16 -> d, ReLU after each; dynamic height and width. Used
    to time the architecture when no trained model is at hand.
    """
    onnx = require("onnx", "building the paper's encoder with random weights")
    TensorProto, helper, numpy_helper = onnx.TensorProto, onnx.helper, onnx.numpy_helper

    rng = np.random.default_rng(seed)
    shapes = [(8, c_in, 3, 3), (8, 8, 3, 3), (16, 8, 1, 1), (d, 16, 1, 1)]
    inits, nodes, prev = [], [], "image"
    for i, shp in enumerate(shapes):
        inits += [
            numpy_helper.from_array(rng.normal(0, 0.3, shp).astype(np.float32), f"w{i}"),
            numpy_helper.from_array(rng.normal(0, 0.05, shp[0]).astype(np.float32), f"b{i}"),
        ]
        pad = [1, 1, 1, 1] if shp[2] == 3 else [0, 0, 0, 0]
        nodes.append(helper.make_node("Conv", [prev, f"w{i}", f"b{i}"], [f"c{i}"], pads=pad))
        out = "descriptors" if i == len(shapes) - 1 else f"r{i}"
        nodes.append(helper.make_node("Relu", [f"c{i}"], [out]))
        prev = out
    graph = helper.make_graph(
        nodes,
        "paper_encoder",
        [helper.make_tensor_value_info("image", TensorProto.FLOAT, [1, c_in, "H", "W"])],
        [helper.make_tensor_value_info("descriptors", TensorProto.FLOAT, [1, d, "H", "W"])],
        initializer=inits,
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    helper.set_model_props(model, {"name": f"paper-architecture-random-d{d}"})
    onnx.save(model, path)
    return path


class _Method:
    """Per-frame timings (milliseconds, one list per stage) and tracked shares of one benchmarked method."""

    def __init__(self, stages: tuple[str, ...]) -> None:
        self.times: dict[str, list[float]] = {stage: [] for stage in stages}
        self.tracked: list[float] = []

    def _record(self, *values: float) -> None:
        for key, val in zip(self.times, values, strict=True):
            self.times[key].append(val)

    def figures(self) -> dict[str, Any]:
        out: dict[str, Any] = {k: timing_stats(v) for k, v in self.times.items()}
        out["tracked_share"] = float(np.mean(self.tracked))
        return out


class _Pipeline(_Method):
    """One LM method of the registry: encoder, pyramid + the tracker's solve from zero flow, GFTT."""

    def __init__(self, method: LMMethod, points: int) -> None:
        super().__init__(("encoder", "solver", "detection", "total"))
        self.method, self.points = method, points
        self.prev_pyr: Any = None
        self.pts = np.zeros((0, 2))

    def step(self, frame: np.ndarray) -> None:
        gray = to_gray(frame)
        m = self.method
        desc, t_enc = _timed(lambda: m.encoder(m.encoder_input(frame, gray)))
        t0 = time.perf_counter()
        pyr = m.pyramid(desc)
        if self.prev_pyr is not None:
            # fresh corners with no prior: the tracker's solve from zero flow on the whole pyramid
            _, status = m.solve(SolveKind.FORWARD, self.prev_pyr, pyr, self.pts)
            self.tracked.append(float(status.mean()) if len(self.pts) else 0.0)
        t_solve = (time.perf_counter() - t0) * 1e3
        self.pts, t_det = _timed(lambda: detect_corners(gray, self.points, min_distance=30))
        first = self.prev_pyr is None
        self.prev_pyr = pyr
        if not first:  # the first frame has nothing to track
            self._record(t_enc, t_solve, t_det, t_enc + t_solve + t_det)


class _OpenCVKLT(_Method):
    """The registry's ``klt``: OpenCV's calcOpticalFlowPyrLK as VINS-Fusion calls it, and GFTT."""

    def __init__(self, points: int) -> None:
        super().__init__(("klt", "detection", "total"))
        self.method = make_method("klt")
        self.points = points
        self.prev: np.ndarray | None = None
        self.pts = np.zeros((0, 2))

    def step(self, frame: np.ndarray) -> None:
        gray = to_gray(frame)
        t_klt = 0.0
        if self.prev is not None and len(self.pts):
            prev = self.prev
            (_, st), t_klt = _timed(lambda: self.method.solve(SolveKind.FORWARD, prev, gray, self.pts))
            self.tracked.append(float(st.mean()))
        found, t_det = _timed(lambda: cv2.goodFeaturesToTrack(gray, self.points, GFTT_QUALITY, 30))
        self.pts = found.reshape(-1, 2).astype(np.float64) if found is not None else np.zeros((0, 2))
        if self.prev is not None:
            self._record(t_klt, t_det, t_klt + t_det)
        self.prev = gray


def _fit_pass_costs(work: np.ndarray, ms: np.ndarray) -> tuple[float, float]:
    """Least-squares (a, b) of ms = a * passes + b * point evaluations; work rows: [passes, evaluations]."""
    if work.ndim != 2 or work.shape[1] != 2 or work.shape[0] != ms.shape[0] or work.shape[0] < 2:
        raise NSFlowError(f"need (n >= 2, 2) work counts and n times, got {work.shape} and {ms.shape}")
    (a, b), *_ = np.linalg.lstsq(work, ms, rcond=None)
    return float(a), float(b)


def solver_cost_model(
    method: LMMethod, frames: list[np.ndarray], points: int, repeats: int = 3
) -> dict[str, float]:
    """Where an LM method's solver time goes: its work per frame and the price of each unit of work.

    The solver is batched, so a pass (one LM iteration of every still-active point at one level, or the
    evaluation of all points at a level's starting flow) costs a fixed amount whatever the number of
    points (call overhead) plus an amount per point evaluated in it. Each pair of consecutive ``frames``
    is tracked from zero flow with the first 1, 4, 16, 64 and all ``points`` GFTT corners; the passes P,
    the point evaluations E and the time (median of ``repeats``) of each run give t = a P + b E by least
    squares, and with all corners a P and b E bound what fewer calls per pass, or cheaper per-point
    arithmetic, can save.

    Returns:
        with all corners, medians per frame: ``passes``, ``point_evaluations``, ``measured_ms``; the fit:
        ``fixed_us_per_pass`` (a) and ``us_per_point_evaluation`` (b); its parts at the median work
        ``fixed_ms`` (a P) and ``per_point_ms`` (b E), and ``modelled_ms`` (their sum).

    Raises:
        NSFlowError: with fewer than two frames, or no corners to track.
    """
    if len(frames) < 2:
        raise NSFlowError(f"the solver cost model needs at least 2 frames, got {len(frames)}")
    grays = [to_gray(f) for f in frames]
    pyrs = [method.prepare(f, g) for f, g in zip(frames, grays, strict=True)]
    corners = [detect_corners(g, points, min_distance=30) for g in grays]
    nlev = min(method.lm.levels, pyrs[0].num_levels)
    rows, times, full = [], [], []
    for prev, cur, pts in zip(pyrs, pyrs[1:], corners, strict=False):
        for count in sorted({min(c, len(pts)) for c in (1, 4, 16, 64, len(pts))} - {0}):
            sub = pts[:count]
            res = method.track_pair_result(prev, cur, sub, record=True)
            # each level also evaluates every point once at its starting flow: a pass of its own
            work = (len(res.history) + nlev, int(res.iterations.sum()) + nlev * count)
            again = functools.partial(method.track_pair_result, prev, cur, sub)
            ms = float(np.median([_timed(again)[1] for _ in range(repeats)]))
            rows.append(work)
            times.append(ms)
            if count == len(pts):
                full.append((*work, ms))
    if not full:
        raise NSFlowError("the solver cost model found no corners to track in its frames")
    a, b = _fit_pass_costs(np.asarray(rows, np.float64), np.asarray(times))
    p, e, measured = (float(v) for v in np.median(np.asarray(full), axis=0))
    return {"passes": p, "point_evaluations": e, "measured_ms": measured, "fixed_us_per_pass": a * 1e3,
            "us_per_point_evaluation": b * 1e3, "fixed_ms": a * p, "per_point_ms": b * e,
            "modelled_ms": a * p + b * e}


def run_benchmark(
    frames: int = 60,
    points: int = 150,
    model: str | None = None,
    threads: int | None = None,
    progress: bool = False,
    providers: str = "cpu",
) -> dict[str, Any]:
    """Run the stage benchmark and return its figures as JSON data.

    Args:
        frames: frames of the 752x480 sequence.
        points: GFTT corners per frame.
        model: ONNX encoder path; None = the shipped model, or the paper architecture with random weights
            when no model is shipped yet (the result says which).
        threads: encoder threads and OpenCV threads; None = the node's ``num_threads`` default.
        progress: print a line per stage to stderr.
        providers: onnxruntime execution providers of the encoder, best first.
    """
    threads = threads or int(setting("num_threads").default)
    cv2.setNumThreads(threads)
    seq = make_frames(frames)
    tmp = None
    try:
        trained = True
        try:
            encoder = load_encoder(model, threads=threads, providers=providers)
            model_desc = str(encoder.path)
        except NSFlowError:
            if model is not None:
                raise
            tmp = tempfile.TemporaryDirectory()
            path = paper_encoder_onnx(Path(tmp.name) / "paper_random.onnx")
            encoder = load_encoder(path, threads=threads, providers=providers)
            model_desc = "paper architecture, random weights (no shipped model found)"
            trained = False
        # the deployed methods, exactly as the tracker builds them (the encoder as given)
        classical = make_method("classical")
        methods: dict[str, _Pipeline | _OpenCVKLT] = {}
        if trained:
            # random descriptors never converge, so solver figures would only time the iteration limit
            nsflow = make_method("nsflow", encoder=encoder)
            methods["nsflow"] = _Pipeline(nsflow, points)  # type: ignore[arg-type]
        methods["classical"] = _Pipeline(classical, points)  # type: ignore[arg-type]
        methods["opencv_klt"] = _OpenCVKLT(points)
        out: dict[str, Any] = {
            "machine": {"cpu_count": os.cpu_count(), "platform": platform.platform(), "threads": threads},
            "setup": {"frames": frames, "points": points, "size": [WIDTH, HEIGHT], "model": model_desc,
                      "descriptor_channels": encoder.channels, "encoder_provider": encoder.provider,
                      "encoder_layout": encoder.layout,
                      "solver": classical.spec.lm.as_dict(), "interleaved": True},  # type: ignore[union-attr]
        }
        # Frame by frame, every method in turn: on a shared machine the load drifts over seconds, and
        # interleaving exposes all methods to the same drift, so their ratios hold even when it is noisy.
        if progress:
            names = ", ".join(methods)
            print(f"[bench] {names} interleaved over {frames} frames ...", file=sys.stderr, flush=True)
        for frame in seq:
            for method in methods.values():
                method.step(frame)
        for name, method in methods.items():
            out[name] = method.figures()
        if progress:
            print("[bench] solver cost model ...", file=sys.stderr, flush=True)
        out["solver_cost_model"] = {
            name: solver_cost_model(method.method, seq[:COST_MODEL_FRAMES], points)
            for name, method in methods.items()
            if isinstance(method, _Pipeline)
        }
        sizes = [("encoder_320x240", encoder, (320, 240)), ("encoder_752x480", encoder, (WIDTH, HEIGHT))]
        if encoder.layout == "bands":  # the model's own graph beside its band layout, in the same run
            whole = load_encoder(encoder.path, threads=threads, providers=providers, bands=False)
            sizes.append(("encoder_752x480_whole_frame", whole, (WIDTH, HEIGHT)))
        for name, enc, size in sizes:
            if progress:
                print(f"[bench] {name} ...", file=sys.stderr, flush=True)
            out[name] = time_encoder(enc, size, 30)
    finally:
        if tmp is not None:
            tmp.cleanup()
    klt, nsflow, classical_ms = out["opencv_klt"], out.get("nsflow"), out["classical"]["solver"]["median_ms"]
    out["ratios"] = {"classical_solver_vs_klt": classical_ms / klt["klt"]["median_ms"]}
    if nsflow is not None:
        out["ratios"]["nsflow_solver_vs_klt"] = nsflow["solver"]["median_ms"] / klt["klt"]["median_ms"]
        out["ratios"]["nsflow_total_vs_klt_total"] = nsflow["total"]["median_ms"] / klt["total"]["median_ms"]
    return out


# The encoder-alone timings: the encoder as the tracker runs it, and on a band layout's model its own graph.
_ENCODER_ROWS = (
    ("encoder_320x240", "encoder alone 320x240"),
    ("encoder_752x480", "encoder alone 752x480"),
    ("encoder_752x480_whole_frame", "encoder alone 752x480, the model's own graph"),
)


def format_table(res: dict[str, Any]) -> str:
    """Human-readable summary of :func:`run_benchmark`'s figures."""
    s = res["setup"]
    lines = [
        f"nsflow_ros benchmark: {s['frames']} frames {s['size'][0]}x{s['size'][1]}, "
        f"{s['points']} GFTT points, "
        f"{res['machine']['cpu_count']} cores, {res['machine']['threads']} threads, methods interleaved"
        + (", large buffers kept on the heap" if res["machine"].get("keep_large_buffers") else ""),
        f"encoder: {s['model']} (d={s['descriptor_channels']}) on {s.get('encoder_provider', 'the CPU')}"
        f" ({s.get('encoder_layout', 'whole frame')})",
        "",
        f"{'stage':34s} {'median ms':>10s} {'p90 ms':>10s}",
    ]

    def row(name: str, st: dict[str, float]) -> None:
        lines.append(f"{name:34s} {st['median_ms']:10.2f} {st['p90_ms']:10.2f}")

    for mode in ("nsflow", "classical"):
        if mode not in res:
            lines.append(f"{mode:34s} (not run: no trained model)")
            continue
        for stage in ("encoder", "solver", "detection", "total"):
            row(f"{mode} {stage}", res[mode][stage])
    row("opencv KLT 21x21 x4 levels", res["opencv_klt"]["klt"])
    row("opencv GFTT", res["opencv_klt"]["detection"])
    row("opencv total", res["opencv_klt"]["total"])
    for name, label in _ENCODER_ROWS:
        if name in res:
            row(label, res[name])
    lines.append("")
    for key, val in res["ratios"].items():
        lines.append(f"ratio {key:30s} {val:6.2f}x")
    for mode, model in res.get("solver_cost_model", {}).items():
        lines.append(
            f"{mode} solver per frame: {model['passes']:.0f} passes x {model['fixed_us_per_pass']:.0f} us "
            f"+ {model['point_evaluations']:.0f} point evaluations x "
            f"{model['us_per_point_evaluation']:.2f} us "
            f"= {model['fixed_ms']:.2f} + {model['per_point_ms']:.2f} = {model['modelled_ms']:.2f} ms "
            f"(measured {model['measured_ms']:.2f}, outside the pipeline)"
        )
    shares = {m: res[m]["tracked_share"] for m in ("nsflow", "classical", "opencv_klt") if m in res}
    lines.append("tracked share: " + ", ".join(f"{m} {v:.3f}" for m, v in shares.items()))
    return "\n".join(lines)


def _size(text: str) -> tuple[int, int]:
    """``WxH`` -> (W, H), both positive (argparse type)."""
    w, sep, h = text.lower().partition("x")
    if not (sep and w.isdigit() and h.isdigit() and int(w) > 0 and int(h) > 0):
        raise argparse.ArgumentTypeError(f"expected WIDTHxHEIGHT such as 1280x800, got {text!r}")
    return int(w), int(h)


def _parser() -> argparse.ArgumentParser:
    """``nsflow-bench``'s options."""
    parser = argparse.ArgumentParser(prog=program_name("nsflow-bench"), description=__doc__.split("\n\n")[0])
    add = parser.add_argument
    add("--frames", type=positive_int, default=60, help="frames of the 752x480 sequence of the stage "
        "benchmark (default 60)")
    add("--points", type=positive_int, default=150, help="GFTT points per frame (default 150)")
    add("--model", help="ONNX encoder: a file, or a shipped model by name (default, fast; default: default)")
    add("--threads", type=positive_int, help="encoder (onnxruntime) threads of the tracker, stage and node "
        f"runs (default: the node's num_threads default, {setting('num_threads').default})")
    add("--providers", default="cpu", help="onnxruntime execution providers of the encoder, best first, e.g. "
        "tensorrt,cuda,cpu (default cpu; as the node's providers parameter)")
    add("--json", action="store_true", help="print the figures as one JSON object")
    add("--tables", type=Path, metavar="DIR", help="also write the tables the docs paste: DIR/bench.json and "
        "DIR/bench.md (date, machine, command and versions in the header; docs/benchmarks.md)")
    add("--tracker-seconds", type=non_negative_float, default=10.0, help="seconds of the 20 Hz sample "
        "sequence for the whole-tracker benchmark, mono and stereo, every method interleaved with klt "
        "(default 10 = 200 frames; 0 = skip it)")
    add("--methods", type=method_variants, default="nsflow,nsflow_lk,classical,klt",
        help="comma-separated tracking methods of the whole-tracker benchmark, each optionally with tracker "
        "settings after colons, e.g. nsflow:reverse_checks=1 (default nsflow,nsflow_lk,classical,klt; klt "
        "is always run as the baseline)")
    add("--modes", default="mono,stereo", help="comma-separated modes of the whole-tracker benchmark: mono, "
        "stereo (default both)")
    add("--large", type=_size, metavar="WxH", help="also run the whole-tracker benchmark on the sample "
        "up-sampled to WxH (e.g. 1280x800, a larger camera; its exact flow scaled alike) with the trackers' "
        "downsample set to --downsample, each method's CPU time there over its own at 752x480 (default: not)")
    add("--downsample", type=positive_int, default=2, metavar="N", help="the trackers' downsample in the "
        "--large runs (1, 2 or 4; default 2)")
    add("--perturb", default="none", choices=tuple(PERTURBATIONS), help="perturb the whole-tracker "
        "benchmark's frames: the illumination levels small / large or dark (low light with sensor noise; "
        "default none)")
    add("--node-seconds", type=non_negative_float, default=20.0, help="seconds of the stereo sample replayed "
        "at camera rate (20 Hz) into a tracker node process over DDS, for nsflow and klt: pairs received / "
        "processed / dropped and latency (default 20; 0 = skip)")
    add("--node-rounds", type=positive_int, default=3, metavar="N", help="node runs per method, the methods "
        "alternating (nsflow, klt, nsflow, ...), so a load that drifts over the minutes meets both alike; "
        "their latencies pooled (default 3)")
    add("--compress", default="none", help="comma-separated image transports of the node benchmark, one run "
        "each: none (raw), jpeg (quality 90), png; none,jpeg,png compares the compressed runs' features "
        "with the raw run's (default none)")
    add("--opencv-threads", type=non_negative_int, help="OpenCV's threads in the whole-tracker benchmark and "
        "the node runs (0 = OpenCV's default pool; default: the node's opencv_threads default, "
        f"{setting('opencv_threads').default})")
    add("--background-load", type=non_negative_float, default=0.0, metavar="CORES", help="run a synthetic "
        "CPU load of this many cores (a process busy that share of every 20 ms) during each node run, "
        "standing in for the VINS estimator on the same cores (default 0)")
    add("--load-nice", type=non_negative_int, default=0, metavar="N", help="niceness of the background load "
        "(0-19; > 0 runs it below the tracker's priority, as an estimator started with nice -n N; default 0)")
    add("--queue-size", type=positive_int, help="the node runs' queue_size (frames waiting for the tracker "
        f"at most; default: the node's, {setting('queue_size').default})")
    add("--late-frame-ms", type=non_negative_float, metavar="MS", help="the node runs' late_frame_ms (a "
        "frame that waited longer for the tracker skips its reverse checks; 0 = always check; default: the "
        f"node's, {setting('late_frame_ms').default:g})")
    add("--covariance", action="store_true", help="the whole-tracker benchmark also runs every method with "
        "publish_covariance on (as <method>+cov, interleaved): what the per-feature covariance costs")
    add("--no-stages", action="store_true", help="skip the stage benchmark (encoder / solver / detection, "
        "solver cost model)")
    add("--system-malloc", action="store_true", help="leave glibc's malloc settings alone (default: keep "
        "large buffers on the heap, as the tracker node does; see nsflow_ros.allocator)")
    add("--node-frames", type=non_negative_int, default=0, help="also run the ROS 2 node benchmark (latency, "
        "memory after 1,000 / 10,000 frames) on this many 320x240 frames, mono and stereo; 10000 takes "
        "several minutes (default 0 = skip)")
    return parser


def _measure(opts: argparse.Namespace, node_threads: int | None) -> dict[str, Any]:
    """Run the parts the options ask for: whole tracker, node at camera rate, stages, node over frames."""
    res: dict[str, Any] = {}
    if opts.tracker_seconds > 0:
        cv_threads = setting("opencv_threads").default if opts.opencv_threads is None else opts.opencv_threads
        res["tracker"] = run_tracker_benchmark(
            opts.tracker_seconds, opts.methods, names(opts.modes), model=opts.model,
            threads=opts.threads, progress=not opts.json, providers=opts.providers,
            opencv_threads=int(cv_threads), covariance=opts.covariance, large=opts.large,
            downsample=opts.downsample, perturb=opts.perturb,
        )
    if opts.node_seconds > 0:
        from nsflow_ros.ros.bench_live import run_live_benchmark

        params = {"opencv_threads": opts.opencv_threads, "queue_size": opts.queue_size,
                  "late_frame_ms": opts.late_frame_ms, "model_path": opts.model, "num_threads": node_threads}
        res["node_live"] = run_live_benchmark(
            opts.node_seconds, ("nsflow", "klt"), progress=not opts.json, compress=opts.compress.split(","),
            background_load=opts.background_load, load_nice=opts.load_nice, rounds=opts.node_rounds,
            params={k: v for k, v in params.items() if v is not None},
        )
    if not opts.no_stages:
        res.update(run_benchmark(opts.frames, opts.points, opts.model, opts.threads, progress=not opts.json,
                                 providers=opts.providers))
    res.setdefault("machine", {"cpu_count": os.cpu_count(), "platform": platform.platform(),
                               "threads": opts.threads})
    if opts.node_frames > 0:
        from nsflow_ros.ros.bench_node import run_node_benchmark

        res["node"] = {mode: run_node_benchmark(opts.node_frames, mode == "stereo", progress=not opts.json,
                                                providers=opts.providers) for mode in ("mono", "stereo")}
    return res


def _print_text(res: dict[str, Any]) -> None:
    """The human-readable tables of every part that ran."""
    if "tracker" in res:
        print(format_tracker_table(res["tracker"]), end="\n\n")
    if "node_live" in res:
        from nsflow_ros.ros.bench_live import format_live_table

        print(format_live_table(res["node_live"]), end="\n\n")
    if "setup" in res:
        print(format_table(res))
    for mode, node in res.get("node", {}).items():
        lat = node["latency_ms"]
        rss = ", ".join(f"{v:.1f} MB after {k} frames" for k, v in node["rss_mb"].items()) or "n/a"
        print(f"node {mode:6s} latency median {lat['median']:.2f} ms, p90 {lat['p90']:.2f} ms; "
              f"RSS {rss}; growth {node['rss_growth_mb']} MB")


def bench_tables(res: dict[str, Any]) -> list[dict[str, Any]]:
    """The Markdown tables of a run (:mod:`nsflow_ros.results`): one per part that ran."""
    tables, tr = [], res.get("tracker")
    if tr:
        rows: dict[bool, list[list[str]]] = {False: [], True: []}
        for mode in tr["setup"]["modes"]:
            for m, f in tr[mode].items():
                cells = [(f["cpu"]["median_ms"], ".2f"), (tr["cpu_ratios"][mode].get(m, 1.0), ".2f"),
                         (f["total"]["median_ms"], ".2f"), (tr["ratios"][mode].get(m, 1.0), ".2f"),
                         (f["carried_share"], ".3f"), (f["error_median_px"], ".3f"),
                         (f["error_over_1px_share"], ".1%"), (f.get("stereo_matched_share"), ".3f"),
                         (f.get("stereo_error_over_1px_share"), ".1%")]
                rows[" " in mode].append([mode, m, *("-" if v is None else format(v, k) for v, k in cells)])
        s = tr["setup"]
        cols = ["mode", "method", "CPU ms", "CPU x klt", "wall ms", "wall x klt", "carried", "err px",
                "> 1 px", "stereo", "stereo > 1 px"]
        tables.append(table("Whole tracker per frame", cols, rows[False], (
            f"{s['frames']} frames {s['size'][0]}x{s['size'][1]} of the sample sequence, perturbation "
            f"{s['perturb']}, methods interleaved frame by frame; encoder on {s['encoder_provider']} with "
            f"{s['encoder_threads']} threads ({s.get('encoder_layout', 'whole frame')}), OpenCV threads "
            f"{s['opencv_threads']}. CPU ms: the process's "
            "CPU time per frame over all its threads; carried: features kept from one frame to the next; err "
            "px, > 1 px: their median error against the exact flow, share over 1 px; stereo: right matches "
            "per left feature.")))
        if rows[True]:
            native = "; ".join(f"{key}: CPU per frame over the same method's at 752x480: " + ", ".join(
                f"{m} {r:.2f}x" for m, r in by.items()) for key, by in tr["native_cpu_ratios"].items())
            tables.append(table("Large cameras: the sample up-sampled, tracked with downsample", cols,
                                rows[True], native))
    if "node_live" in res:
        s, keys = res["node_live"]["setup"], ("frames_sent", "tracker_received", "tracker_processed",
                                              "tracker_unchecked", "tracker_superseded")
        runs = {m: f for m, f in res["node_live"].items() if m != "setup"}
        rounds = int(s.get("rounds", 1))
        rows_ = [[m, *(str(f.get(k, "?")) for k in keys), "{:.1f} / {:.1f}".format(
            f.get("tracker_latency_ms_p50", 0), f.get("tracker_latency_ms_p90", 0)),
            ", ".join(f"{v:.1f}" for v in f.get("round_latency_ms_p90") or [] if v is not None) or "-",
            f"{f.get('tracker_cpu_ms_per_frame', 0):.1f}"] for m, f in runs.items()]
        ratio, base = "", (s.get("methods") or [None])[-1]  # the last method is the baseline
        p90 = {m: f.get("tracker_latency_ms_p90") for m, f in runs.items()}
        if p90.get(base) and len(p90) > 1:
            ratio = f" p90 over {base}'s: " + ", ".join(
                f"{m} {v / p90[base]:.2f}x" for m, v in p90.items() if m != base and v) + "."
        tables.append(table(
            f"Tracker node at 20 Hz stereo over DDS, background load {s.get('background_load_cores', 0):g} "
            "core",
            ["method", "sent", "received", "processed", "late", "superseded", "latency p50 / p90 ms",
             "p90 per round ms", "CPU ms per pair"], rows_,
            f"{rounds} x {s['seconds']:g} s of the stereo sample replayed, the methods' runs alternating; "
            "latency pooled over the rounds; late: tracked without the reverse checks (late_frame_ms); "
            f"superseded: given up for a newer pair while the tracker was busy.{ratio}"))
    if "setup" in res:
        stages = [(f"{mode} {st}", res[mode][st]) for mode in ("nsflow", "classical") if mode in res
                  for st in ("encoder", "solver", "detection", "total")]
        stages += [("opencv KLT", res["opencv_klt"]["klt"]), ("opencv GFTT", res["opencv_klt"]["detection"]),
                   *((label, res[name]) for name, label in _ENCODER_ROWS if name in res)]
        notes = "; ".join(" ".join(x.split()) for x in format_table(res).split("\n\n")[-1].splitlines())
        tables.append(table("Stages per frame (752x480, fresh GFTT points)", ["stage", "median ms", "p90 ms"],
                            [[n, f"{v['median_ms']:.2f}", f"{v['p90_ms']:.2f}"] for n, v in stages], notes))
    return tables


def main(args: list[str] | None = None) -> int:
    """Entry point of ``nsflow-bench`` / ``ros2 run nsflow_ros bench``."""
    opts = _parser().parse_args(args)
    node_threads, opts.threads = opts.threads, opts.threads or int(setting("num_threads").default)
    heap = False if opts.system_malloc else keep_large_buffers()
    try:
        res = _measure(opts, node_threads)
    except NSFlowError as err:
        print(f"nsflow-bench: {err}", file=sys.stderr)
        return 1
    res["machine"]["keep_large_buffers"] = heap
    if opts.tables is not None:
        opts.tables.mkdir(parents=True, exist_ok=True)
        doc = {"header": run_header(command_line("nsflow-bench", args)), "tables": bench_tables(res)}
        write_tables(doc, opts.tables / "bench.json", opts.tables / "bench.md")
    if opts.json:
        print(json.dumps(res, indent=2))
    else:
        _print_text(res)
    return 0


if __name__ == "__main__":
    sys.exit(main())
