"""The main job (``make demo`` / ``nsflow-demo``): the whole system on built-in data, over real ROS 2 topics.

It makes (or reuses) a synthetic EuRoC-like sample sequence with exact ground truth; for each
illumination perturbation level and method starts the ``tracker`` node as its own process, replays the
sequence to it over DDS and collects its features and debug images; prints the tracking figures against
the ground-truth flow, and writes the debug images as a contact sheet and the figures as JSON.
"""

from __future__ import annotations

import argparse
import json
import os
import random
import sys
import time
from pathlib import Path
from typing import Any

from nsflow_ros.argtypes import non_negative_float, positive_float, program_name
from nsflow_ros.errors import NSFlowError
from nsflow_ros.files import atomic_write
from nsflow_ros.optional import require_extra

__all__ = ["format_summary", "main", "run_demo"]


def run_demo(
    out_dir: Path,
    *,
    duration: float = 4.0,
    seed: int = 0,
    rate: float = 1.0,
    levels: tuple[str, ...] = ("none", "small", "large"),
    methods: tuple[str, ...] = ("nsflow", "nsflow_lk", "klt"),
) -> dict[str, Any]:
    """Run the demo; see the module docstring. Returns the figures per level and method."""
    require_extra("eval", "the demo")  # its sample's textures and its figures
    import rclpy

    from nsflow_ros.core.encoder import DEFAULT_MODEL
    from nsflow_ros.data.images import image_for_tracker
    from nsflow_ros.data.sample import make_sample_sequence
    from nsflow_ros.resources import DEFAULT_CONFIG, ResourceError, share_file
    from nsflow_ros.ros.live import run_live
    from nsflow_ros.ros.transport import use_large_image_transport
    from nsflow_ros.vins.sheet import contact_sheet, write_png

    out_dir.mkdir(parents=True, exist_ok=True)
    notes = []
    try:
        share_file(DEFAULT_MODEL)
    except ResourceError:
        from nsflow_ros.core.methods import METHODS

        if any(METHODS[m].learned for m in methods):
            methods = tuple(m for m in methods if not METHODS[m].learned)
            notes.append(f"no trained encoder at {DEFAULT_MODEL}: the learned methods are skipped")
    print(f"[demo] sample sequence ({duration:.0f} s, 752x480 mono, seed {seed}) ...", flush=True)
    seq = make_sample_sequence(
        out_dir / "sample", seed=seed, duration=duration, stereo=False, formats=("ros2",), progress=True
    )
    config = share_file(DEFAULT_CONFIG)
    # a private DDS domain, so the demo neither hears nor disturbs other ROS 2 graphs on this machine
    os.environ.setdefault("ROS_DOMAIN_ID", str(random.randint(100, 200)))
    use_large_image_transport()  # this process and the tracker nodes it starts
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    results: dict[str, dict[str, Any]] = {}
    sheet, labels = [], []
    try:
        for level in levels:
            for method in methods:
                print(f"[demo] {method:9s} perturbation {level:5s}: replaying over ROS 2 ...", flush=True)
                figs, dbg = run_live(
                    ctx, seq, config, method, out_dir / f"tracker_{method}_{level}.log",
                    level=level, seed=seed, rate=rate,
                )
                figs.pop("tracker_latencies_ms", None)  # the summary keeps the node's p50 / p90
                results.setdefault(level, {})[method] = figs
                if dbg is not None:
                    sheet.append(image_for_tracker(dbg))
                    labels.append(f"{method}, {level} perturbation")
    finally:
        rclpy.shutdown(context=ctx)
    summary = {
        "sequence": str(seq.root),
        "duration_s": duration,
        "seed": seed,
        "notes": notes,
        "results": results,
    }
    atomic_write(out_dir / "summary.json", lambda p: p.write_text(json.dumps(summary, indent=2)))
    if sheet:
        img = contact_sheet(sheet, cols=len(methods), labels=labels, legend=True)
        atomic_write(out_dir / "tracks.png", lambda p: write_png(p, img))
    return summary


def format_summary(summary: dict[str, Any]) -> str:
    """The demo's table."""
    head = (
        f"{'perturbation':12s} {'method':10s} {'sent':>5s} {'recv':>5s} {'proc':>5s} {'out':>5s} "
        f"{'feat/frame':>10s} {'track len':>9s} {'err median px':>13s} {'<1 px':>7s}"
    )
    lines = [head, "-" * len(head)]
    for level, per in summary["results"].items():
        for method, f in per.items():
            med = "n/a" if f["error_median_px"] is None else f"{f['error_median_px']:.3f}"
            within = "n/a" if f["error_within_1px"] is None else f"{100 * f['error_within_1px']:.1f}%"
            recv, proc = (
                "?" if f.get(k) is None else str(f[k]) for k in ("tracker_received", "tracker_processed")
            )
            lines.append(
                f"{level:12s} {method:10s} {f['frames_sent']:5d} {recv:>5s} {proc:>5s} {f['frames']:5d} "
                f"{f['features_per_frame']:10.1f} {f['mean_track_length']:9.1f} {med:>13s} {within:>7s}"
            )
    lines.append(
        "sent: frames replayed; recv / proc: frames the tracker node received / tracked (from its summary); "
        "out: feature messages the demo received"
    )
    lines += [f"note: {n}" for n in summary["notes"]]
    return "\n".join(lines)


def main(args: list[str] | None = None) -> int:
    """Entry point of ``nsflow-demo`` / ``ros2 run nsflow_ros demo``."""
    p = argparse.ArgumentParser(
        prog=program_name("nsflow-demo"),
        description="The whole system on built-in data over real ROS 2 topics: makes a synthetic EuRoC-like "
        "sequence, replays it with no, small and large illumination perturbation to the tracker node "
        "(NSFlow, NSFlow descriptors through OpenCV's LK, VINS's KLT), and prints frames, features per "
        "frame, track length and the tracking error against the exact ground-truth flow; writes a "
        "contact sheet and the figures.",
    )
    p.add_argument("--out", type=Path, default=Path("out/demo"), help="output folder (default out/demo)")
    p.add_argument(
        "--duration", type=positive_float, default=4.0, help="seconds of sample sequence (default 4)"
    )
    p.add_argument("--seed", type=int, default=0, help="sequence and perturbation seed (default 0)")
    p.add_argument(
        "--rate",
        type=non_negative_float,
        default=1.0,
        help="replay speed factor (default 1.0 = real time, 0 = as fast as possible)",
    )
    opts = p.parse_args(args)
    t0 = time.monotonic()
    from nsflow_ros.ros.signals import StopRequested, StopSignals

    try:
        with StopSignals(raise_now=True):
            summary = run_demo(opts.out, duration=opts.duration, seed=opts.seed, rate=opts.rate)
    except NSFlowError as err:
        print(f"nsflow-demo: {err}", file=sys.stderr)
        return 1
    except (KeyboardInterrupt, StopRequested):
        print("nsflow-demo: stopped", file=sys.stderr)
        return 0
    print()
    print(format_summary(summary))
    print(
        f"\ncontact sheet: {opts.out / 'tracks.png'}; figures: {opts.out / 'summary.json'} "
        f"({time.monotonic() - t0:.0f} s)"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
