"""Command line of the ATE tools: ``nsflow-ate`` (``ros2 run nsflow_ros ate`` from a ROS workspace).

Three subcommands; ``ape`` is the default when the first argument is not a subcommand::

    ate [ape] GT EST [--align se3|sim3|none] [--n-align N] [--max-diff S] [--offset S]
                     [--rpe-delta N] [--plot OUT.png] [--json]
    ate drift GT EST [--align se3|sim3] [--min-gap S] [--json]
    ate batch ROOT [--gt-root DIR] [--out DIR] [--methods A,B] [--levels none,small,large]
                   [--fail-if any|majority|all] [--min-coverage F] [--max-rmse M] [--plots] [--json]

Exit status: 0 on success, 1 for a known error (unreadable or empty file, no overlapping stamps, NaNs,
fewer than 3 matched poses, ...; the message goes to stderr), 2 for a usage error.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from nsflow_ros.argtypes import finite_float, names, non_negative_float, positive_int, program_name
from nsflow_ros.ate.align import ALIGN_METHODS
from nsflow_ros.ate.batch import (
    FAIL_POLICIES,
    FailureCriteria,
    score_batch,
    write_batch_tables,
)
from nsflow_ros.ate.drift import evaluate_drift
from nsflow_ros.ate.formats import FORMATS, read_trajectory
from nsflow_ros.ate.metrics import STAT_KEYS, evaluate_ape
from nsflow_ros.errors import NSFlowError

__all__ = ["build_parser", "main"]

PROG = "nsflow-ate"
_SUBCOMMANDS = ("ape", "drift", "batch")

_FORMATS_HELP = f"""\
trajectory formats (detected, or named with --gt-format / --est-format: {", ".join(FORMATS)}):
  euroc  EuRoC/ASL ground truth csv: #header, t_ns, px, py, pz, qw, qx, qy, qz, ...
         (an ASL sequence folder holding mav0/ may be given instead of the file)
  tum    t x y z qx qy qz qw, t in seconds, space separated
  vins   VINS-Fusion vio.csv / VINS-Mono vins_result_*.csv: t_ns, px, py, pz, qw, qx, qy, qz, vx, vy, vz,
"""

_BATCH_HELP = """\
layout: ROOT/<sequence>/<level>/<method>/<rep>/vio.csv  (or <rep>.csv|.txt|.tum files)
  ground truth of <sequence> under --gt-root (default ROOT): <sequence>/groundtruth.{csv,txt,tum},
  <sequence>/mav0/state_groundtruth_estimate0/data.csv (an ASL folder), or <sequence>.{csv,txt,tum}
failed run ("F"): empty (no estimate file or no poses), unreadable (malformed row),
  too short (no overlap, < 3 matched poses, or matched span < --min-coverage of the ground truth),
  diverged (NaN, collapsed estimate, or ATE RMSE > --max-rmse)
