"""The Hypotheses stage: HypothesesResult — the target drawn at every competing pose (rivals grey, the
chosen one in its colour) over the reference, and the table of their scores; a pose can be picked by hand.
"""

from __future__ import annotations

from typing import Any

import viser

from treereg_core.geometry.rigid import apply_transform

from ..controller import Snapshot
from ..draw.common import Drawing, display_subset, md_table, pair_label, plural, target_index, title
from ..palette import GREY, scan_color
from ..view_panel import PanelContent
from ..view_state import ViewState
from .base import AppStage, ControlHost, StageControls, StageView, TargetControl, TourStep


def render_hypotheses(scene: viser.SceneApi, root: str, snap: Snapshot, view: ViewState) -> Drawing:
    t = target_index(snap, "hypotheses", view)
    h = snap.output("hypotheses").items[t]
    tgt = snap.output("prepare").items[t + 1].scan
    idx = display_subset(tgt.n_points, min(view.max_points, 15_000), seed=t)
    handles: list[Any] = []
    rows = []
    for n, c in enumerate(h.candidates):
        chosen = c.label == h.chosen
        colour = scan_color(t + 1) if chosen else GREY
        if not chosen:  # the chosen pose is where the scan layer already draws the target
            handles.append(scene.add_point_cloud(f"{root}/candidate{n}", apply_transform(c.T_ref_target, tgt.points[idx]),
                                                 colour, point_size=view.point_size * 0.7, point_shape="circle",
                                                 precision="float32"))
        v = c.visibility
        rows.append((("**" + c.label + "**") if chosen else c.label, c.support or "", f"{v.consistency:.3f}",
                     f"{v.seen_by_both:,}", f"{v.violations:,}"))
    if not h.candidates:
        text = f"{pair_label(snap, t)}: {h.message[0].upper()}{h.message[1:]}."
    else:
        hand = " (chosen by hand)" if h.chosen_by_hand else ""
        text = (f"{pair_label(snap, t)}: **{h.chosen}**{hand} is the most consistent pose; the best distinct rival, "
                f"{h.runner_up or 'none'}, is {h.margin:.3f} less consistent. Grey: the rivals at their polished "
                "poses. Consistency: the share of the points both stations see that lie where the reference saw a "
                "surface, not in space its laser passed through.")
        if h.unscored_modes:  # the coarse stage counts every mode: say where the missing ones went
            text += (f" Not scored: {plural(h.unscored_modes, 'further RANSAC mode')} with fewer than "
                     f"{snap.params.hypotheses.min_mode_support} agreeing ties (hypotheses.min_mode_support).")
    table = md_table(("hypothesis", "tie support", "consistency", "seen by both", "in free space"), rows)
    return handles, PanelContent(title("hypotheses", snap, t), text=text, table=table)


class HypothesisControl(StageControls):
    """"Use hypothesis": a competing pose picked by hand for the pair in view ("automatic": the surfaces choose)."""

    def __init__(self, gui: viser.GuiApi, host: ControlHost, stage: str) -> None:
        self.app = host.app
        self.dropdown = gui.add_dropdown("Use hypothesis", ("automatic",),
                                         hint="Pick a competing pose by hand (it is then marked as chosen by hand).")
        self.dropdown.on_update(lambda _: host.quiet or self._choose())

    def _choose(self) -> None:
        snap = self.app.controller.snapshot
        h = snap.output("hypotheses")
        if h is None or not h.items or not snap.pairs:
            return
        t = min(self.app.view.target, len(h.items) - 1)
        p = snap.pairs[t]
        pair = f"{snap.scans[p.tgt].name} -> {snap.scans[p.ref].name}"
        wanted = None if self.dropdown.value == "automatic" else self.dropdown.value
        if snap.choices.get(pair) != wanted:
            self.app.controller.choose(pair, wanted)

    def show_snapshot(self, snap: Snapshot, view: ViewState) -> None:
        """The hypothesis list of the pair in view, and the choice in force for it."""
        hyp = snap.output("hypotheses")
        if hyp is None or not hyp.items or not snap.pairs:
            return
        t = min(view.target, len(hyp.items) - 1)
        options = ("automatic",) + tuple(c.label for c in getattr(hyp.items[t], "candidates", ()))
        if tuple(self.dropdown.options) != options:
            self.dropdown.options = options
        p = snap.pairs[t]
        current = snap.choices.get(f"{snap.scans[p.tgt].name} -> {snap.scans[p.ref].name}", "automatic")
        if self.dropdown.value != current and current in options:
            self.dropdown.value = current


STAGE = AppStage(
    "hypotheses",
    StageView(
        "hypothesis",
        explanation="A nearly round crown looks alike from several headings: RANSAC's winner can be the wrong one. "
            "So every distinct RANSAC solution and the coarse transform turned about the stem by quarter, third and half turns are "
            "each aligned cheaply by the surfaces and judged by what the reference scanner saw: a target point lying "
            "where the reference's laser passed through empty space speaks against the pose (grey: the rivals). The "
            "most consistent pose goes on to the fine stage; the margin to the best distinct rival says how sure "
            "that is. You can pick another hypothesis here.",
    ),
    draw=render_hypotheses,
    view_fields=("target", "point_size", "max_points"),
    controls=(TargetControl, HypothesisControl),
    tour=(
        TourStep(
            "hypotheses", "Could it be another heading?",
            "A nearly round crown looks alike from several sides, so the best coarse match can be a wrong heading. "
            "treereg keeps every distinct RANSAC solution and the coarse pose turned about the stem (quarter, third and half turns), aligns each "
            "cheaply and asks the reference scanner: a target point where its laser passed through empty space "
            "speaks against the pose.",
            "Read the table: the margin between the chosen pose and its best rival. Pick another under *Use "
            "hypothesis* and watch the later stages run again.",
            view={"panel": "stage"}),
    ),
)
