"""What a registration says about its own trustworthiness, as plain data: the "quality" of
transforms.json, the verdict per scan, and the lines a user reads when a scan is not verified.
Built from the stage outputs alone, so the command line and the app (from a snapshot) agree."""

from __future__ import annotations

from typing import Any, Mapping, Sequence

import numpy as np

from ..params import Params, loosened, loosened_text
from ..scan import Scan
from ..stage import Pair, StageOutput
from .evidence import FAILED, UNVERIFIED, VERIFIED, Check


def json_number(v: Any) -> Any:
    """A value JSON can hold: NaN and infinities as None, numpy numbers as Python ones."""
    if isinstance(v, (float, np.floating)):
        return float(v) if np.isfinite(v) else None
    if isinstance(v, np.integer):
        return int(v)
    return v


def quality_report(scans: Sequence[Scan], pairs: Sequence[Pair], outputs: Mapping[str, StageOutput]) -> dict[str, Any]:
    """{"scans": {name: verdict, reasons, hint, placed through, started_from}, "edges": [per pair: its
    numbers]}. "started_from" names where the start pose the user gave came from (`register --initial`)
    for a scan whose pair with the reference started from it instead of the coarse stage's estimate."""
    graph, verify, coarse = outputs.get("graph"), outputs.get("verify"), outputs.get("coarse")
    started = {scans[p.tgt].name: getattr(coarse.items[k], "started_from", "") for k, p in enumerate(pairs)
               if coarse is not None and k < len(coarse.items) and p.ref == 0}
    per_scan: dict[str, Any] = {}
    for i, s in enumerate(scans):
        pl = graph.items[i] if graph is not None else None
        if pl is None:
            per_scan[s.name] = {"verdict": UNVERIFIED if i else VERIFIED,
                                "reasons": ["the registration stopped before verification"] if i else []}
            if started.get(s.name):
                per_scan[s.name]["started_from"] = started[s.name]
            continue
        entry = {"verdict": pl.verdict, "reasons": list(pl.reasons), "hint": pl.hint,
                 "placed_through": [scans[v].name for v in pl.via]}
        entry.update({m.description: json_number(m.value) for m in pl.metrics
                      if m.description not in ("verdict", "placed through scans")})
        motion = crown_motion(scans, pairs, outputs, i)
        if motion is not None:
            entry["crown_motion"] = motion
        if started.get(s.name):
            entry["started_from"] = started[s.name]
        per_scan[s.name] = entry
    edges = []
    graph_edges = graph.items[0].edges if graph is not None and graph.items else ()
    for k, p in enumerate(pairs):
        row: dict[str, Any] = {"pair": f"{scans[p.tgt].name} -> {scans[p.ref].name}"}
        it = verify.items[k] if verify is not None and k < len(verify.items) else None
        if it is not None and hasattr(it, "evidence"):
            row["verdict"] = it.verdict
            row.update({key: json_number(v) for key, v in it.evidence.as_dict().items()})
            row["reasons"] = list(it.reasons)
            row["checks"] = [check_row(c) for c in getattr(it, "checks", ())]
        else:
            row["verdict"] = FAILED
            row["reasons"] = [getattr(it, "message", "") or "not verified"] if it is not None else ["not verified"]
        for e in graph_edges:
            if (e.i, e.j) == (p.ref, p.tgt):
                row["loop_error_m"] = json_number(e.loop_error_m)
                row["used_in_placement"] = e.used
        edges.append(row)
    return {"scans": per_scan, "edges": edges}


def check_row(c: Check) -> dict[str, Any]:
    """One check of a pair as transforms.json holds it: what, value, unit, relation, limit, the
    parameter that sets it, and passed (null: not judged)."""
    return {"what": c.what, "value": json_number(c.value), "unit": c.unit, "relation": c.relation, "limit": json_number(c.limit),
            "parameter": c.parameter, "passed": c.passed}


