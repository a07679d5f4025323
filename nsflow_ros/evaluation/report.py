"""Runs the selected analyses and writes ``report.md`` and ``results.json``.

An analysis that fails with a known error (:class:`~nsflow_ros.errors.NSFlowError`) is reported as
failed and the others still run, so a long run is never lost to one broken part.
"""

from __future__ import annotations

import json
import math
import os
import platform
import subprocess
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path
from typing import Any

from nsflow_ros.errors import NSFlowError
from nsflow_ros.evaluation.context import EvalContext, atomic_write
from nsflow_ros.evaluation.methods import METHOD_ORDER
from nsflow_ros.evaluation.registry import Analysis
from nsflow_ros.evaluation.section import HeadlineRow, Section
from nsflow_ros.results import cpu_model, run_header, table, table_lines, write_tables

__all__ = [
    "RunResult",
    "headline",
    "headline_table",
    "machine_info",
    "now",
    "render_report",
    "run_analyses",
    "write_report",
]


@dataclass
class RunResult:
    """What a run produced.

    Attributes:
        sections: the finished sections, in registry order.
        seconds: analysis key -> wall-clock seconds it took (failed ones included).
        failures: analysis key -> the error message of an analysis that failed.
    """

    sections: list[Section] = field(default_factory=list)
    seconds: dict[str, float] = field(default_factory=dict)
    failures: dict[str, str] = field(default_factory=dict)


def run_analyses(ctx: EvalContext, analyses: Sequence[Analysis]) -> RunResult:
    """Run each analysis in turn (``ctx.out_dir`` must exist) with a progress bar over them.

    An analysis raising a :class:`~nsflow_ros.errors.NSFlowError` is recorded in ``failures``; other
    exceptions are bugs and propagate.
    """
    result = RunResult()
    for a in ctx.bar(analyses, desc="evaluation", total=len(analyses), unit="analysis"):
        t0 = time.perf_counter()
        try:
            result.sections.append(a.run(ctx))
        except NSFlowError as err:
            result.failures[a.key] = str(err)
        result.seconds[a.key] = time.perf_counter() - t0
    return result


def _git_commit() -> str:
    root = Path(__file__).resolve().parents[2]
    try:
        out = subprocess.run(
            ["git", "-C", str(root), "describe", "--always", "--dirty", "--abbrev=12"],
            capture_output=True,
            text=True,
            timeout=10,
            check=True,
        )
    except (OSError, subprocess.SubprocessError):
        return "unknown (not a git checkout)"
    return out.stdout.strip() or "unknown"


def machine_info(model: Path | None = None) -> dict[str, Any]:
    """Where the figures were measured, as JSON data: CPUs, load, Python and library versions, git commit,
    the NSFlow encoder file (None: the shipped one)."""
    load = os.getloadavg() if hasattr(os, "getloadavg") else (math.nan,) * 3
    return {
        "cpu_count": os.cpu_count(), "load_average_1_5_15": [round(v, 2) for v in load],
        "processor": cpu_model(), "platform": platform.platform(), **run_header("")["versions"],
        "git_commit": _git_commit(),
        "model": str(model) if model is not None else (
            "each method's shipped default (nsflow: models/nsflow_encoder_fast.onnx, "
            "nsflow_lk: models/nsflow_encoder.onnx)"
        ),
    }


def headline_table(sections: Sequence[Section]) -> str:
    """Every section's headline rows as a Markdown table (one column per method, then target and met), or a
    sentence when there are none."""
    rows = [row for s in sections for row in s.headline]
    if not rows:
        return "_No headline figures in this run._"
    return "\n".join(table_lines(headline(rows)))


def headline(rows: Sequence[HeadlineRow]) -> dict[str, Any]:
    """The headline rows as a :func:`nsflow_ros.results.table`."""
    extra = sorted({m for r in rows for m in r.values} - set(METHOD_ORDER))
    cols = [*METHOD_ORDER, *extra]
    met = {None: "-", True: "yes", False: "**no**"}
    cells = [[r.metric, *(r.values.get(c, "-") for c in cols), r.target or "-", met[r.met]] for r in rows]
    return table("Headline", ["metric", *cols, "target", "met"], cells)


