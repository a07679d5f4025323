"""Batch scoring: a directory of runs becomes the paper's EuRoC table, in Markdown and CSV.

Directory layout (hidden folders and ``mav0`` are skipped)::

    <root>/<sequence>/<level>/<method>/<rep>/vio.csv

Sequences are the table's rows, perturbation levels its column groups (:data:`LEVEL_ORDER` first), methods
the columns within a group; a repetition is a folder holding an estimate
(:data:`~nsflow_ros.ate.formats.ESTIMATE_NAMES`) or a trajectory file named after it. A failed
repetition is ``empty``, ``unreadable``, ``too short`` or ``diverged`` (:class:`FailureCriteria`); a cell
shows ``mean/median`` of the successful repetitions' ATE RMSE, "F" per ``fail_if``, or "-" without runs.
"""

from __future__ import annotations

import csv
import io
import math
import re
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from nsflow_ros.ate.errors import ATEError
from nsflow_ros.ate.formats import read_trajectory, resolve_trajectory_path
from nsflow_ros.ate.metrics import STAT_KEYS, APEResult, ErrorStats, evaluate_ape
from nsflow_ros.ate.trajectory import Trajectory

__all__ = [
    "FAIL_POLICIES",
    "LEVEL_ORDER",
    "BatchResult",
    "Cell",
    "FailureCriteria",
    "RunResult",
    "RunSpec",
    "batch_csv",
    "batch_markdown",
    "discover_runs",
    "find_ground_truth",
    "runs_csv",
    "score_batch",
    "write_batch_tables",
]

LEVEL_ORDER: tuple[str, ...] = ("none", "small", "medium", "large")
"""Perturbation levels that come first, in this order; others follow alphabetically."""

FAIL_POLICIES: tuple[str, ...] = ("any", "majority", "all")
"""Values of :attr:`FailureCriteria.fail_if`."""

_GT_NAMES = (
    "groundtruth.csv",
    "groundtruth.txt",
    "groundtruth.tum",
    "mav0/state_groundtruth_estimate0/data.csv",
)
_TRAJ_SUFFIXES = (".csv", ".txt", ".tum")
_SKIP_DIRS = ("mav0",)


def _natural_key(text: str) -> list[object]:
    return [int(tok) if tok.isdigit() else tok.lower() for tok in re.split(r"(\d+)", text)]


def _level_key(level: str) -> tuple[int, list[object]]:
    if level in LEVEL_ORDER:
        return (LEVEL_ORDER.index(level), [])
    return (len(LEVEL_ORDER), _natural_key(level))


@dataclass(frozen=True)
class FailureCriteria:
    """When a repetition counts as failed, and when a cell shows "F".

    A run is ``empty`` without an estimate or poses, ``unreadable`` with a malformed row, ``too short``
    without overlap, with fewer than 3 matched poses or spanning less than ``min_coverage`` of the ground
    truth's duration, ``diverged`` with NaN / inf, a collapsed estimate or an ATE RMSE above ``max_rmse``
    (metres). ``fail_if``: ``"any"``, ``"majority"`` (more than half) or ``"all"`` failed repetitions
    make the cell "F".
    """

    min_coverage: float = 0.5
    max_rmse: float = 10.0
    fail_if: str = "any"

    def __post_init__(self) -> None:
        if not 0.0 <= self.min_coverage <= 1.0:
            raise ATEError(f"min_coverage must be within [0, 1], got {self.min_coverage}")
        if not self.max_rmse > 0:
            raise ATEError(f"max_rmse must be positive, got {self.max_rmse}")
        if self.fail_if not in FAIL_POLICIES:
            raise ATEError(f"fail_if must be one of {', '.join(FAIL_POLICIES)}, got {self.fail_if!r}")


@dataclass(frozen=True)
class RunSpec:
    """One repetition found on disk: its row, column group, column, name and folder or file."""

    sequence: str
    level: str
    method: str
    rep: str
    path: Path


@dataclass(frozen=True)
class RunResult:
    """Score of one repetition.

    Attributes:
        spec: where it came from.
        stats: APE statistics (``None`` when the run failed before scoring).
        reason: empty when the run succeeded, else ``"<category>: <detail>"``.
        coverage: share of the ground truth's duration spanned by the matched poses (0 when unknown).
        estimate: the estimate file read, if any.
    """

    spec: RunSpec
    stats: ErrorStats | None
    reason: str = ""
    coverage: float = 0.0
    estimate: Path | None = None

    @property
    def ok(self) -> bool:
        """Whether the repetition succeeded."""
        return not self.reason

    @property
    def category(self) -> str:
        """``"ok"`` or the failure category."""
        return "ok" if self.ok else self.reason.split(":", 1)[0]


