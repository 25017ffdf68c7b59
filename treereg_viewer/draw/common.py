"""Helpers shared by the stages' drawings: subsampling for display, poses, metric tables, status text."""

from __future__ import annotations

import re
from typing import Any, Iterable, Mapping

import numpy as np
import viser
import viser.transforms as vtf

from treereg_core.coarse.estimate import CoarseResult
from treereg_core.evaluate.icp import IcpResult
from treereg_core.fine.pose import FineResult
from treereg_core.results import Metric
from treereg_core.verify.evidence import PairVerification
from treereg_core.verify.graph import Placement
from treereg_core.verify.hypotheses import HypothesesResult

from ..controller import Snapshot
from ..labels import STAGE_NAMES, label, verdict_badge
from ..text import md
from ..view_panel import PanelContent
from ..view_state import ViewState

#: The scene nodes a drawing made (the drawer removes them before the next draw).
Handles = list[viser.SceneNodeHandle]
#: What a stage's renderer returns: its scene nodes and the docked panel's content.
Drawing = tuple[Handles, PanelContent]
#: The stages whose pair items place the target (`T_ref_target`), and their result types.
POSED_BY: dict[str, type[CoarseResult | HypothesesResult | FineResult | IcpResult]] = {
    "coarse": CoarseResult, "hypotheses": HypothesesResult, "fine": FineResult, "icp": IcpResult}


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
_BREAK_AFTER = re.compile(r"(?<=\w)(\\?[/_.])(?=[A-Za-z])")


def breakable(text: str) -> str:
    """`text` whose long words may wrap after their '/', '_' and '.', escaped (`md`) or not (an HTML
    <wbr>: nothing is added to the text a person copies)."""
    return _BREAK_AFTER.sub("\\1<wbr>", text)


#: A '|' not escaped yet: after an even run of backslashes (none included), which escape each other.
_UNESCAPED_PIPE = re.compile(r"(?<!\\)((?:\\\\)*)\|")


def md_table(header: tuple[str, ...], rows: list[tuple[Any, ...]]) -> str:
    """A markdown table; cells are str()-ed, '|' escaped, long words breakable (`breakable`).

    A cell is markdown: text from outside in it (a scan name, a message) is escaped by the caller
    (`md`); `metrics_table` and `names_cell` do it for theirs. A '|' `md` escaped already is left as
    it is: escaped again ("\\\\|"), viser's GFM tables (micromark) read an escaped backslash and a cell
    break, and a name with a '|' would split its cell and show a backslash."""
    if not rows:
        return ""

    def cell(v: Any) -> str:
        if isinstance(v, float):
            v = f"{v:.4g}" if np.isfinite(v) else "–"  # never "nan" on screen
        return _UNESCAPED_PIPE.sub(r"\1\\|", breakable(str(v)))

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


def metrics_table(columns: Mapping[str, Iterable[Metric]]) -> str:
    """Metric rows side by side: one column per label (e.g. per target scan), one row per metric;
    at most COLUMNS_PER_TABLE columns per table."""
    cols = {md(k): {md(m.description): md(metric_text(m)) for m in v} for k, v in columns.items()}
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
    return f"{head}: {md(pair_label(snap, t))}" + (f" {badges}" if badges else "")


def pair_badges(snap: Snapshot, t: int) -> str:
    """The mark after a pair's name in a heading: its verdict ("[✓ verified]"), once the Verify stage
    has judged it; empty before."""
    v = snap.pair(t).item("verify", PairVerification)
    return f"[{verdict_badge(v.verdict)}]" if v is not None and v.verdict else ""


def plural(n: int, word: str, many: str | None = None) -> str:
    """'1 arc', '3 arcs', '0 arcs' (`many` for irregular plurals)."""
    return f"{n} {word if n == 1 else (many or word + 's')}"


def pair_label(snap: Snapshot, k: int) -> str:
    """'scan2 → scan1' for pair k (`SnapshotPair.label`)."""
    return snap.pair(k).label


