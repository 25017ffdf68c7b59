"""Before and after: which run's result a stage's view draws, and what changed between the two.

A changed parameter drops a stage's result; the view keeps drawing the last one, marked stale, until
the re-run lands (`Snapshot.before` holds it). Once the new result is in, *Previous run*
(`ViewState.show_before`) draws the previous one again, and the panel lists the parameters that
changed and the metrics that moved.
"""

from __future__ import annotations

from typing import Any

from treereg_core.params import SECTIONS, set_text
from treereg_core.results import Metric
from treereg_core.stages import stage as core_stage

from ..controller import Snapshot
from ..labels import label
from ..text import md
from ..view_state import ViewState
from .common import md_table, metric_text, target_index

#: At most this many changed parameters and metrics are listed (a preset changes dozens).
MAX_LISTED = 8


def drawn(snap: Snapshot, view: ViewState, stage: str | None = None) -> tuple[Snapshot, str]:
    """The state whose result of `stage` (default: the view's) the view draws, and why: "now" (the
    latest result), "stale" (the stage has no result for the parameters in force — changed, or
    running again —: the last result, until the re-run lands) or "before" (the run before, asked for
    with *Previous run*)."""
    name = stage or view.stage
    old = snap.before.get(name)
    if old is None or old.output(name) is None:
        return snap, "now"
    if snap.output(name) is None:  # a failed run says why instead
        return (old, "stale") if not snap.crashed else (snap, "now")
    return (old, "before") if view.show_before else (snap, "now")


def changed_params(old: Snapshot, new: Snapshot, stage: str) -> list[tuple[str, str, str]]:
    """(key, before, now) of every parameter the stage or a stage before it reads that differs
    between the two states (what made the result differ)."""
    from treereg_core.stages import STAGE_NAMES

    upto = STAGE_NAMES[: STAGE_NAMES.index(stage) + 1]
    read = {s for n in upto for s in (*core_stage(n).sections, *core_stage(n).borrows)}
    rows = []
    for section in SECTIONS:
        if section not in read:
            continue
        a, b = getattr(old.params, section), getattr(new.params, section)
        if a == b:
            continue
        for f in a.__dataclass_fields__:
            va, vb = getattr(a, f), getattr(b, f)
            if va != vb:
                rows.append((f"{section}.{f}", set_text(va), set_text(vb)))
    return rows


def _metrics(snap: Snapshot, stage: str, view: ViewState) -> dict[str, tuple[Metric, ...]]:
    """The metrics of the item in view (the pair's, or every scan's), by the pair's or scan's name."""
    out = snap.output(stage)
    if out is None:
        return {}
    if core_stage(stage).per == "pair":
        t = target_index(snap, stage, view)
        if t >= len(out.items) or t >= snap.n_pairs:
            return {}
        return {snap.pair(t).label: tuple(getattr(out.items[t], "metrics", ()))}
    return {snap.scans[i].name: tuple(getattr(it, "metrics", ())) for i, it in enumerate(out.items)
            if i < len(snap.scans)}


def changed_metrics(old: Snapshot, new: Snapshot, stage: str, view: ViewState) -> list[tuple[str, str, str]]:
    """(metric, before, now) of the metrics of the item in view that differ between the two runs."""
    a, b = _metrics(old, stage, view), _metrics(new, stage, view)
    several = len(b) > 1
    rows = []
    for who, ms in b.items():
        before = {m.description: m for m in a.get(who, ())}
        for m in ms:
            o = before.get(m.description)
            was, now = ("–" if o is None else metric_text(o)), metric_text(m)
            if was != now:
                rows.append((f"{who}: {m.description}" if several else m.description, was, now))
    return rows


def _listed(rows: list[tuple[str, str, str]], header: tuple[str, str, str]) -> str:
    more = len(rows) - MAX_LISTED
    table = md_table(header, [tuple(md(v) for v in r) for r in rows[:MAX_LISTED]])
    return table + (f"\n\n*… and {more} more.*" if more > 0 else "")


def comparison_text(snap: Snapshot, view: ViewState) -> str:
    """What the panel says above a stage's drawing about before and after (empty: no run before)."""
    name = view.stage
    old = snap.before.get(name)
    if old is None or old.output(name) is None:
        return ""
    mode = drawn(snap, view)[1]
    params = changed_params(old, snap, name)
    what = ", ".join(f"{md(k)} {md(a)} → {md(b)}" for k, a, b in params[:MAX_LISTED])
    if len(params) > MAX_LISTED:
        what += f" and {len(params) - MAX_LISTED} more"
    since = f" ({what})" if what else ""
    if mode == "stale":
        doing = "is running again" if snap.status(name) == "running" else "must run again: press **Run**"
        return (f"**Stale — the last run's result.** {label(name)} {doing}{since}; the new result replaces "
                "this one when it lands.")
    if mode == "before":
        return (f"**The previous run**{since}: untick *Previous run* (Stage tab, under Run) for the "
                "latest result." + _moved(old, snap, name, view))
    return (f"**The latest run**{since}; tick *Previous run* (under Run) to compare."
            + _moved(old, snap, name, view))


def _moved(old: Snapshot, new: Snapshot, name: str, view: ViewState) -> str:
    rows = changed_metrics(old, new, name, view)
    if not rows:
        return " No metric of this view changed."
    return "\n\n" + _listed(rows, ("changed", "before", "now"))


def has_before(snap: Snapshot, stage: str) -> bool:
    """Whether stage `stage` has a run before to compare with (and a latest result to compare it to)."""
    old: Any = snap.before.get(stage)
    return old is not None and old.output(stage) is not None and snap.output(stage) is not None
