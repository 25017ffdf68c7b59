"""One viewer's drawing thread: turns the latest Snapshot and that viewer's ViewState into scene
nodes and panel content.

Separate from the pipeline worker, so stepping through stages and moving sliders stays quick while
a stage re-runs. Requests are coalesced: many slider moves give one redraw of the latest state.
Each layer remembers the key (result identity + the view choices it depends on) it was drawn with
and is redrawn only when that key changes. All updates of one redraw go in one `atomic()` block of
the viewer's connection. Every browser tab has its own Drawer on its own scene; the shared
`Derived` cache keeps tabs from computing the same cross-section twice.

The drawing thread is also where the pipeline's news reaches the tab's GUI (`post`): the worker
thread never calls viser itself (viser's message buffers are not made for a thread that outruns
the app's own; a call from the worker once ended a run with "deque mutated during iteration").

Responsive while the pipeline computes (issue 18): once the tab's first view is drawn the worker
gives way while the browser shows it (`give_way`: `Controller.give_way`).
Plotly's script (4.8 MB, which holds the browser for about a second) is sent when the tab's person
pauses, and a panel with the tab's first plots shows everything else first.
"""

from __future__ import annotations

import logging
import threading
import time
from contextlib import AbstractContextManager
from dataclasses import replace
from typing import Any, Callable

import viser

from treereg_core.stage import Skipped
from treereg_core.stages import stage as core_stage

from .controller import Snapshot
from .derived import Derived, default_height, evaluated_branches, height_range
from .draw import cross_section
from .draw.before import comparison_text, drawn
from .draw.common import evaluated_branch_names, item_message, not_ready_text, target_index, title
from .draw.scan_layer import apply_poses, draw_scan_layer, residual_mode, scan_layer_key, scan_poses, scans_shown
from .stages import STAGE_NAMES, section_available, stage_of
from .view_panel import PanelContent, ViewPanel
from .view_state import ViewState

log = logging.getLogger(__name__)

#: Seconds the worker gives way once the tab's first view is drawn: the browser lays out the whole
#: GUI and renders its first frames. (Later redraws do not ask: measured on the demo, Next answered
#: as fast without, and the run took 2.5 s longer with.)
FIRST_VIEW_GIVE_WAY_S = 1.0
#: Plotly's script holds the browser for about a second wherever it goes: it is sent
#: PLOTS_PENDING_IDLE_S after the first panel with plots was shown without them (its heading, text
#: and images are painted by then). Not before a stage with plots is shown: sent to every idle tab,
#: the script (and plotly's import) grew the server by 40 MB for tabs that never show a plot.
PLOTS_PENDING_IDLE_S = 0.5


def render_stage(scene: viser.SceneApi, root: str, snap: Snapshot, view: ViewState) -> tuple[list[Any], PanelContent]:
    """The current stage's drawing; what every renderer would otherwise begin with is done here:
    nothing to show yet (the panel says why), or the chosen pair skipped (its message). A stage whose
    result a changed parameter dropped draws its last result, marked stale, and one with a run
    before can draw that run (`draw.before`); the panel then says which, and what changed."""
    snap, note = drawn(snap, view)[0], comparison_text(snap, view)
    handles, content = _render(scene, root, snap, view)
    if note:
        content = replace(content, text=f"{note}\n\n{content.text}" if content.text else note)
    return handles, content


def _render(scene: viser.SceneApi, root: str, snap: Snapshot, view: ViewState) -> tuple[list[Any], PanelContent]:
    name = view.stage
    r = stage_of(name)
    out = snap.output(name)
    if r.needs_output and (out is None or not out.items):
        return [], PanelContent(title(name), text=not_ready_text(snap, name))
    if out is not None and core_stage(name).per == "pair":
        t = target_index(snap, name, view)
        if isinstance(out.items[t], Skipped):
            return [], PanelContent(title(name, snap, t), text=item_message(out.items[t]))
    return r.draw(scene, root, snap, view)


