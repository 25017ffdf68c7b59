"""One viewer: what one browser tab sees and drives.

Every tab has its own stage, pair, sliders, cross-section and camera (its `ViewState`), its own
GUI and scene (viser's per-client `client.gui` / `client.scene`) and its own drawing thread; the
computation (the `Controller`'s pipeline) and its results are shared through the app. A viewer
can present ("others follow me": the tabs that follow get its stage, view choices and camera) or
follow the presenter, and can walk the guided tour. While it follows, its parameters and Run are
greyed out (the presenter's); a change of the parameters made in another tab is shown, naming the
tab and the change, with an Undo. Projector mode scales text, 3-D labels, lines and points for a
room; PageDown / PageUp (a clicker), and → ← Space in projector mode or the tour, step (`keys`).

Without a browser (scripts, tests) a viewer can also be built on the server's own GUI and scene;
every tab then sees that one viewer.
"""

from __future__ import annotations

import logging
import math
import threading
from contextlib import AbstractContextManager
from dataclasses import fields, replace
from pathlib import Path
from typing import Any, Callable

import numpy as np
import viser

from treereg_core.errors import ConfigError
from treereg_core.geometry.picking import nearest_to_ray
from treereg_core.params import Params

from . import camera
from .actions import AppHost
from .align import AlignPanel
from .controller import Controller, Snapshot
from .derived import default_height, prepared_scans
from .drawer import Drawer
from .export_panel import ExportPanel
from .keys import StepKeys
from .param_widgets import format_text
from .text import md
from .draw.common import display_subset
from .draw.before import drawn
from .draw.fits import focus_rows, pinned_slice
from .scan_panel import ScanPanel
from .stage_panel import StagePanel
from .stages import STAGE_NAMES, registered, section_available
from .stages.base import pair_labels
from .tour import STEPS, TourPanel
from .view_panel import ViewPanel
from .view_state import ALL_SLICES, ViewState

log = logging.getLogger(__name__)

#: Width of the docked control panel (viser's "large" control width) and of the image panel, in a
#: wide window and in a narrow one (below `NARROW_WINDOW_PX` the panels narrow so that the 3-D view keeps at
#: least half of a 1280 px window).
CONTROL_WIDTH_PX = 400
PANEL_WIDTH_PX = 560
NARROW_CONTROL_PX = 300
NARROW_PANEL_PX = 330
NARROW_WINDOW_PX = 1500
#: What a follower takes over from the presenter: everything it looks at (not its display sizes).
FOLLOWED = tuple(f.name for f in fields(ViewState) if f.name not in ("point_size", "max_points", "hidden_scans",
                                                                    "show_stations", "tour_step", "align_scan",
                                                                    "scale"))
#: Projector mode: text, 3-D labels, lines and points this many times their size (issue 32: at least 1.6).
PROJECTOR_SCALE = 1.6
#: Projector mode's text: viser sizes its GUI in rem of the page's font size, 92.5 % of the browser's
#: (its App.css.ts): at least 1.6 times that (149 %). Our own constant markup (no text from outside),
#: shown as the tables' CSS is (`view_panel.TABLE_CSS`); the element hidden, the style goes with it.
#: A table's words may break anywhere: at this size a column of long words would not fit its panel.
PROJECTOR_CSS = (f"<style>html {{font-size: {math.ceil(92.5 * PROJECTOR_SCALE)}% !important;}} "
                 ".treereg-tables td, .treereg-tables th {overflow-wrap: anywhere !important;}</style>")


def narrow_window(cam: Any, panels_px: int) -> int | None:
    """The window's width when a tab's camera report says it is narrow (below NARROW_WINDOW_PX), else
    None. A report may come before the panels are docked (the canvas then the whole window:
    landscape) or after (between them: the window less both panels, `panels_px`); either reading of
    a narrow window counts."""
    width = int(getattr(cam, "image_width", 0) or 0)
    height = int(getattr(cam, "image_height", 0) or 0)
    if not width:
        return None
    docked = width + panels_px
    whole = width if height and width > 1.2 * height else None
    if docked < NARROW_WINDOW_PX or (whole is not None and whole < NARROW_WINDOW_PX):
        return whole or docked
    return None


