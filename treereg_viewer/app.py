"""treereg's browser app: the server, theme and layout, and the glue between GUI, controller and
drawer.

Layout: on the right the control panel (stage selector, Previous/Next, Run, progress, messages;
tabs "Stage" with one folder per stage, "Scans", "Files"); on the left a wide docked panel with the
current stage's images, plots and tables; the 3-D scene in the middle. Callbacks only record what
changed (parameters go to the `Controller`, display choices to the `ViewState`); the pipeline runs
on the controller's worker and drawing on the `Drawer`'s thread.

    server = viser.ViserServer(host="127.0.0.1", port=0)
    app = TreeregApp(server, Controller(scans, params, truth))
"""

from __future__ import annotations

import ipaddress
import logging
import sys
import threading
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import viser

from treereg_core.errors import ConfigError
from treereg_core.limits import format_bytes
from treereg_core.params import Params

from . import camera
from .controller import Controller, Snapshot
from .drawer import Drawer
from .export_panel import ExportPanel
from .scan_panel import ScanPanel
from .stage_panel import StagePanel
from .stages import STAGE_NAMES, registered
from .view_panel import ViewPanel
from .uploads import UploadReceiver
from .view_state import ViewState

log = logging.getLogger(__name__)

#: Width of the docked control panel (viser's "large" control width).
CONTROL_WIDTH_PX = 400
#: Largest scan file a browser may upload unless the app is told otherwise.
MAX_UPLOAD_BYTES = 1024 * 1000 * 1000


