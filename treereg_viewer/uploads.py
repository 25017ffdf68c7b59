"""Files uploaded from the browser, streamed to a temporary file with a size limit.

viser 1.1 (`GuiApi._handle_file_transfer_*`) keeps every part of an uploaded file in memory, joins
them (twice the file's size at the end), keeps the last file on the button's handle for good, and
broadcasts its progress acknowledgements to *every* tab through the persistent message buffer. So a
tab closed in the middle of a 200 MB upload left the upload button disabled, under a stuck
"Uploading undefined" notice, in every tab opened afterwards, and 400-800 MB of memory held.

`UploadReceiver` takes over the two upload messages (start, part) for the buttons given to it and
passes every other upload on to viser unchanged:
- parts are written to a temporary file as they arrive (nothing of the file is kept in memory);
- a file larger than the button's limit, or than the free disk space, is refused when it starts;
  a name no file can have (a NUL character) too;
- a scan file whose header announces more points than the button's limit is refused when complete,
  before a point is read: a few hundred kB of LAZ or gzip can unpack to tens of millions of points
  (and gigabytes of the server's memory);
- progress is acknowledged to the uploading tab only (its own progress notice), and reported to
  `on_progress` (the app shows it to every tab);
- when the uploading tab disconnects, its unfinished files are deleted and `on_abandoned` says so;
- a finished file is handed to the button's `on_file(name, path)`, which owns (and deletes) it.

This replaces handlers inside viser (its private `_websock_interface`, `_handle_file_transfer_*`,
the client's `_websock_connection`): the least invasive way to fix what viser does with uploads
without patching it. `receive()` feeds a file through the same path (tests, scripts).
"""

from __future__ import annotations

import logging
import shutil
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, BinaryIO, Callable

import viser
from viser import _messages

from treereg_core.io.scans import announced_points
from treereg_core.limits import format_bytes
from treereg_core.text import shown

log = logging.getLogger(__name__)

#: What viser's client sends per part (upload parts are 512 kB).
PART_BYTES = 512 * 1024
#: Keep this much disk free besides an upload.
DISK_MARGIN_BYTES = 200 * 1024 * 1024
#: Parts arriving ahead of their turn that are held in memory, at most (they arrive in order).
MAX_EARLY_PARTS = 16

#: on_file(file name as the user picked it, path of the complete temporary file)
OnFile = Callable[[str, Path], None]
#: on_message(sentence, is_error)
OnMessage = Callable[[str, bool], None]
#: on_progress(text): what is being received, "" when nothing is
OnProgress = Callable[[str], None]


@dataclass
class _Button:
    on_file: OnFile
    max_bytes: int
    what: str  # "scan file", "parameter file"
    gui: int  # id() of the GuiApi the button belongs to
    max_points: int | None = None  # scan files: the most points a file may announce


@dataclass
class _Transfer:
    uuid: str
    client_id: Any
    button: str
    filename: str
    size: int
    part_count: int
    path: Path
    file: BinaryIO
    received: int = 0
    next_part: int = 0
    early: dict[int, bytes] = field(default_factory=dict)
    started: float = field(default_factory=time.monotonic)


