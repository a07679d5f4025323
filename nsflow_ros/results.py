"""Measured tables as JSON and as the Markdown the docs paste (``nsflow-bench --tables``, nsflow-evaluate).

A tables file is ``{"header": {...}, "tables": [{"title", "columns", "rows", "notes"}]}`` with every cell
already a string. :func:`markdown` renders one and reads nothing else, so a stored JSON file regenerates
its Markdown byte for byte (``test/test_results.py`` checks the files under ``docs/results``).
"""

from __future__ import annotations

import json
import os
import platform
import shlex
import sys
from collections.abc import Sequence
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from nsflow_ros.files import atomic_write

__all__ = ["command_line", "cpu_model", "markdown", "run_header", "table", "table_lines", "write_tables"]


def cpu_model() -> str:
    """The CPU's model name (``/proc/cpuinfo``; elsewhere what ``platform`` knows)."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def command_line(program: str, args: Sequence[str] | None = None) -> str:
    """The command as typed, shell-quoted, under its console-script name; ``args`` None = ``sys.argv[1:]``."""
    return shlex.join([program, *(sys.argv[1:] if args is None else args)])


def run_header(command: str) -> dict[str, Any]:
    """Date (UTC), machine (CPU model, cores, load), the exact command and the library versions."""
    import cv2
    import numpy as np
    import onnxruntime

    from nsflow_ros import __version__

    load = os.getloadavg() if hasattr(os, "getloadavg") else ()
    return {
        "date": datetime.now(UTC).strftime("%Y-%m-%d %H:%M UTC"),
        "machine": f"{cpu_model()}, {os.cpu_count()} cores",
        "load_average_1_5_15": " / ".join(f"{v:.1f}" for v in load),
        "command": command,
        "versions": {"nsflow_ros": __version__, "numpy": np.__version__, "opencv": cv2.__version__,
                     "onnxruntime": onnxruntime.__version__, "python": platform.python_version()},
    }


def table(title: str, columns: Sequence[str], rows: Sequence[Sequence[str]], notes: str = "") -> dict:
    """One table of a tables file (cells as strings)."""
    return {"title": title, "columns": list(columns), "rows": [list(r) for r in rows], "notes": notes}


def table_lines(t: dict[str, Any]) -> list[str]:
    """The Markdown lines of one :func:`table` (no title, no notes)."""
    return ["| " + " | ".join(t["columns"]) + " |", "|" + "---|" * len(t["columns"]),
            *("| " + " | ".join(r) + " |" for r in t["rows"])]


def markdown(doc: dict[str, Any]) -> str:
    """The Markdown of a tables file: the header, then each table under its title; a pure function of doc."""
    h = doc["header"]
    versions = ", ".join(f"{k} {v}" for k, v in h["versions"].items())
    load = f" (load average {h['load_average_1_5_15']})" if h.get("load_average_1_5_15") else ""
    lines = [f"Measured {h['date']} on {h['machine']}{load}; {versions}.", "", "```bash", h["command"], "```"]
    for t in doc["tables"]:
        lines += ["", f"**{t['title']}**", "", *table_lines(t), *(["", t["notes"]] if t.get("notes") else [])]
    return "\n".join(lines) + "\n"


def write_tables(doc: dict[str, Any], json_path: Path, md_path: Path) -> None:
    """Write the tables file as JSON and its :func:`markdown`, each atomically."""
    payload = json.dumps(doc, indent=2) + "\n"
    atomic_write(Path(json_path), lambda p: p.write_text(payload, encoding="utf-8"))
    atomic_write(Path(md_path), lambda p: p.write_text(markdown(doc), encoding="utf-8"))
