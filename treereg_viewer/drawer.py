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
"""

from __future__ import annotations

import logging
import threading
import time
from contextlib import AbstractContextManager
from typing import Any, Callable

import viser

from treereg_core.stage import Skipped
from treereg_core.stages import stage as core_stage

from .controller import Snapshot
from .derived import Derived, default_height, evaluated_branches, height_range
from .draw import cross_section
from .draw.common import item_message, not_ready_text, target_index, title
from .draw.scan_layer import apply_poses, draw_scan_layer, residual_mode, scan_layer_key, scan_poses, scans_shown
from .stages import STAGE_NAMES, section_available, stage_of
from .view_panel import PanelContent, ViewPanel
from .view_state import ViewState

log = logging.getLogger(__name__)


def render_stage(scene: viser.SceneApi, root: str, snap: Snapshot, view: ViewState) -> tuple[list[Any], PanelContent]:
    """The current stage's drawing; what every renderer would otherwise begin with is done here:
    nothing to show yet (the panel says why), or the chosen pair skipped (its message)."""
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
        self._groups = {name: scene.add_frame(f"/{name}", show_axes=False, visible=False) for name in STAGE_NAMES}
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
        """Block until every requested redraw and posted job is done (tests)."""
        deadline = time.monotonic() + timeout
        with self._cond:
            while self._dirty or self._jobs or self._busy:
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
                    self._cond.wait()
                if self._stopped:
                    return
                jobs, self._jobs = list(self._jobs.values()), {}
                self._busy = True
            self._run_jobs(jobs)
            with self._cond:  # the jobs may have asked for a redraw
                dirty, self._dirty = self._dirty, False
            try:
                if dirty:
                    t0 = time.perf_counter()
                    self.draw(self._get_snapshot(), self._get_view())
                    self.last_seconds = time.perf_counter() - t0
            except Exception as e:  # a drawing bug must not kill the thread; the user sees one line
                log.exception("drawing failed")
                self._on_error(f"Drawing failed: {type(e).__name__}: {e}")
            finally:
                with self._cond:
                    self._busy = False
                    self.draws += dirty
                    self._cond.notify_all()

    @staticmethod
    def _run_jobs(jobs: list[Callable[[], None]]) -> None:
        for job in jobs:
            try:
                job()
            except Exception:  # one tab's GUI failing must not stop its drawing
                log.exception("GUI update failed")

    def draw(self, snap: Snapshot, view: ViewState) -> None:
        """Bring the scene and the panel up to date with `snap` and `view`."""
        scene = self.scene
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
            key = scan_layer_key(snap, view)
            if self._keys.get("scans") != key:
                self._replace("scans", draw_scan_layer(scene, snap, view, residuals, moved))
                self._scan_frames = {
                    i: h for i, h in enumerate(h for h in self._handles["scans"] if _is_scan_frame(h))
                }
                self._keys["scans"] = key
            apply_poses(self._scan_frames, scan_poses(snap, view))
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
            key = (name, tuple(id(snap.outputs.get(n)) for n in upto), snap.running == name, len(snap.scans),
                   tuple(getattr(view, f) for f in fields))
            stage_changed = self._keys.get("stage") != key
            if stage_changed:
                handles, content = render_stage(scene, f"/{name}", snap, view)
                self._replace("stage", handles)
                self._keys["stage"] = key
                self._stage_content = content
            for k, g in self._groups.items():
                g.visible = k == name
            # The cross-section: its 3-D marker and, in section mode, the panel.
            key = (id(cs), None if branch is None else branch.index, view.show_rejected, sectioning)
            if self._keys.get("section") != key:
                self._replace("section", cross_section.draw_marker(scene, "/section", cs, branch) if sectioning else [])
                self._keys["section"] = key
            panel_key = ("section", key) if sectioning else ("stage", self._keys["stage"])
            if self._keys.get("panel") != panel_key:
                content = cross_section.render(snap, view, cs, branch) if sectioning else self._stage_content
                self.panel.show(content)
                self._keys["panel"] = panel_key
                self.section = cs if sectioning else None
            rng = height_range(snap) if sectioning else None
            self.panel.show_controls(
                view, section_available(snap, view.stage), rng,
                view.section_height if view.section_height is not None else default_height(snap, view.target),
                [f"Branch {b.index + 1} (z = {b.height_m:.2f} m, r = {b.radius_m * 100:.1f} cm)"
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


def _is_scan_frame(h: Any) -> bool:
    name = getattr(h, "name", "")
    return name.startswith("/scans/s") and name.count("/") == 2
