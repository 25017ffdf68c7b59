"""The top of the control panel: stage selector, Previous/Next, Run, progress and messages; and
the "Stage" tab with one folder per stage (its explanation, view controls and parameters).

Only the current stage's folder is visible, so the panel reads like a page of a lesson.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import viser

from treereg_core.pipeline import STAGES

from .controller import Snapshot
from .param_widgets import SectionWidgets
from .checks import stage_warnings
from .stages import APP_STAGES, FIRST_APP_STAGE, AppStage, stage_by_label

if TYPE_CHECKING:
    from .app import TreeregApp

_STATUS_ICON = {"done": "✓", "failed": "✗", "stale": "○", "running": "…"}


class StagePanel:
    """Navigation, run controls and the per-stage folders."""

    def __init__(self, gui: viser.GuiApi, app: "TreeregApp") -> None:
        self.app = app
        self.gui = gui
        self.status_md = gui.add_markdown("")
        self.selector = gui.add_dropdown("Stage", [s.label for s in APP_STAGES], initial_value=APP_STAGES[0].label,
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
        self.selector.on_update(lambda _: app.select_stage(stage_by_label(self.selector.value).index))
        self.step.on_click(lambda e: app.step_stage(-1 if e.target.value == "Previous" else 1))
        self.run_button.on_click(lambda _: app.run_current())

        # Folders, filled by `build_folders` inside the "Stage" tab.
        self.folders: dict[int, Any] = {}
        self.sections: dict[str, SectionWidgets] = {}
        self.view_controls: dict[str, Any] = {}

    def build_folders(self, gui: viser.GuiApi) -> None:
        """One folder per stage: explanation, view controls, then its parameter sections."""
        app = self.app
        params = app.controller.params
        for stage in APP_STAGES:
            folder = gui.add_folder(stage.label, visible=stage.index == 0)
            self.folders[stage.index] = folder
            with folder:
                gui.add_markdown(stage.explanation)
                self._view_controls(gui, stage)
                for section in stage.sections:
                    with gui.add_folder(f"Parameters: {section}", expand_by_default=True):
                        self.sections[section] = SectionWidgets(gui, section, params, app.on_param_change)

    def _view_controls(self, gui: viser.GuiApi, stage: AppStage) -> None:
        app, c = self.app, self.view_controls
        if stage.index == 1:
            c["projection_step"] = gui.add_slider("Rotation step", 0, 1, 1, 0,
                                                  hint="Walk the rotation sequence (index; the angle is shown in the panel).")
            c["projection_step"].on_update(lambda _: app.set_view(projection_step=int(c["projection_step"].value)))
            c["projection_3d"] = gui.add_checkbox("Show rotated clouds in 3-D", False)
            c["projection_3d"].on_update(lambda _: app.set_view(projection_3d=bool(c["projection_3d"].value)))
        if stage.index in (2, 3, 4, 5, 6, 7):
            key = f"target{stage.index}"
            c[key] = gui.add_dropdown("Pair", ["scan2 → scan1"], hint="Which target scan the panel details.")
            c[key].on_update(lambda _, key=key: app.select_target(c[key].value))
        if stage.index == 2:
            c["match_pair"] = gui.add_slider("Image pair", 0, 1, 1, 0, hint="Which chosen image pair's ORB matches to show.")
            c["match_pair"].on_update(lambda _: app.set_view(match_pair=int(c["match_pair"].value)))
        if stage.index == 7:
            c["show_icp"] = gui.add_checkbox("Show ICP pose instead of fine", False)
            c["show_icp"].on_update(lambda _: app.set_view(show_icp=bool(c["show_icp"].value)))

    # ---- updates from the app ------------------------------------------------------------------
    def show_stage(self, index: int) -> None:
        label = APP_STAGES[index].label
        if self.selector.value != label:
            self.selector.value = label
        for k, f in self.folders.items():
            f.visible = k == index

    def show_snapshot(self, snap: Snapshot, stage_index: int) -> None:
        """Status line per stage, message, Run button state, view-control ranges."""
        warned = stage_warnings(snap) if not snap.busy else {}
        parts = []
        for s in APP_STAGES:
            st = snap.status(s.pipeline_stage)
            # Done but implausible (e.g. an SVD transform that turns a scan upside down): not a ✓.
            mark = "⚠" if s.pipeline_stage in warned and FIRST_APP_STAGE[s.pipeline_stage] is s else _STATUS_ICON[st]
            name = f"**{s.index} {s.title}**" if s.index == stage_index else f"{s.index} {s.title}"
            parts.append(f"{mark} {name}")
        self.status_md.content = " · ".join(parts)
        self.run_button.disabled = snap.busy
        lines = []
        if snap.message:
            lines.append(f"**⚠ {snap.message}**" if snap.error else snap.message)
        elif not snap.busy:
            failed = [s for s in STAGES if snap.status(s) == "failed"]
            if failed:
                why = snap.crashed.get(failed[0]) or snap.outputs[failed[0]].message
                lines.append(f"**⚠ {failed[0]} failed:** {why}")
        lines += [f"**⚠** {w}" for ws in warned.values() for w in ws]
        self.message_md.content = "\n\n".join(lines)
        if not snap.busy:
            # At rest the bar shows how much of the pipeline is up to date (a failure stops it there).
            self.progress.value = 100.0 * sum(snap.status(s) == "done" for s in STAGES) / len(STAGES)
            self.progress.animated = False
        else:
            self.progress.animated = True
        # Ranges of the view controls follow the results.
        proj = snap.output("projection")
        if proj is not None and proj.items:
            n = max(len(getattr(s, "angles_deg", ())) for s in proj.items)
            sl = self.view_controls["projection_step"]
            if n > 1 and sl.max != n - 1:
                zero = next((k for k, a in enumerate(proj.items[0].angles_deg) if abs(a) < 1e-9), 0)
                sl.max = n - 1
                sl.value = min(zero, n - 1)
        pairs = [f"{s.name} → {snap.scans[0].name}" for s in snap.scans[1:]] or ["(no target scan)"]
        for key, h in self.view_controls.items():
            if key.startswith("target") and tuple(h.options) != tuple(pairs):
                h.options = pairs
        match = snap.output("matching")
        if match is not None and match.items:
            t = min(self.app.view.target, len(match.items) - 1)
            n = len(getattr(match.items[t], "pairs", ()) or ())
            sl = self.view_controls["match_pair"]
            if n > 1 and sl.max != n - 1:
                sl.max = n - 1
            sl.disabled = n <= 1

    def show_progress(self, fraction: float, text: str) -> None:
        self.progress.value = float(min(max(fraction, 0.0), 1.0) * 100.0)
        self.progress_text.content = f"*{text}*" if text else ""

    def sync_params(self, params: Any) -> None:
        for w in self.sections.values():
            w.sync(params)