class Drawer:
    """Draws on its own thread; `request()` from anywhere asks for a redraw of the latest state."""

    def __init__(
        self,
        scene: viser.SceneApi,
        atomic: Callable[[], AbstractContextManager[Any]],
        panel: ViewPanel,
        get_snapshot: Callable[[], Snapshot],
        get_view: Callable[[], ViewState],
        derived: Derived,
        on_error: Callable[[str], None] | None = None,
        give_way: Callable[[float], None] | None = None,
    ) -> None:
        self.scene = scene
        self.panel = panel
        self._atomic = atomic
        self._get_snapshot = get_snapshot
        self._get_view = get_view
        self.derived = derived
        self._on_error = on_error or (lambda msg: None)
        self._cond = threading.Condition()
        self._dirty = False
        self._jobs: dict[str, Callable[[], None]] = {}  # GUI updates to run on this thread, by kind
        self._busy = False
        self._stopped = False
        self._keys: dict[str, Any] = {}
        self._handles: dict[str, list[Any]] = {}
        self._scan_frames: dict[int, Any] = {}
        self._stage_content: PanelContent | None = None
        self.draws = 0  # number of completed redraws (tests wait on it)
        self.last_seconds = 0.0
        self.section: Any = None  # the cross-section shown last (tests read it)
        #: Called with seconds once this tab's first view is drawn: `Controller.give_way` (without
        #: one nothing needs to give way).
        self.give_way: Callable[[float], None] = give_way or (lambda seconds: None)
        self._drawn_view: ViewState | None = None
        self._asked_at = 0.0  # time.monotonic() of the last redraw a person asked for
        self._plots_pending = False  # the panel shows a stage without its plots: the script is not sent yet
        self._groups = {name: scene.add_frame(f"/{name}", show_axes=False, visible=False) for name in STAGE_NAMES}
        # The scan layer's root: hidden while the tab aligns a scan by hand (the Align tab draws then).
        self._scans_root = scene.add_frame("/scans", show_axes=False)
        self._thread = threading.Thread(target=self._loop, name="treereg-drawer", daemon=True)
        self._thread.start()

    # ---- requests ----------------------------------------------------------------------------
    def request(self) -> None:
        with self._cond:
            self._dirty = True
            self._cond.notify_all()

    def post(self, kind: str, job: Callable[[], None]) -> None:
        """Run `job` (a GUI update) on this thread, before the next redraw. A newer job of the same
        `kind` replaces one not yet run (only the latest snapshot or progress matters); jobs run in the
        order they were last posted."""
        with self._cond:
            self._jobs.pop(kind, None)
            self._jobs[kind] = job
            self._cond.notify_all()

    def wait_idle(self, timeout: float = 30.0) -> bool:
        """Block until every requested redraw and posted job is done, plots shown late included (tests)."""
        deadline = time.monotonic() + timeout
        with self._cond:
            while self._dirty or self._jobs or self._busy or self._plots_pending:
                left = deadline - time.monotonic()
                if left <= 0:
                    return False
                self._cond.wait(timeout=left)
        return True

    def close(self) -> None:
        with self._cond:
            self._stopped = True
            self._cond.notify_all()
        self._thread.join(timeout=10)

    # ---- drawing -------------------------------------------------------------------------------
    def _loop(self) -> None:
        while True:
            with self._cond:
                while not self._dirty and not self._jobs and not self._stopped:
                    wait = self._plots_wait()
                    if wait is not None and wait <= 0:
                        break
                    self._cond.wait(timeout=wait)
                if self._stopped:
                    return
                jobs, self._jobs = list(self._jobs.values()), {}
                if (wait := self._plots_wait()) is not None and wait <= 0:  # no redraw for a while: the plots' script
                    jobs.append(self._prepare_plots)
                self._busy = True
            self._run_jobs(jobs)
            with self._cond:  # the jobs may have asked for a redraw
                dirty, self._dirty = self._dirty, False
            try:
                if dirty:
                    self._redraw()
            except Exception as e:  # a drawing bug must not kill the thread; the user sees one line
                log.exception("drawing failed")
                self._on_error(f"Drawing failed: {type(e).__name__}: {e}")
            finally:
                with self._cond:
                    self._busy = False
                    self.draws += dirty
                    self._cond.notify_all()

    def _redraw(self) -> None:
        """Draw the latest state. A change of the view (not only the pipeline's news) is a person's
        request (the plots' script waits for a pause in them); after the first view the worker gives way."""
        view, first = self._get_view(), self._drawn_view is None
        t0 = time.perf_counter()
        self.draw(self._get_snapshot(), view)
        self.last_seconds = time.perf_counter() - t0
        if view != self._drawn_view:
            self._asked_at = time.monotonic()
        self._drawn_view = view
        if first:
            self.give_way(FIRST_VIEW_GIVE_WAY_S)

    def _plots_wait(self) -> float | None:
        """Seconds until plotly's script is due (None: sent, not asked for yet, or no first view),
        counted from when the panel was shown without its plots."""
        if self._drawn_view is None or self.panel.plots or not self._plots_pending:
            return None
        return self._asked_at + PLOTS_PENDING_IDLE_S - time.monotonic()

    def _prepare_plots(self) -> None:
        """Send plotly's script; a panel that waits for its plots is shown again, with them."""
        with self._atomic():
            self.panel.prepare_plots()
        if self._plots_pending:
            self._plots_pending = False
            self._keys.pop("panel", None)
            self.request()

    @staticmethod
    def _run_jobs(jobs: list[Callable[[], None]]) -> None:
        for job in jobs:
            try:
                job()
            except Exception:  # one tab's GUI failing must not stop its drawing
                log.exception("GUI update failed")

    def draw(self, latest: Snapshot, view: ViewState) -> None:
        """Bring the scene and the panel up to date with `latest` and `view` (the whole view of the
        run it draws: the latest, or the run before, `draw.before.drawn`). In projector mode
        (`view.scale`) every layer is drawn with its labels, lines and points that much larger."""
        scene: Any = self.scene if view.scale == 1.0 else ScaledScene(self.scene, view.scale)
        snap, _ = drawn(latest, view)
        # On-demand results (residuals, the cross-section) are computed before the atomic block:
        # the connection's other messages are not held back meanwhile.
        residuals = (self.derived.residuals(snap, view.result_pose, view.max_points, view.residual_max_m)
                     if residual_mode(view) else None)
        moved = (self.derived.wind_moved(snap, view.result_pose, view.max_points, view.residual_max_m)
                 if residual_mode(view) else None)
        sectioning = section_available(snap, view.stage) and view.panel == "section"
        branch = None
        cs = None
        if sectioning:
            cs = self.derived.cross_section(snap, view)
            branches = evaluated_branches(snap, view.target)
            branch = branches[view.branch] if view.branch is not None and view.branch < len(branches) else None
        with self._atomic():
            # The scan layer: points change only with the scans, preparation and display options.
            key = (scan_layer_key(snap, view), view.scale)
            if self._keys.get("scans") != key:
                self._replace("scans", draw_scan_layer(scene, snap, view, residuals, moved))
                self._scan_frames = {
                    i: h for i, h in enumerate(h for h in self._handles["scans"] if _is_scan_frame(h))
                }
                self._keys["scans"] = key
            self._scans_root.visible = view.align_scan is None
            poses = scan_poses(snap, view)
            apply_poses(self._scan_frames, poses)
            for i, s in enumerate(snap.scans):
                h = self._scan_frames.get(i)
                if h is not None:
                    h.visible = s.name not in view.hidden_scans and scans_shown(view)
            # The current stage's layer; the others are hidden (the scans stay).
            name = view.stage
            fields = stage_of(name).view_fields
            # Drawn anew when its output or an earlier one (its inputs, the poses it draws at) changed,
            # or a view choice it uses.
            upto = STAGE_NAMES[: STAGE_NAMES.index(name) + 1]
            key = (name, tuple(id(snap.outputs.get(n)) for n in upto), latest.running == name, len(snap.scans),
                   tuple(getattr(view, f) for f in fields), comparison_text(latest, view), view.scale)
            stage_changed = self._keys.get("stage") != key
            if stage_changed:
                handles, content = render_stage(scene, f"/{name}", latest, view)
                self._replace("stage", handles)
                self._keys["stage"] = key
                self._stage_content = content
            for k, g in self._groups.items():
                g.visible = k == name and view.align_scan is None  # aligning by hand: the Align tab draws
            # A pair's drawing is in its reference scan's frame: the layer stands where that scan is
            # shown (scan3 -> scan2 where scan2 stands, not at scan1's origin).
            apply_poses({0: self._groups[name]}, [poses[pair_reference(snap, view)]])
            # The cross-section: its 3-D marker and, in section mode, the panel.
            key = (id(cs), None if branch is None else branch.index, view.show_rejected, sectioning, view.scale)
            if self._keys.get("section") != key:
                self._replace("section", cross_section.draw_marker(scene, "/section", cs, branch) if sectioning else [])
                self._keys["section"] = key
            panel_key = ("section", key) if sectioning else ("stage", self._keys["stage"])
            if self._keys.get("panel") != panel_key:
                content = cross_section.render(snap, view, cs, branch) if sectioning else self._stage_content
                # The tab's first plots bring plotly's script, which holds the browser for about a
                # second: the heading, text, images and 3-D go first, the plots once the tab is idle.
                self._plots_pending = bool(content.plots) and not self.panel.plots
                if self._plots_pending:
                    self._asked_at = max(self._asked_at, time.monotonic())
                self.panel.show(replace(content, plots=()) if self._plots_pending else content)
                self._keys["panel"] = panel_key
                self.section = cs if sectioning else None
            rng = height_range(snap) if sectioning else None
            names = evaluated_branch_names(snap, view.target)
            self.panel.show_controls(
                view, section_available(snap, view.stage), rng,
                view.section_height if view.section_height is not None else default_height(snap, view.target),
                [branch_choice(names.get(b.index, f"branch {b.index + 1}"), b)
                 for b in evaluated_branches(snap, view.target)])

    def _replace(self, layer: str, handles: list[Any]) -> None:
        """`handles` (just drawn) take the place of the layer's old nodes. A node drawn again under its
        old name has replaced it already, and viser then resets its pose in the browser too; removing
        the old node first would not: an open tab would keep the old node's pose on the new one (the
        scans stayed registered after stepping back to stage 1). Old nodes not drawn again are removed."""
        kept = {getattr(h, "name", None) for h in handles}
        for h in reversed(self._handles.get(layer, [])):
            name = getattr(h, "name", None)
            if name in kept or any(k and k.startswith(f"{name}/") for k in kept):  # removal takes the children
                continue
            try:
                h.remove()
            except Exception:  # already removed with its parent
                pass
        self._handles[layer] = handles


