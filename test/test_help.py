"""Every console script answers --help: exit 0, plain text (no reST markup), the usage line names the
program as the user typed it (``nsflow-ate`` from pip, ``ate`` through ``ros2 run``), every option
documented."""

from __future__ import annotations

import ast
import importlib
import re
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent


def _tools() -> list[tuple[str, str, str]]:
    """setup.py's TOOLS: (name on PATH, ros2 run name, module:function)."""
    tree = ast.parse((ROOT / "setup.py").read_text())
    for node in tree.body:
        if isinstance(node, ast.Assign) and any(getattr(t, "id", None) == "TOOLS" for t in node.targets):
            return [tuple(x) for x in ast.literal_eval(node.value)]
    raise AssertionError("setup.py has no TOOLS list")


TOOLS = _tools()


def _help(target: str, argv0: str, monkeypatch, capsys) -> str:
    """What the console script prints for ``argv0 --help``: it calls ``sys.exit(main())``."""
    module, _, func = target.partition(":")
    main = getattr(importlib.import_module(module), func)
    monkeypatch.setattr(sys, "argv", [argv0, "--help"])
    try:
        code = main()
    except SystemExit as exc:  # argparse's --help
        code = exc.code
    out = capsys.readouterr()
    assert code in (0, None), out.err
    return out.out


def test_every_tool_is_listed():
    assert sorted(t[0] for t in TOOLS) == sorted(
        ["nsflow-tracker", "nsflow-replay", "nsflow-demo", "nsflow-ate", "nsflow-bench", "nsflow-make-sample",
         "nsflow-train", "nsflow-evaluate", "nsflow-config", "nsflow-scenes"]
    )


@pytest.mark.parametrize(("name", "short", "target"), TOOLS, ids=[t[0] for t in TOOLS])
def test_help_names_the_program_as_typed(name, short, target, monkeypatch, capsys):
    text = _help(target, f"/usr/bin/{name}", monkeypatch, capsys)
    assert text.startswith(f"usage: {name} "), text[:200]
    assert "``" not in text and ":mod:" not in text and ":func:" not in text
    ros = _help(target, f"/ws/install/nsflow_ros/lib/nsflow_ros/{short}", monkeypatch, capsys)
    assert re.match(rf"usage: (ros2 run nsflow_ros )?{short} ", ros), ros[:200]


@pytest.mark.parametrize(
    ("name", "target"), [(t[0], t[2]) for t in TOOLS if t[0] != "nsflow-tracker"], ids=lambda x: x
)
def test_every_option_has_a_help_text(name, target, monkeypatch, capsys):
    text = _help(target, name, monkeypatch, capsys)
    options = text.split("options:", 1)[1]
    # an option line with nothing after its metavar, and no indented description on the next line
    lines = options.splitlines()
    bare = [
        line.strip() for k, line in enumerate(lines)
        if re.match(r"^  -", line) and len(re.split(r"\s{2,}", line.strip())) == 1
        and not (k + 1 < len(lines) and re.match(r"^\s{10,}\S", lines[k + 1]))
    ]
    assert bare == [], f"options without a help text in {name}: {bare}"
