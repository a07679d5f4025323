"""Progress of long work: a bar on a terminal, plain log lines elsewhere.

Every tool shows its progress through :func:`progress_bar`. On a terminal that is a tqdm bar redrawn
in place; when stderr is a file or a pipe (a robot's log, ``nsflow-bench ... 2>&1 | tail``), carriage
returns would fill the log with one line per redraw, so the same calls write one plain line every
tenth of the work (or every ``interval_s`` seconds when the total is unknown) and a last one at the end.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Iterable
from typing import Any

from tqdm import tqdm

__all__ = ["LINE_INTERVAL_S", "progress_bar"]

LINE_INTERVAL_S = 30.0
"""Seconds between plain progress lines when the total is unknown (or a tenth takes longer)."""


class _LineProgress(tqdm):  # type: ignore[misc]
    """A tqdm that writes newline-terminated lines of its statistics, never a carriage return."""

    def __init__(self, *args: Any, interval_s: float = LINE_INTERVAL_S, **kwargs: Any) -> None:
        self._interval_s = interval_s
        self._line_n = 0  # progress at the last line
        self._line_t = time.monotonic()
        super().__init__(*args, **kwargs)

    def _line(self) -> None:
        self.fp.write(self.format_meter(**{**self.format_dict, "ncols": 0}) + "\n")
        self.fp.flush()
        self._line_n, self._line_t = self.n, time.monotonic()

    def display(self, msg: str | None = None, pos: int | None = None) -> bool:
        if msg is not None:  # a request to clear the line: there is nothing to clear
            return False
        n, total = self.n, self.total
        if n == self._line_n:
            return True
        tenth = bool(total) and int(10 * n // total) > int(10 * self._line_n // total)
        if tenth or time.monotonic() - self._line_t >= self._interval_s:
            self._line()
        return True

    def clear(self, nolock: bool = False) -> None:
        """Nothing was drawn in place, so nothing is cleared."""

    def close(self) -> None:
        if not self.disable and self.n != self._line_n:
            self._line()  # the final count
        self.leave = False  # tqdm would end with "\n" (leave) or "\r" (clear); the lines are complete
        super().close()


def progress_bar(
    iterable: Iterable[Any] | None = None,
    *,
    enabled: bool = True,
    interval_s: float = LINE_INTERVAL_S,
    **kwargs: Any,
) -> tqdm:
    """A tqdm progress bar on stderr when it is a terminal, else plain progress lines.

    Args:
        iterable: what to wrap (None: call ``update`` on the result).
        enabled: False = show nothing at all (as tqdm's ``disable=True``).
        interval_s: off a terminal, seconds between lines when the total is unknown.
        **kwargs: tqdm's arguments (``desc``, ``total``, ``unit``, ``leave``, ...); ``file`` is stderr.

    Returns:
        the bar: iterate over it, or call ``update`` / ``set_postfix_str`` / ``close`` (a context manager).
    """
    if kwargs.pop("disable", False):
        enabled = False
    if not enabled or sys.stderr.isatty():
        return tqdm(iterable, disable=not enabled, file=sys.stderr, **kwargs)
    kwargs.pop("dynamic_ncols", None)
    return _LineProgress(iterable, file=sys.stderr, interval_s=interval_s, **kwargs)
