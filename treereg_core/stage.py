"""The stage model: what a stage declares, what it is given, and what it returns.

A stage has a name, a title, the parameter sections it reads, the stages it depends on and a run
function. It works per scan (`prepare`, `projection`) or per pair of scans (everything after);
its output holds one item per scan or pair, each a frozen result with `ok`, `message` and
`metrics`. A pair whose item failed at a stage it depends on is not run again: it gets a
`Skipped` item that says where it failed, and the other pairs go on.

`depends` are hard dependencies (a failed item skips the pair); `uses` are soft ones (the run
function reads them if they succeeded). Both order the stages and both make a stage stale when
they re-run.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable, Literal, Mapping

import numpy as np

from .params import Params
from .results import Metric, Progress
from .scan import Scan


@dataclass(frozen=True)
class Pair:
    """Two scans registered together: `tgt` is mapped onto `ref` (indices into the scans)."""

    ref: int
    tgt: int


@dataclass(frozen=True)
class Skipped:
    """The item of a scan or pair a stage did not run on, because an earlier stage failed for it."""

    ok: bool
    message: str
    metrics: tuple[Metric, ...] = ()


@dataclass(frozen=True)
class StageOutput:
    """One stage's output: an item per scan or per pair, in order."""

    stage: str
    ok: bool
    message: str
    items: tuple[Any, ...]
    seconds: float


@dataclass(frozen=True)
class StageContext:
    """What a stage's run function is given: the inputs, the parameters and the upstream outputs."""

    scans: tuple[Scan, ...]
    pairs: tuple[Pair, ...]
    params: Params
    truth: Mapping[str, np.ndarray] | None
    outputs: Mapping[str, StageOutput]
    live: tuple[bool, ...]
    progress: Progress
    #: Hypotheses picked by hand: pair label ("scan2.ply -> scan1.ply") -> candidate label.
    choices: Mapping[str, str] = field(default_factory=dict)

    def items(self, stage: str) -> tuple[Any, ...]:
        return self.outputs[stage].items

    def item(self, stage: str, k: int) -> Any:
        return self.outputs[stage].items[k]

    def ok_item(self, stage: str, k: int) -> Any | None:
        """Item `k` of a (soft) upstream stage if it ran and succeeded, else None."""
        out = self.outputs.get(stage)
        if out is None or k >= len(out.items) or not getattr(out.items[k], "ok", False):
            return None
        return out.items[k]

    def each(self, fn: Callable[[int], Any], label: Callable[[int], str]) -> list[Any]:
        """`fn(k)` for every live item k (None for the others, which the pipeline marks skipped)."""
        n = len(self.live)
        out: list[Any] = []
        for k in range(n):
            if not self.live[k]:
                out.append(None)
                continue
            self.progress(k / max(n, 1), label(k))
            out.append(fn(k))
        return out


@dataclass(frozen=True)
class Stage:
    """One registered stage.

    Attributes
    ----------
    name
        Key of the stage everywhere (pipeline outputs, the app's renderers and controls, node paths).
    title
        What a person reads ("Slices").
    summary
        One sentence: what the stage does.
    per
        "scan" (one item per scan) or "pair" (one item per registered pair).
    sections
        The parameter sections it reads; a change to one of them makes it stale.
    depends, uses
        Hard and soft upstream stages (see the module docstring).
    result
        The type of its items (besides `Skipped`).
    run
        `run(context) -> list` with one item per scan or pair (None where not live).
    stop_on_failure
        A failed item stops the whole run (a scan that cannot be prepared is an input to fix).
    """

    name: str
    title: str
    summary: str
    per: Literal["scan", "pair"]
    sections: tuple[str, ...]
    depends: tuple[str, ...]
    result: type
    run: Callable[[StageContext], list[Any]] = field(repr=False)
    uses: tuple[str, ...] = ()
    stop_on_failure: bool = False

    @property
    def upstream(self) -> tuple[str, ...]:
        return self.depends + self.uses
