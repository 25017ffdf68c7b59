"""treereg's browser app: the server, the shared state, and one viewer per browser tab.

Shared by every tab: the `Controller` (scans, parameters, the pipeline on its worker thread and the
results it publishes), the `Derived` cache (cross-sections and residuals computed on demand), the
exports folder and who presents. Per tab, a `viewer.Viewer`: its own stage, pair, sliders,
cross-section and camera, GUI and scene, and drawing thread.

Layout of a tab: on the right the control panel (stage selector, Previous/Next, Run, progress,
messages; tabs "Stage" with one folder per stage, "Scans", "Files", "Teach"); on the left a wide
docked panel with the current stage's images, plots and tables, or the cross-section; the 3-D
scene in the middle.

    server = viser.ViserServer(host="127.0.0.1", port=0)
    app = TreeregApp(server, Controller(scans, params, truth), tabs="each")

With `tabs="shared"` (the default: scripts and tests without a browser) there is one viewer, on
the server's own GUI and scene, and every tab sees it; `app.viewer` is that viewer and the app
passes its panels (`app.stages`, `app.panel`, ...) through.
"""

from __future__ import annotations

import logging
import threading
import time
from pathlib import Path
from typing import Any, Literal

import viser

from . import camera
from .controller import Controller, Snapshot
from .derived import Derived
from .stages import STAGE_NAMES
from .view_state import ViewState
from .viewer import Viewer

log = logging.getLogger(__name__)