cell: mean/median of the per-run ATE RMSE over successful repetitions; F per --fail-if
writes <out>/ate_table.md, ate_table.csv (same layout) and ate_table_runs.csv (one row per run)
"""


def _add_common(p: argparse.ArgumentParser, aligns: tuple[str, ...], default_align: str = "se3") -> None:
    p.add_argument(
        "--align",
        choices=aligns,
        default=default_align,
        help=f"Umeyama alignment of the estimate (default {default_align})",
    )
    p.add_argument(
        "--max-diff",
        type=finite_float,
        default=0.01,
        metavar="S",
        help="largest stamp difference of a matched pair, seconds (default 0.01)",
    )
    p.add_argument(
        "--offset",
        type=finite_float,
        default=0.0,
        metavar="S",
        help="seconds added to the estimate's stamps before matching (default 0)",
    )
    p.add_argument("--gt-format", choices=(*FORMATS, "auto"), default="auto", help="ground-truth format")
    p.add_argument("--est-format", choices=(*FORMATS, "auto"), default="auto", help="estimate format")
    p.add_argument("--json", action="store_true", help="print the results as one JSON object")


def build_parser() -> argparse.ArgumentParser:
    """The argument parser with the ``ape``, ``drift`` and ``batch`` subcommands."""
    parser = argparse.ArgumentParser(
        prog=program_name(PROG),
        description="Score trajectories against ground truth: ATE (APE) with optional RPE, UMA-VI drift, "
        "and batch tables in the layout of the paper's EuRoC table. 'ape' is the default subcommand.",
        epilog=_FORMATS_HELP,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--version", action="version", version="%(prog)s (nsflow_ros) 0.1.0")
    sub = parser.add_subparsers(dest="command", required=True, metavar="{ape,drift,batch}")

    ape = sub.add_parser(
        "ape",
        help="absolute trajectory error of one run (default)",
        description="Associate, align and score one estimate; prints rmse, mean, median, std, min, max, n.",
        epilog=_FORMATS_HELP,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    ape.add_argument("gt", type=Path, help="ground truth file or ASL sequence folder")
    ape.add_argument("est", type=Path, help="estimate file or run folder (vio.csv, ...)")
    _add_common(ape, ALIGN_METHODS)
    ape.add_argument(
        "--n-align", type=positive_int, metavar="N", help="fit the alignment on the first N matched poses"
    )
    ape.add_argument(
        "--skip",
        type=non_negative_float,
        default=0.0,
        metavar="S",
        help="leave out the estimate's first S seconds, an estimator's start (default 0)",
    )
    ape.add_argument(
        "--rpe-delta",
        type=positive_int,
        metavar="N",
        help="also report the relative pose error over N matched poses (JSON key 'rpe')",
    )
    ape.add_argument("--rpe-all-pairs", action="store_true", help="RPE over every start pose, not every N-th")
    ape.add_argument("--plot", type=Path, metavar="PNG", help="write a top-view plot coloured by error")

    drift = sub.add_parser(
        "drift",
        help="UMA-VI start/end segment drift (ground truth only at the start and the end)",
        description="Align the estimate separately to the first and the last ground-truth segment "
        "(segments are separated by gaps longer than --min-gap) and report the alignment error "
        "(RMS distance between the two alignments over the whole estimate), the end drift, the rotation "
        "drift and the drift as a percentage of the path length.",
        epilog=_FORMATS_HELP,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    drift.add_argument("gt", type=Path, help="ground truth with a start and an end segment")
    drift.add_argument("est", type=Path, help="estimate file or run folder")
    _add_common(drift, ("se3", "sim3"))
    drift.add_argument(
        "--min-gap",
        type=finite_float,
        default=1.0,
        metavar="S",
        help="a ground-truth gap longer than this separates segments (default 1 s)",
    )

    batch = sub.add_parser(
        "batch",
        help="score a directory of runs into Markdown/CSV tables",
        description="Score every run of a batch directory and write the table of the paper's EuRoC layout: "
        "rows = sequences, column groups = perturbation levels, columns = methods.",
        epilog=_BATCH_HELP,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    batch.add_argument("root", type=Path, help="batch directory")
    batch.add_argument(
        "--gt-root", type=Path, help="folder with the ground truth of each sequence (default ROOT)"
    )
    batch.add_argument("--out", type=Path, help="folder for the tables (default ROOT)")
    batch.add_argument("--methods", type=names, help="comma-separated columns in order (default: all found)")
    batch.add_argument("--levels", type=names, help="comma-separated column groups in order (default: all)")
    batch.add_argument(
        "--n-align", type=positive_int, metavar="N", help="fit the alignment on the first N matched poses"
    )
    batch.add_argument(
        "--fail-if", choices=FAIL_POLICIES, default="any", help="failed repetitions that make a cell F (any)"
    )
    batch.add_argument(
        "--min-coverage",
        type=finite_float,
        default=0.5,
        metavar="F",
        help="share of the ground truth's duration a run must span (default 0.5)",
    )
    batch.add_argument(
        "--max-rmse", type=finite_float, default=10.0, metavar="M",
        help="RMSE above which a run diverged (10 m)",
    )
    batch.add_argument("--digits", type=positive_int, default=3, help="decimals in the Markdown table (3)")
    batch.add_argument("--plots", action="store_true", help="also write <out>/ate_plots/<run>.png per run")
    _add_common(batch, ALIGN_METHODS)
    return parser


def _fmt_opt(fmt: str) -> str | None:
    return None if fmt == "auto" else fmt


def _run_ape(ns: argparse.Namespace) -> int:
    gt = read_trajectory(ns.gt, _fmt_opt(ns.gt_format))
    est = read_trajectory(ns.est, _fmt_opt(ns.est_format))
    result = evaluate_ape(
        gt,
        est,
        align=ns.align,
        n_align=ns.n_align,
        max_diff=ns.max_diff,
        offset=ns.offset,
        rpe_delta=ns.rpe_delta,
        rpe_all_pairs=ns.rpe_all_pairs,
        skip=ns.skip,
    )
    if ns.plot is not None:
        from nsflow_ros.ate.plot import plot_top_view

        plot_top_view(result, ns.plot)
    if ns.json:
        obj: dict[str, object] = dict(result.stats.as_dict())
        if result.rpe is not None:
            obj["rpe"] = result.rpe.as_dict()
        print(json.dumps(obj))
        return 0
    fit = result.alignment
    print(f"APE (position error, m) of {est.name}")
    print(f"  against {gt.name}")
    print(f"  alignment {fit.method}, scale {fit.scale:.6f}, {result.stats.n} matched poses")
    for key in STAT_KEYS[:-1]:
        print(f"  {key:<7}{getattr(result.stats, key):.6f}")
    if result.rpe is not None:
        rpe = result.rpe
        pairs = "all" if rpe.all_pairs else "consecutive"
        print(f"RPE over {rpe.delta} poses ({rpe.translation.n} {pairs} pairs)")
        for key in STAT_KEYS[:-1]:
            t, r = getattr(rpe.translation, key), getattr(rpe.rotation_deg, key)
            print(f"  {key:<7}{t:.6f} m  {r:.6f} deg")
    if ns.plot is not None:
        print(f"plot: {ns.plot}")
    return 0


def _run_drift(ns: argparse.Namespace) -> int:
    gt = read_trajectory(ns.gt, _fmt_opt(ns.gt_format))
    est = read_trajectory(ns.est, _fmt_opt(ns.est_format))
    result = evaluate_drift(
        gt, est, align=ns.align, max_diff=ns.max_diff, offset=ns.offset, min_gap=ns.min_gap
    )
    if ns.json:
        print(json.dumps(result.as_dict()))
        return 0
    print(f"drift of {est.name}")
    print(f"  against the start and end segments of {gt.name} ({ns.align} per segment)")
    print(f"  alignment_error    {result.alignment_error:.6f} m")
    print(f"  end_drift          {result.end_drift:.6f} m")
    print(f"  rotation_drift     {result.rotation_drift_deg:.6f} deg")
    print(f"  path_length        {result.path_length:.3f} m")
    print(f"  drift              {result.drift_percent:.4f} % of the path")
    print(f"  matched poses      start {result.n_start}, end {result.n_end}")
    return 0


def _run_batch(ns: argparse.Namespace) -> int:
    criteria = FailureCriteria(min_coverage=ns.min_coverage, max_rmse=ns.max_rmse, fail_if=ns.fail_if)
    out = ns.out if ns.out is not None else ns.root
    result = score_batch(
        ns.root,
        gt_root=ns.gt_root,
        align=ns.align,
        n_align=ns.n_align,
        max_diff=ns.max_diff,
        offset=ns.offset,
        criteria=criteria,
        methods=ns.methods,
        levels=ns.levels,
        gt_format=_fmt_opt(ns.gt_format),
        est_format=_fmt_opt(ns.est_format),
        plot_dir=out / "ate_plots" if ns.plots else None,
    )
    files = write_batch_tables(result, out, digits=ns.digits)
    if ns.json:
        runs = []
        for r in result.runs:
            item: dict[str, object] = {
                "sequence": r.spec.sequence,
                "level": r.spec.level,
                "method": r.spec.method,
                "rep": r.spec.rep,
                "status": r.category,
                "reason": r.reason,
            }
            item.update(r.stats.as_dict() if r.stats is not None else {})
            runs.append(item)
        print(json.dumps({"files": {k: str(v) for k, v in files.items()}, "runs": runs}))
        return 0
    print(files["markdown"].read_text(encoding="utf-8"), end="")  # the table just written
    print(f"\nwrote {', '.join(str(p) for p in files.values())}")
    return 0


def main(args: list[str] | None = None) -> int:
    """Run the CLI on ``args`` (default ``sys.argv[1:]``); returns the exit status."""
    argv = list(sys.argv[1:] if args is None else args)
    if argv and argv[0] not in (*_SUBCOMMANDS, "-h", "--help", "--version"):
        argv.insert(0, "ape")
    parser = build_parser()
    try:
        ns = parser.parse_args(argv)
    except SystemExit as exc:
        return exc.code if isinstance(exc.code, int) else 2
    handlers = {"ape": _run_ape, "drift": _run_drift, "batch": _run_batch}
    try:
        return handlers[ns.command](ns)
    except NSFlowError as exc:
        print(f"{program_name(PROG)}: error: {exc}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
