"""What every analysis of the evaluation suite receives: :class:`EvalContext`, plus small shared helpers.

An analysis is a function ``run(ctx: EvalContext) -> Section``: it reads its settings from the context,
writes its figures into ``ctx.out_dir`` (:func:`save_figure`) and returns the
:class:`~nsflow_ros.evaluation.section.Section` that the report writer puts together.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

from nsflow_ros import files
from nsflow_ros.evaluation.errors import EvaluationError
from nsflow_ros.evaluation.methods import EvalMethod
from nsflow_ros.optional import require

__all__ = [
    "CONDITIONS",
    "EvalContext",
    "atomic_write",
    "axis_label",
    "condition_label",
    "level_reductions",
    "levels_text",
    "new_figure",
    "sample_sequence",
    "save_figure",
]

T = TypeVar("T")

CONDITIONS = ("none", "light")
"""The photo-pair analyses' lighting conditions: no change, and both frames perturbed at full strength."""


@dataclass
class EvalContext:
    """Settings and shared objects of one evaluation run.

    Attributes:
        methods: the compared methods (:func:`~nsflow_ros.evaluation.methods.default_methods`).
        model: the ONNX encoder file NSFlow uses, or None for the shipped model.
        quick: tiny sizes (tests, CI): every analysis shrinks its work and says so in its text.
        out_dir: the report folder (exists); figures go directly into it, named after the section key.
        progress: show progress (use :meth:`bar`).
        seed: base seed; analyses derive their generators from it (``np.random.default_rng([seed, k])``).
        threads: onnxruntime / OpenCV threads the methods were built with.
        providers: onnxruntime execution providers of the learned encoders, best first.
        extra: free-form settings for an analysis, keyed by the analysis key.
    """

    methods: list[EvalMethod]
    model: Path | None = None
    quick: bool = False
    out_dir: Path = Path("out/evaluation")
    progress: bool = True
    seed: int = 0
    threads: int | None = None
    providers: str = "cpu"
    extra: dict[str, Any] = field(default_factory=dict)

    def bar(
        self, iterable: Iterable[T], desc: str, total: int | None = None, unit: str = "it"
    ) -> Iterator[T]:
        """``iterable`` with a progress bar (:func:`~nsflow_ros.progress.progress_bar`), if ``progress``."""
        from nsflow_ros.progress import progress_bar

        bar = progress_bar(iterable, desc=desc, total=total, unit=unit, enabled=self.progress, leave=False)
        return iter(bar)


def sample_sequence(
    ctx: EvalContext, key: str, seed: int, duration: float, *, stereo: bool, images: bool, progress: bool
) -> Any:
    """A :class:`~nsflow_ros.data.sample.SampleSequence`, made once under the cache folder
    ``ctx.extra[key]["cache_dir"]`` (default ``cache/`` beside ``ctx.out_dir``).

    ``images`` False stores only the poses and scene, for frames rendered when asked.

    Raises:
        EvaluationError: the sequence cannot be made there.
    """
    from nsflow_ros.data.errors import DataError
    from nsflow_ros.data.sample import make_sample_sequence

    cache = Path(ctx.extra.get(key, {}).get("cache_dir", ctx.out_dir.parent / "cache"))
    name = f"sample-seed{seed}-{duration:g}s" + ("-stereo" if stereo else "") + ("" if images else "-meta")
    try:
        return make_sample_sequence(cache / name, seed=seed, duration=duration, stereo=stereo,
                                    formats=("asl",) if images else (), progress=progress)  # fmt: skip
    except (DataError, OSError) as err:
        what = "stereo sample sequence" if stereo else "sample sequence"
        raise EvaluationError(f"cannot make the {what} under {cache}: {err}") from err


def atomic_write(path: Path, write: Callable[[Path], Any]) -> Path:
    """:func:`nsflow_ros.files.atomic_write`, its failure as an :class:`EvaluationError` naming the file."""
    try:
        return files.atomic_write(path, write)
    except OSError as err:
        raise EvaluationError(f"cannot write {path}: {err}") from err


def new_figure(width: float = 8.0, height: float = 4.5) -> Any:
    """A matplotlib ``Figure`` of ``width`` x ``height`` inches on the Agg canvas (no pyplot state)."""
    figure = require("matplotlib.figure", "the evaluation's figures")
    agg = require("matplotlib.backends.backend_agg", "the evaluation's figures")
    fig = figure.Figure(figsize=(width, height))
    agg.FigureCanvasAgg(fig)
    return fig


def save_figure(fig: Any, path: Path, dpi: int = 110) -> Path:
    """Save a figure made by :func:`new_figure` as a PNG, atomically; returns ``path``."""
    return atomic_write(Path(path), lambda p: fig.savefig(p, dpi=dpi, format="png", bbox_inches="tight"))


def axis_label(name: str) -> str:
    """A method's label for a crowded axis: "OpenCV KLT + CLAHE" -> "OpenCV KLT\n+ CLAHE"."""
    return name.replace(" + ", "\n+ ")


def levels_text(methods: Sequence[EvalMethod], fewer: int = 0, stereo: bool = False) -> str:
    """The pyramid depth of the methods (of their stereo solves from zero flow: ``stereo``), ``fewer``
    less: "4 levels"; per solver when they differ ("LM 6, OpenCV LK 4 levels"); else each method's."""

    def depth(m: EvalMethod) -> int:
        return (m.stereo_levels if stereo else m.levels) - fewer

    depths = sorted({depth(m) for m in methods})
    if len(depths) == 1:
        return f"{depths[0]} level{'s' if depths[0] != 1 else ''}"
    by_solver: dict[str, set[int]] = {}
    for m in methods:
        by_solver.setdefault("LM" if m.core.spec.is_lm else "OpenCV LK", set()).add(depth(m))
    if all(len(d) == 1 for d in by_solver.values()):
        return ", ".join(f"{k} {min(d)}" for k, d in by_solver.items()) + " levels"
    return ", ".join(f"{m.name} {depth(m)}" for m in methods) + " levels"


def level_reductions(methods: Sequence[EvalMethod]) -> tuple[int, ...]:
    """Levels fewer to run at: 0 (each method's own depth) and 1 when every method has a level to spare."""
    return (0, 1) if methods and min(m.levels for m in methods) > 1 else (0,)


def condition_label(cond: str) -> str:
    """Words for a lighting condition key: "none" -> "no lighting change", else "lighting change"."""
    return "no lighting change" if cond == "none" else "lighting change"