class Viewer:
    """One tab's view of the shared app (implements `actions.AppActions` for its panels).

    Parameters
    ----------
    host
        The app: controller, shared caches, presenter.
    gui, scene
        Where this viewer builds its controls and draws: a client's (one tab) or the server's (all tabs).
    client
        The tab's connection (None for a viewer on the server's own GUI).
    atomic
        Groups one redraw's messages (the client's or the server's `atomic`).
    """

    def __init__(self, host: AppHost, gui: viser.GuiApi, scene: viser.SceneApi, client: Any | None,
                 atomic: Callable[[], AbstractContextManager[Any]], name: str = "this tab") -> None:
        self.host = host
        self.name = name  # "tab 3": how other tabs name it (ours, never text from outside)
        self.read_only = False  # following the presenter: parameters and runs are the presenter's
        self._undo_fn: Callable[[Viewer], None] | None = None
        self.controller: Controller = host.controller
        self.client = client
        self.gui = gui
        self.scene = scene
        self._lock = threading.Lock()
        self._view = ViewState()
        self._last_progress = 0.0
        self._closed = False
        self.following = False
        self._window_px: int | None = None
        self._view_aspect: float | None = None  # the 3-D view's width / height, as the tab's camera reports it
        self._fov_y: float | None = None
        self._tour_nodes: list[Any] = []

        self.panel = ViewPanel(gui, self.set_view, width=PANEL_WIDTH_PX)
        # Docked, not floating: a floating control panel covers the right third of the scene, where
        # the trees of the other scans stand; docked, the scene is the free space between the panels.
        gui.main_panel.dock_right()
        gui.main_panel.set_width(CONTROL_WIDTH_PX)
        gui.add_markdown("**treereg** · marker-free registration of single-tree TLS scans (rotating projection, "
                         "then stem and branch centres)")
        self.projector_css = gui.add_markdown(PROJECTOR_CSS, visible=False)
        self.keys = StepKeys(gui, self.key_step)
        self.tour = TourPanel(gui, self.tour_go)
        self.follow_md = gui.add_markdown("", visible=False)
        self.follow_box = gui.add_checkbox("Follow the presenter", False, visible=False,
                                           hint="Untick to look around on your own; tick to follow again.")
        self.follow_box.on_update(lambda _: self._set_following(bool(self.follow_box.value)))
        # A change of the shared parameters made in another tab: what and by whom, and an Undo.
        self.changed_md = gui.add_markdown("", visible=False)
        self.undo_button = gui.add_button("Undo that change", icon=viser.Icon.ARROW_BACK_UP, color="gray", visible=False,
                                          hint="Put the parameters back as they were before that change.")
        self.undo_button.on_click(lambda _: self._undo())
        self.stages = StagePanel(gui, self)
        tabs = gui.add_tab_group()
        with tabs.add_tab("Stage", viser.Icon.LIST_NUMBERS):
            self.stages.build_folders(gui)
        with tabs.add_tab("Scans", viser.Icon.TREE):
            self.scans = ScanPanel(gui, self)
        with tabs.add_tab("Align", viser.Icon.HAND_CLICK):
            self.align = AlignPanel(gui, scene, self.controller, lambda name: self.set_view(align_scan=name), self._look,
                                    refined=lambda: self.select_stage("graph"), uploads=host.uploads,
                                    send_file=self.send_file)
        with tabs.add_tab("Files", viser.Icon.FILE_EXPORT):
            self.files = ExportPanel(gui, self)
        with tabs.add_tab("Teach", viser.Icon.SCHOOL):
            gui.add_markdown("**Guided tour:** the stages in order, each with the paper's reasoning and one thing to "
                             "try. **Present:** the other open tabs (a class on this server) follow your stage, "
                             "view and camera until they untick *Follow the presenter*; while they follow, the "
                             f"parameters and Run are yours. This tab is **{name}**. **Keys:** PageDown / PageUp "
                             "(a clicker) step the stages, or the tour's steps; in projector mode and the tour "
                             "also → ← and Space.")
            self.tour_button = gui.add_button("Start the tour", icon=viser.Icon.PLAYER_PLAY, color="blue")
            self.tour_button.on_click(lambda _: self.tour_go(0))
            self.present_box = gui.add_checkbox("Others follow me", False,
                                                hint="Present: every other tab follows this one's stage, view and camera; "
                                                "only the presenter hands the lead over.")
            self.present_box.on_update(lambda _: self._present(bool(self.present_box.value)))
            self.lead_md = gui.add_markdown("", visible=False)
            self.hand_to = gui.add_dropdown("Hand the lead to", ("no other tab",), visible=False,
                                            hint="The tab that presents next; this one then follows it.")
            self.hand_button = gui.add_button("Hand over the lead", icon=viser.Icon.ARROWS_EXCHANGE, color="gray",
                                              visible=False, disabled=True)
            self.hand_button.on_click(lambda _: host.hand_over(self, str(self.hand_to.value)))
            self.projector_box = gui.add_checkbox(
                "Projector mode", False, hint=f"Text, 3-D labels, lines and points {PROJECTOR_SCALE:g} times larger, "
                "for a room; → ← and Space step too.")
            self.projector_box.on_update(lambda _: self.set_projector(bool(self.projector_box.value)))

        self.drawer = Drawer(scene, atomic, self.panel, lambda: self.controller.snapshot, lambda: self.view,
                             host.derived, on_error=lambda msg: self.controller.note(msg, error=True),
                             give_way=self.controller.give_way if client is not None else None)  # a browser tab
        scene.on_click()(self._on_scene_click)
        if client is not None:
            client.camera.on_update(self._on_camera)
            try:  # the tab may have reported its camera while this viewer was being built
                self._on_camera(client.camera)
            except (AssertionError, AttributeError, ValueError):
                pass  # not reported yet: its first report comes to the callback
        if getattr(host, "projector", False):  # `treereg view --projector`
            self.set_projector(True)
        self.on_snapshot(self.controller.snapshot)

    # ---- the view -------------------------------------------------------------------------------
    @property
    def view(self) -> ViewState:
        return self._view

    @property
    def out_dir(self) -> Path | None:
        return self.host.out_dir

    @property
    def uploads(self) -> Any:
        return self.host.uploads

    @property
    def max_upload_bytes(self) -> int:
        return self.host.max_upload_bytes

    @property
    def max_upload_points(self) -> int:
        return self.host.max_upload_points

    def set_view(self, **changes: Any) -> None:
        """Record display choices and ask for a redraw (callbacks call this; it returns at once)."""
        if "stage" in changes and changes["stage"] != self._view.stage and "focus_section" not in changes:
            changes["focus_section"] = None  # a fits row belongs to its stage's table
        if "target" in changes and changes["target"] != self._view.target:
            changes.setdefault("branch", None)  # branches are a pair's
            if self._view.slice_shown != ALL_SLICES:
                changes.setdefault("slice_shown", None)  # and so are slices: the new pair's busiest
        with self._lock:
            new = replace(self._view, **changes)
            new = replace(new, slice_shown=_pinned(self.controller.snapshot, new))
            changed = new != self._view
            self._view = new
        if changed:
            self.drawer.request()
            if any(k in changes for k in ("target", "show_rejected", "stage", "focus_section")):
                self.stages.refresh_focus(self.controller.snapshot, new)
            if self.host.presenter is self:
                self.host.broadcast(self)

    def select_stage(self, name: str) -> None:
        before = self.view.stage
        # The stage's folder first: whatever redraws after it, the selector and the folder shown agree
        # (a full suite once showed 3 Matching selected over the Scans stage's folder).
        self.stages.show_stage(name)
        self.set_view(stage=name)
        if registered(before) != registered(name) or (name in camera.SLICE_STAGES) != (before in camera.SLICE_STAGES):
            # Between the scattered scans (own frames) and the registered tree the content moves, and
            # the Arcs, Fits and Fine stages show one slice close up: follow it. Within a group the
            # camera stays where the user put it.
            self.frame_view()
        snap = self.controller.snapshot
        self.stages.show_snapshot(snap, self.view)
        if self.stages.auto_run.value and not self.read_only and snap.status(name) == "stale" and len(snap.scans) >= 2 \
                and not any(snap.status(s) == "failed" for s in STAGE_NAMES[: STAGE_NAMES.index(name)]):
            self.controller.request_run(name)

    def step_stage(self, delta: int) -> None:
        i = int(np.clip(STAGE_NAMES.index(self.view.stage) + delta, 0, len(STAGE_NAMES) - 1))
        self.select_stage(STAGE_NAMES[i])

    def select_target(self, label: str) -> None:
        snap = self.controller.snapshot
        labels = pair_labels(snap)
        if label in labels:
            self.set_view(target=labels.index(label), match_pair=0)
            self.stages.show_target(label)

    def set_scan_visible(self, name: str, visible: bool) -> None:
        hidden = set(self.view.hidden_scans)
        (hidden.discard if visible else hidden.add)(name)
        self.set_view(hidden_scans=frozenset(hidden))

    def focus_section(self, stage: str, row_label: str) -> None:
        """A row of the fits table picked: outline that fit, look at it closely, cut the cross-section there."""
        rows = focus_rows(self.controller.snapshot, stage, self.view)
        k = next((i for i, r in enumerate(rows) if r.label == row_label), None)
        if k is None:
            self.set_view(focus_section=None)
            return
        s = rows[k].section
        self.set_view(focus_section=k, section_height=float(s.height_m), branch=None)
        self._look(camera.frame_point(self.controller.snapshot, s.centre_m, s.radius_m))

    # ---- actions ---------------------------------------------------------------------------------
    def run_current(self) -> None:
        """Run: bring this stage and the ones after it up to date, reusing earlier results.

        Stale stages run; when nothing from here on is stale, this stage is re-run (and so are the
        later ones, which depend on it). Not while the tab follows the presenter (its runs are the
        presenter's; the buttons are greyed out, and a click sent anyway changes nothing).
        """
        if self.read_only:
            self._tell_tab("Following the presenter: Run is the presenter's. Untick *Follow the presenter* first.")
            return
        self.flush_edits()
        snap = self.controller.snapshot
        stage = self.view.stage
        later = STAGE_NAMES[STAGE_NAMES.index(stage):]
        anything_stale = any(snap.status(s) != "done" for s in later) or self.controller.params != snap.params
        self.controller.request_run(STAGE_NAMES[-1], rerun_from=None if anything_stale else stage)

    def flush_edits(self) -> None:
        """Apply parameter values still being typed (see param_widgets.SETTLE_S)."""
        self.stages.flush_edits()

    def on_param_change(self, section: str, name: str, value: Any) -> str | None:
        if self.read_only:  # greyed out while following; a value sent anyway changes nothing
            self.stages.sections[section].sync(self.controller.params)
            return "following the presenter: the parameters are the presenter's"
        before = self.controller.params
        try:
            after = self.controller.set_param(section, name, value)
        except ConfigError as e:
            # Told this tab at once: the worker's message line waits for the stage it is running
            # (seconds to minutes), and nothing changed for the other tabs.
            self._tell_tab(str(e), error=True)
            self.stages.sections[section].sync(self.controller.params)  # show what is in force
            return str(e)
        self.stages.sections[section].show_in_force(name, self.controller.params)
        old, new = getattr(getattr(before, section), name), getattr(getattr(after, section), name)
        if old != new:
            self._report(before, after, f"{section}.{name} {format_text(old) or 'none'} → {format_text(new) or 'none'}")
        return None

    def load_params(self, params: Params, source: str, note: str = "") -> None:
        if self.read_only:
            self._tell_tab("Following the presenter: the parameters are the presenter's. Untick *Follow the "
                           "presenter* first.")
            return
        before = self.controller.params
        self.controller.set_params(params)
        self.stages.sync_params(params)
        self.controller.note(f"Parameters from {source} in force; press Run to apply them. {note}".rstrip())
        if params != before:
            self._report(before, params, f"the parameters from {source}")

    def choose_hypothesis(self, pair: str, candidate: str | None) -> None:
        """A hypothesis picked by hand for `pair` (None: automatic again); the other tabs are told, and
        can undo it. Not while the tab follows the presenter."""
        if self.read_only:
            return
        before = self.controller.snapshot.choices.get(pair)
        self.controller.choose(pair, candidate)
        what = f"the hypothesis of {pair} {before or 'automatic'} → {candidate or 'automatic'}"
        by = self.name

        def undo(v: Viewer) -> None:
            v.choose_hypothesis(pair, before)
            v.controller.note(f"Undone: {what} (by {by}).")

        self.host.changed_by(self, what, undo)

    # ---- changes of the shared parameters, told to the other tabs --------------------------------
    def _report(self, before: Params, after: Params, what: str) -> None:
        """This tab changed the parameters from `before` to `after`: the other tabs are told, and
        can undo it (while nothing has changed them since)."""
        by = self.name

        def undo(v: Viewer) -> None:
            if v.controller.params != after:
                v._tell_tab("The parameters changed again since; nothing was undone.")
                return
            v.controller.set_params(before)
            v.stages.sync_params(before)
            v.controller.note(f"Undone: {what} (by {by}).")
            v._report(after, before, f"undid {by}'s change ({what})")

        self.host.changed_by(self, what, undo)

    def show_changed_elsewhere(self, by: str, what: str, undo: Callable[[Viewer], None]) -> None:
        """Another tab changed the parameters: say which and what, and offer the undo (not to a tab
        that follows: its parameters are the presenter's)."""
        self._undo_fn = undo
        self.changed_md.content = f"**Changed by {md(by)}:** {md(what)}."
        self.changed_md.visible = True
        self.undo_button.visible = not self.read_only

    def _undo(self) -> None:
        fn, self._undo_fn = self._undo_fn, None
        self.changed_md.visible = False
        self.undo_button.visible = False
        if fn is not None and not self.read_only:
            fn(self)

    def _tell_tab(self, text: str, error: bool = False) -> None:
        """A word for this tab only (a notification; viser shows its body as text, not markup), or the
        app's message line without a browser."""
        if self.client is None:
            self.controller.note(text, error=error)
            return
        try:
            self.client.add_notification("treereg", text, auto_close_seconds=10.0 if error else 6.0,
                                         color="red" if error else None)
        except Exception:
            log.debug("could not notify tab %s", self.name)

    def send_file(self, client: Any, filename: str, data: bytes) -> None:
        """A one-click browser download for the tab that asked."""
        self.host.send_file(client if client is not None else self.client, filename, data)

    # ---- camera ------------------------------------------------------------------------------------
    def _cameras(self) -> list[Any]:
        if self.client is not None:
            return [self.client.camera]
        return [c.camera for c in self.host.server.get_clients().values()]

    def _look(self, pose: camera.CameraPose | None) -> None:
        if pose is None:
            return
        for cam in self._cameras():
            try:
                with cam.client.atomic():
                    # viser moves look_at along with position: set position first, then look_at.
                    cam.position = pose.position
                    cam.look_at = pose.look_at
            except (AssertionError, ValueError):  # a tab that has not reported its camera yet
                log.debug("camera not ready")

    def frame_view(self) -> None:
        """Point this tab's camera at what the current stage draws (the "Frame the view" button)."""
        self._look(camera.frame(self.controller.snapshot, self.view.stage, self.view, aspect=self._view_aspect,
                                fov_y_rad=self._fov_y or camera.FOV_Y_RAD))

    def _on_camera(self, cam: Any) -> None:
        # The tab's reports say how wide its 3-D view is: a narrow window (a 1280 x 720 laptop screen)
        # gets narrower panels, so the scene keeps at least half. A report may come before the panels
        # are docked (the canvas then the whole window: landscape) or after (between them: the window
        # less both panels); either reading of a narrow window narrows, and the panels then stay so.
        width = int(getattr(cam, "image_width", 0) or 0)
        height = int(getattr(cam, "image_height", 0) or 0)
        if width and height:
            self._view_aspect = width / height
            fov = float(getattr(cam, "fov", 0.0) or 0.0)
            self._fov_y = fov if 0.1 < fov < 3.0 else None
        if self._window_px is None and (narrow := narrow_window(cam, self.panel.width + CONTROL_WIDTH_PX)) is not None:
            self._window_px = narrow
            self.panel.set_width(NARROW_PANEL_PX)
            self.gui.main_panel.set_width(NARROW_CONTROL_PX)
        if self.host.presenter is self:
            self.host.camera_moved(self, cam)

    def follow_camera(self, position: Any, look_at: Any, up: Any) -> None:
        if self.client is None or not self.following:
            return
        try:
            with self.client.atomic():
                self.client.camera.up_direction = up
                self.client.camera.position = position
                self.client.camera.look_at = look_at
        except (AssertionError, ValueError):
            log.debug("camera of follower %s not ready", self.client.client_id)

    # ---- clicks in 3-D -----------------------------------------------------------------------------
    def _on_scene_click(self, event: Any) -> None:
        pick_clicked(self.pick, event)

    def pick(self, origin: np.ndarray, direction: np.ndarray) -> None:
        """A click in 3-D: on the Fits and Fine stages a fitted section picks its table row; on the
        Result stage a branch ring picks that branch's cross-section; anywhere on the registered tree
        the click sets the cross-section's height."""
        if self.align.pick(origin, direction):  # aligning a scan by hand: the click picks a point of a pair
            return
        snap = self.controller.snapshot
        view = self.view
        if not section_available(snap, view.stage):
            return
        if view.stage in ("sections", "fine"):
            rows = focus_rows(snap, view.stage, view)
            if rows:
                k = nearest_to_ray(np.array([r.section.centre_m for r in rows]), origin, direction, max_angle_deg=2.0)
                if k is not None:
                    self.focus_section(view.stage, rows[k].label)
                    return
        if view.stage == "evaluation":
            from .derived import evaluated_branches

            branches = evaluated_branches(snap, view.target)
            if branches:
                centres = np.array([b.ref_centres_m.mean(axis=0) for b in branches])
                k = nearest_to_ray(centres, origin, direction, max_angle_deg=2.0)
                if k is not None:
                    self.set_view(branch=k, panel="section")
                    return
        scans = prepared_scans(snap)
        if scans is None:
            return
        ref = scans[0].points
        pts = ref[display_subset(len(ref), 20_000, seed=3)]
        k = nearest_to_ray(pts, origin, direction, max_angle_deg=0.8)
        if k is not None:
            self.set_view(section_height=round(float(pts[k, 2]), 2), branch=None, panel="section")

    # ---- presenting and following -------------------------------------------------------------------
    def _present(self, on: bool) -> None:
        """"Others follow me" ticked or unticked; ticking is refused while another tab presents (only
        the presenter hands the lead over)."""
        if self.host.set_presenter(self, on):
            return
        presenter = self.host.presenter
        who = presenter.name if presenter is not None else "another tab"
        self.present_box.value = False
        self._tell_tab(f"{who} presents: only it can hand the lead over.")

    def show_presenter(self, presenter: Viewer | None) -> None:
        """A presenter started, stopped or handed over: offer (and by default start) following, or say
        who presents; the presenter itself gets the hand-over controls."""
        if presenter is None or presenter is self:
            if self.following:
                self.tour.show(self.view.tour_step)
            self.following = False
            self._set_read_only(False)
            self.follow_md.visible = False
            self.follow_box.visible = False
            self.lead_md.visible = False
            self.present_box.disabled = False
            mine = presenter is self
            if self.present_box.value != mine:
                self.present_box.value = mine
            self.hand_to.visible = mine
            self.hand_button.visible = mine
            return
        self.hand_to.visible = False
        self.hand_button.visible = False
        if self.present_box.value:  # someone else presents now
            self.present_box.value = False
        self.present_box.disabled = True
        self.lead_md.content = f"**{presenter.name} presents.** Only it can hand the lead over."
        self.lead_md.visible = True
        self.follow_md.content = (f"**Following {presenter.name}**, the presenter: its stage, view and camera. "
                                  "While you follow, the parameters and Run are the presenter's (greyed out); "
                                  "untick *Follow the presenter* to look around on your own.")
        self.follow_md.visible = True
        self.follow_box.visible = True
        self.follow_box.value = True
        self._set_following(True)

    def offer_tabs(self, names: list[str]) -> None:
        """The presenter's list of the tabs it can hand the lead to."""
        options = tuple(names) or ("no other tab",)
        if tuple(self.hand_to.options) != options:
            self.hand_to.options = options
        self.hand_button.disabled = not names

    def _set_read_only(self, on: bool) -> None:
        """Following: the parameters, Run, presets, loaded parameters, added scans and start poses are
        the presenter's (greyed out here; refused by the handlers too)."""
        self.read_only = on
        self.align.locked = on
        self.stages.set_read_only(on, self.controller.snapshot.busy)
        for h in (self.files.apply_preset, self.files.load_params, self.scans.upload, self.align.load_starts):
            if h.disabled != on:
                h.disabled = on
        self.undo_button.visible = self.changed_md.visible and self._undo_fn is not None and not on

    def _set_following(self, on: bool) -> None:
        was = self.following
        self.following = on and self.host.presenter is not None and self.host.presenter is not self
        self._set_read_only(self.following)
        if self.following:
            self.follow(self.host.presenter)
        elif was:  # on its own again: the presenter's tour card goes, this tab's own tour (if any) stays
            self.tour.show(self.view.tour_step)

    def follow(self, presenter: Viewer) -> None:
        """Take over what the presenter looks at, and show it in this tab's controls."""
        if not self.following:
            return
        theirs = presenter.view
        before = self.view
        with self._lock:
            self._view = replace(self._view, **{f: getattr(theirs, f) for f in FOLLOWED})
        snap = self.controller.snapshot
        self.stages.show_view(self.view, snap)
        self.stages.show_snapshot(snap, self.view)  # the stage list's bold entry is the stage shown
        self.tour.show(theirs.tour_step, following=True)  # the class reads the presenter's tour card
        self.drawer.request()
        if registered(before.stage) != registered(self.view.stage) and presenter.client is not None:
            try:
                cam = presenter.client.camera
                self.follow_camera(cam.position, cam.look_at, cam.up_direction)
            except (AssertionError, ValueError):
                pass

    # ---- keys and projector mode --------------------------------------------------------------------
    def key_step(self, delta: int) -> None:
        """A stepping key (`keys`): the tour's next or previous step while it runs, else the stage's.
        A tab that follows does not step: the presenter leads."""
        if self.following:
            return
        if self.tour.step is not None:
            self.tour.step_by(delta)
        else:
            self.step_stage(delta)

    def set_projector(self, on: bool) -> None:
        """Projector mode on or off: text (the page's CSS), 3-D labels, lines and points (the drawing's
        `ViewState.scale`) `PROJECTOR_SCALE` times larger; → ← and Space step too."""
        self.projector_css.visible = on
        if self.projector_box.value != on:
            self.projector_box.value = on
        self.keys.bind_all(on or self.view.tour_step is not None)
        self.set_view(scale=PROJECTOR_SCALE if on else 1.0)
        if self.view.tour_step is not None:
            self._highlight(STEPS[self.view.tour_step].highlight)

    # ---- the tour ---------------------------------------------------------------------------------
    def tour_go(self, step: int | None) -> None:
        """Go to tour step `step` (None ends the tour): stage, view, camera and highlight set."""
        self.tour.show(step)
        self._highlight(None)
        self.keys.bind_all(step is not None or self.view.scale != 1.0)
        if step is None:
            self.set_view(tour_step=None)
            return
        s = STEPS[step]
        snap = self.controller.snapshot
        changes = dict(s.view)
        self.set_view(tour_step=step, **changes)
        self.select_stage(s.stage)
        self.stages.show_view(self.view, snap)
        if s.camera == "trunk":
            h = default_height(snap, self.view.target)
            anchor = camera.trunk_anchor(snap, h)
            if anchor is not None:
                self._look(camera.frame_point(snap, anchor, 0.25))
        else:
            self.frame_view()
        self._highlight(s.highlight)

    def _highlight(self, what: str | None) -> None:
        """Labels in 3-D at what the tour step is about."""
        for h in self._tour_nodes:
            try:
                h.remove()
            except Exception:  # gone with its tab
                pass
        self._tour_nodes = []
        if not what:
            return
        snap = self.controller.snapshot
        if what == "trees":
            # Before registration every scan stands in its own frame: name each tree above its top.
            prep = snap.output("prepare")
            for i, scan in enumerate(snap.scans):
                item = prep.items[i] if prep is not None and i < len(prep.items) else None
                pts = item.scan.points if getattr(item, "scan", None) is not None else scan.points
                top = np.array([*np.median(pts[:, :2], axis=0), float(np.quantile(pts[:, 2], 0.995)) + 0.6])
                self._tour_nodes.append(self.scene.add_label(
                    f"/tour/tree{i}", f"▼ scan {i + 1}", font_screen_scale=self.view.scale,
                    position=tuple(float(v) for v in top)))
        elif what == "trunk":
            anchor = camera.trunk_anchor(snap, default_height(snap, self.view.target))
            if anchor is not None:
                self._tour_nodes.append(self.scene.add_label(
                    "/tour/label", "◀ the trunk slice of the cross-section", font_screen_scale=self.view.scale,
                    position=tuple(float(v) for v in anchor + np.array([0.0, 0.0, 0.35]))))

    # ---- from the worker (which never calls viser: the drawing thread shows its news) ---------------
    def on_snapshot(self, snap: Snapshot) -> None:
        if not self._closed:
            self.drawer.post("snapshot", lambda: self._show_snapshot(snap))

    def _show_snapshot(self, snap: Snapshot) -> None:
        if self._closed:
            return
        # The slice shown is pinned once known, and kept while the pair has it (a re-run draws the same
        # slice, the list says so, the framing frames it); the run before is shown only until a change.
        view = self.view
        pinned = _pinned(snap, view)
        before = view.show_before and snap.output(view.stage) is not None
        if pinned != view.slice_shown or before != view.show_before:
            self.set_view(slice_shown=pinned, show_before=before)
        self.stages.show_snapshot(snap, self.view)
        self.scans.show_snapshot(snap)
        self.align.show_snapshot(snap)
        self.stages.sync_params(self.controller.params)  # another tab may have changed them
        self.drawer.request()

    def on_progress(self, fraction: float, text: str) -> None:
        import time

        now = time.perf_counter()
        if fraction < 1.0 and now - self._last_progress < 0.1:  # ~10 updates a second are plenty
            return
        self._last_progress = now
        self.drawer.post("progress", lambda: self.stages.show_progress(fraction, text))

    def close(self) -> None:
        self._closed = True
        self.drawer.close()
        for button in (self.scans.upload, self.files.load_params, self.align.load_starts):
            self.host.uploads.remove(button)


def _pinned(snap: Snapshot, view: ViewState) -> int | None:
    """`ViewState.slice_shown` as it should be (`draw.fits.pinned_slice`): the busiest slice is chosen
    when the view is on a stage that shows one slice (what the person sees first), not while they look
    elsewhere during a run (the busiest by arcs is not the busiest by fits)."""
    if view.slice_shown is None and view.stage not in camera.SLICE_STAGES:
        return None
    return pinned_slice(drawn(snap, view)[0], view)


def pick_clicked(pick: Callable[[np.ndarray, np.ndarray], None], event: Any) -> None:
    """A click in 3-D handed to a tab's `pick` as its ray; a click must never take the tab down."""
    try:
        pick(np.asarray(event.ray_origin, float), np.asarray(event.ray_direction, float))
    except Exception:
        log.exception("pick failed")
