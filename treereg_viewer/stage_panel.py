"""The top of the control panel: stage selector, Previous/Next, Run, progress and messages; and
the "Stage" tab with one folder per stage (its explanation, view controls and parameters).

Only the current stage's folder is visible, so the panel reads like a page of a lesson. Each
browser tab has its own StagePanel: its controls show that tab's ViewState; the parameters are
shared (every tab's inputs show the parameters in force).
"""

from __future__ import annotations

import threading
from typing import Any, Iterator, TypeVar

import viser

from treereg_core.stages import stage as core_stage

from .actions import AppActions
from .checks import stage_warnings
from .controller import Snapshot
from .draw.before import has_before
from .labels import VERDICT_MARKS
from .param_widgets import SectionWidgets
from .stages import STAGE_NAMES, by_label, label, stage_of
from .stages.base import StageControls, TargetControl
from .text import md
from .view_state import ViewState

C = TypeVar("C", bound=StageControls)

#: The Run button under each stage folder's parameters.
RUN_BELOW = "Run with these parameters"

_STATUS_ICON = {"done": "✓", "failed": "✗", "stale": "○", "running": "…"}


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
    return "\n\n**Scans:** " + " · ".join(f"{VERDICT_MARKS.get(pl.verdict, '?')} {i + 1} {md(s.name)}"
                                           for i, (s, pl) in enumerate(zip(snap.scans, graph.items)))


