"""The Hypotheses stage: HypothesesResult — the target drawn at every competing pose (rivals grey, the
chosen one in its colour) over the reference, and the table of their scores; a pose can be picked by hand.
"""

from __future__ import annotations

from typing import Any

import viser

from treereg_core.geometry.rigid import apply_transform
from treereg_core.verify.hypotheses import Candidate, HypothesesResult

from ..controller import Snapshot
from ..draw.common import Drawing, display_subset, md_table, pair_label, plural, target_index, title
from ..palette import GREY
from ..view_panel import PanelContent
from ..text import md, md_sentence
from ..view_state import ViewState
from .base import AppStage, ControlHost, StageControls, StageView, TargetControl, TourStep


def rival_shown(h: HypothesesResult, view: ViewState) -> Candidate | None:
    """The rival drawn beside the chosen pose: the view's pick, else the best distinct rival (else the
    best other candidate)."""
    others = [c for c in h.candidates if c.label != h.chosen]
    by_label = {c.label: c for c in others}
    return by_label.get(view.rival or "") or by_label.get(h.runner_up) or (others[0] if others else None)


def margin_sentence(snap: Snapshot, h: HypothesesResult) -> str:
    """The margin to the best distinct rival against the threshold the verdict holds it to."""
    need = snap.params.verify.min_margin
    if not h.runner_up:
        return "No distinct rival was scored: nothing else explains the scans."
    ok = h.margin >= need
    how = f"{h.margin:.3f} less consistent" if h.margin >= 0 else f"{-h.margin:.3f} more consistent"
    return (f"The best distinct rival, {md(h.runner_up)}, is {how}: margin {h.margin:.3f} "
            f"{'≥' if ok else '<'} {need:g} (verify.min_margin) {'✓' if ok else '✗'}.")


def render_hypotheses(scene: viser.SceneApi, root: str, snap: Snapshot, view: ViewState) -> Drawing:
    pair = snap.pair(target_index(snap, "hypotheses", view))
    t = pair.index
    h, scans = pair.item("hypotheses", HypothesesResult), pair.prepared()
    # The drawer draws a pair that was not skipped: its hypotheses ran on its prepared scans.
    assert h is not None and scans is not None, pair.label
    tgt = scans[1]
    idx = display_subset(tgt.n_points, min(view.max_points, 15_000), seed=t)
    handles: list[Any] = []
    rival = rival_shown(h, view)
    if rival is not None:  # the chosen pose is where the scan layer already draws the target
        handles.append(scene.add_point_cloud(f"{root}/rival", apply_transform(rival.T_ref_target, tgt.points[idx]),
                                             GREY, point_size=view.point_size * 0.7, point_shape="circle",
                                             precision="float32"))
    chosen = next((c for c in h.candidates if c.label == h.chosen), None)
    best = chosen.visibility.consistency if chosen is not None else float("nan")
    need = snap.params.verify.min_margin
    rows = []
    for c in h.candidates:
        v = c.visibility
        name = f"**{md(c.label)}** (chosen)" if c.label == h.chosen else md(c.label)
        if rival is not None and c.label == rival.label:
            name += " · drawn grey"
        if c.label == h.chosen:
            margin = "–"
        else:
            m = best - v.consistency
            margin = f"{m:.3f}" + ((" ✓" if m >= need else " ✗") if c.label == h.runner_up else "")
        rows.append((name, c.support or "", f"{v.consistency:.3f}", f"{v.violations:,} of {v.seen_by_both:,}", margin))
    if not h.candidates:
        text = f"{md(pair_label(snap, t))}: {md_sentence(h.message)}"
    else:
        hand = " (chosen by hand)" if h.chosen_by_hand else ""
        drawn = (f" Grey: {md(rival.label)} at its polished pose (pick another under *Rival shown*, Stage tab)."
                 if rival is not None else "")
        text = (f"{md(pair_label(snap, t))}: **{md(h.chosen)}**{hand} is the most consistent pose. {margin_sentence(snap, h)}"
                f"{drawn} Consistency: the share of the points both stations see that lie where the reference saw a "
                "surface, not in space its laser passed through; margin: the chosen pose's consistency minus the "
                "row's.")
        if h.unscored_modes:  # the coarse stage counts every mode: say where the missing ones went
            text += (f" Not scored: {plural(h.unscored_modes, 'further RANSAC mode')} with fewer than "
                     f"{snap.params.hypotheses.min_mode_support} agreeing ties (hypotheses.min_mode_support).")
    table = md_table(("hypothesis", "ties", "consis&shy;tency", "in free space", f"margin (≥ {need:g})"), rows)
    return handles, PanelContent(title("hypotheses", snap, t), text=text, table=table)


