"""The drawing thread: turns the latest Snapshot and ViewState into scene nodes and panel content.

Separate from the pipeline worker, so stepping through stages and moving sliders stays quick while
a stage re-runs. Requests are coalesced: many slider moves give one redraw of the latest state.
Each layer remembers the key (result identity + the view choices it depends on) it was drawn with
and is redrawn only when that key changes. All updates of one redraw go in one `server.atomic()`.
"""

from __future__ import annotations

import logging
import threading
import time
from typing import Any, Callable

import viser

from treereg_core.stage import Skipped
from treereg_core.stages import stage as core_stage

from .controller import Snapshot
from .renderers import RENDERERS, Renderer
from .renderers.common import item_message, not_ready_text, render_metrics, target_index, title
from .renderers.scans import apply_poses, context_only, draw_scan_layer, scan_poses, scans_shown
from .stages import STAGE_NAMES
from .view_panel import PanelContent, ViewPanel
from .view_state import ViewState

log = logging.getLogger(__name__)

#: Stages without a renderer of their own show their metrics.
_GENERIC = Renderer(render_metrics, ("target",))


def render_stage(scene: viser.SceneApi, root: str, snap: Snapshot, view: ViewState) -> tuple[list[Any], PanelContent]:
    """The current stage's drawing; what every renderer would otherwise begin with is done here:
    nothing to show yet (the panel says why), or the chosen pair skipped (its message)."""
    name = view.stage
    r = RENDERERS.get(name, _GENERIC)
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
        server: viser.ViserServer,
        panel: ViewPanel,
        get_snapshot: Callable[[], Snapshot],
        get_view: Callable[[], ViewState],
        on_error: Callable[[str], None] | None = None,
    ) -> None:
        self.server = server
        self.panel = panel
        self._get_snapshot = get_snapshot
        self._get_view = get_view
        self._on_error = on_error or (lambda msg: None)
        self._cond = threading.Condition()
        self._dirty = False
        self._busy = False
        self._stopped = False
        self._keys: dict[str, Any] = {}
        self._handles: dict[str, list[Any]] = {}
        self._scan_frames: dict[int, Any] = {}
        self.draws = 0  # number of completed redraws (tests wait on it)
        self.last_seconds = 0.0
        scene = server.scene
        self._groups = {name: scene.add_frame(f"/{name}", show_axes=False, visible=False) for name in STAGE_NAMES}
        self._thread = threading.Thread(target=self._loop, name="treereg-drawer", daemon=True)
        self._thread.start()

    # ---- requests ----------------------------------------------------------------------------
    def request(self) -> None:
        with self._cond:
            self._dirty = True
            self._cond.notify_all()

    def wait_idle(self, timeout: float = 30.0) -> bool:
        """Block until every requested redraw is done (tests)."""
        deadline = time.monotonic() + timeout
        with self._cond:
            while self._dirty or self._busy:
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
                while not self._dirty and not self._stopped:
                    self._cond.wait()
                if self._stopped:
                    return
                self._dirty = False
                self._busy = True
            try:
                t0 = time.perf_counter()
                self.draw(self._get_snapshot(), self._get_view())
                self.last_seconds = time.perf_counter() - t0
            except Exception as e:  # a drawing bug must not kill the thread; the user sees one line
                log.exception("drawing failed")
                self._on_error(f"Drawing failed: {type(e).__name__}: {e}")
            finally:
                with self._cond:
                    self._busy = False
                    self.draws += 1
                    self._cond.notify_all()

    def draw(self, snap: Snapshot, view: ViewState) -> None:
        """Bring the scene and the panel up to date with `snap` and `view`."""
        scene = self.server.scene
        with self.server.atomic():
            # The scan layer: points change only with the scans, preparation and display options.
            prep = snap.output("prepare")
            key = (tuple(id(s) for s in snap.scans), id(prep), view.stage == "prepare", context_only(view), view.point_size,
                   view.max_points, view.show_stations)
            if self._keys.get("scans") != key:
                self._replace("scans", [])
                self._handles["scans"] = draw_scan_layer(scene, snap, view)
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
            fields = RENDERERS.get(name, _GENERIC).view_fields
            # Drawn anew when its output or an earlier one (its inputs, the poses it draws at) changed,
            # or a view choice it uses.
            upto = STAGE_NAMES[: STAGE_NAMES.index(name) + 1]
            key = (tuple(id(snap.outputs.get(n)) for n in upto), snap.running == name, len(snap.scans),
                   tuple(getattr(view, f) for f in fields))
            if self._keys.get(name) != key or self._keys.get("panel") != name:
                self._replace(name, [])
                handles, content = render_stage(scene, f"/{name}", snap, view)
                self._handles[name] = handles
                self._keys[name] = key
                self.panel.show(content)
                self._keys["panel"] = name
            for k, g in self._groups.items():
                g.visible = k == name

    def _replace(self, layer: str, handles: list[Any]) -> None:
        # Remove the old nodes first: a new node may reuse an old name.
        for h in reversed(self._handles.get(layer, [])):
            try:
                h.remove()
            except Exception:  # already removed with its parent
                pass
        self._handles[layer] = handles


def _is_scan_frame(h: Any) -> bool:
    name = getattr(h, "name", "")
    return name.startswith("/scans/s") and name.count("/") == 2
