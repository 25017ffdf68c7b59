"""Helpers shared by the stages' drawings: subsampling for display, poses, metric tables, status text."""

from __future__ import annotations

import re
from typing import Any, Iterable

import numpy as np
import viser
import viser.transforms as vtf

from treereg_core.results import Metric

from ..controller import Snapshot
from ..labels import STAGE_NAMES, label, verdict_badge
from ..view_panel import PanelContent
from ..view_state import ViewState

#: The scene nodes a drawing made (the drawer removes them before the next draw).
Handles = list[viser.SceneNodeHandle]
#: What a stage's renderer returns: its scene nodes and the docked panel's content.
Drawing = tuple[Handles, PanelContent]


def display_subset(n: int, max_points: int, seed: int = 0) -> np.ndarray:
    """Sorted indices of at most `max_points` of `n` points (seeded: the same every redraw)."""
    if n <= max_points:
        return np.arange(n)
    rng = np.random.default_rng(seed)
    return np.sort(rng.choice(n, size=max_points, replace=False))


def pose_kwargs(T: np.ndarray) -> dict[str, np.ndarray]:
    """viser's (wxyz, position) of a 4x4 rigid transform."""
    T = np.asarray(T, dtype=np.float64)
    return {"wxyz": vtf.SO3.from_matrix(T[:3, :3]).wxyz, "position": T[:3, 3].copy()}


#: Where a long word may wrap in a narrow table column: after a '/', '_' or '.' followed by a letter
#: (a scan named by its folder, "a/scan1.ply"; a parameter, "verify.min_consistency"), never inside
#: a tag ("</small>": no letter before its '/').
_BREAK_AFTER = re.compile(r"(?<=\w)([/_.])(?=[A-Za-z])")


def breakable(text: str) -> str:
    """`text` whose long words may wrap after their '/', '_' and '.' (an HTML <wbr>: nothing is
    added to the text a person copies)."""
    return _BREAK_AFTER.sub("\\1<wbr>", text)


