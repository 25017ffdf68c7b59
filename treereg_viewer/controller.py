"""The app's controller: one worker thread runs the pipeline; callbacks only record requests.

viser runs GUI callbacks on a thread pool, so two can run at once and none may block for long.
Callbacks therefore call the recording methods here (`set_param`, `request_run`, `add_scan_file`
...), which take the one lock for a moment, note what changed and wake the worker. Only the worker
touches the `Pipeline`; after every change it publishes an immutable `Snapshot` that drawing code
and exports read without locks. Every browser tab sees the same snapshot: one consistent state.
"""

from __future__ import annotations

import logging
import os
import threading
import time
import warnings
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence, TypeVar

import numpy as np

from treereg_core.coarse.start import StartPose
from treereg_core.errors import ConfigError, ScanError
from treereg_core.io.scans import read_scan
from treereg_core.parallel import APP_SPARE_CORES, default_workers
from treereg_core.params import Params
from treereg_core.pipeline import Pipeline
from treereg_core.scan import Scan
from treereg_core.prepare.ground import PreparedScan
from treereg_core.stage import Event, Pair, StageFinished, StageOutput, StageProgress, StageResult, StageStarted
from treereg_core.stages import STAGE_NAMES as STAGES
from treereg_core.stages import stage as core_stage
from treereg_core.survey.mode import is_survey
from treereg_core.survey.register import Survey, register_survey
from treereg_core.verify.graph import Placement
from treereg_core.text import shown

from .labels import label
from .uploads import discard

log = logging.getLogger(__name__)

#: The worker gives way to a tab opening while it computes (its GUI built, its first view drawn and
#: shown): on two cores the browser, the tab's threads and viser's need the CPU (and the GIL) that the
#: pipeline takes. It pauses at its next pipeline event (a few tenths of a second apart) for at most
#: GIVE_WAY_MAX_S, then runs at least GIVE_WAY_GAP_S before it pauses again: tabs opening one after
#: another slow a run at most two-fold.
GIVE_WAY_MAX_S = 2.5
GIVE_WAY_GAP_S = 2.5

R = TypeVar("R", bound=StageResult)


@dataclass(frozen=True, kw_only=True)
class SnapshotPair:
    """Pair `index` of a snapshot as the app draws it: which scans it joins (`tgt` mapped onto `ref`,
    indices into the scans), the scans themselves, its label and its stage results, read by type.
    Renderers and controls read a pair only through this (`Snapshot.pair`): its scans are never
    derived from its index (pair 2 of three scans joins scans 2 and 3, not 1 and 3)."""

    index: int
    ref: int
    tgt: int
    ref_scan: Scan
    tgt_scan: Scan
    outputs: Mapping[str, StageOutput] = field(repr=False, compare=False)

    @property
    def label(self) -> str:
        """How the app names the pair everywhere: 'scan3 → scan2' (target onto reference)."""
        return f"{self.tgt_scan.name} → {self.ref_scan.name}"

    @property
    def key(self) -> str:
        """The pipeline's name of the pair ('scan3 -> scan2'): what `Pipeline.choose` and its choices are keyed by."""
        return f"{self.tgt_scan.name} -> {self.ref_scan.name}"

    def item(self, stage: str, kind: type[R]) -> R | None:
        """The pair's item of per-pair `stage` as a `kind`; None when the stage has no output for it
        or the item is not one (a `Skipped` pair)."""
        if core_stage(stage).per != "pair":
            raise ValueError(f"{stage} is a per-scan stage: read it with scan_items")
        return _item_as(self.outputs.get(stage), self.index, kind)

    def scan_items(self, stage: str, kind: type[R]) -> tuple[R | None, R | None]:
        """The (reference's, target's) items of per-scan `stage` as `kind`s (None where missing)."""
        if core_stage(stage).per != "scan":
            raise ValueError(f"{stage} is a per-pair stage: read it with item")
        out = self.outputs.get(stage)
        return _item_as(out, self.ref, kind), _item_as(out, self.tgt, kind)

    def prepared(self) -> tuple[Scan, Scan] | None:
        """The (reference, target) scans as the prepare stage left them, which the pair's slices, arcs
        and sections index into; None until both are prepared."""
        ref, tgt = self.scan_items("prepare", PreparedScan)
        if ref is None or tgt is None or not (ref.ok and tgt.ok):
            return None
        return ref.scan, tgt.scan


