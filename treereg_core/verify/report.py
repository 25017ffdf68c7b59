"""What a registration says about its own trustworthiness, as plain data: the "quality" of
transforms.json, the verdict per scan, and the lines a user reads when a scan is not verified.
Built from the stage outputs alone, so the command line and the app (from a snapshot) agree."""

from __future__ import annotations

from typing import Any, Mapping, Sequence

import numpy as np

from ..scan import Scan
from ..stage import Pair, StageOutput
from .evidence import FAILED, UNVERIFIED, VERIFIED


def _num(v: Any) -> Any:
    if isinstance(v, (float, np.floating)):
        return float(v) if np.isfinite(v) else None
    if isinstance(v, np.integer):
        return int(v)
    return v


def quality_report(scans: Sequence[Scan], pairs: Sequence[Pair], outputs: Mapping[str, StageOutput]) -> dict[str, Any]:
    """{"scans": {name: verdict, reasons, hint, placed through}, "edges": [per pair: its numbers]}."""
    graph, verify = outputs.get("graph"), outputs.get("verify")
    per_scan: dict[str, Any] = {}
    for i, s in enumerate(scans):
        pl = graph.items[i] if graph is not None else None
        if pl is None:
            per_scan[s.name] = {"verdict": UNVERIFIED if i else VERIFIED,
                                "reasons": ["the registration stopped before verification"] if i else []}
            continue
        entry = {"verdict": pl.verdict, "reasons": list(pl.reasons), "hint": pl.hint,
                 "placed_through": [scans[v].name for v in pl.via]}
        entry.update({m.description: _num(m.value) for m in pl.metrics
                      if m.description not in ("verdict", "placed through scans")})
        per_scan[s.name] = entry
    edges = []
    graph_edges = graph.items[0].edges if graph is not None and graph.items else ()
    for k, p in enumerate(pairs):
        row: dict[str, Any] = {"pair": f"{scans[p.tgt].name} -> {scans[p.ref].name}"}
        it = verify.items[k] if verify is not None and k < len(verify.items) else None
        if it is not None and hasattr(it, "evidence"):
            row["verdict"] = it.verdict
            row.update({key: _num(v) for key, v in it.evidence.as_dict().items()})
            row["reasons"] = list(it.reasons)
        else:
            row["verdict"] = FAILED
            row["reasons"] = [getattr(it, "message", "") or "not verified"] if it is not None else ["not verified"]
        for e in graph_edges:
            if (e.i, e.j) == (p.ref, p.tgt):
                row["loop_error_m"] = _num(e.loop_error_m)
                row["used_in_placement"] = e.used
        edges.append(row)
    return {"scans": per_scan, "edges": edges}


def verdict_lines(verdicts: Mapping[str, tuple[str, tuple[str, ...], str]]) -> list[str]:
    """One line per scan that is not verified: its verdict, why, and what to try."""
    out = []
    for name, (verdict, reasons, hint) in verdicts.items():
        if verdict == VERIFIED:
            continue
        why = "; ".join(reasons) or "no reason recorded"
        out.append(f"{name}: {verdict}: {why}" + (f" (try: {hint})" if hint else ""))
    return out
