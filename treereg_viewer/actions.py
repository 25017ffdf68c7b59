"""What the panels may ask of their viewer: a narrow interface, so no panel holds (or imports) the app.

`viewer.Viewer` (one per browser tab) implements it; a panel receives it at construction and calls
only these.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Protocol

from treereg_core.params import Params

from .controller import Controller
from .uploads import UploadReceiver
from .view_state import ViewState


class AppActions(Protocol):
    """A viewer as its panels see it."""

    controller: Controller
    out_dir: Path | None
    uploads: UploadReceiver
    max_upload_bytes: int
    max_upload_points: int
    read_only: bool  # following the presenter: the parameters and runs are the presenter's

    @property
    def view(self) -> ViewState: ...

    def set_view(self, **changes: Any) -> None: ...

    def select_stage(self, name: str) -> None: ...

    def step_stage(self, delta: int) -> None: ...

    def run_current(self) -> None: ...

    def frame_view(self) -> None: ...

    def select_target(self, label: str) -> None: ...

    def set_scan_visible(self, name: str, visible: bool) -> None: ...

    def focus_section(self, stage: str, row_label: str) -> None: ...

    def flush_edits(self) -> None: ...

    def on_param_change(self, section: str, name: str, value: Any) -> str | None: ...

    def load_params(self, params: Params, source: str, note: str = "") -> None: ...

    def choose_hypothesis(self, pair: str, candidate: str | None) -> None: ...

    def send_file(self, client: Any, filename: str, data: bytes) -> None: ...


class AppHost(Protocol):
    """The shared app as a viewer sees it (`app.TreeregApp` implements it): the computation and its
    caches, the exports folder, the upload receiver, who presents, and the downloads."""

    controller: Controller
    out_dir: Path | None
    uploads: UploadReceiver
    max_upload_bytes: int
    max_upload_points: int
    derived: Any
    server: Any
    presenter: Any

    projector: bool

    def set_presenter(self, viewer: Any, on: bool) -> bool: ...

    def hand_over(self, viewer: Any, to: str) -> bool: ...

    def changed_by(self, by: Any, what: str, undo: Any) -> None: ...

    def broadcast(self, presenter: Any) -> None: ...

    def camera_moved(self, presenter: Any, cam: Any) -> None: ...

    def send_file(self, client: Any, filename: str, data: bytes) -> None: ...