@dataclass(frozen=True)
class Cell:
    """The repetitions of one (sequence, level, method), whether the cell shows "F", and the ATE RMSE of
    the successful ones (m)."""

    runs: tuple[RunResult, ...]
    failed: bool
    values: tuple[float, ...] = field(default=())

    @property
    def mean(self) -> float:
        """Mean over successful repetitions (NaN when none)."""
        return float(np.mean(self.values)) if self.values else math.nan

    @property
    def median(self) -> float:
        """Median over successful repetitions (NaN when none)."""
        return float(np.median(self.values)) if self.values else math.nan


@dataclass(frozen=True)
class BatchResult:
    """Every run of a batch, the table layout (rows, column groups, columns in order), the failure
    criteria and the alignment used."""

    sequences: tuple[str, ...]
    levels: tuple[str, ...]
    methods: tuple[str, ...]
    runs: tuple[RunResult, ...]
    criteria: FailureCriteria
    align: str

    def cell(self, sequence: str, level: str, method: str) -> Cell | None:
        """The cell of a row, column group and column, or ``None`` without a repetition."""
        runs = tuple(
            r
            for r in self.runs
            if (r.spec.sequence, r.spec.level, r.spec.method) == (sequence, level, method)
        )
        if not runs:
            return None
        values = tuple(r.stats.rmse for r in runs if r.ok and r.stats is not None)
        n_failed = len(runs) - len(values)
        policy = self.criteria.fail_if
        if policy == "any":
            failed = n_failed > 0
        elif policy == "majority":
            failed = 2 * n_failed > len(runs)
        else:
            failed = n_failed == len(runs)
        return Cell(runs, failed or not values, values)


def _is_trajectory_file(path: Path) -> bool:
    return path.is_file() and path.suffix.lower() in _TRAJ_SUFFIXES


def _subdirs(path: Path) -> list[Path]:
    return sorted(
        (p for p in path.iterdir() if p.is_dir() and not p.name.startswith(".") and p.name not in _SKIP_DIRS),
        key=lambda p: _natural_key(p.name),
    )


def discover_runs(root: str | Path) -> list[RunSpec]:
    """The repetitions under ``root`` in table order (sequences, methods and repetitions in natural order,
    levels per :data:`LEVEL_ORDER`).

    Raises:
        ATEError: when ``root`` is not a directory.
    """
    root = Path(root)
    if not root.is_dir():
        raise ATEError(f"{root}: batch root is not a directory", reason="missing")
    specs: list[RunSpec] = []
    for seq in _subdirs(root):
        for level in sorted(_subdirs(seq), key=lambda p: _level_key(p.name)):
            for method in _subdirs(level):
                entries = sorted(method.iterdir(), key=lambda p: _natural_key(p.name))
                for rep in entries:
                    if rep.name.startswith("."):
                        continue
                    if rep.is_dir():
                        specs.append(RunSpec(seq.name, level.name, method.name, rep.name, rep))
                    elif _is_trajectory_file(rep):
                        specs.append(RunSpec(seq.name, level.name, method.name, rep.stem, rep))
    return specs


def find_ground_truth(gt_root: str | Path, sequence: str) -> Path:
    """The ground-truth file of a sequence under ``gt_root``, first match of
    ``<sequence>/groundtruth.{csv,txt,tum}``, an ASL folder ``<sequence>/mav0/...`` and
    ``<sequence>.{csv,txt,tum}``.

    Raises:
        ATEError: naming every place searched when none exists.
    """
    base = Path(gt_root)
    candidates = [base / sequence / name for name in _GT_NAMES]
    candidates += [base / f"{sequence}{suffix}" for suffix in _TRAJ_SUFFIXES]
    for cand in candidates:
        if cand.is_file():
            return cand
    tried = ", ".join(str(c) for c in candidates)
    raise ATEError(f"no ground truth for sequence {sequence!r} (looked for {tried})", reason="missing")


_CATEGORY = {
    "missing": "empty",
    "empty": "empty",
    "malformed": "unreadable",
    "invalid": "unreadable",
    "nan": "diverged",
    "degenerate": "diverged",
    "no_overlap": "too short",
    "too_few": "too short",
}


@dataclass(frozen=True)
class _Options:
    align: str
    n_align: int | None
    max_diff: float
    offset: float
    est_format: str | None


