"""The Verify stage: PairVerification — each pair's evidence and verdict, with what to try when it fails.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import viser

from treereg_core.params import loosened, loosened_text
from treereg_core.verify.evidence import PairVerification

from ..controller import Snapshot
from ..draw.common import Drawing, breakable, md_table, metrics_table, pair_label, target_index, title
from ..labels import verdict_badge
from ..text import md, md_sentence
from ..view_panel import PanelContent
from ..view_state import ViewState
from .base import AppStage, StageView, TargetControl, TourStep


#: A check's mark: passed, failed, not judged (not measured, or not applicable).
CHECK_MARK = {True: "✓", False: "✗", None: "–"}


def checks_table(checks: Any) -> str:
    """Every check of the verdict beside its threshold: ✓/✗, what is checked (and the parameter that
    sets the threshold), the measured value, the threshold."""
    rows = []
    for c in checks:
        what = f"{md(c.what)}<br><small>{breakable(md(c.parameter))}</small>" if c.parameter else md(c.what)
        rows.append((CHECK_MARK.get(c.passed, "–"), what, md(c.value_text()), md(c.limit_text() or "–")))
    return md_table(("", "check (set by)", "measured", "threshold"), rows)


def render_verify(scene: viser.SceneApi, root: str, snap: Snapshot, view: ViewState) -> Drawing:
    t = target_index(snap, "verify", view)
    v = snap.pair(t).item("verify", PairVerification)
    assert v is not None, t  # the drawer draws a pair that was not skipped
    text = f"{md(pair_label(snap, t))}: **{verdict_badge(v.verdict)}**.{loosened_note(snap, v.verdict)}"
    e = getattr(v, "evidence", None)
    if e is not None and e.sway_m > 0:
        stable = f"; the stems agree up to {e.stable_height_m:.1f} m above the base" if np.isfinite(e.stable_height_m) else ""
        sway = (f" The crown moved {e.sway_m:.2f} m between the stations (the stem top){stable}." if e.crown else
                f" The stem top stands {e.sway_m:.2f} m off the reference's{stable}, fitted as a bend: the scans hold "
                "no crown, and a bare stem cannot tell wind from a pose that is off.")
        still = (f" Free-space consistency {e.consistency_still:.3f} with no motion granted, {e.consistency:.3f} with it."
                 if np.isfinite(e.consistency_still) and np.isfinite(e.consistency) else "")
        text += (sway + " The evidence is measured with the target unbent by that bend; "
                 f"{e.moved:,} of its points the reference saw through lie within the motion the stems' bend explains "
                 f"(up to {e.motion_m * 100:.0f} cm at the top, less lower down) of a surface the reference saw and count "
                 "as moved (small branches in the wind), not against the pose; a pose that fails its own checks is "
                 "refused for itself." + still)
    if v.reasons:
        text += "\n\n" + "\n\n".join(f"- {md_sentence(r)}" for r in v.reasons)
        if v.hint:
            text += f"\n\nTry: {md(v.hint)}."
    checks = tuple(getattr(v, "checks", ()))
    if checks:
        text += ("\n\nEach check's measured value against its threshold (✓ passed, ✗ failed, – not judged); the "
                 "parameter under each check sets its threshold.")
        table = checks_table(checks)
    else:  # a pair that never reached verification: its message says why
        table = metrics_table({pair_label(snap, t): v.metrics})
    return [], PanelContent(title("verify", snap, t), text=text, table=table)


def loosened_note(snap: Snapshot, verdict: str) -> str:
    """" ⚠ Verified under loosened thresholds (…)." when a verified verdict rests on a threshold set looser
    than its default; the same words as transforms.json and the command line."""
    text = loosened_text(loosened(snap.params)) if verdict == "verified" else ""
    return f" ⚠ {md_sentence(text)}" if text else ""


STAGE = AppStage(
    "verify",
    StageView(
        "fine",
        explanation="A registration must show its evidence before it is trusted: enough coarse tie points agree "
            "compared with what chance gives on the same ties; the target's points lie where the reference scanner "
            "saw a surface, not in space it saw through (where both stations could see); the surfaces fit within "
            "their own noise; no other heading explains the scans almost as well; the scanner stays level and at "
            "its height above the ground. A pair failing any of these is unverified, with the reason.",
    ),
    draw=render_verify,
    view_fields=("target",),
    controls=(TargetControl,),
    tour=(
        TourStep(
            "verify", "Evidence before trust",
            "A registration is trusted only with its evidence. Enough tie points must agree compared with chance, the "
            "target's points lie where the reference saw a surface and not where it saw through, the surfaces fit "
            "within their noise, no rival heading is nearly as good, the scanner stays level.",
            "Read each check's measured value against its threshold (✓ passed, ✗ failed); a failed check says what "
            "to try.",
            view={"panel": "stage"}),
    ),
)
