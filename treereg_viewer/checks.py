"""Warnings the app reads off finished results: a registration can finish and still be wrong.

When a truth.json is known, a final transform far from it is flagged. (Implausible coarse
transforms are rejected by the core itself: `coarse.estimate_coarse`.) These checks only read
results; they compute no geometry. The app marks the stage with ⚠ and says why.
"""

from __future__ import annotations

from .controller import Snapshot

#: Errors against truth beyond these mean the registration failed (the fine stage aims at
#: well under 0.5 deg and 3 cm).
TRUTH_ROT_DEG = 1.0
TRUTH_DISP_M = 0.05


def _pair(snap: Snapshot, k: int) -> str:
    return f"{snap.scans[k + 1].name} → {snap.scans[0].name}" if k + 1 < len(snap.scans) else f"target {k + 1}"


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
            who = snap.scans[k + 1].name if names_only else _pair(snap, k)
            rows.append((who, label, rot, disp, rot <= TRUTH_ROT_DEG and disp <= TRUTH_DISP_M))
    return rows


def truth_warnings(snap: Snapshot) -> list[str]:
    """One sentence per target whose final (fine) transform is far from the known truth."""
    return [
        f"{pair}: the final transform is {rot:.3g}° and {disp:.3g} m from the truth — the registration failed."
        for pair, label, rot, disp, good in truth_rows(snap) if label == "fine" and not good
    ]


def stage_warnings(snap: Snapshot) -> dict[str, list[str]]:
    """Warnings by pipeline stage ("evaluation"), for the pairs that have results."""
    found = {}
    if snap.output("evaluation") is not None and (w := truth_warnings(snap)):
        found["evaluation"] = w
    return found