class TreeregApp:
    """The app on one viewer server.

    Parameters
    ----------
    server
        A running `viser.ViserServer`.
    controller
        Owns the scans, parameters and pipeline.
    out_dir
        When given, exports are also written there.
    autorun
        Run the whole pipeline in the background as soon as the app is up.
    tabs
        "each": every browser tab gets its own viewer (what `treereg view` serves); "shared": one
        viewer on the server's own GUI and scene, seen by every tab (scripts, tests without a browser).
    """

    def __init__(self, server: viser.ViserServer, controller: Controller, out_dir: Path | None = None,
                 autorun: bool = True, tabs: Literal["each", "shared"] = "shared") -> None:
        self.server = server
        self.controller = controller
        self.out_dir = Path(out_dir) if out_dir is not None else None
        self.derived = Derived()
        self.tabs = tabs
        self._lock = threading.Lock()
        self._viewers: dict[int | None, Viewer] = {}
        self.presenter: Viewer | None = None

        server.gui.configure_theme(show_share_button=False, control_width="large", brand_color=(30, 140, 60),
                                   titlebar_content=None)
        server.scene.set_up_direction("+z")
        self._place_camera(controller.snapshot)
        controller.subscribe(self._on_snapshot)
        controller.subscribe_progress(self._on_progress)
        if tabs == "shared":
            self._viewers[None] = Viewer(self, server.gui, server.scene, None, server.atomic)
        else:
            server.on_client_connect(self._connect)
            server.on_client_disconnect(self._disconnect)
        if autorun and len(controller.snapshot.scans) >= 2:
            controller.request_run(STAGE_NAMES[-1])

    # ---- viewers ------------------------------------------------------------------------------------
    def _connect(self, client: viser.ClientHandle) -> None:
        v = Viewer(self, client.gui, client.scene, client, client.atomic)
        with self._lock:
            self._viewers[client.client_id] = v
            presenter = self.presenter
        if presenter is not None:  # a tab joining a class follows the presenter from the start
            v.show_presenter(presenter)

    def _disconnect(self, client: viser.ClientHandle) -> None:
        with self._lock:
            v = self._viewers.pop(client.client_id, None)
            if v is not None and self.presenter is v:
                self.presenter = None
            others = list(self._viewers.values())
        if v is not None:
            v.close()
            if self.presenter is None:
                self._tell(others, None)

    @staticmethod
    def _tell(viewers: list[Viewer], presenter: Viewer | None) -> None:
        """Tell each viewer who presents now; a tab that is closing must not keep the others uninformed."""
        for o in viewers:
            try:
                o.show_presenter(presenter)
            except Exception:
                log.exception("could not update a tab's presenter controls")

    @property
    def viewers(self) -> list[Viewer]:
        with self._lock:
            return list(self._viewers.values())

    def viewer_of(self, client_id: int | None) -> Viewer | None:
        with self._lock:
            return self._viewers.get(client_id)

    # ---- presenting -------------------------------------------------------------------------------
    def set_presenter(self, viewer: Viewer, on: bool) -> None:
        """`viewer` starts (or stops) presenting: every other tab follows it until it unticks
        "Follow the presenter"."""
        with self._lock:
            if on:
                self.presenter = viewer
            elif self.presenter is viewer:
                self.presenter = None
            else:
                return
            presenter = self.presenter
            others = [v for v in self._viewers.values() if v is not viewer]
        self._tell([*others, viewer], presenter)

    def broadcast(self, presenter: Viewer) -> None:
        """The presenter's view changed: its followers take it over."""
        for v in self.viewers:
            if v is not presenter and v.following:
                try:
                    v.follow(presenter)
                except Exception:  # one closing tab must not stop the others following
                    log.exception("a follower could not follow")

    def camera_moved(self, presenter: Viewer, cam: Any) -> None:
        for v in self.viewers:
            if v is not presenter and v.following:
                v.follow_camera(cam.position, cam.look_at, cam.up_direction)

    # ---- shared services -----------------------------------------------------------------------------
    def send_file(self, client: Any, filename: str, data: bytes) -> None:
        """A browser download that starts at once (no link to click) for the tab that asked (all tabs
        when there is no client, as in tests)."""
        target = client if client is not None else self.server
        target.send_file_download(filename, data, save_immediately=True)

    def close(self) -> None:
        self.controller.close()
        for v in self.viewers:
            v.close()

    def _on_snapshot(self, snap: Snapshot) -> None:
        for v in self.viewers:
            try:
                v.on_snapshot(snap)
            except Exception:  # one tab's GUI failing must not stop the others
                log.exception("viewer update failed")

    def _on_progress(self, fraction: float, text: str) -> None:
        for v in self.viewers:
            v.on_progress(fraction, text)

    def _place_camera(self, snap: Snapshot) -> None:
        """The camera a new browser tab starts with (and "Reset View" returns to): the Scans stage's view."""
        pose = camera.frame(snap, STAGE_NAMES[0])
        if pose is None:
            return
        self.server.initial_camera.position = pose.position
        self.server.initial_camera.look_at = pose.look_at
        self.server.initial_camera.up = (0.0, 0.0, 1.0)

    # ---- the one viewer of tabs="shared" (scripts and tests drive it through the app) ----------------
    @property
    def viewer(self) -> Viewer:
        v = self.viewer_of(None)
        if v is None:
            raise AttributeError("this app has a viewer per browser tab (tabs='each'): use app.viewers")
        return v

    @property
    def view(self) -> ViewState:
        return self.viewer.view

    @property
    def stages(self) -> Any:
        return self.viewer.stages

    @property
    def scans(self) -> Any:
        return self.viewer.scans

    @property
    def files(self) -> Any:
        return self.viewer.files

    @property
    def panel(self) -> Any:
        return self.viewer.panel

    @property
    def drawer(self) -> Any:
        return self.viewer.drawer

    def set_view(self, **changes: Any) -> None:
        self.viewer.set_view(**changes)

    def select_stage(self, name: str) -> None:
        self.viewer.select_stage(name)

    def step_stage(self, delta: int) -> None:
        self.viewer.step_stage(delta)

    def frame_view(self) -> None:
        self.viewer.frame_view()


def serve(controller: Controller, host: str = "127.0.0.1", port: int = 8080, out_dir: Path | None = None) -> None:
    """Start the server and the app, print the URL (tests read it), block until Ctrl-C."""
    t0 = time.perf_counter()
    server = viser.ViserServer(host=host, port=port, verbose=False)
    app = TreeregApp(server, controller, out_dir=out_dir, tabs="each")
    url = f"http://{host}:{server.get_port()}/"
    print(f"treereg view: {url}  (app ready in {time.perf_counter() - t0:.1f} s; Ctrl-C to stop)", flush=True)
    try:
        while True:
            time.sleep(1.0)
    except KeyboardInterrupt:
        pass
    finally:
        app.close()
        server.stop()
