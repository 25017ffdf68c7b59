"""The stage model: what a stage declares, what it is given, and what it returns.

A stage has a name, a title, the parameter sections it reads, the stages it depends on and a run
function. It works per scan (`prepare`, `projection`) or per pair of scans (everything after);
its output holds one item per scan or pair, each a frozen result with `ok`, `message` and
`metrics`. A pair whose item failed at a stage it depends on is not run again: it gets a
`Skipped` item that says where it failed, and the other pairs go on.

`depends` are hard dependencies (a failed item skips the pair); `uses` are soft ones (the run
function reads them if they succeeded). Both order the stages and both make a stage stale when
they re-run.

A stage reads only the parameter sections it declares (`Stage.reads`: its own `sections` and those
it `borrows`): its run function is given `DeclaredParams`, which raises `UndeclaredSection` on any
other, so a change to a section re-runs every stage whose results it can alter.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields
from typing import TYPE_CHECKING, Any, Callable, Literal, Mapping, Protocol, TypeVar, Union

import numpy as np

from .parallel import SERIAL, Workers
from .params import SECTIONS, Params
from .results import Metric, Progress
from .scan import Scan

if TYPE_CHECKING:
    from .coarse.start import StartPose


class StageResult(Protocol):
    """What every item of a stage's output is: a frozen result the registry, the pipeline and the
    app's renderers read without knowing its stage (read-only members: results are frozen)."""

    @property
    def ok(self) -> bool: ...

    @property
    def message(self) -> str: ...

    @property
    def metrics(self) -> tuple[Metric, ...]: ...


R = TypeVar("R", bound=StageResult)
T = TypeVar("T")


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
    items: tuple[StageResult, ...]
    seconds: float

    def item(self, k: int, kind: type[R]) -> R:
        """Item `k`, which must be a `kind` (a TypeError says which stage broke that promise)."""
        it = self.items[k]
        if not isinstance(it, kind):
            raise TypeError(f"{self.stage} item {k} is a {type(it).__name__}, not a {kind.__name__}")
        return it

    def items_as(self, kind: type[R]) -> tuple[R, ...]:
        """Every item, each a `kind` (a stage whose items are never skipped: per-scan ones that stop
        the run, the graph)."""
        return tuple(self.item(k, kind) for k in range(len(self.items)))


class UndeclaredSection(RuntimeError):
    """A stage read a parameter section it does not declare: a change to that section would leave its
    cached result stale. Not an AttributeError, which `getattr(params, name, default)` would swallow."""


class DeclaredParams(Params):
    """The parameters as one stage may read them: a `Params` (every helper taking one gets this view)
    whose sections outside `reads` raise `UndeclaredSection` when read.

    Made with `DeclaredParams.of(params, stage, reads)`, never by the constructor."""

    _stage: str
    _reads: frozenset[str]

    @classmethod
    def of(cls, params: Params, stage: str, reads: tuple[str, ...]) -> "DeclaredParams":
        unknown = [r for r in reads if r not in SECTIONS]
        if unknown:
            raise ValueError(f"stage {stage!r} declares unknown parameter sections {unknown}")
        view = object.__new__(cls)
        # Frozen: the fields are copied as dataclasses' own __init__ sets them.
        for f in fields(Params):
            object.__setattr__(view, f.name, object.__getattribute__(params, f.name))
        object.__setattr__(view, "_stage", stage)
        object.__setattr__(view, "_reads", frozenset(reads))
        return view

    def __getattribute__(self, name: str) -> Any:
        if name in SECTIONS and name not in object.__getattribute__(self, "_reads"):
            stage = object.__getattribute__(self, "_stage")
            raise UndeclaredSection(
                f"stage {stage!r} read parameter section {name!r}, which it does not declare: add it to its "
                f"STAGE's sections (or borrows) in treereg_core/stages/{stage}.py, so that a change to it "
                "re-runs the stage")
        return object.__getattribute__(self, name)

    def __repr__(self) -> str:  # the dataclass's repr would read every section
        return f"DeclaredParams(stage={self._stage!r}, reads={sorted(self._reads)})"


