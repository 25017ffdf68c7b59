"""The Fine stage: FineResult — the sections at the final pose, where both scans' should coincide; whether
the update was kept, and the stem's bend (wind) as a plot.
"""

from __future__ import annotations

from typing import Any

import viser

from ..controller import Snapshot
from ..draw.common import Drawing, metrics_table, pair_label, pair_scans, plural, target_index, title
from ..draw.fits import draw_sections, fine_scans
from ..draw.motion import motion_sentence, profile_figure
from ..view_panel import PanelContent
from ..view_state import ViewState
from .base import AppStage, StageView, TargetControl, TourStep
from .sections import FitControls


def fine_status(snap: Snapshot, t: int, f: Any) -> str:
    """One sentence: was the fine update kept, after how many iterations, and why not."""
    n = f.iterations
    if f.accepted:
        text = (f"{pair_label(snap, t)}: the fine update was **kept** after {plural(n, 'iteration')}." if n else
                f"{pair_label(snap, t)}: the fine update was **kept**.")
    else:
        text = f"{pair_label(snap, t)}: the coarse transform **stands** ({plural(n, 'fine iteration')} tried)."
    if f.message:
        text += f" {f.message[0].upper()}{f.message[1:]}."
    fp = snap.params.fine
    if f.stopped_at_limit:
        # Not converged: said, so that a capped run is not read as a settled one.
        limit = f.iteration_limit
        more = f" + {limit - fp.max_iterations} with the stem's bend" if limit > fp.max_iterations else ""
        text += (f" It stopped at the iteration limit (fine.max_iterations = {fp.max_iterations}{more}) with the last "
                 f"update still {f.updates_m[-1] * 1000:.1f} mm (fine.tolerance_m = {fp.tolerance_m * 1000:g} mm).")
    return text


def render_fine(scene: viser.SceneApi, root: str, snap: Snapshot, view: ViewState) -> Drawing:
    t = target_index(snap, "fine", view)
    f = snap.output("fine").items[t]
    text = fine_status(snap, t, f)
    handles: list[Any] = []
    table = ""
    if f.slices is not None and f.sections is not None:
        ref, tgt = fine_scans(snap, t)
        handles, table, _ = draw_sections(scene, root, snap, t, f.slices, f.sections, ref, tgt, view)
        n = f.sections.n_pairs
        text += (f" Shown: the sections at the final pose ({plural(n, 'corresponding pair')}); partners should now "
                 "coincide. The *Cross-section* view (left panel, top) shows the scans' stem arcs at the coarse "
                 "and the fine pose side by side.")
    table = metrics_table({pair_label(snap, t): f.metrics}) + ("\n\n" + table if table else "")
    i, j = pair_scans(snap, t)
    tol = snap.params.wind.stable_tolerance_m
    motion = motion_sentence(f, snap.scans[i].name, snap.scans[j].name, tol)
    if motion:
        text += "\n\n" + motion
    fig = profile_figure(f, snap.scans[i].name, snap.scans[j].name, j, tol)
    plots = ((fig, 1.2),) if fig is not None else ()
    return handles, PanelContent(title("fine", snap, t), text=text, plots=plots, table=table)


STAGE = AppStage(
    "fine",
    StageView(
        "fine",
        scans="hidden",
        explanation="An SVD over the tie points gives the paper's fine transform; treereg's default (fine.method = "
            "joint) instead fits each pair of corresponding sections as one cylinder together with the pose, "
            "re-slices at the new pose and repeats. Directions the sections fix only weakly come from the "
            "scans' surfaces, and the update is kept only when it measurably improves the alignment. "
            "Shown: the sections at the final pose.",
    ),
    draw=render_fine,
    view_fields=("target", "point_size", "show_rejected", "focus_section"),
    controls=(TargetControl, FitControls),
    tour=(
        TourStep(
            "fine", "From separate arcs to one ring",
            "The corresponding sections give the fine transform; treereg fits each pair as one cylinder together with "
            "the pose and keeps the update only when the surfaces agree better. In the cross-section the separate arcs "
            "of the coarse pose close into one ring (paper Figs. 11 and 19).",
            "Compare the coarse and the fine panel side by side, then choose *All three* under *Registration*.",
            view={"panel": "section", "section_poses": "Coarse and fine", "branch": None, "section_height": None},
            camera="trunk", highlight="trunk"),
        TourStep(
            "fine", "Wind: what moved and what did not",
            "Stations are scanned minutes apart; in wind the crown is never where it was, while the stem base and the "
            "ground stay put, and the instrument's pose is in them. treereg fits the stem's bend (a cantilever) with the "
            "pose, so the crown's motion is not taken for a tilt of the scanner; the plot shows the target's stem offset "
            "by height: at zero where the stem holds, bending off above where the crown moved.",
            "Read the plot below the text; in still air it stands at zero all the way up. In *13 Result*, colour by "
            "distance: pink points moved with the wind.",
            view={"panel": "stage"}),
    ),
)