def render_report(
    result: RunResult, info: dict[str, Any], command: str, started: datetime, quick: bool = False
) -> str:
    """The Markdown report of a run: ``info`` is :func:`machine_info`, ``started`` the local start time."""
    total = sum(result.seconds.values())
    lines = [
        "# NSFlow evaluation report",
        "",
        f"- date: {started.strftime('%Y-%m-%d %H:%M %Z').strip()}",
        f"- command: `{command}`",
        f"- run time: {total:.0f} s (" + ", ".join(f"{k} {v:.0f} s" for k, v in result.seconds.items()) + ")",
        f"- machine: {info['cpu_count']} CPUs ({info['processor']}), load average "
        f"{' / '.join(str(v) for v in info['load_average_1_5_15'])} at the end, {info['platform']}",
        f"- software: Python {info['python']}, NumPy {info['numpy']}, OpenCV {info['opencv']}, "
        f"onnxruntime {info['onnxruntime']}; git {info['git_commit']}",
        f"- NSFlow encoder: {info['model']}",
        *(f"- left out: {why}" for why in info.get("left_out", {}).values()),
        "",
    ]
    if quick:
        lines += ["**Quick mode: tiny sizes for testing; the figures below are not meaningful.**", ""]
    if result.failures:
        lines += ["## Failed analyses", ""]
        lines += [f"- **{k}**: {msg}" for k, msg in result.failures.items()]
        lines.append("")
    lines += [
        "## Headline",
        "",
        'Lost points count as infinite error wherever a median is given. "met" says whether NSFlow '
        "meets the target; the figures decide.",
        "",
        headline_table(result.sections),
        "",
    ]
    for s in result.sections:
        lines += [f"## {s.title}", "", s.markdown.rstrip(), ""]
    return "\n".join(lines)


def _jsonable(obj: Any) -> Any:
    """Replace non-finite floats (JSON has none) by strings and NumPy scalars by Python numbers."""
    if isinstance(obj, dict):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if hasattr(obj, "item") and callable(obj.item) and getattr(obj, "ndim", 1) == 0:
        obj = obj.item()
    if hasattr(obj, "tolist"):
        return _jsonable(obj.tolist())
    if isinstance(obj, float) and not math.isfinite(obj):
        return str(obj)
    if isinstance(obj, Path):
        return str(obj)
    return obj


def write_report(
    out_dir: Path,
    result: RunResult,
    info: dict[str, Any],
    command: str,
    started: datetime,
    quick: bool = False,
) -> tuple[Path, Path]:
    """Write ``report.md`` (:func:`render_report`) and ``results.json`` atomically into ``out_dir``.

    Returns:
        (report path, results path).

    Raises:
        EvaluationError: a file cannot be written.
    """
    out_dir = Path(out_dir)
    text = render_report(result, info, command, started, quick)
    results = {
        "date": started.isoformat(timespec="seconds"),
        "command": command,
        "quick": quick,
        "machine": info,
        "seconds": result.seconds,
        "failures": result.failures,
        "headline": [
            {"section": s.key, "metric": r.metric, "values": r.values, "target": r.target, "met": r.met}
            for s in result.sections
            for r in s.headline
        ],
        "sections": {
            s.key: {"title": s.title, "figures": [Path(f).name for f in s.figures], "data": s.data}
            for s in result.sections
        },
    }
    report = atomic_write(out_dir / "report.md", lambda p: p.write_text(text, encoding="utf-8"))
    if rows := [row for s in result.sections for row in s.headline]:  # the table the docs paste
        write_tables({"header": run_header(command), "tables": [headline(rows)]}, out_dir / "tables.json",
                     out_dir / "tables.md")
    payload = json.dumps(_jsonable(results), indent=2, allow_nan=False)
    res = atomic_write(out_dir / "results.json", lambda p: p.write_text(payload + "\n", encoding="utf-8"))
    return report, res


def now() -> datetime:
    """The local time, with its zone."""
    return datetime.now().astimezone()
