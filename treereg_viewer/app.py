"""treereg's browser app: the server, the shared state, and one viewer per browser tab.

Shared by every tab: the `Controller` (scans, parameters, the pipeline on its worker thread and the
results it publishes), the `Derived` cache (cross-sections and residuals computed on demand), the
exports folder and who presents. Per tab, a `viewer.Viewer`: its own stage, pair, sliders,
cross-section and camera, GUI and scene, and drawing thread.

Presenting (issue 32 item 2): one tab at most presents ("Others follow me"); the others follow it and,
while they follow, cannot change the parameters or run (their inputs are greyed out). Only the
presenter hands the lead over (to a tab it names) or gives it up; a tab cannot take it while another
presents. A change of the parameters made in one tab is shown in every other, naming the tab and the
change, with an Undo.

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

import ipaddress
import logging
import sys
import threading
import time
from pathlib import Path
from typing import Any, Literal

import viser

from treereg_core.errors import ConfigError
from treereg_core.limits import MAX_UPLOAD_POINTS, format_bytes

from . import camera
from .controller import Controller, Snapshot
from .derived import Derived
from .stages import STAGE_NAMES
from .survey_view import SurveyViewer
from .uploads import UploadReceiver
from .view_state import ViewState
from .viewer import Viewer

log = logging.getLogger(__name__)


#: Largest scan file a browser may upload unless the app is told otherwise.
MAX_UPLOAD_BYTES = 1024 * 1000 * 1000
#: Seconds the worker gives way to a tab that connects (building its GUI takes up to half a second;
#: its drawer asks for more once the first view is drawn).
CONNECT_GIVE_WAY_S = 1.0


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
    max_upload_bytes
        Largest scan file a browser may upload (uploads stream to a temporary file).
    max_upload_points
        Most points an uploaded scan file may announce (checked before any is read).
    projector
        Open every tab in projector mode (large text, labels, lines and points).
    """

    def __init__(self, server: viser.ViserServer, controller: Controller, out_dir: Path | None = None,
                 autorun: bool = True, tabs: Literal["each", "shared"] = "shared",
                 max_upload_bytes: int = MAX_UPLOAD_BYTES, max_upload_points: int = MAX_UPLOAD_POINTS,
                 projector: bool = False) -> None:
        self.server = server
        #: Tabs open in projector mode (`treereg view --projector`); each tab has its own switch.
        self.projector = bool(projector)
        self._tab_count = 0
        self.controller = controller
        self.out_dir = Path(out_dir) if out_dir is not None else None
        self.derived = Derived()
        self.tabs = tabs
        self._lock = threading.Lock()
        self._viewers: dict[int | None, Viewer] = {}
        self.presenter: Viewer | None = None
        # A whole-plot survey (`Controller.survey_mode`) gets the survey view in every tab instead.
        self._make_viewer: Any = SurveyViewer if controller.survey_mode else Viewer
        self.max_upload_bytes = int(max_upload_bytes)
        self.max_upload_points = int(max_upload_points)
        # One receiver for every tab's upload buttons: each file streams to a temporary file.
        self.uploads = UploadReceiver(server, on_message=lambda text, error: controller.note(text, error=error),
                                      on_progress=self._show_receiving)

        server.gui.configure_theme(show_share_button=False, control_width="large", brand_color=(30, 140, 60),
                                   titlebar_content=None)
        server.scene.set_up_direction("+z")
        self._place_camera(controller.snapshot)
        controller.subscribe(self._on_snapshot)
        controller.subscribe_progress(self._on_progress)
        if tabs == "shared":
            self._viewers[None] = self._make_viewer(self, server.gui, server.scene, None, server.atomic, name="this tab")
        else:
            server.on_client_connect(self._connect)
            server.on_client_disconnect(self._disconnect)
        if autorun and len(controller.snapshot.scans) >= 2:
            controller.request_run(STAGE_NAMES[-1])

    # ---- viewers ------------------------------------------------------------------------------------
    def _connect(self, client: viser.ClientHandle) -> None:
        # A tab opening while the pipeline computes: its GUI is built, its first view drawn and shown
        # while the worker gives way (the tab's drawer extends the pause once it has drawn).
        self.controller.give_way(CONNECT_GIVE_WAY_S)
        with self._lock:
            self._tab_count += 1
            name = f"tab {self._tab_count}"
        v = self._make_viewer(self, client.gui, client.scene, client, client.atomic, name=name)
        with self._lock:
            self._viewers[client.client_id] = v
            presenter = self.presenter
        if presenter is not None:  # a tab joining a class follows the presenter from the start
            v.show_presenter(presenter)
            self._offer_tabs(presenter)

    def _disconnect(self, client: viser.ClientHandle) -> None:
        with self._lock:
            v = self._viewers.pop(client.client_id, None)
            if v is not None and self.presenter is v:
                self.presenter = None
            others = list(self._viewers.values())
        if v is not None:
            v.close()
            presenter = self.presenter
            if presenter is None:
                self._tell(others, None)
            else:
                self._offer_tabs(presenter)

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
    def set_presenter(self, viewer: Viewer, on: bool) -> bool:
        """`viewer` starts (or stops) presenting: every other tab follows it until it unticks
        "Follow the presenter". Refused (False) while another tab presents: only the presenter hands
        the lead over (`hand_over`)."""
        with self._lock:
            if on and self.presenter is viewer:
                return True
            if on and self.presenter is not None:
                return False
            if on:
                self.presenter = viewer
            elif self.presenter is viewer:
                self.presenter = None
            else:
                return True
            presenter = self.presenter
            others = [v for v in self._viewers.values() if v is not viewer]
        self._tell([*others, viewer], presenter)
        if presenter is not None:
            self._offer_tabs(presenter)
        return True

    def hand_over(self, viewer: Viewer, to: str) -> bool:
        """The presenter `viewer` hands the lead to the tab named `to`, which then presents while
        `viewer` follows it. Only the presenter can (False otherwise, or when no tab has that name)."""
        with self._lock:
            target = next((v for v in self._viewers.values() if v.name == to and v is not viewer), None)
            if self.presenter is not viewer or target is None:
                return False
            self.presenter = target
            everyone = list(self._viewers.values())
        self._tell([target, *[v for v in everyone if v is not target]], target)
        self._offer_tabs(target)
        return True

    def _offer_tabs(self, presenter: Viewer) -> None:
        """The presenter's list of tabs it can hand the lead to."""
        with self._lock:
            names = [v.name for v in self._viewers.values() if v is not presenter]
        try:
            presenter.offer_tabs(names)
        except Exception:
            log.exception("could not list the tabs for the presenter")

    def changed_by(self, by: Viewer, what: str, undo: Any) -> None:
        """Tab `by` changed what every tab shares (the parameters, a hypothesis picked by hand): every
        other tab is told what changed, and offered `undo` (a function of the tab that undoes it)."""
        for v in self.viewers:
            if v is not by:
                try:
                    v.show_changed_elsewhere(by.name, what, undo)
                except Exception:
                    log.exception("could not tell a tab of a change")

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
        # The upload folder first: the worker may take a while to finish its stage, and a second
        # signal meanwhile must not leave the folder behind.
        self.uploads.close()
        self.controller.close()
        for v in self.viewers:
            v.close()

    def _on_snapshot(self, snap: Snapshot) -> None:
        for v in self.viewers:
            try:
                v.on_snapshot(snap)
            except Exception:  # one tab's GUI failing must not stop the others
                log.exception("viewer update failed")

    def _show_receiving(self, text: str) -> None:
        """What is being uploaded, shown in every tab (an upload can take minutes)."""
        for v in self.viewers:
            try:
                v.scans.show_receiving(text)
            except Exception:
                log.exception("could not show an upload's progress")

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

    def run_current(self) -> None:
        self.viewer.run_current()

    def flush_edits(self) -> None:
        self.viewer.flush_edits()

    def on_param_change(self, section: str, name: str, value: Any) -> str | None:
        return self.viewer.on_param_change(section, name, value)

    def load_params(self, params: Any, source: str, note: str = "") -> None:
        self.viewer.load_params(params, source, note)

    def frame_view(self) -> None:
        self.viewer.frame_view()


