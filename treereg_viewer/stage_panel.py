"""The top of the control panel: stage selector, Previous/Next, Run, progress and messages; and
the "Stage" tab with one folder per stage (its explanation, view controls and parameters).

Only the current stage's folder is visible, so the panel reads like a page of a lesson. Each
browser tab has its own StagePanel: its controls show that tab's ViewState; the parameters are
shared (every tab's inputs show the parameters in force).
"""

from __future__ import annotations

import threading

from typing import Any

import viser

from treereg_core.stages import stage as core_stage

from .actions import AppActions
from .checks import stage_warnings
from .controller import Snapshot
from .param_widgets import SectionWidgets
from .renderers.fine import focus_rows
from .stages import STAGE_NAMES, by_label, label, view_of
from .view_state import ViewState

_STATUS_ICON = {"done": "✓", "failed": "✗", "stale": "○", "running": "…"}
#: The Result stage's choices, as people read them.
RESULT_POSES = {"Final": "final", "Pairwise fine": "fine", "Coarse": "coarse", "ICP": "icp"}
RESULT_COLOURS = {"Scan colours": "scan", "Scan colours, see-through": "seethrough",
                  "Distance to the other scans": "residual"}
NO_FOCUS = "(none)"


def status_line(snap: Snapshot, current: str, warned: dict[str, list[str]]) -> str:
    """'✓ 1 Scans · ✓ 2 Projection · … · **○ 5 Slices** …': every stage with its state, the current
    one bold. One place, so marks (e.g. per-scan verdicts) can be added beside each stage."""
    parts = []
    for name in STAGE_NAMES:
        # Done but implausible (e.g. an SVD transform that turns a scan upside down): not a ✓.
        mark = "⚠" if name in warned else _STATUS_ICON[snap.status(name)]
        text = f"**{label(name)}**" if name == current else label(name)
        parts.append(f"{mark} {text}")
    return " · ".join(parts)


def verdict_line(snap: Snapshot) -> str:
    """Every scan's verdict, shown above every stage (✓ verified, ⚠ unverified, ✗ failed)."""
    graph = snap.output("graph")
    if graph is None or len(graph.items) != len(snap.scans):
        return ""
    marks = {"verified": "✓", "unverified": "⚠", "failed": "✗"}
    return "\n\n**Scans:** " + " · ".join(f"{marks.get(pl.verdict, '?')} {i + 1} {s.name}"
                                           for i, (s, pl) in enumerate(zip(snap.scans, graph.items)))


