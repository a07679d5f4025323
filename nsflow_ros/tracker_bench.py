"""Whole-tracker benchmark: the VINS-style tracker per frame, every method interleaved, with its quality.

Every tracking method runs the shipped EuRoC configs (mono and stereo) over the same frames of the
sample sequence, taking turns frame by frame so that the drifting load of a shared machine hits them
alike. Per method and mode it reports wall and CPU time per frame (CPU time is the process's over all
its threads, so work spread over a pool counts in full), their ratios to ``klt`` (VINS's own front-end,
measured in the same run) and the quality against the exact optical flow
(:class:`nsflow_ros.data.scoring.FrameQuality`).
"""

from __future__ import annotations

import tempfile
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from nsflow_ros import threads as process_threads
from nsflow_ros.core.encoder import encoder_provider
from nsflow_ros.core.errors import UnsupportedEncoderError
from nsflow_ros.core.methods import BASELINE, METHODS
from nsflow_ros.core.tracker import FeatureTracker
from nsflow_ros.data.scoring import FrameQuality
from nsflow_ros.errors import NSFlowError
from nsflow_ros.evaluation.timing import timing_stats
from nsflow_ros.resources import DEFAULT_CONFIG, STEREO_CONFIG, share_file

__all__ = ["MODES", "format_tracker_table", "run_tracker_benchmark"]

MODES = ("mono", "stereo")
CONFIGS = {
    "mono": DEFAULT_CONFIG,
    "stereo": STEREO_CONFIG,
}


class _Run:
    """One method in one mode: its tracker, its timings and its quality."""

    def __init__(self, tracker: FeatureTracker) -> None:
        self.tracker = tracker
        self.total: list[float] = []
        self.cpu: list[float] = []
        self.stages: dict[str, list[float]] = {}
        self.cpu_stages: dict[str, list[float]] = {}
        self.quality = FrameQuality()
        self.had = 0  # camera-0 features of the previous frame

    def step(self, seq: Any, i: int, left: np.ndarray, right: np.ndarray | None) -> None:
        before = self.had
        t0, c0 = time.perf_counter(), time.process_time()
        frame = self.tracker.process(seq.time(i), left, right)
        wall, cpu = (time.perf_counter() - t0) * 1e3, (time.process_time() - c0) * 1e3
        self.had = len(frame.cameras[0])
        if i == 0:
            return  # nothing to track yet
        self.total.append(wall)
        self.cpu.append(cpu)
        for timings, into in ((frame.timings, self.stages), (frame.cpu_timings, self.cpu_stages)):
            for k, v in timings.items():
                if k != "total":
                    into.setdefault(k, []).append(v)
        self.quality.add_frame(seq, i, frame, before, stereo=right is not None)

    def figures(self) -> dict[str, Any]:
        out: dict[str, Any] = {"total": timing_stats(self.total), "cpu": timing_stats(self.cpu)}
        out["stages"] = {k: timing_stats(v)["median_ms"] for k, v in self.stages.items()}
        out["cpu_stages"] = {k: timing_stats(v)["median_ms"] for k, v in self.cpu_stages.items()}
        out.update(self.quality.figures())
        return out