def _item_as(out: StageOutput | None, k: int, kind: type[R]) -> R | None:
    it = out.items[k] if out is not None and 0 <= k < len(out.items) else None
    return it if isinstance(it, kind) else None


@dataclass(frozen=True)
class Snapshot:
    """What the app draws: the state after the worker's last change. Never mutated."""

    version: int
    scans: tuple[Scan, ...]
    truth: Mapping[str, np.ndarray] | None
    params: Params
    outputs: Mapping[str, StageOutput]
    transforms: Mapping[str, np.ndarray]
    pair_metrics: Mapping[str, list[dict[str, Any]]]
    busy: bool = False
    running: str | None = None
    message: str = ""
    error: bool = False
    crashed: Mapping[str, str] = field(default_factory=dict)  # stage -> error, when it raised
    runs: Mapping[str, int] = field(default_factory=dict)  # stage -> how often it has run (what a change cost)
    pairs: tuple[Pair, ...] = ()  # the registered pairs (the reference's first, in scan order)
    verdicts: Mapping[str, tuple[str, tuple[str, ...], str]] = field(default_factory=dict)  # scan -> (verdict, reasons, hint)
    choices: Mapping[str, str] = field(default_factory=dict)  # hypotheses picked by hand: pair label -> candidate
    starts: Mapping[str, StartPose] = field(default_factory=dict)  # start poses given by hand: scan name -> start
    #: The run before, per stage: the last published state that held the stage's previous result (a
    #: changed parameter dropped it, or a run replaced it), for the tuner's before and after. Its own
    #: `before` is empty; the scans were the same (new scans forget it).
    before: Mapping[str, Snapshot] = field(default_factory=dict, repr=False, compare=False)
    #: A whole-plot survey's registration (`Controller(..., survey=True)`: `treereg_core.survey`, not
    #: the stages), once it has run; None before and in the one-tree app.
    survey: Survey | None = field(default=None, repr=False, compare=False)

    def status(self, stage: str) -> str:
        """'done', 'failed', 'running' or 'stale' for a pipeline stage."""
        if self.running == stage:
            return "running"
        out = self.outputs.get(stage)
        if out is None:
            return "failed" if stage in self.crashed else "stale"
        return "done" if out.ok else "failed"

    def output(self, stage: str) -> StageOutput | None:
        return self.outputs.get(stage)

    def scan_item(self, stage: str, i: int, kind: type[R]) -> R | None:
        """Scan i's item of per-scan `stage` as a `kind`; None when the stage has no output for it
        or the item is not one (a `Skipped` scan). A pair's scans: `pair(k).scan_items`."""
        if core_stage(stage).per != "scan":
            raise ValueError(f"{stage} is a per-pair stage: read it with pair(k).item")
        return _item_as(self.outputs.get(stage), i, kind)

    @property
    def scan_names(self) -> list[str]:
        return [s.name for s in self.scans]

    @property
    def n_pairs(self) -> int:
        """How many pairs the app offers: the pipeline's, or before it knows them (four or more scans
        before the projection stage) the reference with every other scan."""
        return max(len(self.pairs), len(self.scans) - 1)

    def pair(self, k: int) -> SnapshotPair:
        """Pair k (0 <= k < n_pairs): the pipeline's pairs, the reference's first, so pair k < n - 1
        is scan k + 2 onto scan 1 (counting from 1)."""
        if not 0 <= k < self.n_pairs:
            raise IndexError(f"pair {k} of {self.n_pairs}")
        p = self.pairs[k] if k < len(self.pairs) else Pair(ref=0, tgt=k + 1)
        return SnapshotPair(index=k, ref=p.ref, tgt=p.tgt, ref_scan=self.scans[p.ref], tgt_scan=self.scans[p.tgt],
                            outputs=self.outputs)

    def reference_pair(self, i: int) -> SnapshotPair | None:
        """Scan i's pair with the reference (whose transforms place scan i), None for the reference."""
        return next((p for k in range(self.n_pairs) if (p := self.pair(k)).ref == 0 and p.tgt == i), None)