def _shown_pair_item(snap: Snapshot, view: ViewState) -> HypothesesResult | None:
    """The hypotheses of the pair in view (None before the stage ran, or for a skipped pair)."""
    out = snap.output("hypotheses")
    if out is None or not out.items:
        return None
    return snap.pair(target_index(snap, "hypotheses", view)).item("hypotheses", HypothesesResult)


class RivalControl(StageControls):
    """"Rival shown": which competing pose is drawn grey beside the chosen one (one at a time)."""

    def __init__(self, gui: viser.GuiApi, host: ControlHost, stage: str) -> None:
        self.host = host
        self.dropdown = gui.add_dropdown("Rival shown", ("(none)",),
                                         hint="The competing pose drawn in grey beside the chosen one (it opens on the "
                                         "best distinct rival).")
        self.dropdown.on_update(lambda _: None if host.quiet else host.set_view(rival=self.dropdown.value))

    def show_view(self, view: ViewState, snap: Snapshot) -> None:
        self.show_snapshot(snap, view)

    def refresh_focus(self, snap: Snapshot, view: ViewState) -> None:
        self.show_snapshot(snap, view)

    def show_snapshot(self, snap: Snapshot, view: ViewState) -> None:
        h = _shown_pair_item(snap, view)
        if h is None:
            return
        options = tuple(c.label for c in h.candidates if c.label != h.chosen) or ("(none)",)
        if tuple(self.dropdown.options) != options:
            self.dropdown.options = options
        r = rival_shown(h, view)
        want = r.label if r is not None else options[0]
        if self.dropdown.value != want:
            self.dropdown.value = want  # type: ignore[misc]


class HypothesisControl(StageControls):
    """"Use hypothesis": a competing pose picked by hand for the pair in view ("automatic": the surfaces choose)."""

    def __init__(self, gui: viser.GuiApi, host: ControlHost, stage: str) -> None:
        self.app = host.app
        self.dropdown = gui.add_dropdown("Use hypothesis", ("automatic",),
                                         hint="Pick a competing pose by hand (it is then marked as chosen by hand).")
        self.dropdown.on_update(lambda _: None if host.quiet else self._choose())

    def _choose(self) -> None:
        snap = self.app.controller.snapshot
        if _shown_pair_item(snap, self.app.view) is None or self.app.read_only:  # following: the presenter's
            return
        pair = snap.pair(target_index(snap, "hypotheses", self.app.view)).key
        wanted = None if self.dropdown.value == "automatic" else self.dropdown.value
        if snap.choices.get(pair) != wanted:
            self.app.choose_hypothesis(pair, wanted)  # the other tabs are told, and can undo it

    def show_snapshot(self, snap: Snapshot, view: ViewState) -> None:
        """The hypothesis list of the pair in view, and the choice in force for it."""
        h = _shown_pair_item(snap, view)
        if h is None:
            return
        options = ("automatic",) + tuple(c.label for c in h.candidates)
        if tuple(self.dropdown.options) != options:
            self.dropdown.options = options
        current = snap.choices.get(snap.pair(target_index(snap, "hypotheses", view)).key, "automatic")
        if self.dropdown.value != current and current in options:
            self.dropdown.value = current  # type: ignore[misc]


STAGE = AppStage(
    "hypotheses",
    StageView(
        "hypothesis",
        explanation="A nearly round crown looks alike from several headings: RANSAC's winner can be the wrong one. "
            "So every distinct RANSAC solution and the coarse transform turned about the stem by quarter, third and half turns are "
            "each aligned cheaply by the surfaces and judged by what the reference scanner saw: a target point lying "
            "where the reference's laser passed through empty space speaks against the pose (grey: one rival at a time). The "
            "most consistent pose goes on to the fine stage; the margin to the best distinct rival says how sure "
            "that is: the verdict asks for at least verify.min_margin. You can pick another hypothesis here.",
    ),
    draw=render_hypotheses,
    view_fields=("target", "point_size", "max_points", "rival"),
    controls=(TargetControl, RivalControl, HypothesisControl),
    tour=(
        TourStep(
            "hypotheses", "Could it be another heading?",
            "A nearly round crown looks alike from several sides, so the best coarse match can be a wrong heading. "
            "treereg keeps every distinct RANSAC solution and the coarse pose turned about the stem (quarter, third and half turns), aligns each "
            "cheaply and asks the reference scanner: a target point where its laser passed through empty space "
            "speaks against the pose.",
            "Read the table's margin column: the chosen pose's consistency minus each rival's, the best distinct rival "
            "marked ✓ or ✗ against its threshold. Pick another under *Use hypothesis* and watch the later stages run "
            "again.",
            view={"panel": "stage"}),
    ),
)
