"""Whole-tracker benchmark: the VINS-style tracker per frame, every method interleaved, with its quality.

Every tracking method runs the shipped EuRoC configs (mono and stereo) over the same frames of the
sample sequence, taking turns frame by frame so that the drifting load of a shared machine hits them
alike. Per method and mode it reports wall and CPU time per frame (CPU time is the process's over all
its threads, so work spread over a pool counts in full), their ratios to ``klt`` (VINS's own front-end,
measured in the same run) and the quality against the exact optical flow
(:class:`nsflow_ros.data.scoring.FrameQuality`).

A larger camera is stood in for by the sample up-sampled with ``cv2.resize`` (``large``, e.g. 1280x800 or
1504x960; its exact flow scaled by the same factors): those modes run with ``downsample`` beside the 752x480
ones, and each method's CPU time there is also given over its own at 752x480. The frames can be perturbed
first by any perturbation of :data:`nsflow_ros.data.perturb.PERTURBATIONS` (e.g. ``dark``).
"""

from __future__ import annotations

import argparse
import dataclasses
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from nsflow_ros import threads as process_threads
from nsflow_ros.argtypes import method_variant
from nsflow_ros.core.downsample import check_downsample, resize_camera
from nsflow_ros.core.encoder import encoder_provider
from nsflow_ros.core.errors import UnsupportedEncoderError
from nsflow_ros.core.methods import BASELINE, METHODS
from nsflow_ros.core.tracker import FeatureTracker
from nsflow_ros.data.scoring import FrameQuality
from nsflow_ros.errors import NSFlowError
from nsflow_ros.evaluation.timing import timing_stats
from nsflow_ros.resources import DEFAULT_CONFIG, STEREO_CONFIG, share_file

__all__ = ["MODES", "ResizedSample", "format_tracker_table", "run_tracker_benchmark"]

MODES = ("mono", "stereo")
CONFIGS = {
    "mono": DEFAULT_CONFIG,
    "stereo": STEREO_CONFIG,
}


class ResizedSample:
    """A sample sequence seen through ``cv2.resize`` to ``size``: its exact flow in the resized pixels.

    A pixel x of the resized image is ``(x + 0.5) / s - 0.5`` of the sample's (per axis, s = new / old
    size), so a flow f of the sample is ``s f`` here, exactly.
    """

    def __init__(self, sample: Any, size: tuple[int, int]) -> None:
        cam = sample.cameras[0]
        self.sample = sample
        self.size = (int(size[0]), int(size[1]))
        self.scale = np.array([size[0] / cam.width, size[1] / cam.height])

    def image(self, image: np.ndarray) -> np.ndarray:
        """A sample image at this size (bilinear)."""
        return cv2.resize(image, self.size, interpolation=cv2.INTER_LINEAR)

    def time(self, i: int) -> float:
        return float(self.sample.time(i))

    def flow(self, i: int, j: int, pixels: Any, cam: int = 0, cam_j: int | None = None
             ) -> tuple[np.ndarray, np.ndarray]:
        """The sample's exact flow at resized pixels, in resized pixels (see the class docstring)."""
        small = (np.asarray(pixels, np.float64) + 0.5) / self.scale - 0.5
        flow, visible = self.sample.flow(i, j, small, cam, cam_j)
        return flow * self.scale, visible


