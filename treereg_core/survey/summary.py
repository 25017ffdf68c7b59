"""What a registered survey says: one row per station (its verdict, the stations it was placed through,
its largest pair residual in the joint placement, the stems it shares), the "quality" block of
transforms.json and the lines a user reads in the terminal. Built from the `Survey` alone."""

from __future__ import annotations

from typing import Any

import numpy as np

from ..verify.evidence import quantity_text
from ..verify.report import json_number
from .register import Survey

_LOOP = "largest edge residual in the joint solve"


def station_rows(survey: Survey) -> list[list[str]]:
    """Per station: name, verdict, pairs verified / registered, largest residual, placed through, stems."""
    rows = []
    for k, (scan, pl, st) in enumerate(zip(survey.scans, survey.placements, survey.stations)):
        mine = [p for p in survey.pairs if k in (p.i, p.j)]
        verified = sum(p.verdict == "verified" for p in mine)
        loop = next((float(m.value) for m in pl.metrics if m.description == _LOOP), None)
        residual = quantity_text(loop, "m") if loop is not None and np.isfinite(loop) else ("" if k == 0 else "not placed jointly")
        rows.append([scan.name, "reference" if k == 0 else pl.verdict, f"{verified} of {len(mine)}", residual,
                     ", ".join(survey.scans[v].name for v in pl.via), str(len(st.stems))])
    return rows


def survey_table(survey: Survey) -> list[str]:
    """The station rows as aligned text lines, a header first."""
    head = ["station", "verdict", "pairs verified", "loop residual", "placed through", "stems"]
    body = station_rows(survey)
    widths = [max(len(x[j]) for x in [head, *body]) for j in range(len(head))]
    return ["  ".join(x[j].ljust(widths[j]) for j in range(len(head))).rstrip() for x in [head, *body]]


def survey_quality(survey: Survey) -> dict[str, Any]:
    """transforms.json's "quality": per station its verdict, reasons, hint, stations placed through and
    stems; per pair its verdict, reasons and numbers; the survey's counts."""
    scans: dict[str, Any] = {}
    for k, (scan, pl, st) in enumerate(zip(survey.scans, survey.placements, survey.stations)):
        scans[scan.name] = {"verdict": pl.verdict, "reasons": list(pl.reasons), "hint": pl.hint,
                            "placed_through": [survey.scans[v].name for v in pl.via], "stems": len(st.stems)}
        scans[scan.name].update({m.description: json_number(m.value) for m in pl.metrics
                                 if m.description not in ("verdict", "placed through scans")})
    edges = []
    loop = survey.placed_edges()
    for p in survey.pairs:
        e = loop.get((p.i, p.j))
        tgt, ref = survey.pair_names(p)
        edges.append({"reference": ref, "target": tgt, "verdict": p.verdict,
                      "reasons": list(p.reasons), "shared_stems": p.shared_stems, "stems_used": p.fit.stems_used,
                      "stem_residual_m": json_number(p.fit.residual_m), "ground_residual_m": json_number(p.fit.ground_residual_m),
                      "crowns_agree": json_number(p.fit.agreement), "used": bool(e.used) if e is not None else False,
                      "loop_residual_m": json_number(e.loop_error_m) if e is not None else None})
    return {"mode": "survey", "scans": scans, "edges": edges}

