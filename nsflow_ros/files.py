"""File helpers shared by the tools that write results (offline runs, the evaluation report)."""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

__all__ = ["atomic_write"]


def atomic_write(path: str | os.PathLike[str], write: Callable[[Path], Any]) -> Path:
    """Write a file through a temporary name and rename it, so an interrupted run never leaves half a file.

    ``write`` is called with the temporary path and must create the file there; returns ``path``.

    Raises:
        OSError: the file cannot be written or renamed (the temporary file is removed).
    """
    path = Path(path)
    tmp = path.with_name(f".{path.name}.partial-{os.getpid()}")
    try:
        write(tmp)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
    return path