@dataclass(frozen=True)
class StageContext:
    """What a stage's run function is given: the inputs, the parameters (only the sections the stage
    declares: `DeclaredParams`) and the upstream outputs."""

    scans: tuple[Scan, ...]
    pairs: tuple[Pair, ...]
    params: Params
    truth: Mapping[str, np.ndarray] | None
    outputs: Mapping[str, StageOutput]
    live: tuple[bool, ...]
    progress: Progress
    #: Hypotheses picked by hand: pair label ("scan2.ply -> scan1.ply") -> candidate label.
    choices: Mapping[str, str] = field(default_factory=dict)
    #: The run's workers: `each` spreads the items over them.
    workers: Workers = SERIAL
    #: The stage's items hold the GIL (`Stage.processes`): forked processes, where the run may fork.
    fork: bool = False
    #: Start poses a user gave (`Pipeline.starts`): scan name -> `coarse.start.StartPose`, which
    #: the coarse stage takes instead of its estimate for the scan's pairs.
    starts: Mapping[str, StartPose] = field(default_factory=dict)

    def item(self, stage: str, k: int, kind: type[R]) -> R:
        """Item `k` of upstream `stage`, a `kind` (a hard dependency's items are, where live)."""
        return self.outputs[stage].item(k, kind)

    def ok_item(self, stage: str, k: int, kind: type[R]) -> R | None:
        """Item `k` of a (soft) upstream stage if it ran and succeeded, else None."""
        out = self.outputs.get(stage)
        if out is None or k >= len(out.items) or not out.items[k].ok:
            return None
        return out.item(k, kind)

    def each(self, fn: Callable[[int], T], label: Callable[[int], str], side_by_side: bool = True) -> list[T | None]:
        """`fn(k)` for every live item k (None for the others, which the pipeline marks skipped),
        side by side on the run's threads (`workers`; one at a time when not `side_by_side`);
        progress says which item started."""
        n = len(self.live)
        live = [k for k in range(n) if self.live[k]]

        def started(j: int) -> None:
            self.progress(live[j] / max(n, 1), label(live[j]))

        workers = self.workers if side_by_side else SERIAL
        found = workers.each(lambda j: fn(live[j]), len(live), started, fork=self.fork)
        out: list[T | None] = [None] * n
        for k, item in zip(live, found):
            out[k] = item
        return out


#: A stage's run function: one item per scan or pair, None where the item was not live.
RunFunction = Callable[[StageContext], list[StageResult | None]]


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
        Its own parameter sections (the app edits each in this stage's folder; every section is
        some one stage's own); a change to one of them makes it stale.
    depends, uses
        Hard and soft upstream stages (see the module docstring).
    result
        The type of its items (besides `Skipped`), a `StageResult`.
    run
        `run(context) -> list` with one item per scan or pair (None where not live).
    stop_on_failure
        A per-scan stage whose reference item fails stops the whole run (nothing is left to register
        onto); another scan's failed item is that scan's failure, its pairs skipped.
    processes
        Its items are mostly Python between small numpy calls (holding the GIL): side by side they
        run in forked processes where the run may fork, not in threads (`parallel`).
    borrows
        Sections of other stages it reads too (`surface.voxel_m` for the hypotheses); a change to one
        of them makes it stale as well.
    """

    name: str
    title: str
    summary: str
    per: Literal["scan", "pair"]
    sections: tuple[str, ...]
    depends: tuple[str, ...]
    result: type[StageResult]
    run: RunFunction = field(repr=False)
    uses: tuple[str, ...] = ()
    stop_on_failure: bool = False
    processes: bool = False
    borrows: tuple[str, ...] = ()

    @property
    def upstream(self) -> tuple[str, ...]:
        return self.depends + self.uses

    @property
    def reads(self) -> tuple[str, ...]:
        """Every parameter section it reads: the only ones its run function can (`DeclaredParams`)."""
        return self.sections + self.borrows

    def params_view(self, params: Params) -> DeclaredParams:
        """`params` as this stage's run function sees them."""
        return DeclaredParams.of(params, self.name, self.reads)


# ---- what a run tells its subscribers --------------------------------------------------------------
# The pipeline emits, per stage it computes: StageStarted, StageProgress (any number), one
# ItemFinished per item in order, then StageFinished. Cached stages emit nothing.


@dataclass(frozen=True)
class StageStarted:
    """A stage begins computing `n_items` items (one per scan or pair)."""

    stage: str
    n_items: int


@dataclass(frozen=True)
class StageProgress:
    """How far the run has come: `run_fraction` of the stages this run computes, `stage_fraction` of
    the running stage (both in [0, 1], never going back); `text` what the stage does now."""

    stage: str
    run_fraction: float
    stage_fraction: float
    text: str

    @property
    def line(self) -> str:
        """One line for a progress bar: "matching: scan2 -> scan1"."""
        return f"{self.stage}: {self.text}" if self.text else self.stage


@dataclass(frozen=True)
class ItemFinished:
    """Item `index` (`label`: a scan's name or "b -> a") of a stage, as its output holds it (a
    `Skipped` where an earlier stage failed for it)."""

    stage: str
    index: int
    label: str
    item: StageResult


@dataclass(frozen=True)
class StageFinished:
    """A stage's output, computed and cached."""

    output: StageOutput


Event = Union[StageStarted, StageProgress, ItemFinished, StageFinished]
#: A subscriber to a run's events (called on the thread that runs the pipeline).
Events = Callable[[Event], None]
