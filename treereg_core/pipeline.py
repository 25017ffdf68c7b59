"""Runs the registered stages in order, caching each stage's output.

A stage re-runs only when a parameter section it reads (`Stage.reads`, the only ones it can), or a
stage it depends on, changed (`Pipeline.set_params`). The command line, the app's controller, the
tests and the benchmarks all drive this one `Pipeline` (scripts call `register(scans, params)`). The first scan is the
reference; every other scan is registered onto it (the paper's order 2->1, 3->1, ...).
"""

from __future__ import annotations

import time
from collections import Counter
from dataclasses import dataclass, field
from typing import Callable, Sequence

import numpy as np

from . import parallel
from .params import SECTIONS, Params
from .results import MetricRow, Progress
from .scan import Scan
from .coarse.estimate import CoarseResult
from .coarse.start import StartPose
from .errors import ConfigError
from .coarse.sequences import ImageSequence
from .coarse.similarity import scan_similarity
from .fine.pose import FineResult
from .prepare.level import as_given
from .stage import (Event, Events, ItemFinished, Pair, Skipped, Stage, StageContext, StageFinished, StageOutput,
                    StageProgress, StageResult, StageStarted)
from .stages import STAGE_NAMES, STAGES, affected_by, downstream, stage
from .verify.graph import Placement, select_pairs


