"""Warnings the app reads off finished results: a registration can finish and still be wrong.

When a truth.json is known, a final transform far from it is flagged. (Implausible coarse
transforms are rejected by the core itself: `coarse.estimate_coarse`.) These checks only read
results; they compute no geometry. The app marks the stage with ⚠ and says why.
"""

from __future__ import annotations

from .controller import Snapshot
from .labels import verdict_badge
from .text import md

#: Errors against truth beyond these mean the registration failed (the fine stage aims at
#: well under 0.5 deg and 3 cm).
TRUTH_ROT_DEG = 1.0
TRUTH_DISP_M = 0.05


def truth_rows(snap: Snapshot, names_only: bool = False) -> list[tuple[str, str, float, float, bool]]:
    """(pair, registration, rotation error deg, mean displacement m, within tolerance) per known truth.

    With `names_only` the first column is the target's name alone (a narrow table column).
    """
    out = snap.output("evaluation")
    if out is None or not snap.truth:
        return []
    rows = []
    for k, rep in enumerate(out.items):
        if not rep.ok:  # skipped: no transform to judge
            continue
        for label, ev in rep.by_method().items():
            if ev.rotation_error_deg is None or ev.mean_displacement_m is None:
                continue
            rot, disp = float(ev.rotation_error_deg), float(ev.mean_displacement_m)
            p = snap.pair(k)
            who = p.tgt_scan.name if names_only and p.ref == 0 else p.label
            rows.append((who, label, rot, disp, rot <= TRUTH_ROT_DEG and disp <= TRUTH_DISP_M))
    graph = snap.output("graph")
    for i, pl in enumerate(graph.items if graph is not None else ()):
        m = {x.description: x.value for x in pl.metrics}
        if i == 0 or "rotation error against truth" not in m:
            continue
        rot, disp = float(m["rotation error against truth"]), float(m["mean displacement against truth"])
        who = snap.scans[i].name if names_only else f"{snap.scans[i].name} → {snap.scans[0].name}"
        rows.append((who, "placed (joint)", rot, disp, rot <= TRUTH_ROT_DEG and disp <= TRUTH_DISP_M))
    return rows


def truth_warnings(snap: Snapshot) -> list[str]:
    """One sentence per scan whose final transform (its joint placement, else its pair's fine one) is
    far from the known truth."""
    rows = truth_rows(snap)
    final = "placed (joint)" if any(label == "placed (joint)" for _, label, *_ in rows) else "fine"
    return [
        f"{pair}: the final transform is {rot:.3g}° and {disp:.3g} m from the truth — the registration failed."
        for pair, label, rot, disp, good in rows if label == final and not good
    ]


def verdict_warnings(snap: Snapshot) -> list[str]:
    """One sentence per scan that is not verified: its verdict and the reasons (no truth needed)."""
    graph = snap.output("graph")
    if graph is None:
        return []
    return [f"{verdict_badge(pl.verdict)}: {snap.scans[i].name}: {'; '.join(pl.reasons)}"
            + (f" (try: {pl.hint})" if pl.hint else "")
            for i, pl in enumerate(graph.items) if pl.verdict != "verified"]


def stage_warnings(snap: Snapshot) -> dict[str, list[str]]:
    """Warnings by pipeline stage ("evaluation"), for the pairs that have results, each line with its
    mark: ✗ a registration far from the truth; a verdict's own (⚠ unverified, ✗ failed). Markdown,
    the names and reasons in it escaped."""
    found = {}
    if snap.output("evaluation") is not None and (w := truth_warnings(snap)):
        found["evaluation"] = [f"**✗** {md(line)}" for line in w]
    if w := verdict_warnings(snap):
        found["graph"] = [md(line) for line in w]
    return found