class UploadReceiver:
    """Streams uploads of the registered buttons to temporary files (see the module docstring)."""

    def __init__(self, server: viser.ViserServer, on_message: OnMessage, on_progress: OnProgress | None = None) -> None:
        self.server = server
        self._on_message = on_message
        self._on_progress = on_progress or (lambda text: None)
        self._buttons: dict[str, _Button] = {}
        self._transfers: dict[str, _Transfer] = {}
        self._lock = threading.Lock()
        self._last_progress = 0.0
        self._inline = threading.local()  # receive(): hand finished files over on the calling thread
        self.tmp_root = Path(tempfile.mkdtemp(prefix="treereg-uploads-"))
        # Per GUI whose buttons we receive (the server's, or a browser tab's own: viser dispatches a
        # tab's messages to both), viser's own two handlers, for every upload that is not ours.
        self._viser: dict[int, tuple[Any, Callable[..., None], Callable[..., None]]] = {}
        self._hook(server.gui)
        server.on_client_disconnect(self._disconnected)

    def _hook(self, gui: Any) -> None:
        if id(gui) in self._viser:
            return
        ws = gui._websock_interface
        start, part = gui._handle_file_transfer_start, gui._handle_file_transfer_part
        ws.unregister_handler(_messages.FileTransferStartUpload, start)
        ws.unregister_handler(_messages.FileTransferPart, part)
        ws.register_handler(_messages.FileTransferStartUpload, lambda cid, m, g=id(gui): self._start(cid, m, g))
        ws.register_handler(_messages.FileTransferPart, lambda cid, m, g=id(gui): self._part(cid, m, g))
        self._viser[id(gui)] = (gui, start, part)

    # ---- setup -----------------------------------------------------------------------------------
    def add(self, button: Any, on_file: OnFile, max_bytes: int, what: str = "file", max_points: int | None = None) -> None:
        """Receive `button`'s uploads: at most `max_bytes`, and for scan files at most `max_points`
        announced points, handed to `on_file` when complete."""
        gui = button._impl.gui_api
        self._hook(gui)
        self._buttons[button._impl.uuid] = _Button(on_file, int(max_bytes), what, id(gui), max_points)

    def remove(self, button: Any) -> None:
        """Stop receiving `button`'s uploads (its tab closed); forget its GUI once none of ours is left
        on it (a closed tab's GUI is not kept alive)."""
        b = self._buttons.pop(button._impl.uuid, None)
        if b is not None and b.gui != id(self.server.gui) and not any(o.gui == b.gui for o in self._buttons.values()):
            self._viser.pop(b.gui, None)

    @property
    def in_flight(self) -> list[tuple[str, float]]:
        """(file name, fraction received) of every upload under way."""
        with self._lock:
            return [(t.filename, t.received / max(t.size, 1)) for t in self._transfers.values()]

    def close(self) -> None:
        with self._lock:
            for t in self._transfers.values():
                t.file.close()
            self._transfers.clear()
        shutil.rmtree(self.tmp_root, ignore_errors=True)

    def receive(self, button: Any, filename: str, data: bytes, client_id: Any = None) -> None:
        """Feed `data` through the upload path as a browser would (start message, then parts); returns
        once the button's `on_file` has been called (or the file refused)."""
        parts = [data[i:i + PART_BYTES] for i in range(0, len(data), PART_BYTES)]
        uuid = f"local-{time.monotonic_ns()}"
        self._inline.on = True
        try:
            self._start(client_id, _messages.FileTransferStartUpload(button._impl.uuid, uuid, filename, "", len(parts), len(data)))
            for k, part in enumerate(parts):
                self._part(client_id, _messages.FileTransferPart(button._impl.uuid, uuid, k, part))
        finally:
            self._inline.on = False

    # ---- the messages (viser's event loop) ---------------------------------------------------------
    def _start(self, client_id: Any, msg: _messages.FileTransferStartUpload, gui: int | None = None) -> None:
        button = self._buttons.get(msg.source_component_uuid)
        if button is None:  # not ours: viser's own handling
            if gui in self._viser:
                self._viser[gui][1](client_id, msg)
            return
        if gui is not None and gui != button.gui:
            return  # the same message, dispatched to another GUI's handlers too
        name = Path(msg.filename).name or "upload"
        size = int(msg.size_bytes)
        problem = None
        if "\0" in name:  # no file system takes it (open() raises ValueError, not OSError)
            problem = "its name holds a NUL character, which no file name can hold; rename the file"
        elif size > button.max_bytes:
            problem = (f"{format_bytes(size)} is more than the {format_bytes(button.max_bytes)} a {button.what} may "
                       "have here (treereg view --max-upload-mb)")
        elif size + DISK_MARGIN_BYTES > shutil.disk_usage(self.tmp_root).free:
            problem = f"{format_bytes(size)} does not fit on the disk of the server ({self.tmp_root})"
        if problem is None:
            try:
                folder = Path(tempfile.mkdtemp(dir=self.tmp_root))
                path = folder / name
                fh = open(path, "wb")
            except OSError as e:
                problem = f"cannot be stored on the server ({(e.strerror or str(e)).lower()})"
        if problem is not None:
            self._ack(client_id, msg.source_component_uuid, msg.transfer_uuid, size, size)  # re-enable its button
            self._on_message(f"Upload rejected — {name}: {problem}; nothing was added.", True)
            return
        t = _Transfer(msg.transfer_uuid, client_id, msg.source_component_uuid, name, size, int(msg.part_count), path, fh)
        with self._lock:
            self._transfers[t.uuid] = t
        self._progress(force=True)
        if t.part_count == 0:  # an empty file: no part will come
            self._finish(t)

    def _part(self, client_id: Any, msg: _messages.FileTransferPart, gui: int | None = None) -> None:
        button = self._buttons.get(msg.source_component_uuid)
        if button is None:
            if gui in self._viser:
                self._viser[gui][2](client_id, msg)
            return
        if gui is not None and gui != button.gui:
            return
        with self._lock:
            t = self._transfers.get(msg.transfer_uuid)
        if t is None or client_id != t.client_id:
            return  # a refused, abandoned or foreign transfer: its parts are dropped
        k = int(msg.part_index)
        if k < t.next_part or k >= t.part_count or k in t.early:
            return  # a duplicate or out of range
        t.early[k] = bytes(msg.content)
        if len(t.early) > MAX_EARLY_PARTS:
            self._abort(t, "its parts arrived out of order")
            return
        try:
            while t.next_part in t.early:
                data = t.early.pop(t.next_part)
                t.file.write(data)
                t.received += len(data)
                t.next_part += 1
        except OSError as e:
            self._abort(t, f"cannot be stored on the server ({(e.strerror or str(e)).lower()})")
            return
        if t.received > t.size:
            self._abort(t, "more bytes arrived than the file's size")
            return
        self._ack(client_id, t.button, t.uuid, t.received, t.size)
        if t.next_part == t.part_count:
            if t.received != t.size:
                self._abort(t, f"{t.received} bytes arrived instead of {t.size}")
            else:
                self._finish(t)
        else:
            self._progress()

    async def _disconnected(self, client: viser.ClientHandle) -> None:
        with self._lock:
            gone = [t for t in self._transfers.values() if t.client_id == client.client_id]
        for t in gone:
            self._drop(t)
            self._on_message(f"Upload of {t.filename} abandoned at {100 * t.received / max(t.size, 1):.0f}% "
                             "(its browser tab was closed); nothing was added.", True)
        if gone:
            self._progress(force=True)

    # ---- endings -----------------------------------------------------------------------------------
    def _drop(self, t: _Transfer) -> None:
        with self._lock:
            self._transfers.pop(t.uuid, None)
        t.file.close()
        t.early.clear()
        shutil.rmtree(t.path.parent, ignore_errors=True)

    def _abort(self, t: _Transfer, why: str) -> None:
        self._drop(t)
        self._ack(t.client_id, t.button, t.uuid, t.size, t.size)
        self._on_message(f"Upload rejected — {t.filename}: {why}; nothing was added.", True)
        self._progress(force=True)

    def _finish(self, t: _Transfer) -> None:
        with self._lock:
            self._transfers.pop(t.uuid, None)
        t.file.close()
        self._progress(force=True)
        button = self._buttons[t.button]

        def hand_over() -> None:  # off the event loop: parsing a scan takes a while
            try:
                too_many = _too_many_points(t.path, button.max_points)
                if too_many:
                    discard(t.path)
                    self._on_message(f"Upload rejected — {t.filename}: {too_many}; nothing was added.", True)
                    return
                button.on_file(t.filename, t.path)
            except Exception as e:  # a bug must not leave the file behind or go unsaid
                log.exception("handling upload %s failed", shown(t.filename))
                self._on_message(f"Upload rejected — {t.filename}: {type(e).__name__}: {e}", True)
                discard(t.path)

        if getattr(self._inline, "on", False):
            hand_over()
        else:
            threading.Thread(target=hand_over, name="treereg-upload", daemon=True).start()

    # ---- to the browser ----------------------------------------------------------------------------
    def _ack(self, client_id: Any, button: str, uuid: str, received: int, size: int) -> None:
        """Progress for the uploading tab only (viser broadcast it to every tab, and kept it for new ones)."""
        client = self.server.get_clients().get(client_id) if client_id is not None else None
        if client is None:
            return
        client._websock_connection.queue_message(_messages.FileTransferPartAck(
            source_component_uuid=button, transfer_uuid=uuid, transferred_bytes=received, total_bytes=size))

    def _progress(self, force: bool = False) -> None:
        now = time.monotonic()
        if not force and now - self._last_progress < 0.25:
            return
        self._last_progress = now
        with self._lock:
            ts = list(self._transfers.values())
        self._on_progress("; ".join(f"Receiving {t.filename}: {100 * t.received / max(t.size, 1):.0f}% of "
                                    f"{format_bytes(t.size)}" for t in ts))


def _too_many_points(path: Path, max_points: int | None) -> str | None:
    """Why a received scan file holds too many points to be read here (None when it does not, or its
    header cannot be read: reading it then says what is wrong)."""
    if max_points is None:
        return None
    counted = announced_points(path, stop_after=max_points)
    if counted is None or counted[0] <= max_points:
        return None
    n, announced = counted
    holds = f"its header announces {n:,} points" if announced else f"it holds more than {max_points:,} lines of points"
    return (f"{holds}, more than the {max_points:,} an uploaded scan may have here (treereg view "
            "--max-upload-points)")


def discard(path: Path) -> None:
    """Delete a received file, and the private folder it was received in once that is empty."""
    path.unlink(missing_ok=True)
    try:
        path.parent.rmdir()
    except OSError:  # not empty, or not ours to remove
        pass