class TreeregApp:
    """The app on one viser server. Every browser tab sees the same GUI and the same state.

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
    max_upload_bytes
        Largest scan file a browser may upload (uploads stream to a temporary file).
    """

    def __init__(self, server: viser.ViserServer, controller: Controller, out_dir: Path | None = None,
                 autorun: bool = True, max_upload_bytes: int = MAX_UPLOAD_BYTES) -> None:
        self.server = server
        self.controller = controller
        self.out_dir = Path(out_dir) if out_dir is not None else None
        self.max_upload_bytes = int(max_upload_bytes)
        self.uploads = UploadReceiver(server, on_message=lambda text, error: controller.note(text, error=error),
                                      on_progress=lambda text: self.scans.show_receiving(text))
        self._view_lock = threading.Lock()
        self._view = ViewState()
        self._last_progress = 0.0

        server.gui.configure_theme(show_share_button=False, control_width="large", brand_color=(30, 140, 60),
                                   titlebar_content=None)
        server.scene.set_up_direction("+z")
        self.panel = ViewPanel(server)
        # Docked, not floating: a floating control panel covers the right third of the scene, where
        # the trees of the other scans stand; docked, the scene is the free space between the panels.
        server.gui.main_panel.dock_right()
        server.gui.main_panel.set_width(CONTROL_WIDTH_PX)
        gui = server.gui
        gui.add_markdown("**treereg** · marker-free registration of single-tree TLS scans (rotating projection, "
                         "then stem and branch centres)")
        self.stages = StagePanel(gui, self)
        tabs = gui.add_tab_group()
        with tabs.add_tab("Stage", viser.Icon.LIST_NUMBERS):
            self.stages.build_folders(gui)
        with tabs.add_tab("Scans", viser.Icon.TREE):
            self.scans = ScanPanel(gui, self)
        with tabs.add_tab("Files", viser.Icon.FILE_EXPORT):
            self.files = ExportPanel(gui, self)

        self.drawer = Drawer(server, self.panel, lambda: controller.snapshot, lambda: self.view,
                             on_error=lambda msg: controller.note(msg, error=True))
        controller.subscribe(self._on_snapshot)
        controller.subscribe_progress(self._on_progress)
        self._on_snapshot(controller.snapshot)
        self._place_camera(controller.snapshot)
        if autorun and len(controller.snapshot.scans) >= 2:
            controller.request_run(STAGE_NAMES[-1])

    # ---- view state ------------------------------------------------------------------------------
    @property
    def view(self) -> ViewState:
        return self._view

    def set_view(self, **changes: Any) -> None:
        """Record display choices and ask for a redraw (callbacks call this; it returns at once)."""
        with self._view_lock:
            self._view = replace(self._view, **changes)
        self.drawer.request()

    def select_stage(self, name: str) -> None:
        before = self.view.stage
        self.set_view(stage=name)
        if registered(before) != registered(name):
            # Between the scattered scans (own frames) and the registered tree the content moves:
            # follow it. Within a group the camera stays where the user put it.
            self.frame_view()
        self.stages.show_stage(name)
        snap = self.controller.snapshot
        self.stages.show_snapshot(snap, name)
        if self.stages.auto_run.value and snap.status(name) == "stale" and len(snap.scans) >= 2 \
                and not any(snap.status(s) == "failed" for s in STAGE_NAMES[: STAGE_NAMES.index(name)]):
            self.controller.request_run(name)

    def step_stage(self, delta: int) -> None:
        i = int(np.clip(STAGE_NAMES.index(self.view.stage) + delta, 0, len(STAGE_NAMES) - 1))
        self.select_stage(STAGE_NAMES[i])

    def select_target(self, label: str) -> None:
        snap = self.controller.snapshot
        labels = [f"{s.name} → {snap.scans[0].name}" for s in snap.scans[1:]]
        if label in labels:
            self.set_view(target=labels.index(label), match_pair=0)
            for key, h in self.stages.view_controls.items():
                if key.startswith("target") and h.value != label:
                    h.value = label

    def set_scan_visible(self, name: str, visible: bool) -> None:
        hidden = set(self.view.hidden_scans)
        (hidden.discard if visible else hidden.add)(name)
        self.set_view(hidden_scans=frozenset(hidden))

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
        return None

    def load_params(self, params: Params, source: str, note: str = "") -> None:
        self.controller.set_params(params)
        self.stages.sync_params(params)
        self.controller.note(f"Parameters from {source} in force; press Run to apply them. {note}".rstrip())

    def send_file(self, client: Any, filename: str, data: bytes) -> None:
        """A browser download for the tab that asked (all tabs when there is no client, as in tests)."""
        target = client if client is not None else self.server
        target.send_file_download(filename, data)

    def close(self) -> None:
        self.controller.close()
        self.drawer.close()
        self.uploads.close()

    # ---- from the worker ----------------------------------------------------------------------
    def _on_snapshot(self, snap: Snapshot) -> None:
        self.stages.show_snapshot(snap, self.view.stage)
        self.scans.show_snapshot(snap)
        if not snap.busy:
            self.stages.progress_text.content = ""
        self.drawer.request()

    def _on_progress(self, fraction: float, text: str) -> None:
        now = time.perf_counter()
        if fraction < 1.0 and now - self._last_progress < 0.1:  # ~10 updates a second are plenty
            return
        self._last_progress = now
        self.stages.show_progress(fraction, text)

    def _place_camera(self, snap: Snapshot) -> None:
        """The camera a new browser tab starts with (and "Reset View" returns to): the Scans stage's view."""
        pose = camera.frame(snap, STAGE_NAMES[0])
        if pose is None:
            return
        self.server.initial_camera.position = pose.position
        self.server.initial_camera.look_at = pose.look_at
        self.server.initial_camera.up = (0.0, 0.0, 1.0)

    def frame_view(self) -> None:
        """Point every tab's camera at what the current stage draws (the "Frame the view" button)."""
        pose = camera.frame(self.controller.snapshot, self.view.stage)
        if pose is None:
            return
        for client in self.server.get_clients().values():
            try:
                with client.atomic():
                    # viser moves look_at along with position: set position first, then look_at.
                    client.camera.position = pose.position
                    client.camera.look_at = pose.look_at
            except (AssertionError, ValueError):  # a tab that has not reported its camera yet
                log.debug("camera of client %s not ready", client.client_id)


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
          max_upload_bytes: int = MAX_UPLOAD_BYTES) -> None:
    """Start the server and the app, print the URL (tests read it), block until Ctrl-C.

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
    app = TreeregApp(server, controller, out_dir=out_dir, max_upload_bytes=max_upload_bytes)
    warning = exposure_warning(host, server.get_port(), out_dir, max_upload_bytes)
    if warning:
        print(warning, file=sys.stderr, flush=True)
    url = f"http://{host}:{server.get_port()}/"
    print(f"treereg view: {url}  (app ready in {time.perf_counter() - t0:.1f} s; Ctrl-C to stop)", flush=True)
    try:
        while True:
            time.sleep(1.0)
    except KeyboardInterrupt:
        print("treereg view: stopped (Ctrl-C)", flush=True)
    finally:
        app.close()
        server.stop()
