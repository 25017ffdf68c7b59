"""The Arcs stage: SliceArcs — each slice's arcs (connected components in the scan's angular grid), one
colour per arc, the target at the pose the fine stage starts from.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import viser

from treereg_core.fine.arcs import SliceArcs
from treereg_core.fine.slicing import SliceResult
from treereg_core.geometry.rigid import apply_transform

from ..controller import Snapshot
from ..draw.common import Drawing, md_table, metrics_table, pair_label, target_index, target_pose, title
from ..draw.fits import fine_scans, slice_label, slice_point_size, slice_shown
from ..palette import categorical
from ..view_panel import PanelContent
from ..text import md
from ..view_state import ViewState
from .base import AppStage, StageView, TargetControl, TourStep
from .slices import SliceControl


def _arc_points(scene: viser.SceneApi, root: str, ar: SliceArcs, T: np.ndarray | None, ref: Any, tgt: Any,
                size: float, only: int | None) -> tuple[list[Any], list[tuple[str, str]]]:
    """Both scans' arcs coloured one per arc (of slice `only`, or every slice); per slice the arc counts."""
    handles: list[Any] = []
    counts: list[tuple[str, str]] = []
    for k in range(max(len(ar.ref), len(ar.tgt))):
        drawn = only in (None, k)
        row = []
        for who, arcs, scan, M, offset in (("ref", ar.ref, ref, None, 0), ("tgt", ar.tgt, tgt, T, 5)):
            if k >= len(arcs):
                row.append("")
                continue
            a = arcs[k]
            row.append(f"{a.n_arcs}" + ("" if a.ok else f" ({md(a.message)})"))
            if len(a.indices) == 0 or not drawn:
                continue
            pts = scan.points[a.indices]
            if M is not None:
                pts = apply_transform(M, pts)
            # Offset the target's palette so its arcs do not look like the reference's.
            labels = np.where(a.labels >= 0, a.labels + offset, -1)
            handles.append(scene.add_point_cloud(f"{root}/{who}{k}", pts, categorical(labels), point_size=size,
                                                 point_shape="circle", precision="float32"))
        counts.append((row[0], row[1]))
    return handles, counts


def render_arcs(scene: viser.SceneApi, root: str, snap: Snapshot, view: ViewState) -> Drawing:
    t = target_index(snap, "arcs", view)
    pair = snap.pair(t)
    ar, sl = pair.item("arcs", SliceArcs), pair.item("slices", SliceResult)
    assert ar is not None and sl is not None, pair.label  # the drawer draws a pair that was not skipped
    ref, tgt = fine_scans(snap, t)
    only = slice_shown(snap, t, view, sl.n_slices)
    handles, counts = _arc_points(scene, root, ar, target_pose(snap, "hypothesis", t), ref, tgt,
                                  slice_point_size(view, only, whole=2.0), only)
    rows = [(("▶ " if k == only else "") + str(k + 1), f"{sl.heights_m[k]:.2f}" if k < len(sl.heights_m) else "", *c)
            for k, c in enumerate(counts)]
    shown = (f"Shown: {slice_label(only, sl.heights_m)} of {sl.n_slices} (▶ in the table; pick another under *Slice*, "
             "Stage tab). " if only is not None else f"Shown: all {sl.n_slices} slices. ")
    text = (shown + "Colours tell the arcs of a slice apart (an arc: a connected component in the scan's own angular "
            f"grid, neighbours within c = {snap.params.arcs.connectivity:g} angular steps; the same colour recurs from "
            f"slice to slice, and no arc has a scan's colour); grey points belong to arcs smaller than "
            f"{snap.params.arcs.min_points} points (arcs.min_points). The target is at the pose the fine stage starts "
            "from (5 Hypotheses).")
    table = md_table(("slice", "height (m)", f"arcs, scan {pair.ref + 1}", f"arcs, scan {pair.tgt + 1}"), rows)
    table += "\n\n" + metrics_table({pair_label(snap, t): ar.metrics})
    return handles, PanelContent(title("arcs", snap, t), text=text, table=table)


STAGE = AppStage(
    "arcs",
    StageView(
        "hypothesis",
        scans="hidden",
        explanation="Each slice holds several arcs (trunk and branch sections). Because the scanner samples a fixed "
            "angular grid, two points are neighbours when their angles differ by at most c·φ and c·ϕ "
            "(paper: c = 3, 2.2.2); connected components give the arcs, coloured one per component.",
    ),
    draw=render_arcs,
    view_fields=("target", "point_size", "slice_shown"),
    controls=(TargetControl, SliceControl),
    tour=(
        TourStep(
            "arcs", "Arcs by angular connectivity",
            "Within a slice, two points belong to one arc when they are neighbours in the scanner's own angular grid "
            "(2.2.2, Fig. 6): the connected cells of the raster below the top view. A slice through the crown holds "
            "many arcs, one per branch.",
            "Raise *Height* into the crown and watch the raster split into arcs of different colours.",
            view={"panel": "section", "section_poses": "Coarse", "branch": None}, camera="trunk", highlight="trunk"),
    ),
)