def md_table(header: tuple[str, ...], rows: list[tuple[Any, ...]]) -> str:
    """A markdown table; cells are str()-ed, '|' escaped, long words breakable (`breakable`)."""
    if not rows:
        return ""

    def cell(v: Any) -> str:
        if isinstance(v, float):
            v = f"{v:.4g}" if np.isfinite(v) else "–"  # never "nan" on screen
        return breakable(str(v)).replace("|", "\\|")

    lines = ["| " + " | ".join(cell(h) for h in header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(cell(v) for v in r) + " |" for r in rows]
    return "\n".join(lines)


#: Value columns per metrics table: more (many stations) continue in a table below, so that a table
#: fits a narrow panel (330 px at 1280 x 720).
COLUMNS_PER_TABLE = 3


def metric_text(m: Metric) -> str:
    """A metric's value as shown: never "nan" (a value not measured says so)."""
    v = m.value
    if isinstance(v, float) and not np.isfinite(v):
        return "not measured"
    return m.formatted()


def metrics_table(columns: dict[str, Iterable[Metric]]) -> str:
    """Metric rows side by side: one column per label (e.g. per target scan), one row per metric;
    at most COLUMNS_PER_TABLE columns per table."""
    cols = {k: {m.description: metric_text(m) for m in v} for k, v in columns.items()}
    names: list[str] = []
    for c in cols.values():
        names += [n for n in c if n not in names]
    keys = list(cols)
    tables = []
    for a in range(0, max(len(keys), 1), COLUMNS_PER_TABLE):
        part = keys[a:a + COLUMNS_PER_TABLE]
        rows = [(n, *(cols[k].get(n, "") for k in part)) for n in names]
        tables.append(md_table(("metric", *part), rows))
    return "\n\n".join(t for t in tables if t)


def target_index(snap: Snapshot, name: str, view: ViewState) -> int:
    """The view's target pair, clamped to the items stage `name` has."""
    out = snap.output(name)
    n = len(out.items) if out is not None else 0
    return int(min(max(view.target, 0), max(n - 1, 0)))


def title(name: str, snap: Snapshot | None = None, t: int | None = None) -> str:
    """A panel heading: '4 Coarse', or '4 Coarse: scan2 → scan1' for a target pair, followed by the
    pair's badges (`pair_badges`)."""
    head = label(name)
    if snap is None or t is None:
        return head
    # A verdict is the Verify stage's: shown from there on (an earlier stage's view is not redrawn
    # when a later stage re-runs, so a badge there could be stale).
    badges = pair_badges(snap, t) if STAGE_NAMES.index(name) >= STAGE_NAMES.index("verify") else ""
    return f"{head}: {pair_label(snap, t)}" + (f" {badges}" if badges else "")


def pair_badges(snap: Snapshot, t: int) -> str:
    """The mark after a pair's name in a heading: its verdict ("[✓ verified]"), once the Verify stage
    has judged it; empty before."""
    out = snap.output("verify")
    verdict = getattr(out.items[t], "verdict", None) if out is not None and t < len(out.items) else None
    return f"[{verdict_badge(str(verdict))}]" if verdict else ""


def plural(n: int, word: str, many: str | None = None) -> str:
    """'1 arc', '3 arcs', '0 arcs' (`many` for irregular plurals)."""
    return f"{n} {word if n == 1 else (many or word + 's')}"


def pair_scans(snap: Snapshot, k: int) -> tuple[int, int]:
    """(reference, target) scan indices of pair k: the pipeline's pairs, the reference's first
    (pair k < n - 1 is scan k + 1 onto scan 1)."""
    if k < len(snap.pairs):
        return snap.pairs[k].ref, snap.pairs[k].tgt
    return 0, k + 1


def pair_label(snap: Snapshot, k: int) -> str:
    """'scan2 → scan1' for pair k."""
    i, j = pair_scans(snap, k)
    return f"{snap.scans[j].name} → {snap.scans[i].name}"


def not_ready_text(snap: Snapshot, name: str) -> str:
    """What the panel says when a stage has nothing to show."""
    status = snap.status(name)
    if status == "running":
        return f"*{label(name)} is running…*"
    if len(snap.scans) < 2:
        return "*Registration needs at least two scans: upload another scan (Scans tab).*"
    for s, why in snap.crashed.items():
        return f"**{label(s)} failed:** {why}\n\nLater stages are stale until it succeeds."
    for s, out in snap.outputs.items():
        if not out.ok:
            return f"**{label(s)} failed:** {out.message}\n\nLater stages are stale until it succeeds."
    return f"*{label(name)} has not run for the current scans and parameters: press **Run**.*"


def item_message(item: Any) -> str:
    """A failed item's message, as a line for the panel (empty when ok)."""
    if getattr(item, "ok", True):
        return ""
    return f"**Failed:** {getattr(item, 'message', '')}"


def target_pose(snap: Snapshot, pose: str | None, k: int) -> np.ndarray | None:
    """Pair `k`'s transform for a view's `pose` ("coarse", "hypothesis", "fine", "icp", "final"),
    falling back to the best earlier one that succeeded; None before registration or when none did.
    "final" is the joint placement of scan k + 1 (the graph stage), k being its pair with the reference."""
    if pose == "final":
        graph = snap.output("graph")
        item = graph.items[k + 1] if graph is not None and k + 1 < len(graph.items) else None
        if item is not None and item.T_ref_scan is not None:
            return np.asarray(item.T_ref_scan, dtype=np.float64)
    order = {"coarse": ("coarse",), "hypothesis": ("hypotheses", "coarse"), "fine": ("fine", "hypotheses", "coarse"),
             "icp": ("icp", "fine", "coarse"), "final": ("fine", "hypotheses", "coarse")}.get(pose or "", ())
    for name in order:
        out = snap.output(name)
        item = out.items[k] if out is not None and k < len(out.items) else None
        if item is not None and item.ok and getattr(item, "ran", True):
            return np.asarray(item.T_ref_target, dtype=np.float64)
    return None
