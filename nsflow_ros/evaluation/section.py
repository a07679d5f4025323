"""One part of the evaluation report: its Markdown text, its figures and its headline rows."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

__all__ = ["QUICK_NOTE", "HeadlineRow", "Section", "config_data", "quick_note"]

QUICK_NOTE = " **Quick mode: tiny sizes, figures not meaningful.**"
"""What a quick run's section appends to its first paragraph."""


@dataclass(frozen=True)
class HeadlineRow:
    """One row of the report's headline table: a metric and each method's value as printed text.

    Attributes:
        metric: what is measured, with its unit ("median error, large perturbation (px)").
        values: method name -> formatted value; methods missing from a row print as "-".
        target: the issue's target for this metric in words ("<= 0.5 px"), or "" when it has none.
        met: whether NSFlow meets the target; None when there is no target.
    """

    metric: str
    values: dict[str, str]
    target: str = ""
    met: bool | None = None


@dataclass(frozen=True)
class Section:
    """A finished analysis, ready to be written into the report.

    Attributes:
        key: short identifier, also the stem of the section's files ("pairs", "convergence").
        title: the heading in the report.
        markdown: the body (tables, one paragraph of method, the figures' captions and links); figure
            links are relative to the report folder.
        figures: PNG files the section wrote into the report folder.
        headline: rows for the report's headline table.
        data: the raw figures, JSON-serialisable, written to ``results.json``.
    """

    key: str
    title: str
    markdown: str
    figures: list[Path] = field(default_factory=list)
    headline: list[HeadlineRow] = field(default_factory=list)
    data: dict = field(default_factory=dict)


def quick_note(quick: bool) -> str:
    """:data:`QUICK_NOTE` in a quick run, else nothing."""
    return QUICK_NOTE if quick else ""


def config_data(cfg: Any) -> dict[str, Any]:
    """An analysis's settings dataclass as the section's JSON data (tuples as lists)."""
    return {k: (list(v) if isinstance(v, tuple) else v) for k, v in vars(cfg).items()}
