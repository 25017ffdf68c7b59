"""The "Scans" tab: display options of the scan layer, show/hide per scan, and scan upload."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import viser

from treereg_core.limits import format_bytes

from .actions import AppActions
from .controller import Snapshot
from .palette import scan_color
from .text import md
from .uploads import discard

#: File types treereg_core.io reads (the upload dialog's filter is only a hint: anything may come).
SCAN_SUFFIXES = ".ply,.las,.laz,.xyz,.txt,.csv,.npy,.npz"


class ScanPanel:
    def __init__(self, gui: viser.GuiApi, app: AppActions) -> None:
        self.app = app
        self.gui = gui
        v = app.view
        self.point_size = gui.add_slider("Point size (m)", 0.005, 0.1, 0.005, v.point_size,
                                         hint="Small points let the scans' colours mix where they overlap.")
        self.max_points = gui.add_number("Points shown per scan", v.max_points, min=1000, max=2_000_000, step=1000,
                                         hint="Display subsampling only; every stage uses all points.")
        self.stations = gui.add_checkbox("Show scanner stations", v.show_stations)
        self.point_size.on_update(lambda _: app.set_view(point_size=float(self.point_size.value)))
        self.max_points.on_update(lambda _: app.set_view(max_points=int(self.max_points.value)))
        self.stations.on_update(lambda _: app.set_view(show_stations=bool(self.stations.value)))
        self.visibility_folder = gui.add_folder("Show / hide")
        self._pool: list[Any] = []  # one checkbox per scan index ever shown
        self._checkboxes: list[Any] = []  # those of the current scans
        self._names: tuple[str, ...] = ()
        self.upload = gui.add_upload_button("Add a scan file", icon=viser.Icon.UPLOAD, mime_type="*/*",
                                            hint=f"Appends a scan ({SCAN_SUFFIXES}, up to "
                                                 f"{format_bytes(app.max_upload_bytes)} and {app.max_upload_points:,} "
                                                 "points); the first scan stays the reference.")
        # Streamed to a temporary file on the server (see uploads.py), then read by the worker.
        app.uploads.add(self.upload, self._add_file, app.max_upload_bytes, what="scan file",
                        max_points=app.max_upload_points)
        self.receiving = gui.add_markdown("")
        gui.add_markdown("Uploaded scans are registered onto scan 1. A file that cannot be read is "
                         "reported above and changes nothing.")
        # A wrong upload must be undoable without restarting the app.
        self.remove_choice = gui.add_dropdown("Scan to remove", ("(none)",), hint="A target scan (scan 1 is the reference and stays).")
        self.remove_button = gui.add_button("Remove scan", icon=viser.Icon.TRASH, color="gray", disabled=True)
        self.remove_button.on_click(lambda _: self._remove())

    def show_receiving(self, text: str) -> None:
        """What is being uploaded, and how far (every tab sees it); "" when nothing is."""
        self.receiving.content = f"*{md(text)}*" if text else ""

    def _add_file(self, filename: str, path: Path) -> None:
        """A scan file received: added, unless this tab follows the presenter (its scans are the
        presenter's; the button is greyed out, and a file sent anyway is dropped)."""
        if self.app.read_only:
            discard(path)
            self.app.controller.note("A scan file was not added: the tab that sent it follows the presenter.")
            return
        self.app.controller.add_scan_file(filename, path)

    def _remove(self) -> None:
        name = self.remove_choice.value
        if name in self._names[1:] and not self.app.read_only:  # a follower's scans are the presenter's
            self.app.controller.remove_scan(name)

    def show_snapshot(self, snap: Snapshot) -> None:
        """Rebuild the show/hide checkboxes when the set of scans changed."""
        names = tuple(s.name for s in snap.scans)
        if names == self._names:
            return
        self._names = names
        targets = names[1:]
        self.remove_choice.options = targets or ("(none)",)
        self.remove_button.disabled = not targets
        # Checkboxes are reused, never removed: viser keeps every removal message for the tabs that
        # open later, so removing and re-adding them on each upload would grow without end.
        with self.visibility_folder:
            while len(self._pool) < len(names):
                i = len(self._pool)
                r, g, b = scan_color(i)
                cb = self.gui.add_checkbox(f"{i + 1}", True, hint=f"scan colour rgb({r}, {g}, {b})")
                cb.on_update(lambda _, i=i: self._toggled(i))
                self._pool.append(cb)
        for i, cb in enumerate(self._pool):
            if i < len(names):
                cb.label = f"{i + 1}: {names[i]}"
                cb.value = names[i] not in self.app.view.hidden_scans
            cb.visible = i < len(names)
        self._checkboxes = self._pool[: len(names)]

    def _toggled(self, i: int) -> None:
        if i < len(self._names):
            self.app.set_scan_visible(self._names[i], bool(self._pool[i].value))