class StagePanel:
    """Navigation, run controls and the per-stage folders of one viewer."""

    def __init__(self, gui: viser.GuiApi, app: AppActions) -> None:
        self.app = app
        self.gui = gui
        # Set while this panel puts values into its own controls (on the thread doing so only: a
        # person's change arriving meanwhile on another thread is not swallowed).
        self._local = threading.local()
        self.status_md = gui.add_markdown("")
        self.selector = gui.add_dropdown("Stage", [label(n) for n in STAGE_NAMES], initial_value=label(STAGE_NAMES[0]),
                                         hint="Pick a stage; its layers are shown, the others hidden (scans stay).")
        self.step = gui.add_button_group("Step", ("Previous", "Next"))
        self.run_button = gui.add_button("Run", icon=viser.Icon.PLAYER_PLAY, color="green",
                                         hint="Run this stage and the ones after it (earlier results are reused).")
        self.auto_run = gui.add_checkbox("Run when stepping", True,
                                         hint="Run a stale stage when you step onto it.")
        self.frame_button = gui.add_button("Frame the view", icon=viser.Icon.FOCUS_CENTERED, color="gray",
                                           hint="Point the camera at what this stage draws.")
        self.frame_button.on_click(lambda _: app.frame_view())
        self.progress = gui.add_progress_bar(0.0, animated=False)
        self.progress_text = gui.add_markdown("")
        self.message_md = gui.add_markdown("")
        self.selector.on_update(lambda _: self._quiet or app.select_stage(by_label(self.selector.value)))
        self.step.on_click(lambda e: app.step_stage(-1 if e.target.value == "Previous" else 1))
        self.run_button.on_click(lambda _: app.run_current())

        # Folders, filled by `build_folders` inside the "Stage" tab.
        self.folders: dict[str, Any] = {}
        self.sections: dict[str, SectionWidgets] = {}
        self.view_controls: dict[str, Any] = {}

    def build_folders(self, gui: viser.GuiApi) -> None:
        """One folder per stage: explanation, view controls, then its parameter sections."""
        app = self.app
        params = app.controller.params
        for name in STAGE_NAMES:
            folder = gui.add_folder(label(name), visible=name == STAGE_NAMES[0])
            self.folders[name] = folder
            with folder:
                gui.add_markdown(view_of(name).explanation or core_stage(name).summary)
                self._view_controls(gui, name)
                for section in core_stage(name).sections:
                    if section in self.sections:  # a section read by several stages is edited where it belongs
                        continue
                    with gui.add_folder(f"Parameters: {section}", expand_by_default=True):
                        self.sections[section] = SectionWidgets(gui, section, params, app.on_param_change)

    @property
    def _quiet(self) -> bool:
        return getattr(self._local, "quiet", False)

    def _set(self, **changes: Any) -> None:
        if not self._quiet:
            self.app.set_view(**changes)

    def _view_controls(self, gui: viser.GuiApi, name: str) -> None:
        app, c = self.app, self.view_controls
        wanted = view_of(name).controls
        if "mixed" in wanted:
            c["mixed"] = gui.add_checkbox("Show removed mixed pixels", True,
                                          hint="Draw (near-black) the returns behind the stems' and branches' edges "
                                          "that the preparation removed as mixed pixels (prepare.mixed_pixels).")
            c["mixed"].on_update(lambda _: self._set(show_mixed=bool(c["mixed"].value)))
        if "projection_step" in wanted:
            # Counted from 1, as the panel's "Step k of n" reads.
            c["projection_step"] = gui.add_slider("Rotation step", 1, 2, 1, 1,
                                                  hint="Walk the rotation sequence (the angle is shown in the panel).")
            c["projection_step"].on_update(lambda _: self._set(projection_step=int(c["projection_step"].value) - 1))
            c["projection_3d"] = gui.add_checkbox("Show rotated clouds in 3-D", False)
            c["projection_3d"].on_update(lambda _: self._set(projection_3d=bool(c["projection_3d"].value)))
        if "target" in wanted:
            key = f"target_{name}"
            c[key] = gui.add_dropdown("Pair", ["scan2 → scan1"], hint="Which target scan the panel details.")
            c[key].on_update(lambda _, key=key: self._quiet or app.select_target(c[key].value))
        if "match_pair" in wanted:
            c["match_pair"] = gui.add_slider("Image pair", 1, 2, 1, 1, hint="Which chosen image pair's ORB matches to show.")
            c["match_pair"].on_update(lambda _: self._set(match_pair=int(c["match_pair"].value) - 1))
        if "hypothesis" in wanted:
            c["hypothesis"] = gui.add_dropdown("Use hypothesis", ("automatic",),
                                               hint="Pick a competing pose by hand (it is then marked as chosen by hand).")
            c["hypothesis"].on_update(lambda _: self._quiet or self._choose())
        if "fits" in wanted:
            key = f"rejected_{name}"
            c[key] = gui.add_checkbox("Show rejected fits", False,
                                      hint="Also list and draw (grey) the fits judged implausible; never larger than their slice.")
            c[key].on_update(lambda _, key=key: self._set(show_rejected=bool(c[key].value), focus_section=None))
            fkey = f"focus_{name}"
            c[fkey] = gui.add_dropdown("Frame a fit", (NO_FOCUS,),
                                       hint="A row of the fits table: the camera goes there and the fit is outlined in yellow.")
            c[fkey].on_update(lambda _, fkey=fkey, name=name: self._quiet or app.focus_section(name, c[fkey].value))
        if "result" in wanted:
            c["result_pose"] = gui.add_button_group("Targets at", tuple(RESULT_POSES))
            c["result_pose"].on_click(lambda e: self._set(result_pose=RESULT_POSES[e.target.value]))
            c["result_colour"] = gui.add_dropdown("Colour by", tuple(RESULT_COLOURS), initial_value="Scan colours",
                                                  hint="Scan colours (opaque or see-through where scans overlap), or "
                                                  "each point's distance to the other scans' surface.")
            c["result_colour"].on_update(lambda _: self._set(result_colour=RESULT_COLOURS[c["result_colour"].value]))
            c["residual_max"] = gui.add_slider("Colour map top (mm)", 2, 100, 1, 20,
                                               hint="Distances from here on get the top colour (red).")
            c["residual_max"].on_update(lambda _: self._set(residual_max_m=float(c["residual_max"].value) / 1000.0))

    # ---- updates from the viewer -----------------------------------------------------------------
    def show_stage(self, name: str) -> None:
        text = label(name)
        self._local.quiet = True
        try:
            if self.selector.value != text:
                self.selector.value = text
        finally:
            self._local.quiet = False
        for k, f in self.folders.items():
            f.visible = k == name

    def show_view(self, view: ViewState, snap: Snapshot) -> None:
        """Put the view's choices into the controls (a followed presenter, the tour), without
        reporting them back as changes."""
        c = self.view_controls
        self._local.quiet = True
        try:
            self.show_stage(view.stage)
            self._local.quiet = True
            if "projection_step" in c and c["projection_step"].value != view.projection_step + 1 \
                    and view.projection_step + 1 <= c["projection_step"].max:
                c["projection_step"].value = view.projection_step + 1
            if "projection_3d" in c:
                c["projection_3d"].value = view.projection_3d
            if "mixed" in c:
                c["mixed"].value = view.show_mixed
            if "match_pair" in c and view.match_pair + 1 <= c["match_pair"].max:
                c["match_pair"].value = view.match_pair + 1
            for key, h in c.items():
                if key.startswith("rejected_"):
                    h.value = view.show_rejected
            if "result_colour" in c:
                c["result_colour"].value = next(k for k, v in RESULT_COLOURS.items() if v == view.result_colour)
                c["residual_max"].value = max(2, min(100, round(view.residual_max_m * 1000)))
            pairs = self._pairs(snap)
            if view.target < len(pairs):
                for key, h in c.items():
                    if key.startswith("target") and h.value != pairs[view.target]:
                        h.value = pairs[view.target]
        finally:
            self._local.quiet = False
        self.refresh_focus(snap, view)

    def refresh_focus(self, snap: Snapshot, view: ViewState) -> None:
        """The "Frame a fit" lists follow the fits tables (their pair and the rejected-fits switch)."""
        self._local.quiet = True
        try:
            for name in ("sections", "fine"):
                h = self.view_controls.get(f"focus_{name}")
                if h is None:
                    continue
                rows = focus_rows(snap, name, view) if name == view.stage else []
                options = (NO_FOCUS, *(r.label for r in rows))
                if tuple(h.options) != options:
                    h.options = options
                want = rows[view.focus_section].label if (name == view.stage and view.focus_section is not None
                                                          and view.focus_section < len(rows)) else NO_FOCUS
                if h.value != want:
                    h.value = want
        finally:
            self._local.quiet = False

    @staticmethod
    def _pairs(snap: Snapshot) -> list[str]:
        return [f"{s.name} → {snap.scans[0].name}" for s in snap.scans[1:]] or ["(no target scan)"]

    def show_snapshot(self, snap: Snapshot, view: ViewState) -> None:
        """Status line per stage, message, Run button state, view-control ranges."""
        warned = stage_warnings(snap) if not snap.busy else {}
        self.status_md.content = status_line(snap, view.stage, warned) + verdict_line(snap)
        self.run_button.disabled = snap.busy
        lines = []
        if snap.message:
            lines.append(f"**⚠ {snap.message}**" if snap.error else snap.message)
        elif not snap.busy:
            failed = [s for s in STAGE_NAMES if snap.status(s) == "failed"]
            if failed:
                why = snap.crashed.get(failed[0]) or snap.outputs[failed[0]].message
                lines.append(f"**⚠ {label(failed[0])} failed:** {why}")
        lines += [f"**⚠** {w}" for ws in warned.values() for w in ws]
        self.message_md.content = "\n\n".join(lines)
        if not snap.busy:
            # At rest the bar shows how much of the pipeline is up to date (a failure stops it there).
            self.progress.value = 100.0 * sum(snap.status(s) == "done" for s in STAGE_NAMES) / len(STAGE_NAMES)
            self.progress.animated = False
        else:
            self.progress.animated = True
        # Ranges of the view controls follow the results (counted from 1).
        self._local.quiet = True
        try:
            proj = snap.output("projection")
            if proj is not None and proj.items:
                n = max(len(getattr(s, "angles_deg", ())) for s in proj.items)
                sl = self.view_controls["projection_step"]
                if n > 1 and sl.max != n:
                    zero = next((k for k, a in enumerate(proj.items[0].angles_deg) if abs(a) < 1e-9), 0)
                    sl.max = n
                    sl.value = min(zero, n - 1) + 1
                    self._local.quiet = False
                    self._set(projection_step=min(zero, n - 1))
                    self._local.quiet = True
            pairs = self._pairs(snap)
            for key, h in self.view_controls.items():
                if key.startswith("target") and tuple(h.options) != tuple(pairs):
                    h.options = pairs
            match = snap.output("matching")
            if match is not None and match.items:
                t = min(view.target, len(match.items) - 1)
                n = len(getattr(match.items[t], "pairs", ()) or ())
                sl = self.view_controls["match_pair"]
                if n > 1 and sl.max != n:
                    sl.max = n
                sl.disabled = n <= 1
            self._show_hypotheses(snap, view)
        finally:
            self._local.quiet = False
        self.refresh_focus(snap, view)

    def _choose(self) -> None:
        snap = self.app.controller.snapshot
        h = snap.output("hypotheses")
        if h is None or not h.items or not snap.pairs:
            return
        t = min(self.app.view.target, len(h.items) - 1)
        p = snap.pairs[t]
        pair = f"{snap.scans[p.tgt].name} -> {snap.scans[p.ref].name}"
        value = self.view_controls["hypothesis"].value
        wanted = None if value == "automatic" else value
        if snap.choices.get(pair) != wanted:
            self.app.controller.choose(pair, wanted)

    def _show_hypotheses(self, snap: Snapshot, view: ViewState) -> None:
        """The hypothesis list of the pair in view, and the choice in force for it."""
        hyp = snap.output("hypotheses")
        h = self.view_controls.get("hypothesis")
        if hyp is None or not hyp.items or h is None or not snap.pairs:
            return
        t = min(view.target, len(hyp.items) - 1)
        options = ("automatic",) + tuple(c.label for c in getattr(hyp.items[t], "candidates", ()))
        if tuple(h.options) != options:
            h.options = options
        p = snap.pairs[t]
        current = snap.choices.get(f"{snap.scans[p.tgt].name} -> {snap.scans[p.ref].name}", "automatic")
        if h.value != current and current in options:
            h.value = current

    def show_progress(self, fraction: float, text: str) -> None:
        self.progress.value = float(min(max(fraction, 0.0), 1.0) * 100.0)
        self.progress_text.content = f"*{text}*" if text else ""

    def flush_edits(self) -> None:
        """Apply parameter values still being typed (Run, an export: they must see what the user typed)."""
        for w in self.sections.values():
            w.flush()

    def sync_params(self, params: Any) -> None:
        for w in self.sections.values():
            w.sync(params)