@dataclass
class Pipeline:
    """Cached, stage-by-stage registration of `scans` (scan 0 = reference)."""

    scans: list[Scan]
    params: Params = field(default_factory=Params)
    truth: dict[str, np.ndarray] | None = None  # scan name -> true T_ref_scan, when known
    _out: dict[str, StageOutput] = field(default_factory=dict, repr=False)
    #: How often each stage has run (what a parameter change cost; tests read it).
    runs: Counter[str] = field(default_factory=Counter, repr=False)
    #: Hypotheses picked by hand (the app): pair label "b -> a" -> candidate label.
    choices: dict[str, str] = field(default_factory=dict)
    #: Start poses a user gave (`register --initial`; `start`): scan name -> StartPose, which replaces
    #: the coarse result of that scan's pairs; the stages after it run from it and judge it as any pose.
    starts: dict[str, StartPose] = field(default_factory=dict)
    #: Workers of a run (`parallel.Workers`; None: the machine's cores). Results are the same for
    #: any number.
    workers: int | None = None
    #: GIL-bound stages may fork processes (`Stage.processes`): only where this process runs no
    #: other threads (the command line; the app's server has its own, and uses threads).
    fork: bool = False
    _pairs_key: tuple[object, ...] | None = field(default=None, repr=False)
    _pairs_cache: tuple[tuple[int, int], ...] = field(default=(), repr=False)

    # ---- state -------------------------------------------------------------------------
    @property
    def pairs(self) -> tuple[Pair, ...]:
        """The pairs registered: the reference with every other scan (2->1, 3->1, ...) and, with four
        or more scans, the pairs the projection sequences show alike (`verify.graph.select_pairs`;
        with three, all three). The reference's pairs come first, in scan order."""
        n = len(self.scans)
        star = [(0, k) for k in range(1, n)]
        if n == 3:
            star.append((1, 2))
        elif n > 3:
            proj = self._out.get("projection")
            if proj is not None and proj.ok:
                key = (id(proj), self.params.matching.similarity, self.params.graph.extra_pairs)
                if self._pairs_key != key:
                    sim = scan_similarity(list(proj.items_as(ImageSequence)), self.params.matching.similarity)
                    chosen = select_pairs(sim, self.params.graph.extra_pairs)
                    self._pairs_cache = tuple(star + [e for e in chosen if e[0] != 0])
                    self._pairs_key = key
                star = list(self._pairs_cache)
        return tuple(Pair(i, j) for i, j in star)

    def set_params(self, params: Params) -> list[str]:
        """Adopt `params`; drop the cached outputs of every stage that reads a changed section (and of
        every per-pair stage when the pairs changed) and of every stage downstream of it. Returns the
        stages whose outputs were dropped."""
        stale = {s for sec in SECTIONS if getattr(params, sec) != getattr(self.params, sec) for s in affected_by(sec)}
        pairs = self.pairs
        self.params = params
        if self.pairs != pairs:  # with four scans or more the pairs follow parameters (`pairs`)
            stale.update(downstream(next(s.name for s in STAGES if s.per == "pair")))
        dropped = [s for s in STAGE_NAMES if s in stale and s in self._out]
        for s in stale:
            self._out.pop(s, None)
        return dropped

    def choose(self, pair_label: str, candidate: str | None) -> list[str]:
        """Pick a pose hypothesis of a pair by hand (None: let the surfaces choose again); the
        hypotheses stage and what depends on it become stale. Returns the stages dropped."""
        if candidate is None:
            if self.choices.pop(pair_label, None) is None:
                return []
        elif self.choices.get(pair_label) == candidate:
            return []
        else:
            self.choices[pair_label] = candidate
        return self.invalidate("hypotheses")

    def start(self, name: str, pose: StartPose | None) -> list[str]:
        """Give scan `name` a start pose (None: estimate it again): its pairs' coarse results become
        that pose, and the coarse stage and what depends on it become stale. Raises ConfigError (naming
        `pose.source`) for a scan that is not one of the scans, the reference, or a start whose file
        names another reference. Returns the stages dropped."""
        if pose is None:
            return self.invalidate("coarse") if self.starts.pop(name, None) is not None else []
        names = [s.name for s in self.scans]
        where = f"{pose.source}: the start pose of {name!r}"
        if name not in names:
            raise ConfigError(f"{where}: there is no scan of that name; the scans are {', '.join(map(repr, names))}")
        if name == names[0]:
            raise ConfigError(f"{where}: {name!r} is the reference, which every other scan is mapped onto; "
                              "give start poses of the other scans")
        if pose.reference is not None and pose.reference != names[0]:
            raise ConfigError(f"{where}: the file maps it onto {pose.reference!r}, but the reference of this "
                              f"registration is {names[0]!r} (the first scan given)")
        self.starts[name] = pose
        return self.invalidate("coarse")

    def set_scans(self, scans: Sequence[Scan], truth: dict[str, np.ndarray] | None = None) -> None:
        self.scans = list(scans)
        self.truth = truth
        names = {s.name for s in self.scans}
        self.choices = {k: v for k, v in self.choices.items() if all(n in names for n in k.split(" -> "))}
        self.starts = {k: v for k, v in self.starts.items() if k in names and k != self.scans[0].name}
        self.invalidate(STAGE_NAMES[0])

    def invalidate(self, name: str) -> list[str]:
        """Drop `name` and every stage downstream of it; returns those that had outputs."""
        later = downstream(stage(name).name)
        dropped = [s for s in later if s in self._out]
        for s in later:
            self._out.pop(s, None)
        return dropped

    @property
    def outputs(self) -> dict[str, StageOutput]:
        """Every cached output, by stage name (a copy: the pipeline's own stays private)."""
        return dict(self._out)

    def output(self, name: str) -> StageOutput | None:
        """The cached output of stage `name`, or None if it has not run since its inputs changed."""
        return self._out.get(name)

    def status(self, name: str) -> str:
        """'done', 'failed' or 'stale' (not run for the current inputs)."""
        out = self._out.get(name)
        if out is None:
            return "stale"
        return "done" if out.ok else "failed"

    @property
    def target_names(self) -> list[str]:
        """A label per pair: the target's name for the reference's pairs, "b -> a" for the others."""
        return [self.scans[p.tgt].name if p.ref == 0 else f"{self.scans[p.tgt].name} -> {self.scans[p.ref].name}"
                for p in self.pairs]

    # ---- running -----------------------------------------------------------------------
    def run(self, until: str = STAGE_NAMES[-1], events: Events | None = None,
            between: Callable[[], None] | None = None) -> StageOutput | None:
        """Run every stage up to `until` (in run order) that has no cached output.

        A pair (or scan) that fails at one stage is skipped by the stages that depend on it, which
        go on with the others (a scan that cannot be prepared is that scan's failure); the run stops
        when a per-scan stage fails for the reference (nothing is left to register onto) or a stage
        has no successful item left. `events(event)` hears each stage computed start, progress, finish
        its items and finish (`stage.StageStarted` ...); cached stages are silent. Returns the
        output of the last stage run (or cached), which may be a failure. `between()` is called by
        every thread of the run before it starts an item (the app pauses its run there while a tab
        opens: `parallel.Workers`).
        """
        emit = events or _no_events
        if len(self.scans) < 2:
            raise ValueError("registration needs at least two scans")
        todo = STAGES[: STAGE_NAMES.index(stage(until).name) + 1]
        fresh = self.stale(until)  # what this run computes: the fraction of the run counts these
        last: StageOutput | None = None
        budget = parallel.Workers(self.workers or parallel.default_workers(), may_fork=self.fork, between=between)
        with parallel.using(budget) as workers:
            for st in todo:
                out = self._out.get(st.name)
                if out is None:
                    out = self._run_stage(st, _stage_progress(st.name, fresh.index(st.name), len(fresh), emit), emit,
                                          workers)
                    self._out[st.name] = out
                    self.runs[st.name] += 1
                    emit(StageFinished(out))
                last = out
                # A reference that cannot be prepared or projected leaves nothing to register onto:
                # stop. Another scan that cannot is its own failure (a scan of only ground among good
                # ones): its pairs are skipped by the later stages while the other pairs go on.
                # Nor does a stage before coarse that failed for every pair when a pair has a start.
                if (st.stop_on_failure and not out.items[0].ok) or (
                        not any(it.ok for it in out.items) and not self._started_after(st)):
                    break
        return last

    def stale(self, until: str = STAGE_NAMES[-1]) -> list[str]:
        """The stages up to `until` that have no cached output: what `run(until)` would compute."""
        return [s for s in STAGE_NAMES[: STAGE_NAMES.index(stage(until).name) + 1] if s not in self._out]

    def _run_stage(self, st: Stage, progress: Progress, emit: Events, workers: parallel.Workers) -> StageOutput:
        n = len(self.scans) if st.per == "scan" else len(self.pairs)
        why = [self._blocked(st, k) for k in range(n)]
        emit(StageStarted(st.name, n))
        ctx = StageContext(tuple(self.scans), self.pairs, st.params_view(self.params), self.truth, dict(self._out),
                           tuple(w is None for w in why), progress, dict(self.choices), workers, st.processes,
                           dict(self.starts))
        t0 = time.perf_counter()
        items = tuple(_item(st, it, w) for it, w in zip(st.run(ctx), why))
        seconds = time.perf_counter() - t0
        progress(1.0, "done")
        # Items are announced once the run function returned: some stages make all items together
        # (prepare picks the target tree across every scan).
        for i, it in enumerate(items):
            emit(ItemFinished(st.name, i, self._item_name(st, i), it))
        bad = [(self._item_name(st, i), it) for i, it in enumerate(items) if not it.ok]
        msg = "; ".join(f"{name}: {it.message}" for name, it in bad)
        return StageOutput(st.name, not bad, msg, items, seconds)

    def _started(self, k: int) -> bool:
        """Pair k's coarse result is a start the user gave (`starts`: the coarse stage's `given_start`)."""
        p = self.pairs[k]
        return self.scans[p.tgt].name in self.starts and (p.ref == 0 or self.scans[p.ref].name in self.starts)

    def _started_after(self, st: Stage) -> bool:
        """`st` comes before the coarse stage, which some pair takes from a start."""
        return STAGE_NAMES.index(st.name) < STAGE_NAMES.index("coarse") and any(
            self._started(k) for k in range(len(self.pairs)))

    def _blocked(self, st: Stage, k: int) -> str | None:
        """Why item `k` of stage `st` cannot run (a hard dependency failed for it), or None. A pair
        the user gave a start needs no tie points: its coarse item runs where both scans were prepared."""
        if st.name == "coarse" and self._started(k):
            prep = self._out["prepare"]
            for i in (self.pairs[k].ref, self.pairs[k].tgt):
                if not prep.items[i].ok:
                    it = prep.items[i]
                    return it.message if isinstance(it, Skipped) else f"not run: prepare failed for this scan ({it.message})"
            return None
        for dep in st.depends:
            dep_st = stage(dep)
            if dep_st.per == st.per:
                idx = [k]
            else:  # a pair stage reading a per-scan stage: both scans must be fine
                idx = [self.pairs[k].ref, self.pairs[k].tgt]
            for i in idx:
                it = self._out[dep].items[i]
                if not it.ok:
                    return f"not run: {dep} failed for this {'scan' if dep_st.per == 'scan' else 'pair'} ({it.message})" \
                        if not isinstance(it, Skipped) else it.message
        return None

    def _item_name(self, st: Stage, i: int) -> str:
        if st.per == "scan":
            return self.scans[i].name
        p = self.pairs[i]
        return f"{self.scans[p.tgt].name} -> {self.scans[p.ref].name}"

    # ---- results -------------------------------------------------------------------------
    def transforms(self) -> dict[str, np.ndarray]:
        """The best available T_ref_scan per scan name (verified or not: `verdicts` says which): the
        joint placement when the graph stage ran, else the fine or coarse result of the scan's pair
        with the reference. The reference maps to the identity; scans with nothing are left out."""
        graph = self._out.get("graph")
        # The stages register levelled scans (prepare/level.py): what users get is of the scans as given.
        if graph is not None:
            return {s.name: self._as_given(it.T_ref_scan, 0, i) for i, (s, it) in enumerate(zip(self.scans, graph.items_as(Placement)))
                    if it.T_ref_scan is not None}
        out = {self.scans[0].name: np.eye(4)}
        for k, p in enumerate(self.pairs):
            T = self._pair_transform(k) if p.ref == 0 else None
            if T is not None:
                out[self.scans[p.tgt].name] = self._as_given(T, p.ref, p.tgt)
        return out

    def _as_given(self, T: np.ndarray, ref: int, tgt: int) -> np.ndarray:
        """A transform between two prepared (levelled) scans as one between the scans as given."""
        prep = self._out.get("prepare")
        level = [getattr(prep.items[j], "T_level", None) if prep is not None and j < len(prep.items) else None
                 for j in (ref, tgt)]
        return T if level[0] is None and level[1] is None else as_given(T, level[0], level[1])

    def _pair_transform(self, k: int) -> np.ndarray | None:
        """Pair k's fine transform if it succeeded, else its coarse one, else None."""
        fine, coarse = self._out.get("fine"), self._out.get("coarse")
        if fine is not None and fine.items[k].ok:
            return fine.item(k, FineResult).T_ref_target
        if coarse is not None and coarse.items[k].ok:
            return coarse.item(k, CoarseResult).T_ref_target
        return None

    def verdicts(self) -> dict[str, tuple[str, tuple[str, ...], str]]:
        """Per scan name: (verdict, reasons, what to try). Before the graph stage has run nothing is
        verified: the reasons say at which stage the registration stopped."""
        graph = self._out.get("graph")
        if graph is not None:
            return {s.name: (it.verdict, it.reasons, it.hint) for s, it in zip(self.scans, graph.items_as(Placement))}
        T = self.transforms()
        last = next((s for s in reversed(STAGE_NAMES) if s in self._out), "none")
        out: dict[str, tuple[str, tuple[str, ...], str]] = {self.scans[0].name: ("verified", (), "")}
        for s in self.scans[1:]:
            if s.name in T:
                out[s.name] = ("unverified", (f"the registration stopped at the {last} stage, before verification",),
                               "run the fine stage (treereg register without --until coarse)")
            else:
                out[s.name] = ("failed", (self._why_failed(s.name),), "see the stage messages above")
        return out

    def _why_failed(self, name: str) -> str:
        for st in STAGES:
            out = self._out.get(st.name)
            if out is None or st.per != "pair":
                continue
            for p, it in zip(self.pairs, out.items):
                if self.scans[p.tgt].name == name and p.ref == 0 and not it.ok:
                    return f"{st.name}: {it.message}"
        return "not registered"

    def pair_metrics(self) -> dict[str, list[MetricRow]]:
        """Per target scan, the metric rows of every per-pair stage that ran (transform files, tables)."""
        rows: dict[str, list[MetricRow]] = {n: [] for n in self.target_names}
        for st in STAGES:
            out = self._out.get(st.name)
            if out is None or st.per != "pair":
                continue
            for name, item in zip(self.target_names, out.items):
                rows[name] += [{"stage": st.name, "metric": m.description, "unit": m.unit, "value": m.value}
                               for m in item.metrics]
        return rows