class _Run:
    """One method in one mode: its tracker, its timings and its quality."""

    def __init__(self, tracker: FeatureTracker, scale: float = 1.0) -> None:
        self.tracker = tracker
        self.scale = scale  # resized pixels per 752x480 pixel
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
        if self.scale != 1.0 and self.quality.err:  # the same threshold in 752x480 pixels
            err = np.concatenate(self.quality.err)
            out["error_over_1px_at_752_share"] = float(np.mean(err > self.scale))
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
    large: tuple[int, int] | None = None,
    downsample: int = 1,
    perturb: str = "none",
    covariance: bool = False,
) -> dict[str, Any]:
    """Time the whole tracker per frame for each method and mode, interleaved, with its quality.

    Args:
        duration: seconds of the 20 Hz sample sequence.
        methods: registry names, each optionally with tracker settings (``nsflow:reverse_checks=1``,
            :func:`~nsflow_ros.argtypes.method_variant`); ``klt`` is always added (the ratios' baseline).
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
        large: also run every mode on the sample up-sampled to this (width, height), as a larger camera
            (modes named e.g. ``stereo 1280x800 /2``); None = not.
        downsample: the trackers' ``downsample`` in the ``large`` modes.
        perturb: a perturbation of :data:`~nsflow_ros.data.perturb.PERTURBATIONS` applied to the frames
            (seeded by ``seed``) before any resize.
        covariance: also run every method with ``publish_covariance`` on, as ``<method>+cov``, interleaved
            with the others: the covariance's cost is its CPU ratio over the method's own.

    Returns:
        ``{"setup": ..., "mono": {method: figures}, "stereo": ..., "ratios": {mode: {method: x}},
        "cpu_ratios": ...}``: figures hold ``total`` and ``cpu`` (median / p90 ms), ``stages`` and
        ``cpu_stages`` (median ms) and the quality; the ratios are medians over ``klt``'s, wall and CPU;
        with ``large``, ``"native_cpu_ratios"``: ``{large mode: {method: CPU median / its 752x480 one}}``.

    Raises:
        NSFlowError: an unknown method or mode, or a model / config that cannot be loaded.
    """
    from nsflow_ros.data.perturb import make_perturber
    from nsflow_ros.data.sample import make_sample_sequence
    from nsflow_ros.vins.config import load_vins_config
    from nsflow_ros.vins.tracker import tracker_from_config

    names = list(dict.fromkeys([*methods, "klt"]))
    try:
        chosen = {m: method_variant(m) for m in names}
    except argparse.ArgumentTypeError as err:
        raise NSFlowError(str(err)) from err
    unknown = [m for m, (name, _) in chosen.items() if name not in METHODS]
    bad_modes = [m for m in modes if m not in MODES]
    if unknown or bad_modes:
        raise NSFlowError(f"unknown method(s) {unknown} or mode(s) {bad_modes}; "
                          f"methods: {list(METHODS)}, modes: {list(MODES)}")
    if not duration > 0:
        raise NSFlowError(f"duration must be > 0 s, got {duration}")
    perturber = make_perturber(perturb, seed)  # an unknown name fails here, before any work
    check_downsample(downsample)
    tmp = tempfile.TemporaryDirectory() if cache_dir is None else None
    try:
        root = Path(tmp.name if tmp else cache_dir) / f"sample-seed{seed}-{duration:g}s"
        seq = make_sample_sequence(root, seed=seed, duration=duration, stereo=True, formats=("asl",),
                                   progress=progress)
        runs: dict[str, dict[str, _Run]] = {}
        views: dict[str, ResizedSample | None] = {}  # mode -> the resized view (None: 752x480)
        left_out: dict[str, str] = {}
        variants = [(mode, None) for mode in modes]
        if large is not None:
            variants += [(mode, ResizedSample(seq, large)) for mode in modes]
        for mode, view in variants:
            cfg = load_vins_config(share_file(CONFIGS[mode]))
            over: dict[str, Any] = {"stereo": mode == "stereo", "num_threads": threads,
                                    "providers": providers}
            if model is not None:
                over["model_path"] = model
            key = mode
            if view is not None:
                w, h = view.size
                cfg = dataclasses.replace(cfg, cameras=tuple(resize_camera(c, w, h) for c in cfg.cameras),
                                          image_width=w, image_height=h)
                over["downsample"] = downsample
                key = f"{mode} {w}x{h} /{downsample}"
            runs[key], views[key] = {}, view
            for m in names:
                try:
                    scale = 1.0 if view is None else float(view.scale.mean())
                    name, settings_of_m = chosen[m]
                    for cov in (False, True) if covariance else (False,):
                        settings = {**over, **settings_of_m, "method": name, "publish_covariance": cov}
                        runs[key][f"{m}+cov" if cov else m] = _Run(tracker_from_config(cfg, settings), scale)
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
                left = perturber(seq.image(i, 0), seq.time(i))
                right = perturber(seq.image(i, 1), seq.time(i)) if stereo else None
                resized: dict[tuple[int, int], tuple[np.ndarray, np.ndarray | None]] = {}
                # Frame by frame, every method and mode in turn.
                for key, by_method in runs.items():
                    view = views[key]
                    l_img, r_img = left, right
                    if view is not None:
                        if view.size not in resized:  # once per frame for every mode and method
                            resized[view.size] = (view.image(left),
                                                  None if right is None else view.image(right))
                        l_img, r_img = resized[view.size]
                    for run in by_method.values():
                        run.step(view or seq, i, l_img, r_img if key.startswith("stereo") else None)
    finally:
        if tmp is not None:
            tmp.cleanup()
    out: dict[str, Any] = {"setup": {"frames": len(seq), "size": [752, 480], "duration_s": duration,
                                     "methods": names, "left_out": left_out, "modes": list(runs),
                                     "large": None if large is None else list(large),
                                     "downsample": downsample, "perturb": perturb,
                                     "interleaved": True,
                                     "configs": {m: CONFIGS[m] for m in modes},
                                     "encoder_provider": _provider(runs),
                                     "encoder_layout": _layout(runs),
                                     "encoder_threads": threads, "opencv_threads": used_cv}}
    out["ratios"], out["cpu_ratios"] = {}, {}
    for mode, by_method in runs.items():
        out[mode] = {m: run.figures() for m, run in by_method.items()}
        for key, kind in (("ratios", "total"), ("cpu_ratios", "cpu")):
            base = out[mode][BASELINE][kind]["median_ms"]
            out[key][mode] = {m: out[mode][m][kind]["median_ms"] / base for m in names if m != BASELINE}
    if large is not None:
        out["native_cpu_ratios"] = {
            key: {m: out[key][m]["cpu"]["median_ms"] / out[_native(key)][m]["cpu"]["median_ms"]
                  for m in names}
            for key in runs if views[key] is not None
        }
    return out