Listener = Callable[[Snapshot], None]
ProgressListener = Callable[[float, str], None]
#: Turns an uploaded file (the name the user picked, the path it was received at) into a Scan and the
#: notes a user should read (rows repaired, ...), raising ScanError when it cannot.
ScanParser = Callable[[str, Path], "tuple[Scan, list[str]]"]


@dataclass
class _Run:
    """The stage a run is computing, as the pipeline's events say (None between stages)."""

    stage: str | None


#: The worker's (and its run's threads') nice value: the browser, the server and the tabs' drawers
#: come first when they want the cores (on a 2-core machine the browser's own rendering needs one).
#: Modest: at 10 the demo's verdicts came 0.8 s later while the page rendered, at 0 a Next took 1.05 s
#: (benchmarks/RESULTS.md, issue 20).
COMPUTE_NICE = 5


def _lower_priority() -> None:
    """Lower this thread's scheduling priority (Linux: the nice value is per thread, and the threads
    it starts inherit it); nothing where that is not possible."""
    try:
        os.setpriority(os.PRIO_PROCESS, 0, min(os.getpriority(os.PRIO_PROCESS, 0) + COMPUTE_NICE, 19))
    except (AttributeError, OSError):
        pass


class _Closing(Exception):
    """Raised on a run's threads between two items once the app is closing: the run ends there."""


@dataclass
class _GiveWay:
    """When the worker pauses for the tabs (guarded by the controller's lock)."""

    until: float = 0.0  # time.monotonic() until which a tab asked the worker to wait
    not_before: float = 0.0  # the worker ran too little since its last pause: no pause before this
    paused_s: float = 0.0  # total time paused (what giving way cost the runs)
    since: float | None = None  # when the pause under way began (the run's threads share it)


@dataclass
class _Requests:
    """What callbacks asked for since the worker last looked (guarded by the controller's lock)."""

    params_changed: bool = False
    run_until: str | None = None
    rerun_from: str | None = None
    uploads: list[tuple[str, Path]] = field(default_factory=list)  # received files; the worker deletes them
    removals: list[str] = field(default_factory=list)
    scans: list[Scan] | None = None
    truth: dict[str, np.ndarray] | None = None
    notes: list[tuple[str, bool]] = field(default_factory=list)
    choices: list[tuple[str, str | None]] = field(default_factory=list)
    starts: list[tuple[str, StartPose | None]] = field(default_factory=list)

    def pending(self) -> bool:
        return bool(self.params_changed or self.run_until or self.uploads or self.removals or self.scans is not None
                    or self.notes or self.choices or self.starts)


def parse_scan_upload(filename: str, path: Path) -> tuple[Scan, list[str]]:
    """Read an uploaded scan file (received at `path`, under the name the user picked) with treereg_core.io.

    Returns the scan and what the reader repaired (its warnings, e.g. rows with NaN dropped). Errors
    and notes name the uploaded file, never the temporary path the user has not seen.
    """
    name = Path(filename).name or "upload"
    try:
        # Only the worker thread reads uploads, so recording warnings here catches its own.
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            scan = read_scan(path)
    except ScanError as e:
        raise ScanError(name, e.problem.replace(str(path), name)) from None
    notes = [str(w.message).replace(str(path), name) for w in caught if issubclass(w.category, UserWarning)]
    # The temporary file goes away: name the scan after the uploaded file, not the temp path. Only the
    # source changes (a scan rebuilt field by field lost the file's pose and the steps' provenance).
    return replace(scan, source=Path(name)), notes