def _no_events(event: Event) -> None:
    """The default subscriber: ignore."""


def _stage_progress(name: str, j: int, n: int, emit: Events) -> Progress:
    """The `progress(fraction, text)` a stage is given: StageProgress events of the j-th of the n
    stages this run computes."""
    done = 0.0

    def progress(fraction: float, text: str) -> None:
        nonlocal done
        done = max(done, min(max(float(fraction), 0.0), 1.0))  # a bar never goes back
        emit(StageProgress(name, (j + done) / n, done, text))

    return progress


def _item(st: Stage, item: StageResult | None, why: str | None) -> StageResult:
    """An output's item: what the run function returned, or `Skipped` where it could not run."""
    if why is not None:
        return Skipped(False, why)
    if item is None:
        raise RuntimeError(f"stage {st.name!r} returned no item for a scan or pair it could run on")
    return item


@dataclass(frozen=True)
class Registration:
    """What `register` returns: transforms per scan name and the pipeline that made them."""

    ok: bool
    message: str
    transforms: dict[str, np.ndarray]
    pipeline: Pipeline


def register(
    scans: Sequence[Scan],
    params: Params | None = None,
    until: str = "graph",
    truth: dict[str, np.ndarray] | None = None,
    events: Events | None = None,
    workers: int | None = None,
    fork: bool = False,
    starts: dict[str, StartPose] | None = None,
) -> Registration:
    """One call: register every scan onto the first; `until` is a stage name (default "graph": fine
    registration, verification and the joint placement, so `pipeline.verdicts()` says which scans
    are verified; "coarse" or "fine" stop earlier, every scan then unverified; "evaluation" adds the
    paper's evaluation and ICP); `events` hears the run (`Pipeline.run`); `workers` compute threads
    (`parallel`; None: the machine's cores; the result is the same for any number), forking
    processes for GIL-bound stages with `fork` (`Pipeline.fork`); `starts` the start poses a user
    gave (scan name -> `StartPose`, checked by `Pipeline.start` before anything runs)."""
    pipe = Pipeline(list(scans), params or Params(), truth, workers=workers, fork=fork)
    for name, pose in (starts or {}).items():
        pipe.start(name, pose)
    last = pipe.run(until, events)
    ok = last is not None and last.ok and last.stage == until
    return Registration(ok, last.message if last else "", pipe.transforms(), pipe)
