"""The Fine stage: FineResult — the sections at the final pose, where both scans' should coincide; whether
the update was kept, and the stem's bend (wind) as a plot.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import viser

from treereg_core.fine.pose import FineResult
from treereg_core.fine.sections import SectionsResult
from treereg_core.fine.slicing import SliceResult
from treereg_core.geometry.rigid import apply_transform, invert

from ..controller import Snapshot
from ..draw.common import Drawing, metrics_table, pair_label, plural, target_index, title
from ..draw.fits import draw_sections, fine_scans, slice_shown, tie_mask
from ..palette import OFFSET
from ..draw.motion import motion_sentence, profile_figure
from ..view_panel import PanelContent
from ..text import md, md_sentence
from ..view_state import ViewState
from .slices import SliceControl
from .base import AppStage, StageView, TargetControl, TourStep
from .sections import FitControls


def fine_status(snap: Snapshot, t: int, f: FineResult) -> str:
    """One sentence: was the fine update kept, after how many iterations, and why not."""
    n = f.iterations
    pair = md(pair_label(snap, t))
    if f.accepted:
        text = (f"{pair}: the fine update was **kept** after {plural(n, 'iteration')}." if n else
                f"{pair}: the fine update was **kept**.")
    else:
        text = f"{pair}: the coarse transform **stands** ({plural(n, 'fine iteration')} tried)."
    if f.message:
        text += f" {md_sentence(f.message)}"
    fp = snap.params.fine
    if f.stopped_at_limit:
        # Not converged: said, so that a capped run is not read as a settled one.
        limit = f.iteration_limit
        more = f" + {limit - fp.max_iterations} with the stem's bend" if limit > fp.max_iterations else ""
        text += (f" It stopped at the iteration limit (fine.max_iterations = {fp.max_iterations}{more}) with the last "
                 f"update still {f.updates_m[-1] * 1000:.1f} mm (fine.tolerance_m = {fp.tolerance_m * 1000:g} mm).")
    return text


def fine_offsets(scene: viser.SceneApi, root: str, snap: Snapshot, view: ViewState, t: int,
                 T_fine: np.ndarray) -> tuple[list[Any], str]:
    """Fine against Fits: a line from each of the target's tie points at the pose the Fits stage
    started from to where the fine pose puts it (of the slice in view), and a sentence with their
    mean length."""
    pair = snap.pair(t)
    sec, sl = pair.item("sections", SectionsResult), pair.item("slices", SliceResult)
    if sec is None or sl is None or not len(sec.tie_points_tgt):
        return [], ""
    keep = tie_mask(sec, sl, slice_shown(snap, t, view, sl.n_slices))
    start = np.asarray(sec.tie_points_tgt, dtype=float)[keep]
    if not len(start):
        return [], ""
    moved = apply_transform(np.asarray(T_fine, dtype=float) @ invert(np.asarray(sec.T_ref_target, dtype=float)), start)
    d = np.linalg.norm(moved - start, axis=1)
    k = magnification(float(np.mean(d)))
    tips = start + k * (moved - start)
    handles = [scene.add_line_segments(f"{root}/offsets", np.stack([start, tips], axis=1).astype(np.float32), OFFSET,
                                       thickness=4.0, thickness_units="screen")]
    longer = f", drawn {k:g} times longer to be seen" if k > 1 else ""
    return handles, (f" Black lines: how far the fine pose moved each of the target's tie points from where they stood "
                     f"in *8 Fits* (the starting pose){longer}: {np.mean(d) * 1000:.1f} mm on average, at most "
                     f"{np.max(d) * 1000:.1f} mm, of the {plural(len(d), 'tie point')} shown.")


#: Offsets of a few millimetres are drawn longer, so that they reach out of the fitted sections
#: (decimetres across; the tie points sit at their centres): the mean offset is drawn about this
#: long (m), by a round factor.
SHOWN_OFFSET_M = 0.3


def magnification(mean_offset_m: float) -> float:
    """1, 2, 5, ... 500: the round factor that draws the mean offset about SHOWN_OFFSET_M long."""
    want = SHOWN_OFFSET_M / max(mean_offset_m, 1e-6)
    return float(max([1.0] + [f for f in (2.0, 5.0, 10.0, 20.0, 50.0, 100.0, 200.0, 500.0) if f <= want]))


def render_fine(scene: viser.SceneApi, root: str, snap: Snapshot, view: ViewState) -> Drawing:
    t = target_index(snap, "fine", view)
    pair = snap.pair(t)
    f = pair.item("fine", FineResult)
    assert f is not None, pair.label  # the drawer draws a pair that was not skipped
    text = fine_status(snap, t, f)
    handles: list[Any] = []
    table = ""
    if f.slices is not None and f.sections is not None:
        ref, tgt = fine_scans(snap, t)
        handles, table, _ = draw_sections(scene, root, snap, t, f.slices, f.sections, ref, tgt, view)
        n = f.sections.n_pairs
        lines, moved = fine_offsets(scene, root, snap, view, t, f.T_ref_target)
        handles += lines
        text += (f" Shown: the sections at the final pose ({plural(n, 'corresponding pair')}); partners should now "
                 f"coincide.{moved} The *Cross-section* view (left panel, top) shows the scans' stem arcs at the "
                 "coarse and the fine pose side by side.")
    table = metrics_table({pair_label(snap, t): f.metrics}) + ("\n\n" + table if table else "")
    tol = snap.params.wind.stable_tolerance_m
    motion = motion_sentence(f, pair.ref_scan.name, pair.tgt_scan.name, tol)
    if motion:
        text += "\n\n" + motion
    fig = profile_figure(f, pair.ref_scan.name, pair.tgt_scan.name, pair.tgt, tol)
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
    view_fields=("target", "point_size", "show_rejected", "focus_section", "slice_shown"),
    controls=(TargetControl, SliceControl, FitControls),
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
