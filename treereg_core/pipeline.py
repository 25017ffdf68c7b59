"""Runs the registration stages in order, caching each stage's output.

A stage re-runs only when one of its own parameter sections, or an upstream output, changed
(`Pipeline.set_params`). The app's controller drives one `Pipeline` on a worker thread; scripts
call `register(scans, params)`. The first scan is the reference; every other scan is registered
onto it (the paper's order 2->1, 3->1, ...).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any, Sequence

import numpy as np

from .params import Params
from .results import Metric, Progress, no_progress
from .scan import Scan

#: The stages, in order. The app's stages 4-6 (slices, arcs, fits) are views of "fine".
STAGES: tuple[str, ...] = ("prepare", "projection", "matching", "coarse", "fine", "evaluation")

#: Which parameter sections each stage reads.
STAGE_SECTIONS: dict[str, tuple[str, ...]] = {
    "prepare": ("prepare",),
    "projection": ("projection",),
    "matching": ("matching",),
    "coarse": ("coarse",),
    "fine": ("slicing", "arcs", "fitting", "fine"),
    "evaluation": ("evaluation", "icp"),
}


@dataclass(frozen=True)
class StageOutput:
    """One stage's output: per scan (prepare, projection) or per target scan (the others)."""

    stage: str
    ok: bool
    message: str
    items: tuple[Any, ...]
    seconds: float


@dataclass(frozen=True)
class PairReport:
    """Evaluation of one target scan: coarse, fine and (optionally) ICP from coarse."""

    target: str
    coarse: Any  # evaluation.EvaluationResult
    fine: Any  # evaluation.EvaluationResult
    icp: Any | None = None  # icp.IcpResult
    icp_eval: Any | None = None  # evaluation.EvaluationResult
    ok: bool = True
    message: str = ""
    metrics: tuple[Metric, ...] = ()


