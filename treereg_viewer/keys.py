"""Keyboard stepping: PageDown, → and Space go to the next stage (or tour step), PageUp and ← to the
previous one; a presentation clicker sends PageDown and PageUp.

viser forwards no raw key events to Python. Its own mechanism is the command palette:
`gui.add_command(label, hotkey=...)` registers a command the browser triggers on that key (Mantine's
`useHotkeys`, which ignores keys typed into inputs, text areas and selects), and `on_trigger` calls
back here. A command per key, on the tab's own GUI (`client.gui`): each tab steps itself. The
commands are also listed in viser's command palette (Ctrl+K).

→, ← and Space are bound only while they cannot mean something else: in projector mode and during
the guided tour (elsewhere a focused slider steps with the arrows and Space presses a focused
button). PageDown and PageUp are always bound.
"""

from __future__ import annotations

from typing import Any, Callable

import viser

#: (label in the command palette, viser's hotkey name, step, always bound).
KEYS: tuple[tuple[str, str, int, bool], ...] = (
    ("Next (PageDown)", "pagedown", 1, True),
    ("Previous (PageUp)", "pageup", -1, True),
    ("Next (→)", "arrowright", 1, False),
    ("Previous (←)", "arrowleft", -1, False),
    ("Next (Space)", "space", 1, False),
)


class StepKeys:
    """The stepping keys of one tab: `step(+1 or -1)` is called when one is pressed."""

    def __init__(self, gui: viser.GuiApi, step: Callable[[int], None]) -> None:
        self._step = step
        self.commands: dict[str, Any] = {}
        self._always: dict[str, bool] = {}
        for label, key, delta, always in KEYS:
            h = gui.add_command(label, description="Step through the stages, or the tour's steps while it runs.",
                                hotkey=key, disabled=not always)  # type: ignore[arg-type]
            h.on_trigger(lambda _, d=delta: self._step(d))
            self.commands[key] = h
            self._always[key] = always

    def bind_all(self, on: bool) -> None:
        """Bind →, ← and Space too (projector mode, the tour), or only PageDown and PageUp."""
        for key, h in self.commands.items():
            want = not (on or self._always[key])
            if h.disabled != want:
                h.disabled = want
