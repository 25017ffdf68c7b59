"""The Fits stage (`sections`): SectionsResult — the circles and cylinders fitted to the arcs, drawn as
the stage made them (at the pose it started from), their tie lines, the table of fits; and the fits
controls the Fine stage shares.
"""

from __future__ import annotations

import viser

from treereg_core.fine.sections import SectionsResult
from treereg_core.fine.slicing import SliceResult

from ..controller import Snapshot
from ..draw.common import Drawing, metrics_table, pair_label, plural, target_index, title
from ..draw.fits import draw_sections, fine_scans, focus_rows
from ..view_panel import PanelContent
from ..text import md_sentence
from ..view_state import ViewState
from .slices import SliceControl
from .base import AppStage, ControlHost, StageControls, StageView, TargetControl, TourStep


def sections_sentence(n_pairs: int, n_ties: int, pose: str) -> str:
    """'At the coarse pose, 3 corresponding sections give 5 tie points.' — or why there are none."""
    if n_pairs == 0:
        return (f"At the {pose} pose no section of the target corresponds to one of the reference, so the sections "
                "give no tie points.")
    return (f"At the {pose} pose, {plural(n_pairs, 'corresponding section')} "
            f"{'gives' if n_pairs == 1 else 'give'} {plural(n_ties, 'tie point')} (yellow lines join partners).")


def render_sections(scene: viser.SceneApi, root: str, snap: Snapshot, view: ViewState) -> Drawing:
    t = target_index(snap, "sections", view)
    pair = snap.pair(t)
    sec, sl = pair.item("sections", SectionsResult), pair.item("slices", SliceResult)
    assert sec is not None and sl is not None, pair.label  # the drawer draws a pair that was not skipped
    ref, tgt = fine_scans(snap, t)
    handles, table, _ = draw_sections(scene, root, snap, t, sl, sec, ref, tgt, view)
    text = (sections_sentence(sec.n_pairs, len(sec.tie_points_ref), "starting") + " Only accepted fits are drawn, in "
            "their scan's colour; only the sliced points are shown with them. Pick a row under *Frame a fit* (Stage "
            "tab) or click a fit in 3-D to look at it closely.")
    if sec.message:
        text += f"\n\n{md_sentence(sec.message)}"
    table += "\n\n" + metrics_table({pair_label(snap, t): sec.metrics})
    return handles, PanelContent(title("sections", snap, t), text=text, table=table)


#: The "Frame a fit" list's entry for no fit.
NO_FOCUS = "(none)"


class FitControls(StageControls):
    """"Show rejected fits" and "Frame a fit" (a row of the fits table), on the Fits and the Fine stage."""

    def __init__(self, gui: viser.GuiApi, host: ControlHost, stage: str) -> None:
        self.stage = stage
        self.rejected = gui.add_checkbox("Show rejected fits", False,
                                         hint="Also list and draw (grey) the fits judged implausible; never larger than their slice.")
        self.rejected.on_update(lambda _: host.set_view(show_rejected=bool(self.rejected.value), focus_section=None))
        self.focus = gui.add_dropdown("Frame a fit", (NO_FOCUS,),
                                      hint="A row of the fits table: the camera goes there and the fit is outlined in yellow.")
        self.focus.on_update(lambda _: None if host.quiet else host.app.focus_section(stage, self.focus.value))

    def show_view(self, view: ViewState, snap: Snapshot) -> None:
        self.rejected.value = view.show_rejected  # type: ignore[misc]

    def refresh_focus(self, snap: Snapshot, view: ViewState) -> None:
        """The list follows the fits table (its pair and the rejected-fits switch), on this stage only."""
        here = self.stage == view.stage
        rows = focus_rows(snap, self.stage, view) if here else []
        options = (NO_FOCUS, *(r.label for r in rows))
        if tuple(self.focus.options) != options:
            self.focus.options = options
        want = (rows[view.focus_section].label if here and view.focus_section is not None
                and view.focus_section < len(rows) else NO_FOCUS)
        if self.focus.value != want:
            self.focus.value = want  # type: ignore[misc]


STAGE = AppStage(
    "sections",
    StageView(
        "hypothesis",
        scans="hidden",
        explanation="The trunk in the lowest slice is fitted with a Taubin circle, the other sections with least-squares "
            "cylinders (2.2.3); the circle centre, and on each cylinder axis its start and the point one unit "
            "further up, are the tie points, joined here to their partners in the other scan (at the pose "
            "the hypotheses stage chose). Fits that fail a plausibility check, e.g. the paper's rule that a section is no wider "
            "than the one below it (4.2), are not used; tick *Show rejected fits* to see them in grey.",
    ),
    draw=render_sections,
    view_fields=("target", "point_size", "show_rejected", "focus_section", "slice_shown"),
    controls=(TargetControl, SliceControl, FitControls),
    tour=(
        TourStep(
            "sections", "Circles, cylinders and their centres",
            "The trunk's arcs get Taubin circles, the branches' least-squares cylinders (2.2.3); their centres pair up "
            "between the scans and become the fine tie points. A section wider than the part below it is a "
            "mis-separated arc and is dropped (4.2).",
            "Tick *Show rejected fits*, then pick a row under *Frame a fit*.",
            view={"panel": "stage", "show_rejected": False}),
    ),
)
