"""A one-line text progress bar on stderr (a `Progress` callback for long commands, or a subscriber
to a pipeline run's events)."""

from __future__ import annotations

import sys
import time
from typing import TYPE_CHECKING

from treereg_core.text import shown

if TYPE_CHECKING:  # the stage model loads the whole core: a command that only prints must not wait for it
    from treereg_core.stage import Event

#: Streams a bar has left mid-line (the next message must start on a fresh line).
_open_lines: set[int] = set()


def end_line() -> None:
    """Finish a half-drawn progress line, so the next message starts on a line of its own."""
    for stream in (sys.stderr, sys.stdout):
        if id(stream) in _open_lines:
            stream.write("\n")
            stream.flush()
    _open_lines.clear()


class ProgressBar:
    """A one-line text progress bar on stderr; usable as a `Progress` callback, and `on_event` as a
    pipeline run's subscriber (`register(..., events=bar.on_event)`)."""

    def __init__(self, label: str, stream=None, width: int = 30) -> None:
        self.label = label
        self.stream = stream if stream is not None else sys.stderr
        self.width = width
        self.t0 = time.perf_counter()
        self._last = -1.0
        self._done = False

    def on_event(self, event: Event) -> None:
        """A pipeline event: its progress moves the bar ("matching: scan2 -> scan1")."""
        from treereg_core.stage import StageProgress  # loaded by the run that sends the event

        if isinstance(event, StageProgress):
            self(event.run_fraction, event.line)

    def finish(self, text: str = "done") -> None:
        """Fill the bar and end its line, unless it is already full (a run that stopped early)."""
        if not self._done:
            self(1.0, text)

    def __call__(self, fraction: float, text: str = "") -> None:
        fraction = min(max(float(fraction), 0.0), 1.0)
        now = time.perf_counter()
        if fraction < 1.0 and now - self._last < 0.1:
            return
        self._last = now
        n = int(round(fraction * self.width))
        bar = "#" * n + "-" * (self.width - n)
        line = f"\r{self.label} [{bar}] {fraction * 100:5.1f}% {now - self.t0:6.1f}s {shown(text)[:40]:<40}"
        _open_lines.add(id(self.stream))  # before writing: Ctrl-C may land right after the write
        self.stream.write(line)
        if fraction >= 1.0:
            self.stream.write("\n")
            _open_lines.discard(id(self.stream))
            self._done = True
        self.stream.flush()
