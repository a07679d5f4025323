"""Libraries of the optional extras, imported on use and named with their extra when missing.

The base install is the node and the tools that feed an estimator (tracker, replay, feature bag,
nsflow-config); the evaluation, the sample renderer, the demo, the figures and the benchmark's random
encoder need the ``eval`` extra, training the ``train`` extra. Every import of such a library goes through
:func:`require`, so a tool run without its extra stops with one line that says what to install, and the
runtime modules provably import none of them (test/test_optional.py hides them and runs the replay).
"""

from __future__ import annotations

import importlib
import importlib.util
from types import ModuleType

from nsflow_ros.errors import NSFlowError

__all__ = ["EXTRAS", "MissingExtraError", "install_hint", "require", "require_extra"]

# Top-level module -> the extra of setup.py that installs it.
EXTRAS: dict[str, str] = {
    "matplotlib": "eval",
    "skimage": "eval",
    "onnx": "eval",
    "torch": "train",
}


class MissingExtraError(NSFlowError):
    """An optional library is not installed; the message names the extra that installs it."""


def install_hint(extra: str) -> str:
    """The pip command that installs ``extra`` (from PyPI-style name, and from a git clone)."""
    return f"pip install 'nsflow_ros[{extra}]' (from a git clone: pip install -e '.[{extra}]')"


def require(module: str, purpose: str) -> ModuleType:
    """Import ``module`` (a library of an extra, or one of its submodules) for ``purpose``.

    Args:
        module: dotted module name whose top level is a key of :data:`EXTRAS`, e.g. ``"matplotlib.figure"``.
        purpose: what needs it, completing "<purpose> needs <library>", e.g. "the ATE plot".

    Returns:
        The imported module.

    Raises:
        MissingExtraError: the library is not installed (message: what needs it and the pip command).
        KeyError: ``module`` is no library of an extra (a programming error, not a user's).
    """
    top = module.split(".")[0]
    extra = EXTRAS[top]  # one table: a new optional library is declared there, not at its import site
    try:
        return importlib.import_module(module)
    except ModuleNotFoundError as err:
        if err.name is None or err.name.split(".")[0] != top:
            raise  # the library is there but one of its own dependencies is broken: show that as is
        raise MissingExtraError(
            f"{purpose} needs {top}, which comes with the {extra!r} extra: {install_hint(extra)}"
        ) from err


def require_extra(extra: str, tool: str) -> None:
    """Check up front that every library of ``extra`` is installed, for a ``tool`` that needs them all.

    Args:
        extra: an extra of setup.py, e.g. ``"eval"``.
        tool: what needs it, completing "<tool> needs <libraries>", e.g. "the evaluation".

    A tool made of many steps (the evaluation, the demo) would otherwise fail at its first step that
    imports one, after minutes of work, or once per step.

    Raises:
        MissingExtraError: naming the missing libraries and the pip command.
    """
    missing = []
    for module in sorted(m for m, e in EXTRAS.items() if e == extra):
        try:
            found = importlib.util.find_spec(module) is not None
        except (ImportError, ValueError):  # a broken or hidden installation counts as missing
            found = False
        if not found:
            missing.append(module)
    if missing:
        names = ", ".join(missing)
        raise MissingExtraError(f"{tool} needs {names}, of the {extra!r} extra: {install_hint(extra)}")
