"""What the panels may ask of the app: a narrow interface, so no panel holds (or imports) the app.

`TreeregApp` implements it; a panel receives it at construction and calls only these.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Protocol

from treereg_core.params import Params

from .controller import Controller
from .uploads import UploadReceiver
from .view_state import ViewState


class AppActions(Protocol):
    """The app as the panels see it."""

    controller: Controller
    out_dir: Path | None
    uploads: UploadReceiver
    max_upload_bytes: int

    @property
    def view(self) -> ViewState: ...

    def set_view(self, **changes: Any) -> None: ...

    def select_stage(self, name: str) -> None: ...

    def step_stage(self, delta: int) -> None: ...

    def run_current(self) -> None: ...

    def frame_view(self) -> None: ...

    def select_target(self, label: str) -> None: ...

    def set_scan_visible(self, name: str, visible: bool) -> None: ...

    def flush_edits(self) -> None: ...

    def on_param_change(self, section: str, name: str, value: Any) -> str | None: ...

    def load_params(self, params: Params, source: str, note: str = "") -> None: ...

    def send_file(self, client: Any, filename: str, data: bytes) -> None: ...
