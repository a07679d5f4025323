"""Conventions shared by the command-line tools: argparse value types and the program name in usage lines.

Each type raises ``argparse.ArgumentTypeError`` naming the text given, so argparse itself rejects a bad
value (usage line, one error line naming the option, exit 2) and no tool starts work it would abandon on
an argument it could have checked up front.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
from typing import Any

__all__ = [
    "finite_float",
    "method_variant",
    "method_variants",
    "names",
    "non_negative_float",
    "non_negative_int",
    "positive_float",
    "positive_int",
    "program_name",
]


def finite_float(text: str) -> float:
    """A finite number."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"expected a finite number, got {text!r}")
    return value


def _integer(text: str, minimum: int) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
    if value < minimum:
        raise argparse.ArgumentTypeError(f"expected an integer >= {minimum}, got {value}")
    return value


def positive_int(text: str) -> int:
    """An integer >= 1."""
    return _integer(text, 1)


def non_negative_int(text: str) -> int:
    """An integer >= 0."""
    return _integer(text, 0)


def positive_float(text: str) -> float:
    """A finite number > 0."""
    value = finite_float(text)
    if value <= 0:
        raise argparse.ArgumentTypeError(f"expected a number > 0, got {text}")
    return value


def non_negative_float(text: str) -> float:
    """A finite number >= 0."""
    value = finite_float(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"expected a number >= 0, got {text}")
    return value


def names(text: str) -> list[str]:
    """A comma-separated list, spaces and empty items dropped: ``"a, b,"`` -> ``["a", "b"]``."""
    return [n.strip() for n in text.split(",") if n.strip()]


def method_variant(text: str) -> tuple[str, dict[str, Any]]:
    """A method with tracker settings, ``name[:key=value...]`` (e.g. ``nsflow:reverse_checks=1``), as
    (registry name, settings); values are YAML scalars (``1``, ``0.3``, ``true``)."""
    import yaml

    name, *pairs = text.split(":")
    overrides: dict[str, Any] = {}
    for pair in pairs:
        key, sep, value = pair.partition("=")
        if not sep or not key:
            raise argparse.ArgumentTypeError(f"method {text!r}: settings go as name:key=value, got {pair!r}")
        overrides[key] = yaml.safe_load(value)
    return name, overrides


def method_variants(text: str) -> list[str]:
    """A comma-separated list of :func:`method_variant` entries, each checked; returns the entries."""
    entries = names(text)
    for entry in entries:
        method_variant(entry)
    return entries


def program_name(name: str) -> str:
    """The program name for usage lines: as the user typed it, ``nsflow-ate`` or ``ate`` (``ros2 run``).

    Returns:
        the basename of ``sys.argv[0]`` when it is the console-script ``name`` or its ``ros2 run`` short
        name (``ate``, ``make_sample``), else ``name`` (run as a module or from a test).
    """
    typed = os.path.basename(sys.argv[0]) if sys.argv and sys.argv[0] else ""
    short = name.removeprefix("nsflow-").replace("-", "_")
    return typed if typed in (name, short) else name
