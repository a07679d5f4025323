"""What every analysis of the evaluation suite receives: :class:`EvalContext`, plus small shared helpers.

An analysis is a function ``run(ctx: EvalContext) -> Section``. It reads its settings from the context,
writes its figures into ``ctx.out_dir`` (with :func:`atomic_write` / :func:`save_figure`) and returns
the :class:`~nsflow_ros.evaluation.section.Section` that the report writer puts together.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

from nsflow_ros import files
from nsflow_ros.evaluation.errors import EvaluationError
from nsflow_ros.evaluation.methods import PairMethod

__all__ = [
    "EvalContext",
    "atomic_write",
    "axis_label",
    "condition_label",
    "levels_text",
    "new_figure",
    "save_figure",
]

T = TypeVar("T")


@dataclass
class EvalContext:
    """Settings and shared objects of one evaluation run.

    Attributes:
        methods: the compared methods (:func:`~nsflow_ros.evaluation.methods.default_methods`: NSFlow,
            NSFlow + OpenCV LK, LM (intensity), OpenCV KLT, OpenCV KLT + CLAHE), all at the tracker's
            deployed pyramid depth (4 levels).
        model: the ONNX encoder file NSFlow uses, or None for the shipped model (for sections that need
            the file itself, e.g. parameter / FLOP counts).
        quick: tiny sizes (tests, CI): the whole quick run must take well under a minute, so every
            analysis shrinks its pairs / frames / grids drastically and says so in its text.
        out_dir: the report folder (exists); figures go directly into it, named after the section key.
        progress: show progress (use :meth:`bar`).
        seed: base seed; analyses derive their generators from it (``np.random.default_rng([seed, k])``)
            so a run is reproducible.
        threads: onnxruntime / OpenCV threads the methods were built with (for timing sections).
        providers: onnxruntime execution providers of the learned encoders, best first.
        extra: free-form settings for an analysis, keyed by the analysis key (unused by default).
    """

    methods: list[PairMethod]
    model: Path | None = None
    quick: bool = False
    out_dir: Path = Path("out/evaluation")
    progress: bool = True
    seed: int = 0
    threads: int | None = None
    providers: str = "cpu"
    extra: dict[str, Any] = field(default_factory=dict)

    def method(self, name: str) -> PairMethod:
        """The method called ``name`` (see :data:`~nsflow_ros.evaluation.methods.NSFLOW` etc.).

        Raises:
            EvaluationError: no such method in this run.
        """
        for m in self.methods:
            if m.name == name:
                return m
        raise EvaluationError(f"no method {name!r} in this run; have {[m.name for m in self.methods]}")

    def bar(
        self, iterable: Iterable[T], desc: str, total: int | None = None, unit: str = "it"
    ) -> Iterator[T]:
        """``iterable`` with a progress bar (:func:`~nsflow_ros.progress.progress_bar`), if ``progress``."""
        from nsflow_ros.progress import progress_bar

        bar = progress_bar(iterable, desc=desc, total=total, unit=unit, enabled=self.progress, leave=False)
        return iter(bar)


def atomic_write(path: Path, write: Callable[[Path], Any]) -> Path:
    """Write a file through a temporary name and rename it, so a crash never leaves half a file.

    Args:
        path: the final file.
        write: called with the temporary path; must create the file there.

    Returns:
        ``path``.

    Raises:
        EvaluationError: the folder is not writable.
    """
    try:
        return files.atomic_write(path, write)
    except OSError as err:
        raise EvaluationError(f"cannot write {path}: {err}") from err


def new_figure(width: float = 8.0, height: float = 4.5) -> Any:
    """A matplotlib ``Figure`` on the Agg canvas (no pyplot state, no display needed).

    Args:
        width, height: size in inches.

    Returns:
        the figure; add axes with ``fig.subplots(...)`` and save with :func:`save_figure`.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width, height))
    FigureCanvasAgg(fig)
    return fig


def axis_label(name: str) -> str:
    """A method's label for a crowded axis: "OpenCV KLT + CLAHE" -> "OpenCV KLT\n+ CLAHE"."""
    return name.replace(" + ", "\n+ ")


def levels_text(methods: list[PairMethod], fewer: int = 0) -> str:
    """The pyramid depth of the methods ("4 levels", or each method's when they differ), ``fewer`` less."""
    depths = sorted({m.levels - fewer for m in methods})
    if len(depths) == 1:
        return f"{depths[0]} level{'s' if depths[0] != 1 else ''}"
    return ", ".join(f"{m.name} {m.levels - fewer}" for m in methods) + " levels"


def condition_label(cond: str) -> str:
    """Words for a lighting condition key: "none" -> "no lighting change", else "lighting change"."""
    return "no lighting change" if cond == "none" else "lighting change"


def save_figure(fig: Any, path: Path, dpi: int = 110) -> Path:
    """Save a figure made by :func:`new_figure` as a PNG, atomically.

    Args:
        fig: a ``matplotlib.figure.Figure``.
        path: the PNG file.
        dpi: resolution.

    Returns:
        ``path``.
    """
    return atomic_write(Path(path), lambda p: fig.savefig(p, dpi=dpi, format="png", bbox_inches="tight"))