class StagePanel:
    """Navigation, run controls and the per-stage folders of one viewer."""

    def __init__(self, gui: viser.GuiApi, app: AppActions) -> None:
        self.app = app
        self.gui = gui
        # Set while this panel puts values into its own controls (on the thread doing so only: a
        # person's change arriving meanwhile on another thread is not swallowed).
        self._local = threading.local()
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
        # Before and after: shown once the stage has a run before to compare with (`draw.before`).
        self.before_box = gui.add_checkbox("Previous run", False, visible=False,
                                           hint="Draw this stage's result from before the last change of its "
                                           "parameters; untick for the latest. The panel lists what changed.")
        self.before_box.on_update(lambda _: self.set_view(show_before=bool(self.before_box.value)))
        self.progress = gui.add_progress_bar(0.0, animated=False)
        self.progress_text = gui.add_markdown("")
        # Below the buttons: the stages' status grows by a line as a run goes on (the verdicts), and
        # above them it moved Next under a person's pointer (a click aimed at it missed).
        self.status_md = gui.add_markdown("")
        self.message_md = gui.add_markdown("")
        self.selector.on_update(lambda _: self.quiet or app.select_stage(by_label(self.selector.value)))
        self.step.on_click(lambda e: app.step_stage(-1 if e.target.value == "Previous" else 1))
        self.run_button.on_click(lambda _: app.run_current())

        # Folders, filled by `build_folders` inside the "Stage" tab.
        self.folders: dict[str, Any] = {}
        self.sections: dict[str, SectionWidgets] = {}
        # Each stage's view controls (`treereg_viewer/stages/<name>.py` makes them), in its folder's order.
        self.controls: dict[str, tuple[StageControls, ...]] = {}
        self.run_below: list[Any] = []  # the Run buttons under each folder's parameters
        #: While the tab follows a presenter its parameters and Run are the presenter's (`set_read_only`).
        self.read_only = False

    def build_folders(self, gui: viser.GuiApi) -> None:
        """One folder per stage: explanation, view controls, then its parameter sections."""
        app = self.app
        params = app.controller.params
        for name in STAGE_NAMES:
            folder = gui.add_folder(label(name), visible=name == STAGE_NAMES[0])
            self.folders[name] = folder
            with folder:
                stage = stage_of(name)
                gui.add_markdown(stage.view.explanation or core_stage(name).summary)
                self.controls[name] = tuple(make(gui, self, name) for make in stage.controls)
                own = [s for s in core_stage(name).sections if s not in self.sections]
                for section in own:  # a section read by several stages is edited where it belongs
                    with gui.add_folder(f"Parameters: {section}", expand_by_default=True):
                        self.sections[section] = SectionWidgets(gui, section, params, app.on_param_change)
                if own:
                    # Under the parameters too: the Run at the top scrolls out of view while one far
                    # down is edited (a 720 px high window).
                    button = gui.add_button(RUN_BELOW, icon=viser.Icon.PLAYER_PLAY, color="green",
                                            hint="Run this stage and the ones after it with the parameters above.")
                    button.on_click(lambda _: app.run_current())
                    self.run_below.append(button)

    @property
    def quiet(self) -> bool:
        """True while this panel puts values into its own controls (on this thread)."""
        return getattr(self._local, "quiet", False)

    def set_view(self, **changes: Any) -> None:
        if not self.quiet:
            self.app.set_view(**changes)

    def all_controls(self) -> Iterator[StageControls]:
        return (c for cs in self.controls.values() for c in cs)

    def control(self, stage: str, kind: type[C]) -> C:
        """Stage `stage`'s controls of type `kind` (e.g. its `TargetControl`)."""
        return next(c for c in self.controls[stage] if isinstance(c, kind))

    def show_target(self, pair: str) -> None:
        """One stage's "Pair" list picked `pair`: every stage's list shows it."""
        for c in self.all_controls():
            if isinstance(c, TargetControl):
                c.show_choice(pair)

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
        self._local.quiet = True
        try:
            self.show_stage(view.stage)
            self._local.quiet = True
            for c in self.all_controls():
                c.show_view(view, snap)
        finally:
            self._local.quiet = False
        self.refresh_focus(snap, view)

    def refresh_focus(self, snap: Snapshot, view: ViewState) -> None:
        """The "Frame a fit" lists follow the fits tables (their pair and the rejected-fits switch)."""
        self._local.quiet = True
        try:
            for c in self.all_controls():
                c.refresh_focus(snap, view)
        finally:
            self._local.quiet = False

    def show_snapshot(self, snap: Snapshot, view: ViewState) -> None:
        """Status line per stage, message, Run button state, view-control ranges."""
        warned = stage_warnings(snap) if not snap.busy else {}
        self.status_md.content = status_line(snap, view.stage, warned) + verdict_line(snap)
        self.run_button.disabled = snap.busy or self.read_only
        for button in self.run_below:
            button.disabled = snap.busy or self.read_only
        lines = []
        if snap.message:
            lines.append(f"**⚠ {md(snap.message)}**" if snap.error else md(snap.message))
        elif not snap.busy:
            failed = [s for s in STAGE_NAMES if snap.status(s) == "failed"]
            if failed:
                why = snap.crashed.get(failed[0]) or snap.outputs[failed[0]].message
                lines.append(f"**⚠ {label(failed[0])} failed:** {md(why)}")
        lines += [w for ws in warned.values() for w in ws]  # each with its mark (`checks.stage_warnings`)
        self.message_md.content = "\n\n".join(lines)
        if not snap.busy:
            # At rest the bar shows how much of the pipeline is up to date (a failure stops it there),
            # and says so: a part-full bar must not read as a run that hangs.
            # A stage that failed ran for these inputs too: counted as run, and its failures said.
            done = sum(snap.status(s) == "done" for s in STAGE_NAMES)
            failed = [s for s in STAGE_NAMES if snap.status(s) == "failed"]
            ran = done + len(failed)
            self.progress.value = 100.0 * ran / len(STAGE_NAMES)
            self.progress.animated = False
            failures = f" ({len(failed)} failed)" if failed else ""
            self.progress_text.content = (f"*{ran} of {len(STAGE_NAMES)} stages run for these parameters{failures}; "
                                          "nothing is running.*" if done < len(STAGE_NAMES) else "")
        else:
            self.progress.animated = True
        # Ranges of the view controls follow the results (counted from 1).
        self._local.quiet = True
        try:
            self.before_box.visible = has_before(snap, view.stage)
            if self.before_box.value != view.show_before:
                self.before_box.value = view.show_before
            for c in self.all_controls():
                c.show_snapshot(snap, view)
        finally:
            self._local.quiet = False
        self.refresh_focus(snap, view)

    def show_progress(self, fraction: float, text: str) -> None:
        self.progress.value = float(min(max(fraction, 0.0), 1.0) * 100.0)
        self.progress_text.content = f"*{md(text)}*" if text else ""

    def flush_edits(self) -> None:
        """Apply parameter values still being typed (Run, an export: they must see what the user typed)."""
        for w in self.sections.values():
            w.flush()

    def set_read_only(self, on: bool, busy: bool) -> None:
        """Parameters, Run and "Run when stepping" greyed out (a tab that follows the presenter) or
        usable again."""
        self.read_only = on
        for w in self.sections.values():
            w.set_disabled(on)
        self.run_button.disabled = busy or on
        for button in self.run_below:
            button.disabled = busy or on
        self.auto_run.disabled = on

    def sync_params(self, params: Any) -> None:
        for w in self.sections.values():
            w.sync(params)