def _motion_pair(pairs: Sequence[Pair], outputs: Mapping[str, StageOutput], i: int) -> int | None:
    """The pair that tells scan i's crown motion: its pair with the reference, else its first."""
    verify = outputs.get("verify")
    if verify is None:
        return None
    ks = [k for k, p in enumerate(pairs) if p.tgt == i and hasattr(verify.items[k], "evidence")]
    ks.sort(key=lambda k: pairs[k].ref != 0)
    return ks[0] if ks else None


def crown_motion(scans: Sequence[Scan], pairs: Sequence[Pair], outputs: Mapping[str, StageOutput],
                 i: int) -> dict[str, Any] | None:
    """How far scan i's crown had moved from where its pair's reference saw it (wind between the
    stations), when it moved measurably: top sway (m), its direction (deg, that scan's frame), its
    noise, the height above the stem's base up to which the two stems agree, how far the small
    branches moved beyond the stem's bend (what the free-space consistency would need granted), what
    the motion model granted them at the top (the branches' flutter the bend explains), the
    consistency with no motion granted, and whether the tree holds a crown (False: the bend was fitted
    to a bare stem); None otherwise."""
    k = _motion_pair(pairs, outputs, i)
    if k is None:
        return None
    e = outputs["verify"].items[k].evidence
    if not e.sway_m > 0:
        return None
    return {"relative_to": scans[pairs[k].ref].name, "top_sway_m": json_number(e.sway_m),
            "direction_deg": json_number(e.sway_direction_deg), "sway_std_m": json_number(e.sway_std_m),
            "stems_agree_up_to_m": json_number(e.stable_height_m), "branches_moved_m": json_number(e.motion_needed_m),
            "branches_allowed_m": json_number(e.motion_m), "consistency_no_motion": json_number(e.consistency_still),
            "crown": bool(e.crown)}


def motion_lines(scans: Sequence[Scan], pairs: Sequence[Pair], outputs: Mapping[str, StageOutput]) -> list[str]:
    """One line per scan whose crown moved measurably between its station and its pair's reference (on
    a stem without crown: how far its top stands off, not called a crown's motion)."""
    out = []
    for i, s in enumerate(scans):
        m = crown_motion(scans, pairs, outputs, i) if i else None
        if m is None:
            continue
        stable = m["stems_agree_up_to_m"]
        if not m["crown"]:
            out.append(f"{s.name}: the stem top stands {m['top_sway_m']:.2f} m off {m['relative_to']}'s (towards "
                       f"{m['direction_deg']:.0f}° in {m['relative_to']}'s frame): a bend fitted to a stem without crown, which cannot tell "
                       "wind from a pose that is off")
            continue
        out.append(f"{s.name}: the crown moved {m['top_sway_m']:.2f} m (stem top, towards {m['direction_deg']:.0f}° in "
                   f"{m['relative_to']}'s frame) between the stations of {m['relative_to']} and {s.name}"
                   + (f"; the stems agree up to {stable:.1f} m above the base" if stable is not None else "")
                   + "; the pose rests on what did not move")
    return out


def verdict_text(verdict: str, params: Params, reference: bool = False) -> str:
    """A scan's verdict as it is shown: "verified under loosened thresholds (verify.min_margin 0.01 <
    default 0.03)" when it was verified with a threshold looser than its default (the reference
    is verified by definition)."""
    note = loosened_text(loosened(params)) if verdict == VERIFIED and not reference else ""
    return note or verdict


def verdict_lines(verdicts: Mapping[str, tuple[str, tuple[str, ...], str]]) -> list[str]:
    """One line per scan that is not verified: its verdict, why, and what to try."""
    out = []
    for name, (verdict, reasons, hint) in verdicts.items():
        if verdict == VERIFIED:
            continue
        why = "; ".join(reasons) or "no reason recorded"
        out.append(f"{name}: {verdict}: {why}" + (f" (try: {hint})" if hint else ""))
    return out
