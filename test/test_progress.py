"""Progress bars only on a terminal; plain lines in a log (nsflow_ros.progress)."""

from __future__ import annotations

import io
import sys

import pytest

from nsflow_ros import progress
from nsflow_ros.progress import progress_bar


class _Stream(io.StringIO):
    def __init__(self, tty: bool) -> None:
        super().__init__()
        self.tty = tty

    def isatty(self) -> bool:
        return self.tty


@pytest.fixture
def stderr(monkeypatch):
    def use(tty: bool) -> _Stream:
        stream = _Stream(tty)
        monkeypatch.setattr(sys, "stderr", stream)
        return stream

    return use


def _work() -> None:
    for _ in progress_bar(range(40), desc="iterate", unit="frame"):
        pass
    with progress_bar(total=200, desc="update", unit="frame", leave=False, mininterval=0) as bar:
        for i in range(200):
            bar.set_postfix_str(f"{i}")
            bar.update(1)
    bar = progress_bar(desc="open-ended", unit="frame", mininterval=0, interval_s=0)
    for _ in range(3):
        bar.update(1)
    bar.close()


def test_off_a_terminal_progress_is_plain_lines_without_carriage_returns(stderr):
    err = stderr(False)
    _work()
    text = err.getvalue()
    assert "\r" not in text and "\x1b" not in text
    lines = text.splitlines()
    assert lines[0].startswith("iterate: 100% 40/40")
    update = [line for line in lines if line.startswith("update:")]
    assert [line.split()[1] for line in update] == [f"{p}%" for p in range(10, 101, 10)]
    open_ended = [line.split()[1] for line in lines if line.startswith("open-ended:")]
    assert open_ended == ["1frame", "2frame", "3frame"]
    assert all(line.strip() for line in lines)  # no blank lines either


def test_on_a_terminal_the_bar_is_drawn_in_place(stderr):
    err = stderr(True)
    _work()
    assert "\r" in err.getvalue()


def test_disabled_shows_nothing_anywhere(stderr):
    for tty in (False, True):
        err = stderr(tty)
        for _ in progress_bar(range(10), desc="quiet", enabled=False):
            pass
        with progress_bar(total=5, disable=True) as bar:
            bar.update(5)
        assert err.getvalue() == ""


def test_every_tool_goes_through_the_helper():
    from pathlib import Path

    root = Path(progress.__file__).parent
    # no module but the helper names tqdm: every tool shows progress through it
    users = [p for p in root.rglob("*.py") if "tqdm" in p.read_text() and p.name != "progress.py"]
    assert users == []
