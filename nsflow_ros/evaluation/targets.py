"""The evaluation's targets as data: one row both prints the target in words and decides whether it is met,
so the headline row's text and verdict cannot drift apart.

A :class:`Target` compares one figure of NSFlow (or another subject method) with a conjunction of
:class:`Clause` s, each against a fixed bound ("<= 0.5 px") or a multiple of other methods' figures.
"""

from __future__ import annotations

import operator
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

from nsflow_ros.evaluation.errors import EvaluationError
from nsflow_ros.evaluation.methods import NSFLOW
from nsflow_ros.evaluation.section import HeadlineRow

__all__ = ["OPERATORS", "Clause", "Target", "headline_row"]

OPERATORS: dict[str, Callable[[Any, Any], Any]] = {
    "<": operator.lt,
    "<=": operator.le,
    ">": operator.gt,
    ">=": operator.ge,
}
"""The comparisons a clause may use, by the symbol it prints."""


@dataclass(frozen=True)
class Clause:
    """One comparison of the subject's figure: ``figure <op> reference``.

    Attributes:
        op: one of :data:`OPERATORS`.
        rivals: methods whose figure, times ``scale``, is the reference (the highest of those evaluated
            when there are several); empty for a fixed ``bound``.
        scale: factor on the rivals' figure.
        bound: the fixed reference when there are no rivals.
        unit: the bound's unit in the text: ``"%"`` prints a share as a percentage, else ``"px"`` etc.
        label: the reference in words (default: the rivals' names, or the bound with its unit);
            ``{rivals}`` in it is replaced by the names of the rivals evaluated.
        optional: left out (text and check) when none of its rivals was evaluated.

    Raises:
        EvaluationError: an unknown operator, or neither rivals nor bound.
    """

    op: str
    rivals: tuple[str, ...] = ()
    scale: float = 1.0
    bound: float | None = None
    unit: str = ""
    label: str | None = None
    optional: bool = False

    def __post_init__(self) -> None:
        if self.op not in OPERATORS:
            raise EvaluationError(f"unknown comparison {self.op!r}; expected one of {list(OPERATORS)}")
        if not self.rivals and self.bound is None:
            raise EvaluationError("a target clause needs rivals or a bound")

    def present(self, figures: Mapping[str, Any]) -> list[str]:
        """The rivals that have a figure."""
        return [r for r in self.rivals if figures.get(r) is not None]

    def applies(self, figures: Mapping[str, Any]) -> bool:
        """Whether the clause is part of the target for these figures (an optional one needs a rival)."""
        return not (self.optional and not self.present(figures))

    def text(self, figures: Mapping[str, Any]) -> str:
        """The clause in words, e.g. ``<= 1.2x KLT`` or ``>= 97 %``."""
        if self.label is not None:
            ref = self.label.replace("{rivals}", ", ".join(self.present(figures)))
        elif self.rivals:
            ref = ", ".join(self.rivals)
        elif self.unit == "%":
            ref = f"{100 * float(self.bound or 0.0):g} %"
        else:
            ref = f"{self.bound:g} {self.unit}".rstrip()
        scale = "" if self.scale == 1.0 else f"{self.scale:g}x "
        return f"{self.op} {scale}{ref}"

    def holds(self, value: Any, figures: Mapping[str, Any]) -> bool | None:
        """Whether ``value`` satisfies the clause; None when its reference is unknown (no rival evaluated)."""
        if not self.rivals:
            return bool(OPERATORS[self.op](value, self.bound))
        present = self.present(figures)
        if not present:
            return None
        return bool(OPERATORS[self.op](value, self.scale * max(figures[r] for r in present)))


@dataclass(frozen=True)
class Target:
    """A target: the subject method's figure against every clause (all must hold).

    Attributes:
        figure: which figure is compared (its key in the section's data), for the reader.
        clauses: the comparisons, printed joined by "and".
        stretch: a stretch goal rather than a requirement (printed ``stretch: ...``).
        subject: the method whose figure is checked.
        subject_text: words naming the subject before the clauses (e.g. ``NSFlow here``); empty: implied.
    """

    figure: str
    clauses: tuple[Clause, ...]
    stretch: bool = False
    subject: str = NSFLOW
    subject_text: str = ""

    def text(self, figures: Mapping[str, Any]) -> str:
        """The target in words, as the report prints it."""
        body = " and ".join(c.text(figures) for c in self.clauses if c.applies(figures))
        if self.subject_text:
            body = f"{self.subject_text} {body}"
        return f"stretch: {body}" if self.stretch else body

    def check(self, figures: Mapping[str, Any]) -> bool | None:
        """Whether the target is met by ``figures`` (method name -> figure; None or absent: not evaluated);
        None when the subject or a required rival was not evaluated."""
        value = figures.get(self.subject)
        if value is None:
            return None
        verdicts = [c.holds(value, figures) for c in self.clauses if c.applies(figures)]
        if any(v is None for v in verdicts):
            return None
        return all(verdicts)

    def row(self, metric: str, values: dict[str, str], figures: Mapping[str, Any]) -> HeadlineRow:
        """The headline row of this target: the formatted values, the target in words and its verdict."""
        return HeadlineRow(metric, values, self.text(figures), self.check(figures))


def headline_row(
    metric: str, figures: Mapping[str, Any], fmt: Callable[[Any], str], target: Target | None = None
) -> HeadlineRow:
    """A headline row: each method's figure printed by ``fmt``, and ``target``'s text and verdict if given."""
    values = {name: fmt(v) for name, v in figures.items()}
    return HeadlineRow(metric, values) if target is None else target.row(metric, values, figures)