def _score_run(
    spec: RunSpec, gt: Trajectory, criteria: FailureCriteria, opts: _Options
) -> tuple[RunResult, APEResult | None]:
    estimate: Path | None = None
    try:
        estimate = resolve_trajectory_path(spec.path)
        est = read_trajectory(estimate, opts.est_format)
        result = evaluate_ape(
            gt, est, align=opts.align, n_align=opts.n_align, max_diff=opts.max_diff, offset=opts.offset
        )
    except ATEError as exc:
        reason = f"{_CATEGORY.get(exc.reason, 'unreadable')}: {exc}"
        return RunResult(spec, None, reason, 0.0, estimate), None
    span = float(result.ref.stamps.max() - result.ref.stamps.min())
    coverage = span / gt.duration if gt.duration > 0 else 1.0
    stats = result.stats
    if coverage < criteria.min_coverage:
        reason = (
            f"too short: matched poses span {100 * coverage:.1f}% of the ground truth "
            f"(< {100 * criteria.min_coverage:.0f}%)"
        )
        return RunResult(spec, stats, reason, coverage, estimate), result
    if stats.rmse > criteria.max_rmse:
        reason = f"diverged: ATE RMSE {stats.rmse:.3f} m > {criteria.max_rmse} m"
        return RunResult(spec, stats, reason, coverage, estimate), result
    return RunResult(spec, stats, "", coverage, estimate), result


def score_batch(
    root: str | Path,
    *,
    gt_root: str | Path | None = None,
    align: str = "se3",
    n_align: int | None = None,
    max_diff: float = 0.01,
    offset: float = 0.0,
    criteria: FailureCriteria | None = None,
    methods: Sequence[str] | None = None,
    levels: Sequence[str] | None = None,
    gt_format: str | None = None,
    est_format: str | None = None,
    plot_dir: str | Path | None = None,
) -> BatchResult:
    """Score every repetition under ``root`` against its sequence's ground truth.

    Args:
        root: batch folder.
        gt_root: where the ground truth of each sequence lives (:func:`find_ground_truth`; default
            ``root``).
        align: one of :data:`~nsflow_ros.ate.align.ALIGN_METHODS`.
        n_align: fit the alignment on the first N matched poses only.
        max_diff: association tolerance in seconds.
        offset: seconds added to the estimates' stamps.
        criteria: failure criteria (default :class:`FailureCriteria()`).
        methods: columns, in this order (default: all found); runs of other methods are ignored.
        levels: column groups, in this order (default: all found).
        gt_format: ground-truth format (default: detected).
        est_format: estimate format (default: detected).
        plot_dir: when given, a top-view PNG per scored run is written there.

    Raises:
        ATEError: when ``root`` holds no repetition, a sequence has no ground truth or it cannot be read,
            or an option is invalid. A failing repetition is not an error: it is recorded as failed.
    """
    criteria = criteria or FailureCriteria()
    specs = discover_runs(root)
    if methods is not None:
        specs = [s for s in specs if s.method in methods]
    if levels is not None:
        specs = [s for s in specs if s.level in levels]
    if not specs:
        raise ATEError(
            f"{root}: no runs found (expected <root>/<sequence>/<level>/<method>/<rep>/vio.csv)",
            reason="empty",
        )
    gt_base = Path(gt_root) if gt_root is not None else Path(root)
    opts = _Options(align, n_align, max_diff, offset, est_format)
    ground_truth: dict[str, Trajectory] = {}
    runs: list[RunResult] = []
    for spec in specs:
        if spec.sequence not in ground_truth:
            path = find_ground_truth(gt_base, spec.sequence)
            ground_truth[spec.sequence] = read_trajectory(path, gt_format)
        run, result = _score_run(spec, ground_truth[spec.sequence], criteria, opts)
        runs.append(run)
        if plot_dir is not None and result is not None and run.stats is not None:
            from nsflow_ros.ate.plot import plot_top_view

            name = f"{spec.sequence}_{spec.level}_{spec.method}_{spec.rep}.png"
            title = f"{spec.sequence} / {spec.level} / {spec.method} / {spec.rep}"
            plot_top_view(result, Path(plot_dir) / name, title=title)
    sequences = tuple(sorted({s.sequence for s in specs}, key=_natural_key))
    found_levels = sorted({s.level for s in specs}, key=_level_key)
    found_methods = sorted({s.method for s in specs}, key=_natural_key)
    return BatchResult(
        sequences=sequences,
        levels=tuple(levels) if levels is not None else tuple(found_levels),
        methods=tuple(methods) if methods is not None else tuple(found_methods),
        runs=tuple(runs),
        criteria=criteria,
        align=align,
    )


def _fmt(value: float, digits: int) -> str:
    return f"{value:.{digits}f}"


