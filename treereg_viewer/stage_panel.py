"""The top of the control panel: stage selector, Previous/Next, Run, progress and messages; and
the "Stage" tab with one folder per stage (its explanation, view controls and parameters).

Only the current stage's folder is visible, so the panel reads like a page of a lesson.
"""

from __future__ import annotations

from typing import Any

import viser

from treereg_core.stages import stage as core_stage

from .actions import AppActions
from .checks import stage_warnings
from .controller import Snapshot
from .param_widgets import SectionWidgets
from .stages import STAGE_NAMES, by_label, label, view_of

_STATUS_ICON = {"done": "✓", "failed": "✗", "stale": "○", "running": "…"}


class StagePanel:
    """Navigation, run controls and the per-stage folders."""

    def __init__(self, gui: viser.GuiApi, app: AppActions) -> None:
        self.app = app
        self.gui = gui
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
        self.selector.on_update(lambda _: app.select_stage(by_label(self.selector.value)))
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

    def _view_controls(self, gui: viser.GuiApi, name: str) -> None:
        app, c = self.app, self.view_controls
        wanted = view_of(name).controls
        if "projection_step" in wanted:
            c["projection_step"] = gui.add_slider("Rotation step", 0, 1, 1, 0,
                                                  hint="Walk the rotation sequence (index; the angle is shown in the panel).")
            c["projection_step"].on_update(lambda _: app.set_view(projection_step=int(c["projection_step"].value)))
            c["projection_3d"] = gui.add_checkbox("Show rotated clouds in 3-D", False)
            c["projection_3d"].on_update(lambda _: app.set_view(projection_3d=bool(c["projection_3d"].value)))
        if "target" in wanted:
            key = f"target_{name}"
            c[key] = gui.add_dropdown("Pair", ["scan2 → scan1"], hint="Which target scan the panel details.")
            c[key].on_update(lambda _, key=key: app.select_target(c[key].value))
        if "match_pair" in wanted:
            c["match_pair"] = gui.add_slider("Image pair", 0, 1, 1, 0, hint="Which chosen image pair's ORB matches to show.")
            c["match_pair"].on_update(lambda _: app.set_view(match_pair=int(c["match_pair"].value)))
        if "show_icp" in wanted:
            c["show_icp"] = gui.add_checkbox("Show ICP pose instead of fine", False)
            c["show_icp"].on_update(lambda _: app.set_view(show_icp=bool(c["show_icp"].value)))

    # ---- updates from the app ------------------------------------------------------------------
    def show_stage(self, name: str) -> None:
        text = label(name)
        if self.selector.value != text:
            self.selector.value = text
        for k, f in self.folders.items():
            f.visible = k == name

    def show_snapshot(self, snap: Snapshot, current: str) -> None:
        """Status line per stage, message, Run button state, view-control ranges."""
        warned = stage_warnings(snap) if not snap.busy else {}
        parts = []
        for name in STAGE_NAMES:
            # Done but implausible (e.g. an SVD transform that turns a scan upside down): not a ✓.
            mark = "⚠" if name in warned else _STATUS_ICON[snap.status(name)]
            text = f"**{label(name)}**" if name == current else label(name)
            parts.append(f"{mark} {text}")
        self.status_md.content = " · ".join(parts)
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

    def flush_edits(self) -> None:
        """Apply parameter values still being typed (Run, an export: they must see what the user typed)."""
        for w in self.sections.values():
            w.flush()

    def sync_params(self, params: Any) -> None:
        for w in self.sections.values():
            w.sync(params)