class Controller:
    """Owns the pipeline and the worker thread that runs it.

    Parameters
    ----------
    scans
        The scans, reference first.
    params
        Parameters to start with.
    truth
        True `T_ref_scan` per scan name, when known (the demo), for errors against truth.
    parse_upload
        How uploaded bytes become a Scan (tests may pass their own).
    workers
        Threads a run uses (None: one less than the machine's cores, at least one: APP_SPARE_CORES).
        The app's server has threads of its own, so the pipeline never forks here (`Pipeline.fork`).
    survey
        Register the scans as a whole-plot survey (`treereg_core.survey.register_survey`, on the same
        worker, its progress to the same listeners, its result in `Snapshot.survey`) instead of
        running the stages. None: `survey.mode.is_survey` decides (more than 8 stations, or
        params.survey.mode).
    """

    def __init__(
        self,
        scans: Sequence[Scan],
        params: Params | None = None,
        truth: Mapping[str, np.ndarray] | None = None,
        parse_upload: ScanParser = parse_scan_upload,
        workers: int | None = None,
        survey: bool | None = None,
    ) -> None:
        self._lock = threading.Lock()
        self._wake = threading.Condition(self._lock)
        self._idle = threading.Event()
        self._pipeline = Pipeline(list(scans), params or Params(), dict(truth) if truth else None,
                                  workers=workers or default_workers(spare=APP_SPARE_CORES))
        self._desired = self._pipeline.params
        self._req = _Requests()
        self._listeners: list[Listener] = []
        self._progress_listeners: list[ProgressListener] = []
        self._parse_upload = parse_upload
        self._version = 0
        self._stopped = False
        self._crashed: dict[str, str] = {}  # stages that raised, until inputs change or Run is pressed
        self._give_way = _GiveWay()
        self._before: dict[str, Snapshot] = {}
        self.survey_mode = is_survey(len(scans), self._pipeline.params) if survey is None else bool(survey)
        self._survey: Survey | None = None
        self._snapshot = self._make_snapshot(busy=False, running=None, message="", error=False)
        self._thread = threading.Thread(target=self._loop, name="treereg-worker", daemon=True)
        self._thread.start()

    # ---- subscription ----------------------------------------------------------------------
    def subscribe(self, listener: Listener) -> None:
        """Call `listener(snapshot)` (on the worker thread) after every published change."""
        self._listeners.append(listener)

    def subscribe_progress(self, listener: ProgressListener) -> None:
        """Call `listener(fraction, text)` (on the worker thread) while a stage runs."""
        self._progress_listeners.append(listener)

    @property
    def snapshot(self) -> Snapshot:
        """The latest published state (an immutable object: safe to read from any thread)."""
        return self._snapshot

    @property
    def params(self) -> Params:
        """The parameters as the user last set them (may be newer than the snapshot's)."""
        with self._lock:
            return self._desired

    # ---- recording requests (any thread; quick) -------------------------------------------
    def set_param(self, section: str, name: str, value: Any) -> Params:
        """Record one parameter change; raises ConfigError (and changes nothing) when invalid."""
        with self._wake:
            new = self._desired.with_value(section, name, value)
            if new != self._desired:
                self._desired = new
                self._req.params_changed = True
                self._notify()
            return new

    def set_params(self, params: Params) -> None:
        """Record a whole new parameter set (a loaded file or a preset)."""
        with self._wake:
            if params != self._desired:
                self._desired = params
                self._req.params_changed = True
                self._notify()

    def request_run(self, until: str = STAGES[-1], rerun_from: str | None = None) -> None:
        """Ask the worker to run every stale stage up to `until`.

        `rerun_from` also drops that stage's cached output first (the user pressed Run on a stage
        that was up to date). Requests made while a run is under way are merged and run after it.
        """
        if until not in STAGES or (rerun_from is not None and rerun_from not in STAGES):
            raise ValueError(f"unknown stage {until!r} / {rerun_from!r}")
        with self._wake:
            r = self._req
            if r.run_until is None or STAGES.index(until) > STAGES.index(r.run_until):
                r.run_until = until
            if rerun_from is not None and (r.rerun_from is None or STAGES.index(rerun_from) < STAGES.index(r.rerun_from)):
                r.rerun_from = rerun_from
            self._notify()

    def add_scan_file(self, filename: str, path: Path) -> None:
        """Queue an uploaded file (received at `path`, which the worker deletes once read); the worker
        parses it, and a bad file only produces a message."""
        with self._wake:
            self._req.uploads.append((filename, Path(path)))
            self._notify()

    def remove_scan(self, name: str) -> None:
        """Queue the removal of a target scan (the reference stays: every transform is onto it)."""
        with self._wake:
            self._req.removals.append(name)
            self._notify()

    def set_scans(self, scans: Sequence[Scan], truth: Mapping[str, np.ndarray] | None = None) -> None:
        """Replace all scans (first = reference); every stage becomes stale."""
        with self._wake:
            self._req.scans = list(scans)
            self._req.truth = dict(truth) if truth else None
            self._notify()

    def choose(self, pair_label: str, candidate: str | None) -> None:
        """Record a hypothesis picked by hand for a pair (None: automatic again); it re-runs from there."""
        with self._wake:
            self._req.choices.append((pair_label, candidate))
            self._notify()

    def start(self, name: str, pose: StartPose | None, run: bool = True) -> None:
        """Record a start pose given by hand for scan `name` (None: the coarse stage estimates it again);
        the worker gives it to the pipeline (`Pipeline.start`: the coarse stage and what follows become
        stale) and runs every stage again from there, to the verdict (`run`; False: restored with the
        parameters, it waits for Run as they do)."""
        with self._wake:
            self._req.starts.append((name, pose))
            if run:
                self._req.run_until = STAGES[-1]
            self._notify()

    def note(self, message: str, error: bool = False) -> None:
        """Publish a message for the user (e.g. a rejected parameter), in order with other changes."""
        with self._wake:
            self._req.notes.append((message, error))
            self._notify()

    def give_way(self, seconds: float) -> None:
        """Ask the worker to pause for `seconds` from now (a tab opens); it does at its next pipeline
        event, within the bounds of GIVE_WAY_MAX_S and GIVE_WAY_GAP_S. Any thread; returns at once."""
        with self._lock:
            self._give_way.until = max(self._give_way.until, time.monotonic() + seconds)

    @property
    def paused_s(self) -> float:
        """Seconds the worker has paused for the tabs so far (runs took this much longer)."""
        return self._give_way.paused_s

    def wait_idle(self, timeout: float = 60.0) -> bool:
        """Block until the worker has nothing left to do (tests, CLI exports). True if idle."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self._idle.wait(timeout=max(0.0, deadline - time.monotonic())):
                with self._lock:
                    if not self._req.pending():
                        return True
                time.sleep(0.005)
        return False

    def close(self) -> None:
        """Stop the worker: a run stops before its next item (a pair, a scan), not at its end
        (`treereg view` stopped 8-11 s after SIGTERM while the demo's first run went on)."""
        with self._wake:
            self._stopped = True
            self._wake.notify_all()
        self._thread.join(timeout=30)

    def _notify(self) -> None:
        # Called with the lock held.
        self._idle.clear()
        self._wake.notify_all()

    # ---- the worker ------------------------------------------------------------------------
    def _loop(self) -> None:
        _lower_priority()
        while True:
            with self._wake:
                while not self._req.pending() and not self._stopped:
                    self._idle.set()
                    self._wake.wait()
                if self._stopped:
                    self._idle.set()
                    return
                req, self._req = self._req, _Requests()
                desired = self._desired
            try:
                self._handle(req, desired)
            except Exception as e:  # never let the worker die; the user sees one line, the log the rest
                log.exception("treereg worker failed")
                self._publish(message=f"Internal error: {type(e).__name__}: {e}", error=True)

    def _handle(self, req: _Requests, desired: Params) -> None:
        pipe = self._pipeline
        message, error = "", False
        for text, err in req.notes:
            message, error = text, err
        if req.scans is not None:
            pipe.set_scans(req.scans, req.truth)
            message, error = f"Loaded {len(req.scans)} scans.", False
        for name in req.removals:
            names = [s.name for s in pipe.scans]
            if name not in names:
                message, error = f"{name} is not loaded.", True
            elif names.index(name) == 0:
                message, error = f"{name} is the reference (scan 1): every other scan is registered onto it, so it stays.", True
            else:
                truth = {k: v for k, v in pipe.truth.items() if k != name} if pipe.truth else None
                pipe.set_scans([s for s in pipe.scans if s.name != name], truth)
                message, error = f"Removed {name}; {len(pipe.scans)} scans remain: press Run to register them.", False
        for filename, path in req.uploads:
            try:
                scan, notes = self._parse_upload(filename, path)
            except (ScanError, ConfigError) as e:
                message, error = f"Upload rejected — {e}; nothing was added.", True
                continue
            except Exception as e:  # a reader bug must not take the app down either
                log.exception("reading upload %s failed", shown(filename))
                message, error = f"Upload rejected — {filename}: could not be read ({type(e).__name__}: {e})", True
                continue
            finally:
                discard(path)  # read (or refused): the received copy is not needed any more
            scan = _unique_name(scan, {s.name for s in pipe.scans})
            pipe.set_scans([*pipe.scans, scan], pipe.truth)
            message, error = (f"Added {scan.name} ({scan.n_points:,} points) as scan {len(pipe.scans)}; "
                              "press Run to register it."), False
            if notes:  # repaired rows and the like: the user should know what was not read
                message += " Note: " + "; ".join(notes) + "."
        for pair_label, candidate in req.choices:
            if pipe.choose(pair_label, candidate):
                message, error = ((f"{candidate} chosen by hand for {pair_label}; press Run." if candidate else
                                   f"{pair_label}: the surfaces choose the hypothesis again; press Run."), False)
        for name, pose in req.starts:
            try:
                pipe.start(name, pose)
            except ConfigError as e:
                message, error = f"Start pose refused — {e}", True
                continue
            if req.notes and not req.run_until:
                continue  # a note from the same moment says more (a params.json's starts restored with it)
            then = f"the stages from {label('coarse')} on run from it." if req.run_until else "press Run to run from it."
            message, error = ((f"{name}: the start pose from {pose.source} in force; {then}") if pose is not None else
                              f"{name}: the coarse stage estimates its pose again."), False
        if req.scans is not None or req.uploads or req.removals or req.params_changed or req.run_until:
            self._crashed.clear()  # new inputs or an explicit run: try again
        if req.params_changed or desired != pipe.params:
            stale = pipe.set_params(desired)
            if stale and not req.run_until:
                changed = f"Parameters changed: {', '.join(label(s) for s in stale)} must re-run (press Run)."
                # A note from the same moment (a preset applied, a value rejected) says more: keep it.
                message, error = (message, error) if req.notes else (changed, False)
        self._publish(message=message, error=error)
        if req.run_until:
            if self.survey_mode:
                self._run_survey()
            else:
                self._run(req.run_until, req.rerun_from)

    def _run_survey(self) -> None:
        """Register the scans as a survey (`register_survey`): its progress to the progress listeners,
        the tabs given way to between its steps, its result published in `Snapshot.survey`."""
        pipe = self._pipeline
        if len(pipe.scans) < 2:
            self._publish(message="A survey needs at least two stations.", error=True)
            return
        self._survey = None
        self._publish(busy=True, running="survey", message=f"Registering {len(pipe.scans)} stations as a survey…")

        def progress(fraction: float, text: str) -> None:
            self._pause_for_tabs()
            for fn in self._progress_listeners:
                fn(fraction, f"Survey: {text.replace(' -> ', ' → ')}")

        t0 = time.perf_counter()
        try:
            survey = register_survey(pipe.scans, pipe.params, workers=pipe.workers or 1, progress=progress)
        except _Closing:
            return
        except Exception as e:
            if not isinstance(e, (ConfigError, ScanError)):
                log.exception("survey registration failed")
            self._publish(message=f"The survey failed: {type(e).__name__}: {e}", error=True)
            return
        self._survey = survey
        verdicts = [pl.verdict for pl in survey.placements[1:]]
        counts = ", ".join(f"{verdicts.count(v)} {v}" for v in ("verified", "unverified", "failed") if verdicts.count(v))
        failed = verdicts.count("failed")
        self._publish(message=f"Registered {len(pipe.scans)} stations in {time.perf_counter() - t0:.1f} s on "
                              f"{len(survey.pairs)} pairs: {counts}.", error=bool(failed))

    def _run(self, until: str, rerun_from: str | None) -> None:
        pipe = self._pipeline
        if len(pipe.scans) < 2:
            self._publish(message="Registration needs at least two scans: upload another scan.", error=True)
            return
        if rerun_from is not None:
            pipe.invalidate(rerun_from)
        todo = pipe.stale(until)
        t0 = time.perf_counter()
        run = _Run(todo[0] if todo else None)
        self._publish(busy=True, running=run.stage, message="Running…" if todo else "")
        try:
            last = pipe.run(until, events=lambda event: self._on_event(run, event), between=self._pause_for_tabs)
        except _Closing:
            if run.stage is not None:
                pipe.invalidate(run.stage)  # started, not finished
            return
        except Exception as e:
            # The stage that raised is the one started and not finished (else the first still stale).
            stage = run.stage or next((s for s in todo if pipe.output(s) is None), until)
            if isinstance(e, (ConfigError, ScanError)):  # the input asks for the impossible: the message says what to change
                why = str(e)
            else:
                log.exception("pipeline stage %s failed", stage)
                why = f"{type(e).__name__}: {e}"
            pipe.invalidate(stage)  # the stage has no valid output: it and all later ones are stale
            self._crashed[stage] = why
            self._publish(message=f"{label(stage)} failed: {why}", error=True)
            return
        seconds = time.perf_counter() - t0
        # Report the first stage that failed (the cause); pairs that did not fail went on past it.
        failed = next((s for s in todo if (o := pipe.output(s)) is not None and not o.ok), None)
        ran = [s for s in todo if pipe.output(s) is not None]
        took = f"Ran {', '.join(label(s) for s in ran)} in {seconds:.1f} s. " if ran else ""
        if failed == "graph":
            # Scans that failed their verdict: named here, their reasons once, in the lines below.
            graph = pipe.output("graph")
            placed = graph.items_as(Placement) if graph is not None else ()
            gone = [pipe.scans[i].name for i, pl in enumerate(placed) if pl.verdict == "failed"]
            self._publish(message=f"{took}✗ {', '.join(gone) or 'a scan'} failed: not placed (why: below, and in "
                                  f"{label('graph')}).", error=True)
        elif failed is not None:
            went_on = last is not None and last.stage != failed and any(it.ok for it in last.items)
            more = f" The other pairs went on to {label(last.stage)}." if went_on and last is not None else ""
            why = o.message if (o := pipe.output(failed)) is not None else ""
            self._publish(message=f"{took}{label(failed)} failed: {why}.{more}", error=True)
        elif todo:
            self._publish(message=f"Ran {', '.join(label(s) for s in todo)} in {seconds:.1f} s.")
        else:
            self._publish(message="")

    def _on_event(self, run: _Run, event: Event) -> None:
        """The pipeline's events, on the worker thread: a snapshot as each stage starts (so it holds
        the outputs of the stages before it: a tab on an early stage, e.g. Arcs after an arcs
        parameter changed, sees its result while later stages still run), and the progress. A tab
        that asked the worker to give way gets its pause here."""
        self._pause_for_tabs()
        if isinstance(event, StageStarted):
            if event.stage != run.stage:
                run.stage = event.stage
                self._publish(busy=True, running=event.stage, message=f"Running {label(event.stage)}…")
        elif isinstance(event, StageFinished):
            run.stage = None
        elif isinstance(event, StageProgress):
            # The stage as the page names it, and the page's arrow ("13 Result: scan3 → scan2"),
            # not the command line's "evaluation: scan3 -> scan2".
            text = event.text.replace(" -> ", " → ")
            line = f"{label(event.stage)}: {text}" if text else label(event.stage)
            for fn in self._progress_listeners:
                fn(event.run_fraction, line)

    def _pause_for_tabs(self) -> None:
        """On the worker and the run's other threads (between two items): wait while a tab asked
        the worker to give way (see GIVE_WAY_MAX_S). The threads that arrive during a pause wait
        with it; the first to wake closes it. Once the app is closing, ends the run (`_Closing`)."""
        if self._stopped:
            raise _Closing
        with self._wake:
            gw, now = self._give_way, time.monotonic()
            if now < gw.not_before or now >= gw.until:
                return
            if gw.since is None:
                gw.since = now
            start = gw.since
            while not self._stopped and (left := min(gw.until, start + GIVE_WAY_MAX_S) - time.monotonic()) > 0:
                self._wake.wait(timeout=left)
            if gw.since is not None:
                end = time.monotonic()
                gw.paused_s += end - start
                gw.not_before = end + GIVE_WAY_GAP_S
                gw.since = None

    def _make_snapshot(self, busy: bool, running: str | None, message: str, error: bool) -> Snapshot:
        pipe = self._pipeline
        outputs = {s: o for s in STAGES if (o := pipe.output(s)) is not None}
        self._remember_before(outputs)
        self._version += 1
        return Snapshot(
            version=self._version,
            scans=tuple(pipe.scans),
            truth=pipe.truth,
            params=pipe.params,
            outputs=outputs,
            transforms=_safe(pipe.transforms, {}),
            pair_metrics=_safe(pipe.pair_metrics, {}),
            busy=busy,
            running=running,
            message=message,
            error=error,
            crashed=dict(self._crashed),
            runs=dict(pipe.runs),
            pairs=_safe(lambda: pipe.pairs, ()),
            verdicts=_safe(pipe.verdicts, {}),
            choices=dict(pipe.choices),
            starts=dict(pipe.starts),
            before=dict(self._before),
            survey=getattr(self, "_survey", None),
        )

    def _remember_before(self, outputs: Mapping[str, StageOutput]) -> None:
        """Keep, for every stage whose result is going (dropped by a change, or replaced by a run), the
        last published state that held it: what the app shows as the run before. New scans forget
        every run before (their results are of other scans)."""
        prev: Snapshot | None = getattr(self, "_snapshot", None)
        if prev is None:
            return
        scans = self._pipeline.scans
        if len(prev.scans) != len(scans) or any(a is not b for a, b in zip(prev.scans, scans)):
            self._before.clear()
            return
        kept = replace(prev, before={})
        for s, old in prev.outputs.items():
            if outputs.get(s) is not old:
                self._before[s] = kept

    def _publish(self, busy: bool = False, running: str | None = None, message: str = "", error: bool = False) -> None:
        snap = self._make_snapshot(busy, running, message, error)
        self._snapshot = snap
        for fn in self._listeners:
            try:
                fn(snap)
            except Exception:  # a drawing bug must not stop the pipeline
                log.exception("snapshot listener failed")


def _safe(fn: Callable[[], Any], default: Any) -> Any:
    try:
        return fn()
    except Exception:
        log.exception("reading pipeline results failed")
        return default


def _unique_name(scan: Scan, taken: set[str]) -> Scan:
    """Rename an uploaded scan whose name is already used ('scan2' -> 'scan2-2')."""
    if scan.name not in taken:
        return scan
    k = 2
    while f"{scan.name}-{k}" in taken:
        k += 1
    return scan.with_points(scan.points, name=f"{scan.name}-{k}")