def exposure_warning(host: str, port: int, out_dir: Path | None, max_upload_bytes: int) -> str | None:
    """What binding `host` exposes, when it is more than this machine (None for loopback addresses)."""
    try:
        loopback = host == "localhost" or ipaddress.ip_address(host).is_loopback
    except ValueError:  # a host name
        loopback = False
    if loopback:
        return None
    writes = f", and write exports into {out_dir}" if out_dir is not None else ""
    return (f"treereg view: warning: --host {host} lets anyone who can reach this machine on port {port} use the "
            f"app: see the scans, upload files of up to {format_bytes(max_upload_bytes)} to it, run "
            f"registrations{writes}. There is no login; use --host 127.0.0.1 unless this network is trusted.")


def serve(controller: Controller, host: str = "127.0.0.1", port: int = 8080, out_dir: Path | None = None,
          max_upload_bytes: int = MAX_UPLOAD_BYTES, max_upload_points: int = MAX_UPLOAD_POINTS,
          projector: bool = False) -> None:
    """Start the server and the app, print the URL (tests read it), block until Ctrl-C (or SIGTERM,
    which `treereg` raises as a KeyboardInterrupt named "SIGTERM"); then close the app (its upload
    folder removed).

    A port in use is an error (`ConfigError`): viser would silently take the next one. `port=0`
    asks for any free port.
    """
    t0 = time.perf_counter()
    server = viser.ViserServer(host=host, port=port, verbose=False)
    if port and server.get_port() != port:
        server.stop()
        controller.close()
        raise ConfigError(f"--port {port}: the port is in use (another treereg view?); choose another port, "
                          "or --port 0 for any free one")
    app = TreeregApp(server, controller, out_dir=out_dir, tabs="each", max_upload_bytes=max_upload_bytes,
                     max_upload_points=max_upload_points, projector=projector)
    warning = exposure_warning(host, server.get_port(), out_dir, max_upload_bytes)
    if warning:
        print(warning, file=sys.stderr, flush=True)
    url = f"http://{host}:{server.get_port()}/"
    try:  # from the line a user (or a test) waits for on, a signal finds the app's clean-up in place
        print(f"treereg view: {url}  (app ready in {time.perf_counter() - t0:.1f} s; Ctrl-C to stop)", flush=True)
        while True:
            time.sleep(1.0)
    except KeyboardInterrupt as e:
        print(f"treereg view: stopped ({e or 'Ctrl-C'})", flush=True)
    finally:
        app.close()
        server.stop()
