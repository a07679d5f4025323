"""The manual: every relative link resolves, every tool option and node parameter has a home, the pages keep
their size, and the tables the tools wrote regenerate from their stored JSON byte for byte and appear in the
docs whole."""

from __future__ import annotations

import contextlib
import importlib
import json
import re
import sys
from pathlib import Path

import pytest
from test_help import TOOLS, _help

from nsflow_ros.results import markdown
from nsflow_ros.ros.tracker_params import PARAMETERS

ROOT = Path(__file__).resolve().parent.parent
PAGES = [ROOT / "README.md", ROOT / "models" / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
RESULTS = sorted((ROOT / "docs" / "results").rglob("*.json"))
LIMITS = {"README.md": 150, "models/README.md": 150, "docs/design.md": 300}


def _text() -> str:
    return "\n".join(p.read_text(encoding="utf-8") for p in PAGES)


def _anchors(page: Path) -> set[str]:
    """GitHub's heading anchors: lower case, punctuation but '-' and '_' dropped, spaces to '-'."""
    text = re.sub(r"```.*?```", "", page.read_text(encoding="utf-8"), flags=re.S)
    heads = re.findall(r"^#+ (.+)$", text, re.M)
    return {re.sub(r"[^\w\- ]", "", h.strip().lower()).replace(" ", "-") for h in heads}


@pytest.mark.parametrize("page", PAGES, ids=lambda p: str(p.relative_to(ROOT)))
def test_relative_links_resolve(page):
    text = re.sub(r"```.*?```", "", page.read_text(encoding="utf-8"), flags=re.S)
    for target in re.findall(r"\]\(([^)\s]+)\)", text):
        if re.match(r"[a-z]+:", target):
            continue
        path, _, anchor = target.partition("#")
        dest = (page.parent / path).resolve() if path else page
        assert dest.exists(), f"{page.name}: {target}"
        if anchor and dest.suffix == ".md":
            assert anchor in _anchors(dest), f"{page.name}: {target}"


@pytest.mark.parametrize("page", PAGES, ids=lambda p: str(p.relative_to(ROOT)))
def test_pages_keep_their_size(page):
    name = str(page.relative_to(ROOT))
    assert len(page.read_text(encoding="utf-8").splitlines()) <= LIMITS.get(name, 400)


@pytest.mark.parametrize(("name", "short", "target"), TOOLS, ids=[t[0] for t in TOOLS])
def test_every_tool_option_is_documented(name, short, target, monkeypatch, capsys):
    monkeypatch.setenv("COLUMNS", "1000")  # no option name broken across lines
    text, helps = _text(), _help(target, name, monkeypatch, capsys)
    if name == "nsflow-ate":
        helps += "".join(_help_sub(target, sub, monkeypatch, capsys) for sub in ("ape", "drift", "batch"))
    options = set(re.findall(r"(?<![\w-])(--[a-z][A-Za-z0-9-]+)", helps)) - {"--help", "--ros-args"}
    missing = sorted(o for o in options if not re.search(rf"{re.escape(o)}(?![\w-])", text))
    assert missing == [], f"{name} options without a home in the docs: {missing}"


def _help_sub(target: str, sub: str, monkeypatch, capsys) -> str:
    """``nsflow-ate SUB --help``."""
    module, _, func = target.partition(":")
    monkeypatch.setattr(sys, "argv", ["nsflow-ate", sub, "--help"])
    with contextlib.suppress(SystemExit):
        getattr(importlib.import_module(module), func)()
    return capsys.readouterr().out


def test_every_node_parameter_is_documented():
    text = _text()
    missing = [p.name for p in PARAMETERS if f"`{p.name}`" not in text and f"{p.name}:=" not in text]
    assert missing == [], f"node parameters without a home in the docs: {missing}"


def test_the_docs_have_stored_tables():
    assert {p.stem for p in RESULTS} >= {"bench", "evaluation"}


@pytest.mark.parametrize("stored", RESULTS, ids=lambda p: str(p.relative_to(ROOT / "docs" / "results")))
def test_tables_regenerate_and_are_pasted_whole(stored):
    text = markdown(json.loads(stored.read_text(encoding="utf-8")))
    assert stored.with_suffix(".md").read_text(encoding="utf-8") == text
    docs = "".join(page.read_text(encoding="utf-8") for page in sorted((ROOT / "docs").glob("*.md")))
    assert text in docs, f"{stored.with_suffix('.md').name} is not pasted whole into the docs"


def test_the_readme_pastes_the_whole_tracker_table_whole():
    doc = json.loads((ROOT / "docs" / "results" / "bench.json").read_text(encoding="utf-8"))
    head = markdown({"header": doc["header"], "tables": doc["tables"][:1]})
    assert doc["tables"][0]["title"] == "Whole tracker per frame"
    assert head in (ROOT / "README.md").read_text(encoding="utf-8")


def test_make_bench_runs_the_documented_command():
    make = (ROOT / "Makefile").read_text(encoding="utf-8").replace("\\\n", " ")
    recipe = re.search(r"^bench:.*\n\t\$\(BIN\)/(.+)$", make, re.M)
    page = (ROOT / "docs" / "benchmarks.md").read_text(encoding="utf-8")
    documented = re.search(r"## The command that regenerates the tables\n\n```bash\n(.+)\n```", page)
    assert recipe and documented
    assert " ".join(recipe[1].split()) == documented[1]
