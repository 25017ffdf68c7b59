"""The Slices stage: SliceResult — both scans' slice points, the target at the pose the fine stage starts
from (the paper slices the coarsely aligned scans).
"""

from __future__ import annotations

import numpy as np
import viser

from treereg_core.fine.slicing import SliceResult

from ..controller import Snapshot
from ..draw.before import drawn
from ..draw.common import Drawing, md_table, metrics_table, target_index, target_pose, title
from ..draw.fits import fine_scans, slice_label, slice_points, slice_shown
from ..view_panel import PanelContent
from ..text import md
from ..view_state import ALL_SLICES, ViewState
from .base import AppStage, ControlHost, StageControls, StageView, TargetControl, TourStep

#: The "Slice" list's entry for every slice at once.
EVERY_SLICE = "all slices"


class SliceControl(StageControls):
    """"Slice": the one slice the Arcs, Fits and Fine views show and frame (they open on the slice with
    the most fits), or every slice."""

    def __init__(self, gui: viser.GuiApi, host: ControlHost, stage: str) -> None:
        self.host = host
        self.stage = stage
        self.dropdown = gui.add_dropdown("Slice", (EVERY_SLICE,),
                                         hint="One slice, framed close up (the view opens on the slice with the most "
                                         "fits), or every slice at once.")
        self.dropdown.on_update(lambda _: None if host.quiet else self._picked())

    def _options(self, snap: Snapshot, view: ViewState) -> tuple[str, ...]:
        sl = snap.output("slices")
        item = snap.pair(target_index(snap, "slices", view)).item("slices", SliceResult) if sl is not None else None
        heights = item.heights_m if item is not None and item.ok else ()
        return (EVERY_SLICE, *(slice_label(k, heights) for k in range(len(heights))))

    def _picked(self) -> None:
        options = tuple(self.dropdown.options)
        k = options.index(self.dropdown.value) - 1 if self.dropdown.value in options else ALL_SLICES
        self.host.set_view(slice_shown=ALL_SLICES if k < 0 else k, focus_section=None)
        self.host.app.frame_view()

    def show_view(self, view: ViewState, snap: Snapshot) -> None:
        self.show_snapshot(snap, view)

    def refresh_focus(self, snap: Snapshot, view: ViewState) -> None:
        self.show_snapshot(snap, view)  # another pair has other slices

    def show_snapshot(self, snap: Snapshot, view: ViewState) -> None:
        snap = drawn(snap, view)[0]  # the slices of the run the view draws (a stale one's, until its re-run)
        options = self._options(snap, view)
        if tuple(self.dropdown.options) != options:
            self.dropdown.options = options
        k = slice_shown(snap, target_index(snap, "slices", view), view, len(options) - 1)
        want = EVERY_SLICE if k is None else options[k + 1]
        if self.dropdown.value != want:
            self.dropdown.value = want  # type: ignore[misc]



def _slice_text(snap: Snapshot, sl: SliceResult) -> str:
    q = snap.params.slices.quantiles
    where = (f"quantiles {', '.join(f'{v:g}' for v in q)}" if len(q) <= 5
             else f"{len(q)} quantiles from {min(q):g} to {max(q):g}")
    text = (f"Slices {sl.thickness_m * 100:.0f} cm thick at {where} of the tree's height "
            f"({sl.z_extent_m[0]:.2f} to {sl.z_extent_m[1]:.2f} m, reference frame), the target at its coarse pose.")
    if not sl.ok:
        text += f"\n\n**Slicing failed:** {md(sl.message)}"
    return text


def render_slices(scene: viser.SceneApi, root: str, snap: Snapshot, view: ViewState) -> Drawing:
    t = target_index(snap, "slices", view)
    pair = snap.pair(t)
    sl = pair.item("slices", SliceResult)
    assert sl is not None, pair.label  # the drawer draws a pair that was not skipped
    ref, tgt = fine_scans(snap, t)
    T = target_pose(snap, "hypothesis", t)
    handles = slice_points(scene, root, pair, sl, T, ref, tgt, 2.0 * view.point_size)
    rows = []
    for k, h in enumerate(sl.heights_m):
        r_idx, t_idx = sl.ref_indices[k], sl.tgt_indices[k]
        anchor = ref.points[r_idx].mean(axis=0) if len(r_idx) else np.array([0.0, 0.0, h])
        handles.append(scene.add_label(f"{root}/label{k}", f"z = {h:.2f} m", position=(anchor[0], anchor[1], h),
                                       anchor="center-left"))
        rows.append((k + 1, f"{h:.2f}", f"{len(r_idx):,}", f"{len(t_idx):,}"))
    table = md_table(("slice", "height (m)", f"{md(pair.ref_scan.name)} points", f"{md(pair.tgt_scan.name)} points"), rows)
    table += "\n\n" + metrics_table({"slices": sl.metrics})
    return handles, PanelContent(title("slices", snap, t), text=_slice_text(snap, sl), table=table)


STAGE = AppStage(
    "slices",
    StageView(
        "hypothesis",
        scans="faded",
        explanation="Fine registration starts from the coarse pose. Both scans are cut into thin horizontal slices at "
            "quantiles of tree height (paper: the three quartiles, 10 cm thick, 2.2.1; treereg takes more): low "
            "slices hold the trunk, high ones branches, whose centres become the fine tie points.",
    ),
    draw=render_slices,
    view_fields=("target", "point_size"),
    controls=(TargetControl,),
    tour=(
        TourStep(
            "slices", "Slices at the coarse pose",
            "Fine registration cuts both scans into thin horizontal slices (2.2.1). Seen from above, a slice of the trunk "
            "holds one arc per scan; at the coarse pose the arcs do not yet close into one circle.",
            "Drag *Height* in the cross-section (left panel), or click the stem in 3-D.",
            view={"panel": "section", "section_poses": "Coarse", "branch": None, "section_height": None},
            camera="trunk", highlight="trunk"),
    ),
)