def batch_markdown(result: BatchResult, digits: int = 3, bold_best: bool = True) -> str:
    """The Markdown table in the paper's EuRoC layout plus the list of failed runs, with ``digits``
    decimals and, with ``bold_best``, the lowest mean of each (sequence, level) group in bold."""
    crit = result.criteria
    lines = [
        f"ATE RMSE [m], alignment {result.align}; each cell: mean/median over repetitions; "
        f"F: failed (fail_if={crit.fail_if}, min_coverage={crit.min_coverage}, max_rmse={crit.max_rmse} m); "
        "-: no run.",
        "",
    ]
    header = ["Seq."] + [f"{lv}: {m}" for lv in result.levels for m in result.methods]
    lines.append("| " + " | ".join(header) + " |")
    lines.append("|" + "|".join(["---"] + [":---:"] * (len(header) - 1)) + "|")
    for seq in result.sequences:
        row = [seq]
        for level in result.levels:
            cells = [result.cell(seq, level, m) for m in result.methods]
            means = [c.mean for c in cells if c is not None and not c.failed]
            best = min(means) if means and len(result.methods) > 1 else None
            for c in cells:
                if c is None:
                    row.append("-")
                elif c.failed:
                    row.append("F")
                else:
                    text = f"{_fmt(c.mean, digits)}/{_fmt(c.median, digits)}"
                    row.append(f"**{text}**" if bold_best and best is not None and c.mean == best else text)
        lines.append("| " + " | ".join(row) + " |")
    failed = [r for r in result.runs if not r.ok]
    if failed:
        lines += ["", "Failed runs:", ""]
        for r in failed:
            s = r.spec
            lines.append(f"- {s.sequence} / {s.level} / {s.method} / {s.rep}: {r.reason}")
    return "\n".join(lines) + "\n"


def batch_csv(result: BatchResult, digits: int = 6) -> str:
    """The table as CSV: a row per sequence, ``<level>:<method>:mean`` and ``:median`` columns per cell
    (metres, ``F`` for a failed cell, empty for no run)."""
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    header = ["sequence"]
    for level in result.levels:
        for m in result.methods:
            header += [f"{level}:{m}:mean", f"{level}:{m}:median"]
    writer.writerow(header)
    for seq in result.sequences:
        row = [seq]
        for level in result.levels:
            for m in result.methods:
                c = result.cell(seq, level, m)
                if c is None:
                    row += ["", ""]
                elif c.failed:
                    row += ["F", "F"]
                else:
                    row += [_fmt(c.mean, digits), _fmt(c.median, digits)]
        writer.writerow(row)
    return buf.getvalue()


def runs_csv(result: BatchResult, digits: int = 6) -> str:
    """One CSV row per repetition: where it is, its status (``ok`` or the failure category), its
    statistics, coverage, reason and estimate file."""
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    keys = STAT_KEYS[:-1]  # all but n, which is written as an integer
    writer.writerow(
        ["sequence", "level", "method", "rep", "status", *keys, "n", "coverage", "reason", "estimate"]
    )
    for r in result.runs:
        s = r.spec
        stats = [_fmt(getattr(r.stats, k), digits) for k in keys] if r.stats else [""] * len(keys)
        n = str(r.stats.n) if r.stats else ""
        writer.writerow(
            [
                s.sequence,
                s.level,
                s.method,
                s.rep,
                r.category,
                *stats,
                n,
                _fmt(r.coverage, 4),
                r.reason,
                str(r.estimate or ""),
            ]
        )
    return buf.getvalue()


def write_batch_tables(
    result: BatchResult, out_dir: str | Path, stem: str = "ate_table", digits: int = 3
) -> dict[str, Path]:
    """Write ``<stem>.md`` (``digits`` decimals), ``<stem>.csv`` and ``<stem>_runs.csv`` into ``out_dir``.

    Returns:
        ``{"markdown": path, "csv": path, "runs": path}``.

    Raises:
        ATEError: when a file cannot be written.
    """
    out = Path(out_dir)
    files = {
        "markdown": (out / f"{stem}.md", batch_markdown(result, digits=digits)),
        "csv": (out / f"{stem}.csv", batch_csv(result)),
        "runs": (out / f"{stem}_runs.csv", runs_csv(result)),
    }
    try:
        out.mkdir(parents=True, exist_ok=True)
        for path, text in files.values():
            path.write_text(text, encoding="utf-8")
    except OSError as exc:
        raise ATEError(f"{out}: cannot write the batch tables ({exc.strerror})") from exc
    return {key: path for key, (path, _) in files.items()}
