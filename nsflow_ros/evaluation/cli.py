"""``nsflow-evaluate`` / ``ros2 run nsflow_ros evaluate``: the paper's analyses for NSFlow beside the
classical baselines, written as one Markdown report with figures.

Examples::

    nsflow-evaluate                          # everything, into out/evaluation/
    nsflow-evaluate --quick --out /tmp/ev    # tiny sizes (under a minute), for tests and CI
    nsflow-evaluate --only pairs,convergence --model my_encoder.onnx
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from nsflow_ros.allocator import keep_large_buffers
from nsflow_ros.argtypes import names, program_name
from nsflow_ros.core.encoder import model_file
from nsflow_ros.errors import NSFlowError
from nsflow_ros.evaluation.context import EvalContext
from nsflow_ros.evaluation.errors import EvaluationError
from nsflow_ros.evaluation.methods import usable_methods
from nsflow_ros.evaluation.registry import ANALYSES, select
from nsflow_ros.evaluation.report import machine_info, now, run_analyses, write_report
from nsflow_ros.optional import require_extra
from nsflow_ros.results import command_line

__all__ = ["build_parser", "main"]


def build_parser() -> argparse.ArgumentParser:
    """The command's argument parser."""
    listing = "; ".join(f"{a.key}: {a.title}" for a in ANALYSES)
    parser = argparse.ArgumentParser(
        prog=program_name("nsflow-evaluate"),
        description="Run the NSFlow evaluation suite (NSFlow, NSFlow + OpenCV LK, the LM solver on "
        "intensity, OpenCV KLT, OpenCV KLT + CLAHE, all at the tracker's deployed pyramid depth) and "
        "write report.md, results.json and the figures.",
        epilog=f"analyses: {listing}",
    )
    parser.add_argument("--out", default="out/evaluation", help="report folder (default out/evaluation)")
    parser.add_argument(
        "--quick", action="store_true", help="tiny sizes: well under a minute, figures not meaningful"
    )
    parser.add_argument(
        "--model", default=None,
        help="NSFlow ONNX encoder: a file, or a shipped model by name (default, fast; default: default)",
    )
    parser.add_argument("--only", type=names, default=[], metavar="KEY[,KEY]", help="run only these analyses")
    parser.add_argument(
        "--skip", type=names, default=[], metavar="KEY[,KEY]", help="leave these analyses out"
    )
    parser.add_argument("--seed", type=int, default=0, help="base seed of every random choice (default 0)")
    parser.add_argument("--threads", type=int, default=None, help="encoder threads (default: all cores)")
    parser.add_argument(
        "--providers", default="cpu",
        help="onnxruntime execution providers of the encoder, best first, e.g. cuda,cpu (default cpu)",
    )
    parser.add_argument("--no-progress", action="store_true", help="no progress bars")
    parser.add_argument("--list", action="store_true", help="list the analyses and exit")
    return parser


def main(args: list[str] | None = None) -> int:
    """Entry point (``args`` None: ``sys.argv[1:]``); returns 0 when the report is written and every
    analysis ran, 1 on a known error."""
    opts = build_parser().parse_args(args)
    if opts.list:
        for a in ANALYSES:
            print(f"{a.key:12s} {a.title}")
        return 0
    keep_large_buffers()  # as the tracker node does, so that per-frame times compare
    started = now()
    try:
        require_extra("eval", "the evaluation")  # one line now, rather than one per analysis at its turn
        analyses = select(opts.only, opts.skip)
        model = model_file(opts.model) if opts.model is not None else None
        if model is not None and not model.is_file():
            raise EvaluationError(f"model file not found: {model}")
        out = Path(opts.out)
        try:
            out.mkdir(parents=True, exist_ok=True)
        except OSError as err:
            raise EvaluationError(f"cannot create the report folder {out}: {err}") from err
        methods, left_out = usable_methods(str(model) if model else None, threads=opts.threads,
                                           providers=opts.providers)
        for why in left_out.values():
            print(f"nsflow-evaluate: left out {why}", file=sys.stderr)
        ctx = EvalContext(
            methods=methods,
            model=model,
            quick=opts.quick,
            out_dir=out,
            progress=not opts.no_progress,
            seed=opts.seed,
            threads=opts.threads,
            providers=opts.providers,
        )
        result = run_analyses(ctx, analyses)
        info = machine_info(model)
        info["left_out"] = left_out
        command = command_line("nsflow-evaluate", args)
        report, _ = write_report(out, result, info, command, started, quick=opts.quick)
    except NSFlowError as err:
        print(f"nsflow-evaluate: {err}", file=sys.stderr)
        return 1
    print(f"nsflow-evaluate: wrote {report} ({sum(result.seconds.values()):.0f} s)")
    for key, msg in result.failures.items():
        print(f"nsflow-evaluate: analysis {key} failed: {msg}", file=sys.stderr)
    return 1 if result.failures else 0


if __name__ == "__main__":
    sys.exit(main())
