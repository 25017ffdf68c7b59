"""One row per scan at the end of a registration: its verdict and the checks a user weighs it by,
each beside its threshold (issue 32, item 8). The command line prints it as a table; the per-pair
tables of every stage's numbers are behind `--details`.

Built from the stage outputs alone (like `report`), so it says the same as transforms.json."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping, Sequence

import numpy as np

from ..scan import Scan
from ..stage import Pair, StageOutput
from .evidence import Check, PairVerification, quantity_text
from .graph import Placement

#: The checks of a scan's pair with the reference shown in its row, by `Check.what`, and their headings.
COLUMNS = (("free-space consistency", "consistency"), ("surface residual", "residual"),
           ("ambiguity margin", "margin"))
#: The graph stage's metric of a placement's worst edge in the joint solve.
_LOOP = "largest edge residual in the joint solve"


@dataclass(frozen=True, kw_only=True)
class ScanSummary:
    """A scan's row: `verdict` ("reference" for the reference), its pair with the reference's checks
    in `COLUMNS` order (None: not measured, e.g. the pair failed before verification), the largest
    residual of its edges in the joint placement (None: not placed jointly) and the scans it was
    placed through."""

    name: str
    verdict: str
    checks: tuple[Check | None, ...]
    loop_m: float | None
    via: tuple[str, ...]


def scan_summaries(scans: Sequence[Scan], pairs: Sequence[Pair], outputs: Mapping[str, StageOutput]) -> list[ScanSummary]:
    """Every scan's row, the reference first."""
    graph, verify = outputs.get("graph"), outputs.get("verify")
    rows = [ScanSummary(name=scans[0].name, verdict="reference", checks=(None,) * len(COLUMNS), loop_m=None, via=())]
    for i in range(1, len(scans)):
        k = next((k for k, p in enumerate(pairs) if (p.ref, p.tgt) == (0, i)), None)
        pv = verify.items[k] if verify is not None and k is not None and k < len(verify.items) else None
        found = {c.what: c for c in pv.checks} if isinstance(pv, PairVerification) else {}
        pl = graph.items[i] if graph is not None and i < len(graph.items) else None
        placement = pl if isinstance(pl, Placement) else None
        loop = next((float(m.value) for m in placement.metrics if m.description == _LOOP), None) if placement else None
        verdict = placement.verdict if placement is not None else (pv.verdict if isinstance(pv, PairVerification)
                                                                   else "unverified")
        rows.append(ScanSummary(
            name=scans[i].name, verdict=verdict, checks=tuple(found.get(what) for what, _ in COLUMNS),
            loop_m=loop if loop is not None and np.isfinite(loop) else None,
            via=tuple(scans[v].name for v in placement.via) if placement is not None else ()))
    return rows


def cell(check: Check | None) -> str:
    """"0.9996 ✓ ≥ 0.95", "1.6 mm ✓ ≤ 5.6 mm", "0.010 ✗ ≥ 0.03", "0.9996 (not judged)", "not measured"."""
    if check is None:
        return "not measured"
    if check.passed is None:
        return f"{check.value_text()} (not judged)"
    return f"{check.value_text()} {'✓' if check.passed else '✗'} {check.limit_text()}"


def summary_table(rows: Sequence[ScanSummary]) -> list[str]:
    """The rows as aligned text lines, a header first (no "nan": unmeasured values say so)."""
    head = ["scan", "verdict", *(h for _, h in COLUMNS), "loop residual", "placed through"]
    body = [[r.name, r.verdict, *(cell(c) if r.verdict != "reference" else "" for c in r.checks),
             quantity_text(r.loop_m, "m") if r.loop_m is not None else ("" if r.verdict == "reference" else "not placed jointly"),
             ", ".join(r.via)] for r in rows]
    widths = [max(len(x[j]) for x in [head, *body]) for j in range(len(head))]
    return ["  ".join(x[j].ljust(widths[j]) for j in range(len(head))).rstrip() for x in [head, *body]]