@dataclass
class Pipeline:
    """Cached, stage-by-stage registration of `scans` (scan 0 = reference)."""

    scans: list[Scan]
    params: Params = field(default_factory=Params)
    truth: dict[str, np.ndarray] | None = None  # scan name -> true T_ref_scan, when known
    _out: dict[str, StageOutput] = field(default_factory=dict, repr=False)

    # ---- state -------------------------------------------------------------------------
    def set_params(self, params: Params) -> list[str]:
        """Adopt `params`; drop the cached outputs of the first changed stage and all after it.

        Returns the stages that became stale.
        """
        first = next(
            (s for s in STAGES if any(getattr(params, sec) != getattr(self.params, sec) for sec in STAGE_SECTIONS[s])),
            None,
        )
        self.params = params
        return self.invalidate(first) if first else []

    def set_scans(self, scans: Sequence[Scan], truth: dict[str, np.ndarray] | None = None) -> None:
        self.scans = list(scans)
        self.truth = truth
        self.invalidate(STAGES[0])

    def invalidate(self, stage: str) -> list[str]:
        """Drop `stage` and every later stage; returns those that had outputs."""
        later = STAGES[STAGES.index(stage):]
        dropped = [s for s in later if s in self._out]
        for s in later:
            self._out.pop(s, None)
        return dropped

    def output(self, stage: str) -> StageOutput | None:
        """The cached output of `stage`, or None if it has not run since its inputs changed."""
        return self._out.get(stage)

    def status(self, stage: str) -> str:
        """'done', 'failed' or 'stale' (not run for the current inputs)."""
        out = self._out.get(stage)
        if out is None:
            return "stale"
        return "done" if out.ok else "failed"

    @property
    def target_names(self) -> list[str]:
        return [s.name for s in self.scans[1:]]

    # ---- running -----------------------------------------------------------------------
    def run(self, until: str = STAGES[-1], progress: Progress | None = None) -> StageOutput | None:
        """Run every stage up to `until` that has no cached output.

        A pair (or scan) that fails at one stage is skipped by the later stages, which go on with the
        others; the run stops when a stage has no successful item left. Returns the output of the
        last stage run (or cached), which may be a failure.
        """
        progress = progress or no_progress
        if len(self.scans) < 2:
            raise ValueError("registration needs at least two scans")
        todo = STAGES[: STAGES.index(until) + 1]
        last: StageOutput | None = None
        for k, stage in enumerate(todo):
            out = self._out.get(stage)
            if out is None:
                lo, hi = k / len(todo), (k + 1) / len(todo)

                def sub(f: float, text: str, lo: float = lo, hi: float = hi, stage: str = stage) -> None:
                    progress(lo + (hi - lo) * f, f"{stage}: {text}" if text else stage)

                t0 = time.perf_counter()
                items = getattr(self, f"_run_{stage}")(sub)
                bad = [(self._item_name(stage, i), it) for i, it in enumerate(items) if not it.ok]
                msg = "; ".join(f"{name}: {it.message}" for name, it in bad)
                out = StageOutput(stage, not bad, msg, tuple(items), time.perf_counter() - t0)
                self._out[stage] = out
            last = out
            # A scan that cannot be prepared or projected is an input to fix: stop. A pair that
            # fails later is skipped by the later stages while the other pairs go on.
            per_scan = stage in ("prepare", "projection")
            if (per_scan and not out.ok) or not any(it.ok for it in out.items):
                break
        progress(1.0, "done")
        return last

    def _item_name(self, stage: str, i: int) -> str:
        if stage in ("prepare", "projection"):
            return self.scans[i].name
        return f"{self.scans[i + 1].name} -> {self.scans[0].name}"

    def _items(self, stage: str) -> tuple[Any, ...]:
        out = self._out[stage]
        return out.items

    def _run_prepare(self, progress: Progress) -> list[Any]:
        from .ground import prepare_scan

        res = []
        for i, s in enumerate(self.scans):
            progress(i / len(self.scans), s.name)
            res.append(prepare_scan(s, self.params.prepare))
        return res

    def _prepared(self) -> list[Scan]:
        return [p.scan for p in self._items("prepare")]

    def _run_projection(self, progress: Progress) -> list[Any]:
        from .sequences import build_sequence

        scans = self._prepared()
        res = []
        for i, s in enumerate(scans):
            progress(i / len(scans), s.name)
            res.append(build_sequence(s, self.params.projection, len(scans)))
        return res

    def _run_matching(self, progress: Progress) -> list[Any]:
        from .coarse import match_sequences

        scans, seqs = self._prepared(), self._items("projection")
        res = []
        for i in range(1, len(scans)):
            progress((i - 1) / (len(scans) - 1), scans[i].name)
            res.append(match_sequences(seqs[0], seqs[i], scans[0], scans[i], self.params.matching))
        return res

    def _run_coarse(self, progress: Progress) -> list[Any]:
        from .coarse import estimate_coarse

        return [estimate_coarse(m, self.params.coarse) for m in self._items("matching")]

    def _run_fine(self, progress: Progress) -> list[Any]:
        from .fine import register_fine

        from .fine import skipped_fine

        scans, coarse = self._prepared(), self._items("coarse")
        res = []
        for i in range(1, len(scans)):
            progress((i - 1) / (len(scans) - 1), scans[i].name)
            c = coarse[i - 1]
            res.append(register_fine(scans[0], scans[i], c.T_ref_target, self.params) if c.ok
                       else skipped_fine(c.T_ref_target, "not run: the coarse stage failed for this pair"))
        return res

    def _run_evaluation(self, progress: Progress) -> list[Any]:
        from .evaluation import evaluate_pair, find_branches
        from .icp import icp

        scans, coarse, fine = self._prepared(), self._items("coarse"), self._items("fine")
        p = self.params
        branches = find_branches(scans[0], p.evaluation)  # the reference's: shared by every evaluation
        res = []
        for i in range(1, len(scans)):
            progress((i - 1) / (len(scans) - 1), scans[i].name)
            ref, tgt = scans[0], scans[i]
            if not fine[i - 1].ok:
                res.append(PairReport(tgt.name, None, None, ok=False,
                                      message="not evaluated: the pair has no fine result"))
                continue
            T_true = (self.truth or {}).get(tgt.name)
            ev_c = evaluate_pair(ref, tgt, coarse[i - 1].T_ref_target, p.evaluation, T_true, branches)
            ev_f = evaluate_pair(ref, tgt, fine[i - 1].T_ref_tgt, p.evaluation, T_true, branches)
            ic = ev_i = None
            if p.evaluation.run_icp:
                ic = icp(ref.points, tgt.points, coarse[i - 1].T_ref_target, p.icp)
                ev_i = evaluate_pair(ref, tgt, ic.T, p.evaluation, T_true, branches)
            res.append(PairReport(tgt.name, ev_c, ev_f, ic, ev_i, metrics=_report_metrics(ev_c, ev_f, ev_i)))
        return res

    # ---- results -------------------------------------------------------------------------
    def transforms(self) -> dict[str, np.ndarray]:
        """The best available T_ref_scan per scan name: fine if it succeeded for that pair, else
        coarse; the reference maps to the identity. Scans with neither are left out.
        """
        out = {self.scans[0].name: np.eye(4)}
        fine, coarse = self._out.get("fine"), self._out.get("coarse")
        for k, s in enumerate(self.scans[1:]):
            if fine is not None and fine.items[k].ok:
                out[s.name] = fine.items[k].T_ref_tgt
            elif coarse is not None and coarse.items[k].ok:
                out[s.name] = coarse.items[k].T_ref_target
        return out

    def pair_metrics(self) -> dict[str, list[dict[str, Any]]]:
        """Per target scan, the metric rows of every stage that ran (for transform files and tables)."""
        rows: dict[str, list[dict[str, Any]]] = {n: [] for n in self.target_names}
        for stage in ("matching", "coarse", "fine", "evaluation"):
            out = self._out.get(stage)
            if out is None:
                continue
            for name, item in zip(self.target_names, out.items):
                rows[name] += [
                    {"stage": stage, "metric": m.description, "unit": m.unit, "value": m.value} for m in item.metrics
                ]
        return rows


def _report_metrics(ev_c: Any, ev_f: Any, ev_i: Any | None) -> tuple[Metric, ...]:
    rows: list[Metric] = []
    for label, ev in (("coarse", ev_c), ("fine", ev_f), ("ICP", ev_i)):
        if ev is None:
            continue
        rows += [Metric(f"{label}: {m.description}", m.unit, m.value) for m in ev.metrics]
    return tuple(rows)


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
    until: str = "fine",
    truth: dict[str, np.ndarray] | None = None,
    progress: Progress | None = None,
) -> Registration:
    """One call: register every scan onto the first; `until` is a stage name ('coarse', 'fine', 'evaluation')."""
    pipe = Pipeline(list(scans), params or Params(), truth)
    last = pipe.run(until, progress)
    ok = last is not None and last.ok and last.stage == until
    return Registration(ok, last.message if last else "", pipe.transforms(), pipe)
