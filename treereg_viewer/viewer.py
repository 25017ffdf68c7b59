"""One viewer: what one browser tab sees and drives.

Every tab has its own stage, pair, sliders, cross-section and camera (its `ViewState`), its own
GUI and scene (viser's per-client `client.gui` / `client.scene`) and its own drawing thread; the
computation (the `Controller`'s pipeline) and its results are shared through the app. A viewer
can present ("others follow me": the tabs that follow get its stage, view choices and camera) or
follow the presenter, and can walk the guided tour.

Without a browser (scripts, tests) a viewer can also be built on the server's own GUI and scene;
every tab then sees that one viewer.
"""

from __future__ import annotations

import logging
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
                                                                    "show_stations", "tour_step", "align_scan"))


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
                 atomic: Callable[[], AbstractContextManager[Any]]) -> None:
        self.host = host
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
        self._tour_nodes: list[Any] = []

        self.panel = ViewPanel(gui, self.set_view, width=PANEL_WIDTH_PX)
        # Docked, not floating: a floating control panel covers the right third of the scene, where
        # the trees of the other scans stand; docked, the scene is the free space between the panels.
        gui.main_panel.dock_right()
        gui.main_panel.set_width(CONTROL_WIDTH_PX)
        gui.add_markdown("**treereg** · marker-free registration of single-tree TLS scans (rotating projection, "
                         "then stem and branch centres)")
        self.tour = TourPanel(gui, self.tour_go)
        self.follow_md = gui.add_markdown("", visible=False)
        self.follow_box = gui.add_checkbox("Follow the presenter", False, visible=False,
                                           hint="Untick to look around on your own; tick to follow again.")
        self.follow_box.on_update(lambda _: self._set_following(bool(self.follow_box.value)))
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
                             "view and camera until they untick *Follow the presenter*.")
            self.tour_button = gui.add_button("Start the tour", icon=viser.Icon.PLAYER_PLAY, color="blue")
            self.tour_button.on_click(lambda _: self.tour_go(0))
            self.present_box = gui.add_checkbox("Others follow me", False,
                                                hint="Present: every other tab follows this one's stage, view and camera.")
            self.present_box.on_update(lambda _: host.set_presenter(self, bool(self.present_box.value)))

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
        if self.stages.auto_run.value and snap.status(name) == "stale" and len(snap.scans) >= 2 \
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
        later ones, which depend on it).
        """
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
        try:
            self.controller.set_param(section, name, value)
        except ConfigError as e:
            self.controller.note(str(e), error=True)
            self.stages.sections[section].sync(self.controller.params)  # show what is in force
            return str(e)
        self.stages.sections[section].show_in_force(name, self.controller.params)
        return None

    def load_params(self, params: Params, source: str, note: str = "") -> None:
        self.controller.set_params(params)
        self.stages.sync_params(params)
        self.controller.note(f"Parameters from {source} in force; press Run to apply them. {note}".rstrip())

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
        self._look(camera.frame(self.controller.snapshot, self.view.stage, self.view))

    def _on_camera(self, cam: Any) -> None:
        # The tab's reports say how wide its 3-D view is: a narrow window (a 1280 x 720 laptop screen)
        # gets narrower panels, so the scene keeps at least half. A report may come before the panels
        # are docked (the canvas then the whole window: landscape) or after (between them: the window
        # less both panels); either reading of a narrow window narrows, and the panels then stay so.
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
        try:
            self.pick(np.asarray(event.ray_origin, float), np.asarray(event.ray_direction, float))
        except Exception:  # a click must never take the tab down
            log.exception("pick failed")

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
    def show_presenter(self, presenter: Viewer | None) -> None:
        """A presenter started or stopped: offer (and by default start) following, or say who presents."""
        if presenter is None or presenter is self:
            if self.following:
                self.tour.show(self.view.tour_step)
            self.following = False
            self.follow_md.visible = False
            self.follow_box.visible = False
            if presenter is None and self.present_box.value:
                self.present_box.value = False
            return
        if self.present_box.value:  # someone else presents now
            self.present_box.value = False
        self.follow_md.content = "**Presenting:** another tab leads; this one follows its stage, view and camera."
        self.follow_md.visible = True
        self.follow_box.visible = True
        self.follow_box.value = True
        self._set_following(True)

    def _set_following(self, on: bool) -> None:
        was = self.following
        self.following = on and self.host.presenter is not None and self.host.presenter is not self
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

    # ---- the tour ---------------------------------------------------------------------------------
    def tour_go(self, step: int | None) -> None:
        """Go to tour step `step` (None ends the tour): stage, view, camera and highlight set."""
        self.tour.show(step)
        self._highlight(None)
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
                    f"/tour/tree{i}", f"▼ scan {i + 1}",
                    position=tuple(float(v) for v in top)))
        elif what == "trunk":
            anchor = camera.trunk_anchor(snap, default_height(snap, self.view.target))
            if anchor is not None:
                self._tour_nodes.append(self.scene.add_label(
                    "/tour/label", "◀ the trunk slice of the cross-section",
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
