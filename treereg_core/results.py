"""What every stage result shares: metric rows and the progress callback type.

A stage returns a frozen dataclass with at least `ok: bool` and `message: str` (empty when all is
well; when `ok` is False, a sentence a user can act on) and `metrics: tuple[Metric, ...]`, rows that
both the terminal table and the app render (the protocol `stage.StageResult` says so for type checkers).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

#: progress(fraction in [0, 1], what is being done now)
Progress = Callable[[float, str], None]

#: One metric of one stage as transforms.json and tables list it: stage, metric, unit, value.
MetricRow = dict[str, float | int | str]


def no_progress(fraction: float, text: str) -> None:
    """The default progress callback: ignore."""


@dataclass(frozen=True)
class Metric:
    """One row of a result table, e.g. Metric("rotation error", "deg", 0.12)."""

    description: str
    unit: str
    value: float | int | str

    def formatted(self) -> str:
        v = self.value
        text = f"{v:.4g}" if isinstance(v, float) else str(v)
        return f"{text} {self.unit}".strip()


def metrics_table(rows: tuple[Metric, ...] | list[Metric]) -> str:
    """Markdown table of metric rows."""
    lines = ["| metric | value |", "|---|---|"]
    lines += [f"| {m.description} | {m.formatted()} |" for m in rows]
    return "\n".join(lines)