def not_ready_text(snap: Snapshot, name: str) -> str:
    """What the panel says when a stage has nothing to show."""
    status = snap.status(name)
    if status == "running":
        return f"*{label(name)} is running…*"
    if len(snap.scans) < 2:
        return "*Registration needs at least two scans: upload another scan (Scans tab).*"
    for s, why in snap.crashed.items():
        return f"**{label(s)} failed:** {md(why)}\n\nLater stages are stale until it succeeds."
    for s, out in snap.outputs.items():
        if not out.ok:
            return f"**{label(s)} failed:** {md(out.message)}\n\nLater stages are stale until it succeeds."
    return f"*{label(name)} has not run for the current scans and parameters: press **Run**.*"


def item_message(item: Any) -> str:
    """A failed item's message, as a line for the panel (empty when ok)."""
    if getattr(item, "ok", True):
        return ""
    return f"**Failed:** {md(getattr(item, 'message', ''))}"


def target_pose(snap: Snapshot, pose: str | None, k: int) -> np.ndarray | None:
    """Pair `k`'s transform for a view's `pose` ("coarse", "hypothesis", "fine", "icp", "final"),
    falling back to the best earlier one that succeeded; None before registration or when none did.
    "final" is the joint placement of the pair's target (the graph stage) when the pair is with the
    reference (a placement maps onto the reference, not onto another target)."""
    pair = snap.pair(k)
    if pose == "final" and pair.ref == 0:
        placed = pair.scan_items("graph", Placement)[1]
        if placed is not None and placed.T_ref_scan is not None:
            return np.asarray(placed.T_ref_scan, dtype=np.float64)
    order = {"coarse": ("coarse",), "hypothesis": ("hypotheses", "coarse"), "fine": ("fine", "hypotheses", "coarse"),
             "icp": ("icp", "fine", "coarse"), "final": ("fine", "hypotheses", "coarse")}.get(pose or "", ())
    for name in order:
        item = pair.item(name, POSED_BY[name])
        if item is not None and item.ok and getattr(item, "ran", True):
            return np.asarray(item.T_ref_target, dtype=np.float64)
    return None


#: From the lowest evaluated "branch" up, the thickest at each height is the stem's while it is at
#: least this share of the stem's radius below it (the stem tapers; a crown branch is a fraction of it).
STEM_TAPER = 0.5


def branch_names(branches: Iterable[Any]) -> dict[int, str]:
    """What the app calls each evaluated branch (`evaluate.branches.BranchError`, by its `index`).

    The evaluation takes every plausible upright cylinder of the reference's slices for a branch, so
    the stem's sections are among them: from the lowest up, the thickest at each height is the stem's
    while it keeps at least `STEM_TAPER` of the stem's radius below it ("stem at 1.31 m"); the others
    are branches, numbered bottom to top ("branch 1"). Give every evaluation's branches of a pair at
    once (a branch one registration lost still has its name)."""
    by_index = {int(b.index): b for b in branches}
    heights: dict[float, list[Any]] = {}
    for b in by_index.values():
        heights.setdefault(round(float(b.height_m), 2), []).append(b)
    stem: set[int] = set()
    below: float | None = None
    for h in sorted(heights):
        thickest = max(heights[h], key=lambda b: float(b.radius_m))
        if below is None or float(thickest.radius_m) >= STEM_TAPER * below:
            stem.add(int(thickest.index))
            below = float(thickest.radius_m)
    names: dict[int, str] = {}
    n = 0
    for i in sorted(by_index, key=lambda i: (float(by_index[i].height_m), i)):
        if i in stem:
            names[i] = f"stem at {float(by_index[i].height_m):.2f} m"
        else:
            n += 1
            names[i] = f"branch {n}"
    return names


def evaluated_branch_names(snap: Snapshot, target: int) -> dict[int, str]:
    """The names of the branches the Result stage evaluated for a target ("stem at 1.31 m", "branch 2":
    `branch_names` over every registration's evaluation of the pair)."""
    from treereg_core.evaluate.report import PairReport

    report = snap.pair(target).item("evaluation", PairReport) if 0 <= target < snap.n_pairs else None
    if report is None or not report.ok:
        return {}
    return branch_names(b for ev in report.by_method().values() for b in ev.branches)