def run_tracker_benchmark(
    duration: float = 10.0,
    methods: Sequence[str] = ("nsflow", "nsflow_lk", "classical", "klt"),
    modes: Sequence[str] = MODES,
    *,
    model: str | None = None,
    threads: int | None = None,
    providers: str = "cpu",
    opencv_threads: int | None = None,
    seed: int = 0,
    cache_dir: str | Path | None = None,
    progress: bool = False,
    covariance: bool = False,
) -> dict[str, Any]:
    """Time the whole tracker per frame for each method and mode, interleaved, with its quality.

    Args:
        duration: seconds of the 20 Hz sample sequence.
        methods: registry names; ``klt`` is always added (the ratios' baseline).
        modes: "mono" and / or "stereo".
        model: ONNX encoder of the learned methods; None = the shipped one.
        threads: encoder threads; None = all usable cores.
        providers: onnxruntime execution providers of the learned encoders, best first.
        opencv_threads: OpenCV's threads for the run (:func:`nsflow_ros.threads.opencv_threads`),
            restored afterwards; None = leave OpenCV's setting alone.
        seed: the sample sequence's seed.
        cache_dir: where the sample sequence is rendered (reused when it is there); None = a temporary
            folder removed afterwards.
        progress: a progress bar on stderr.
        covariance: also run every method with ``publish_covariance`` on, as ``<method>+cov``, interleaved
            with the others: the covariance's cost is its CPU ratio over the method's own.

    Returns:
        ``{"setup": ..., "mono": {method: figures}, "stereo": ..., "ratios": {mode: {method: x}},
        "cpu_ratios": ...}``: figures hold ``total`` and ``cpu`` (median / p90 ms), ``stages`` and
        ``cpu_stages`` (median ms) and the quality; the ratios are medians over ``klt``'s, wall and CPU.

    Raises:
        NSFlowError: an unknown method or mode, or a model / config that cannot be loaded.
    """
    from nsflow_ros.data.sample import make_sample_sequence
    from nsflow_ros.vins.config import load_vins_config
    from nsflow_ros.vins.tracker import tracker_from_config

    names = list(dict.fromkeys([*methods, "klt"]))
    unknown = [m for m in names if m not in METHODS]
    bad_modes = [m for m in modes if m not in MODES]
    if unknown or bad_modes:
        raise NSFlowError(f"unknown method(s) {unknown} or mode(s) {bad_modes}; "
                          f"methods: {list(METHODS)}, modes: {list(MODES)}")
    if not duration > 0:
        raise NSFlowError(f"duration must be > 0 s, got {duration}")
    tmp = tempfile.TemporaryDirectory() if cache_dir is None else None
    try:
        root = Path(tmp.name if tmp else cache_dir) / f"sample-seed{seed}-{duration:g}s"
        seq = make_sample_sequence(root, seed=seed, duration=duration, stereo=True, formats=("asl",),
                                   progress=progress)
        runs: dict[str, dict[str, _Run]] = {}
        left_out: dict[str, str] = {}
        for mode in modes:
            cfg = load_vins_config(share_file(CONFIGS[mode]))
            over: dict[str, Any] = {"stereo": mode == "stereo", "num_threads": threads,
                                    "providers": providers}
            if model is not None:
                over["model_path"] = model
            runs[mode] = {}
            for m in names:
                try:
                    runs[mode][m] = _Run(tracker_from_config(cfg, {**over, "method": m,
                                                                    "publish_covariance": False}))
                    if covariance:
                        runs[mode][f"{m}+cov"] = _Run(tracker_from_config(cfg, {**over, "method": m,
                                                                                 "publish_covariance": True}))
                except UnsupportedEncoderError as err:  # e.g. OpenCV's LK and unbounded descriptors
                    left_out[m] = str(err)
        names = [m for m in names if m not in left_out]
        if covariance:
            names += [f"{m}+cov" for m in names]
        frames = range(len(seq))
        if progress:
            from nsflow_ros.progress import progress_bar

            frames = progress_bar(frames, desc="tracker benchmark", unit="frame", leave=False)
        stereo = "stereo" in modes
        with process_threads.opencv_threads(opencv_threads) as used_cv:
            for i in frames:
                left = seq.image(i, 0)
                right = seq.image(i, 1) if stereo else None
                # Frame by frame, every method and mode in turn.
                for mode, by_method in runs.items():
                    for run in by_method.values():
                        run.step(seq, i, left, right if mode == "stereo" else None)
    finally:
        if tmp is not None:
            tmp.cleanup()
    out: dict[str, Any] = {"setup": {"frames": len(seq), "size": [752, 480], "duration_s": duration,
                                     "methods": names, "left_out": left_out, "modes": list(modes),
                                     "interleaved": True,
                                     "configs": {m: CONFIGS[m] for m in modes},
                                     "encoder_provider": _provider(runs),
                                     "encoder_threads": threads, "opencv_threads": used_cv}}
    out["ratios"], out["cpu_ratios"] = {}, {}
    for mode, by_method in runs.items():
        out[mode] = {m: run.figures() for m, run in by_method.items()}
        for key, kind in (("ratios", "total"), ("cpu_ratios", "cpu")):
            base = out[mode][BASELINE][kind]["median_ms"]
            out[key][mode] = {m: out[mode][m][kind]["median_ms"] / base for m in names if m != BASELINE}
    return out


def _provider(runs: dict[str, dict[str, _Run]]) -> str:
    """The execution provider of the learned encoders ("none" when no method has one)."""
    found = {encoder_provider(r.tracker.encoder) for by in runs.values() for r in by.values()} - {"none"}
    return ", ".join(sorted(found)) or "none"


def format_tracker_table(res: dict[str, Any]) -> str:
    """The whole-tracker figures as a text table, one row per mode and method."""
    s = res["setup"]
    threads = s.get("encoder_threads")
    lines = [
        f"whole tracker (VINS-style, shipped EuRoC configs, flow-back on), {s['frames']} frames "
        f"{s['size'][0]}x{s['size'][1]} of the sample sequence, methods interleaved; encoder on "
        f"{s.get('encoder_provider', 'none')}, encoder threads "
        f"{'all cores' if threads is None else threads}, OpenCV threads {s.get('opencv_threads', '?')}",
        *(f"left out: {why}" for why in s.get("left_out", {}).values()),
        "",
        f"{'mode':7s}{'method':11s}{'median ms':>10s}{'p90 ms':>8s}{'x klt':>7s}{'CPU ms':>8s}{'x klt':>7s}"
        f"{'carried':>9s}{'err px':>8s}{'>1px':>7s}{'stereo':>8s}{'s.err px':>9s}{'s.>1px':>7s}"
        "  stages (median ms, wall / CPU)",
    ]
    for mode in s["modes"]:
        for m, f in res[mode].items():
            ratio = res["ratios"][mode].get(m, 1.0)
            cpu_ratio = res.get("cpu_ratios", {}).get(mode, {}).get(m, 1.0)
            cpu = f.get("cpu", {}).get("median_ms", float("nan"))
            cpu_st = f.get("cpu_stages", {})
            st = " ".join(f"{k} {v:.1f}/{cpu_st.get(k, float('nan')):.1f}" for k, v in f["stages"].items())
            stereo = (f"{f['stereo_matched_share']:8.3f}{f['stereo_error_median_px']:9.3f}"
                      f"{f['stereo_error_over_1px_share']:7.1%}" if "stereo_matched_share" in f else " " * 24)
            lines.append(
                f"{mode:7s}{m:11s}{f['total']['median_ms']:10.2f}{f['total']['p90_ms']:8.2f}{ratio:6.2f}x"
                f"{cpu:8.2f}{cpu_ratio:6.2f}x"
                f"{f['carried_share']:9.3f}{f['error_median_px']:8.3f}{f['error_over_1px_share']:7.1%}"
                f"{stereo}  {st}"
            )
    lines.append("CPU ms: the process's CPU time per frame over all its threads; x klt: median over klt's")
    return "\n".join(lines)