class ScaledScene:
    """A tab's scene as the drawing sees it in projector mode: labels, lines and points `scale` times
    their size (a label's screen scale, a line's thickness, a cloud's point size); everything else
    passed through. One place, so no renderer needs to know about projector mode."""

    def __init__(self, scene: viser.SceneApi, scale: float) -> None:
        self._scene = scene
        self._scale = float(scale)

    def __getattr__(self, name: str) -> Any:
        return getattr(self._scene, name)

    def add_label(self, *args: Any, **kwargs: Any) -> Any:
        kwargs["font_screen_scale"] = kwargs.get("font_screen_scale", 1.0) * self._scale
        return self._scene.add_label(*args, **kwargs)

    def add_line_segments(self, *args: Any, **kwargs: Any) -> Any:
        kwargs["thickness"] = kwargs.get("thickness", 0.01) * self._scale
        return self._scene.add_line_segments(*args, **kwargs)

    def add_point_cloud(self, *args: Any, **kwargs: Any) -> Any:
        kwargs["point_size"] = kwargs.get("point_size", 0.1) * self._scale
        return self._scene.add_point_cloud(*args, **kwargs)


def branch_choice(name: str, b: Any) -> str:
    """A branch as the cross-section's *Section of* list offers it: 'Stem at 1.31 m (r = 9.5 cm)',
    'Branch 2 (z = 3.54 m, r = 1.3 cm)'."""
    where = "" if name.startswith("stem") else f"z = {b.height_m:.2f} m, "
    return f"{name[:1].upper()}{name[1:]} ({where}r = {b.radius_m * 100:.1f} cm)"


def pair_reference(snap: Snapshot, view: ViewState) -> int:
    """The scan whose frame the current stage's drawing is in: the reference scan of the pair in view
    (0 on a per-scan stage, or before there is a pair)."""
    if core_stage(view.stage).per != "pair" or snap.n_pairs == 0:
        return 0
    return snap.pair(target_index(snap, view.stage, view)).ref


def _is_scan_frame(h: Any) -> bool:
    name = getattr(h, "name", "")
    return name.startswith("/scans/s") and name.count("/") == 2