def _native(key: str) -> str:
    """The 752x480 mode of a mode key ("stereo 1280x800 /2" -> "stereo")."""
    return key.split()[0]


def _onnx_encoders(runs: dict[str, dict[str, _Run]]) -> list[Any]:
    """The methods' onnxruntime encoders (the classical and OpenCV methods have none)."""
    encoders = (r.tracker.encoder for by in runs.values() for r in by.values())
    return [e for e in encoders if encoder_provider(e) != "none"]


def _provider(runs: dict[str, dict[str, _Run]]) -> str:
    """The execution provider of the learned encoders ("none" when no method has one)."""
    return ", ".join(sorted({encoder_provider(e) for e in _onnx_encoders(runs)})) or "none"


def _layout(runs: dict[str, dict[str, _Run]]) -> str:
    """How the learned encoders encode a frame (:attr:`~nsflow_ros.core.encoder.OnnxEncoder.layout`)."""
    return ", ".join(sorted({e.layout for e in _onnx_encoders(runs)})) or "none"


def format_tracker_table(res: dict[str, Any]) -> str:
    """The whole-tracker figures as a text table, one row per mode and method."""
    s = res["setup"]
    threads = s.get("encoder_threads")
    wm = max(7, *(len(m) + 1 for m in s["modes"]))  # the mode column
    lines = [
        f"whole tracker (VINS-style, shipped EuRoC configs, flow-back on), {s['frames']} frames "
        f"{s['size'][0]}x{s['size'][1]} of the sample sequence, methods interleaved; encoder on "
        f"{s.get('encoder_provider', 'none')} ({s.get('encoder_layout', 'whole frame')}), encoder threads "
        f"{'all cores' if threads is None else threads}, OpenCV threads {s.get('opencv_threads', '?')}",
        *(f"left out: {why}" for why in s.get("left_out", {}).values()),
        "",
        f"{'mode':{wm}s}{'method':11s}{'median ms':>10s}{'p90 ms':>8s}{'x klt':>7s}"
        f"{'CPU ms':>8s}{'x klt':>7s}{'carried':>9s}{'err px':>8s}{'>1px':>7s}{'stereo':>8s}"
        f"{'s.err px':>9s}{'s.>1px':>7s}"
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
                f"{mode:{wm}s}{m:11s}{f['total']['median_ms']:10.2f}{f['total']['p90_ms']:8.2f}{ratio:6.2f}x"
                f"{cpu:8.2f}{cpu_ratio:6.2f}x"
                f"{f['carried_share']:9.3f}{f['error_median_px']:8.3f}{f['error_over_1px_share']:7.1%}"
                f"{stereo}  {st}"
            )
    lines.append("CPU ms: the process's CPU time per frame over all its threads; x klt: median over klt's")
    for key, ratios in res.get("native_cpu_ratios", {}).items():
        w, h = s["large"]
        lines.append(
            f"{key}: the sample up-sampled to {w}x{h} (exact flow scaled), tracked with downsample "
            f"{s['downsample']}; CPU per frame over the same method's at 752x480: "
            + ", ".join(f"{m} {r:.2f}x" for m, r in ratios.items())
        )
        shares = []
        for m, f in res[key].items():
            native = res[_native(key)][m]["error_over_1px_share"]
            at752 = f.get("error_over_1px_at_752_share", float("nan"))
            shares.append(f"{m} {1 - f['error_over_1px_share']:.1%} (at 752x480 scale {1 - at752:.1%}; "
                          f"752x480 run {1 - native:.1%})")
        lines.append(f"  features within 1 px of the truth, in {w}x{h} pixels: " + "; ".join(shares))
    return "\n".join(lines)
